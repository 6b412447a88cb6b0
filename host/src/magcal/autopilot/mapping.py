# SPDX-License-Identifier: Apache-2.0
"""Map a magcal calibration onto ArduPilot and PX4 compass parameters, and back.

magcal gives ``m_b = D⁻¹ (y − o)`` with ``‖m_b‖ = 1``; times the local field strength ``F``
it is the field in physical units. ``y`` is the magnetometer vector in the autopilot's raw
units (ArduPilot mG, PX4 gauss) *after* the rotation in force (``R_old``/``Rot0``, identity when
``y`` is in the sensor frame) and before any offset or scale correction.

On-board corrections, as in the sources:

- ArduPilot ``libraries/AP_Compass/AP_Compass_Backend.cpp`` (commit 20172681):
  ``rotate_field`` (driver/board rotation, then ``COMPASS_ORIENTn`` for an external compass,
  or the custom matrix for ROTATION_CUSTOM), then ``correct_field``: ``mag += offsets``;
  ``mag *= scale_factor`` only if ``have_scale_factor`` (AP_Compass.cpp: within
  [COMPASS_MIN_SCALE_FACTOR, COMPASS_MAX_SCALE_FACTOR]); ``mag = M · mag`` with
  ``M = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]`` (all-zero
  diagonals → 1); then motor compensation, ``mag += COMPASS_MOT·u`` (u the battery current
  for COMPASS_MOTCT 2, the throttle 0…1 for 1; :func:`to_ardupilot`'s ``motor_b``).
  So ``B = M · s · (R · raw + OFS)``, as ``docs/autopilots.md`` says. An *internal* compass is
  rotated by AHRS_ORIENTATION, not COMPASS_ORIENT: its rotation cannot be changed by us.
  The custom matrix is ``Matrix3::from_euler(roll, pitch, yaw)`` (3-2-1); in the commit read,
  ROTATION_CUSTOM = 100 with the compass's own custom angles; newer releases use 101/102 with
  ``CUST_ROT1_*``/``CUST_ROT2_*`` (AP_CustomRotations.cpp: "euler 321 (yaw, pitch, roll)
  ordering", degrees; AP_AHRS.cpp converts the old 100 to 101). We write 101/102.
- PX4 ``src/lib/sensor_calibration/Magnetometer.hpp`` ``Correct()`` (commit 021ee44a):
  ``_rotation * (_scale * ((data + power·comp) − _offset))`` (power: the throttle, or the
  current in kA, per CAL_MAG_COMP_TYP: VehicleMagnetometer.cpp); ``Magnetometer.cpp``
  (commit 033e9cee) builds ``_scale`` from SCALE (diagonal) and ODIAG (0,1), (0,2), (1,2)
  symmetric, and ``_rotation = get_rot_matrix(CAL_MAGn_ROT)``; an external ROT outside
  [0, ROTATION_MAX) is reset to 0 and an internal one is −1 (board rotation). That commit has
  **no** custom rotation: ROT = 100 with ``CAL_MAGn_ROLL/PITCH/YAW`` (docs/autopilots.md) is not
  in that commit (an external ROT of 100 is reset to 0 there); newer releases have it, so
  :func:`to_px4` writes it only with ``allow_custom``, which ``flash`` sets when the vehicle
  reports ``CAL_MAGn_ROLL/PITCH/YAW`` (unless ``--no-custom-rotation``).
- Limits: ArduPilot |OFS| < COMPASS_OFFS_MAX (default 1800 mG), DIA 0.2–5.0, |ODI| < 1
  (docs/autopilots.md, ArduPilot's own calibrator); SCALE used only in [0.85, 1.4]
  (CompassCalibrator.h COMPASS_MIN/MAX_SCALE_FACTOR). PX4 scales 0.1–3.0 (docs/autopilots.md);
  offsets beyond 1.3 G only draw a warning on board (mag_calibration.cpp
  MAG_MAX_OFFSET_LEN) and here too; no off-diagonal limit was found in the sources read.

Mapping (``docs/autopilots.md``): ArduPilot ``F·D⁻¹ = P'·U'`` (left polar) ⇒ ``R_new = U'·R_old``,
``OFS = −U'·o``, ``M·s = P'``. PX4 ``F·D⁻¹ = U·P`` (right polar) ⇒ ``Rot = U·Rot0``,
``S = Rot0ᵀ·P·Rot0``, ``off = Rot0ᵀ·o``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from magcal.autopilot import rotations
from magcal.calib import frames
from magcal.calib.diagnostics import quality
from magcal.errors import MagcalError

AP_OFFS_MAX_DEFAULT_MG = 1800.0
AP_DIA_MIN, AP_DIA_MAX = 0.2, 5.0
AP_ODI_MAX = 1.0
AP_SCALE_MIN, AP_SCALE_MAX = 0.85, 1.4
AP_CUSTOM_ORIENT = (101, 102)
PX4_SCALE_MIN, PX4_SCALE_MAX = 0.1, 3.0
PX4_OFFSET_WARN_GAUSS = 1.3
PX4_CUSTOM_ROT = 100
#: PX4 takes a CAL_MAGn_ vector from the parameters only when it differs from the one in use
#: by more than this (``Vector3f(in_use − new).longerThan(0.01f)`` in
#: src/lib/sensor_calibration/Magnetometer.cpp): set_offset, set_scale and set_offdiagonal in
#: the 2021 sources (the release the test emulator models); the 2022 sources load the offsets
#: and scales exactly (ParametersLoad) and keep the rule for the off-diagonals only. At boot
#: the one in use is Reset()'s, PX4_RESET_VALUES, so a vector within the threshold of it is
#: never applied, even after a reboot.
PX4_UPDATE_THRESHOLD = 0.01
PX4_RESET_VALUES = {"OFF": (0.0, 0.0, 0.0), "SCALE": (1.0, 1.0, 1.0), "ODIAG": (0.0, 0.0, 0.0)}
#: Motor compensation. ArduPilot's COMPASS_MOTCT and PX4's CAL_MAG_COMP_TYP per input (one
#: setting for every compass of the vehicle); PX4's 2 is the current of battery 0.
AP_MOTCT_NAME, PX4_COMP_TYP_NAME = "COMPASS_MOTCT", "CAL_MAG_COMP_TYP"
AP_MOTCT = {"throttle": 1, "current": 2}
PX4_COMP_TYP = {"throttle": 1, "current": 2}
#: PX4 compensates per kA of current (VehicleMagnetometer.cpp: ``bat_stat.current_a * 0.001f``,
#: "current in [kA]"; CAL_MAGn_XCOMP "[G/kA]") and per unit of throttle (0…1, "[G]").
PX4_POWER_PER_INPUT_UNIT = {"current": 1e-3, "throttle": 1.0}
#: ArduPilot's COMPASS_MOT_X/Y/Z range (AP_Compass.cpp ``@Range: -1000 1000``), mG per A or
#: mG at full throttle.
AP_MOT_MAX = 1000.0
#: Field inclination used for the heading error of a dropped rotation (a mid latitude).
DEFAULT_INCLINATION_DEG = 60.0


class AutopilotMappingError(MagcalError):
    """A calibration cannot be expressed in an autopilot's compass parameters."""


@dataclass(frozen=True)
class AutopilotParams:
    """Compass parameters for one autopilot, plus how faithful they are.

    params               : name → value, ready to write (mG / gauss, degrees)
    rotation             : (3, 3) sensor→body rotation the parameters select
    residual_angle_deg   : angle of the misalignment left out (0 when represented)
    heading_rms_deg      : RMS heading error over SO(3) caused by leaving it out
    notes                : human-readable remarks (nearest rotation chosen, warnings)
    snapped              : the rotation left out is within its own uncertainty (written as
                           the enumerated or board rotation it is close to)
    """

    params: dict[str, float]
    rotation: np.ndarray
    residual_angle_deg: float = 0.0
    heading_rms_deg: float = 0.0
    notes: tuple[str, ...] = field(default_factory=tuple)
    snapped: bool = False


def polar_right(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A (3, 3) = U · P, U orthogonal, P symmetric positive semi-definite."""
    U, P = scipy.linalg.polar(np.asarray(A, dtype=float), side="right")
    return U, (P + P.T) / 2.0


def polar_left(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A (3, 3) = P' · U', P' symmetric positive semi-definite, U' orthogonal."""
    U, P = scipy.linalg.polar(np.asarray(A, dtype=float), side="left")
    return (P + P.T) / 2.0, U


def _check_calibration(D_inv: np.ndarray, field_strength: float, what: str) -> np.ndarray:
    A = field_strength * np.asarray(D_inv, dtype=float)
    if A.shape != (3, 3) or not np.all(np.isfinite(A)):
        raise AutopilotMappingError(f"{what}: D⁻¹ must be a finite 3×3 matrix")
    if not field_strength > 0:
        raise AutopilotMappingError(f"{what}: field strength {field_strength} must be > 0")
    if np.linalg.det(A) <= 0:
        raise AutopilotMappingError(
            f"{what}: det(D⁻¹) ≤ 0 (a reflection), no rotation can represent it: "
            "check the sensor axes and recalibrate"
        )
    return A


def _heading_rms_deg(A_true: np.ndarray, A_used: np.ndarray, inclination_deg: float) -> float:
    """RMS heading error (deg) when the correction ``A_used (y − o)`` replaces ``A_true (y − o)``.

    Same metric as quality.calibration_heading_errors: noise-free fields over an SO(3) grid.
    """
    m_n = frames.field_direction(np.deg2rad(inclination_deg))
    D_true = np.linalg.inv(A_true)
    D_used = np.linalg.inv(A_used)
    o = np.zeros(3)
    return quality.rms_deg(quality.calibration_heading_errors(D_true, o, m_n, D_used, o))


#: ArduPilot's compass parameter names: COMPASS_OFS_X, COMPASS_OFS2_X, ... (every release
#: checked), or one group per instance, COMPASS1_OFS_X, COMPASS2_OFS_X, ..., which pymavlink's
#: tools/magfit_WMM.py also accepts ("new param format"; not found in a release read). A
#: vehicle's naming is detected by asking for COMPASS_OFS_X and COMPASS1_OFS_X.
AP_NAMING_LEGACY, AP_NAMING_PER_INSTANCE = "legacy", "per-instance"


def _ap_names(compass: int, naming: str = AP_NAMING_LEGACY) -> dict[str, str]:
    """Role ("OFS_X", "DIA_Y", "ODI_Z", "SCALE", "ORIENT", "DEV_ID") → parameter name of
    compass 1, 2, 3 in ``naming`` (AP_NAMING_LEGACY or AP_NAMING_PER_INSTANCE)."""
    if naming == AP_NAMING_PER_INSTANCE:
        p = f"COMPASS{compass}_"
        names = {f"{g}_{a}": f"{p}{g}_{a}" for g in ("OFS", "DIA", "ODI") for a in "XYZ"}
        return names | {"SCALE": p + "SCALE", "ORIENT": p + "ORIENT", "DEV_ID": p + "DEV_ID"}
    if naming != AP_NAMING_LEGACY:
        raise ValueError(f"unknown ArduPilot parameter naming {naming!r}")
    k = "" if compass == 1 else str(compass)
    names = {f"OFS_{a}": f"COMPASS_OFS{k}_{a}" for a in "XYZ"}
    names |= {f"DIA_{a}": f"COMPASS_DIA{k}_{a}" for a in "XYZ"}
    names |= {f"ODI_{a}": f"COMPASS_ODI{k}_{a}" for a in "XYZ"}
    names |= {"SCALE": f"COMPASS_SCALE{k}", "ORIENT": f"COMPASS_ORIENT{k}"}
    # the device id: ID for the first compass, ID2, ID3 after it (AP_Compass.cpp "DEV_ID")
    names["DEV_ID"] = f"COMPASS_DEV_ID{k}"
    return names


ap_param_names = _ap_names


def ap_motor_names(compass: int, naming: str = AP_NAMING_LEGACY) -> tuple[str, str, str]:
    """COMPASS_MOT_X/Y/Z of compass 1, COMPASS_MOT2_X… of 2, COMPASS_MOT3_X… of 3; per-instance
    COMPASSn_MOT_X… (unconfirmed, like that naming)."""
    if naming == AP_NAMING_PER_INSTANCE:
        return tuple(f"COMPASS{compass}_MOT_{a}" for a in "XYZ")  # type: ignore[return-value]
    k = "" if compass == 1 else str(compass)
    return tuple(f"COMPASS_MOT{k}_{a}" for a in "XYZ")  # type: ignore[return-value]


def px4_motor_names(index: int) -> tuple[str, str, str]:
    """CAL_MAG{index}_XCOMP/YCOMP/ZCOMP."""
    return tuple(f"CAL_MAG{index}_{a}COMP" for a in "XYZ")  # type: ignore[return-value]


def _motor_input(motor_input: str) -> str:
    if motor_input not in AP_MOTCT:
        raise AutopilotMappingError(
            f"motor interference input {motor_input!r}: magcal maps 'current' and 'throttle'"
        )
    return motor_input


def ap_external_name(compass: int, naming: str = AP_NAMING_LEGACY) -> str:
    """The parameter saying whether compass 1, 2, 3 is external (0 internal, 1 external,
    2 forced external): COMPASS_EXTERNAL, COMPASS_EXTERN2, ...; per-instance COMPASSn_EXTERN
    (unconfirmed, like that naming)."""
    if naming == AP_NAMING_PER_INSTANCE:
        return f"COMPASS{compass}_EXTERN"
    return "COMPASS_EXTERNAL" if compass == 1 else f"COMPASS_EXTERN{compass}"


def _split_scale(P: np.ndarray) -> tuple[np.ndarray, float]:
    """Split P' into M · s. s = 1 (SCALE written as 1.0) unless a diagonal is out of
    [0.2, 5]; then s moves the geometric mean of the diagonal towards 1 within [0.85, 1.4].
    Keeping s = 1 puts the whole soft-iron correction in M, where it is exact; SCALE is a
    single scalar the on-board calibrator uses for field-strength only."""
    d = np.diag(P)
    if np.all((d >= AP_DIA_MIN) & (d <= AP_DIA_MAX)):
        return P, 1.0
    s = float(np.clip(np.exp(np.mean(np.log(d))), AP_SCALE_MIN, AP_SCALE_MAX))
    return P / s, s


#: A rotation is written as the nearest enumerated one when their difference is within the
#: estimate's own uncertainty: Σ (Δ_i / σ_i)² ≤ this (the 99 % point of χ² with 3 degrees of
#: freedom), Δ the rotation vector from the enumerated rotation to the estimate and σ the
#: misalignment's standard deviation per axis.
SNAP_CHI2 = 11.34


def within_uncertainty(R_want: np.ndarray, R_near: np.ndarray, sigma_deg) -> bool:
    """Whether R_want (3, 3) is R_near within its uncertainty (:data:`SNAP_CHI2`; sigma_deg:
    (3,) the misalignment's σ per axis, degrees, or None: unknown, never)."""
    if sigma_deg is None:
        return False
    sigma = np.asarray(sigma_deg, dtype=float)
    if sigma.shape != (3,) or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        return False
    delta = rotations.rotation_vector_deg(R_want @ R_near.T)
    return float(np.sum((delta / sigma) ** 2)) <= SNAP_CHI2


def to_ardupilot(
    D_inv: np.ndarray,
    o: np.ndarray,
    field_mG: float,
    R_old: np.ndarray,
    *,
    compass: int = 1,
    naming: str = AP_NAMING_LEGACY,
    external: bool = True,
    allow_custom: bool = True,
    custom_slot: int = 1,
    offs_max_mG: float = AP_OFFS_MAX_DEFAULT_MG,
    inclination_deg: float = DEFAULT_INCLINATION_DEG,
    rotation_sigma_deg: np.ndarray | None = None,
    motor_b: np.ndarray | None = None,
    motor_input: str = "current",
) -> AutopilotParams:
    """ArduPilot parameters for ``B = F · D⁻¹ (y − o − b·u)``, ``y = R_old · raw`` (mG).

    D_inv : (3, 3) unit-field calibration, per mG;  o : (3,) offset in mG (y frame)
    field_mG : local field strength F (mG);  R_old : (3, 3) rotation in force when y was taken
    compass : 1, 2, 3 (parameter names COMPASS_OFS_X, COMPASS_OFS2_X, … in ``naming``)
    external : an internal compass follows AHRS_ORIENTATION, so its rotation stays R_old
    allow_custom : may ORIENT be 101/102 (CUST_ROT_ENABLE and CUST_ROTn_ROLL/PITCH/YAW)
    rotation_sigma_deg : (3,) the estimated misalignment's σ: a rotation within it of an
        enumerated one is written as that one (:func:`within_uncertainty`)
    motor_b : (3,) b, the motors' field in y per unit of ``motor_input`` ("current": mG/A,
        "throttle": mG at full throttle), or None: the motor parameters are not written.
        ArduPilot adds ``COMPASS_MOT·u`` after the soft-iron matrix (AP_Compass_Backend.cpp
        ``correct_field``, releases since 2017; older ones added it before), so the
        corrected field ``M·s·(R_new·raw + OFS) + MOT·u`` equals ``P'·C·(y − o − b·u)``
        (C = R_new·R_oldᵀ, the rotation written) when ``MOT = −P'·C·b``: the interference
        in the frame of the correction as written, with the sign that removes it. With the
        rotation represented, ``P'·C = F·D⁻¹`` and ``MOT = −F·D⁻¹·b``. COMPASS_MOTCT is
        written as 2 (current) or 1 (throttle)
    """
    A = _check_calibration(D_inv, field_mG, "ArduPilot mapping")
    o = np.asarray(o, dtype=float)
    R_old = np.asarray(R_old, dtype=float)
    P, U = polar_left(A)
    R_want = U @ R_old
    notes: list[str] = []
    snapped = False  # left out within its own uncertainty
    params: dict[str, float] = {}
    names = _ap_names(compass, naming)
    near = rotations.nearest(R_want, "ardupilot")
    if not external:
        # an internal compass follows AHRS_ORIENTATION, which also turns the IMU
        R_new, orient = R_old, None
        left_deg = rotations.rotation_angle_deg(R_want, R_old)
        if left_deg >= 1e-6:
            notes.append(
                "misalignment not represented (an internal compass follows AHRS_ORIENTATION): "
                f"rotation left {left_deg:.2f}° from the estimate"
            )
    elif near.angle_deg < 1e-6:
        R_new, orient = near.matrix, near.index
    elif snapped := within_uncertainty(R_want, near.matrix, rotation_sigma_deg):
        R_new, orient = near.matrix, near.index
        notes.append(_snapped_note(near))
    elif allow_custom:
        R_new, orient = R_want, AP_CUSTOM_ORIENT[custom_slot - 1]
        roll, pitch, yaw = rotations.matrix_to_euler_deg(R_want)
        params["CUST_ROT_ENABLE"] = 1.0
        params |= {
            f"CUST_ROT{custom_slot}_ROLL": roll,
            f"CUST_ROT{custom_slot}_PITCH": pitch,
            f"CUST_ROT{custom_slot}_YAW": yaw,
        }
    else:
        R_new, orient = near.matrix, near.index
        notes.append(
            "misalignment not represented (custom rotations are not allowed): nearest "
            f"enumerated rotation {near.index} {near.name} is {near.angle_deg:.2f}° from the "
            "estimate"
        )
    # y-frame correction actually applied: P' · R_new R_oldᵀ (y − o);  OFS = −R_new R_oldᵀ o
    C = R_new @ R_old.T
    ofs = -C @ o
    M, s = _split_scale(P)
    _check_ardupilot_limits(ofs, M, s, offs_max_mG)
    params |= {names[f"OFS_{a}"]: float(ofs[i]) for i, a in enumerate("XYZ")}
    params |= {names[f"DIA_{a}"]: float(M[i, i]) for i, a in enumerate("XYZ")}
    params |= {
        names["ODI_X"]: float(M[0, 1]),
        names["ODI_Y"]: float(M[0, 2]),
        names["ODI_Z"]: float(M[1, 2]),
    }
    params[names["SCALE"]] = s
    if orient is not None:
        params[names["ORIENT"]] = float(orient)
    if motor_b is not None:
        kind = _motor_input(motor_input)
        mot = -(P @ C) @ np.asarray(motor_b, dtype=float)
        for name, v in zip(ap_motor_names(compass, naming), mot, strict=True):
            if not abs(v) <= AP_MOT_MAX:
                raise AutopilotMappingError(
                    f"ArduPilot {name} = {v:.1f} is outside ±{AP_MOT_MAX:g} "
                    f"({'mG/A' if kind == 'current' else 'mG at full throttle'}): the motor "
                    "interference is too strong for ArduPilot's compensation; move the compass "
                    "away from the power wiring"
                )
            params[name] = float(v)
        params[AP_MOTCT_NAME] = float(AP_MOTCT[kind])
    residual = rotations.rotation_angle_deg(R_want, R_new)
    heading = 0.0 if residual < 1e-6 else _heading_rms_deg(A, P @ C, inclination_deg)
    if heading and not snapped:
        notes.append(f"leaving it out costs {heading:.2f}° RMS heading error")
    return AutopilotParams(params, R_new, residual, heading, tuple(notes), snapped)


def _snapped_note(near) -> str:
    return (
        f"the estimated rotation is {near.angle_deg:.2f}° from enumerated rotation {near.index} "
        f"{near.name}, within its uncertainty: written as {near.index} (no custom rotation)"
    )


def _check_ardupilot_limits(ofs: np.ndarray, M: np.ndarray, s: float, offs_max: float) -> None:
    for i, a in enumerate("XYZ"):
        if abs(ofs[i]) >= offs_max:
            raise AutopilotMappingError(
                f"ArduPilot COMPASS_OFS_{a} = {ofs[i]:.0f} mG exceeds COMPASS_OFFS_MAX "
                f"{offs_max:.0f} mG: move the compass away from magnetic parts or raise "
                "COMPASS_OFFS_MAX"
            )
        if not AP_DIA_MIN <= M[i, i] <= AP_DIA_MAX:
            raise AutopilotMappingError(
                f"ArduPilot COMPASS_DIA_{a} = {M[i, i]:.3f} outside {AP_DIA_MIN}–{AP_DIA_MAX} "
                f"(COMPASS_SCALE {s:.3f}): check the field strength and the raw units (mG)"
            )
    for a, v in zip("XYZ", (M[0, 1], M[0, 2], M[1, 2]), strict=True):
        if abs(v) >= AP_ODI_MAX:
            raise AutopilotMappingError(
                f"ArduPilot COMPASS_ODI_{a} = {v:.3f} outside ±{AP_ODI_MAX}: the soft-iron "
                "distortion is too strong for ArduPilot; check the calibration"
            )


def px4_param_names(index: int) -> dict[str, str]:
    """Role ("XOFF", "YSCALE", "ZODIAG", "ROT", "ROLL", "PITCH", "YAW", "ID") → parameter name
    of CAL_MAG{index}_*."""
    p = f"CAL_MAG{index}_"
    names = {f"{a}OFF": f"{p}{a}OFF" for a in "XYZ"}
    names |= {f"{a}SCALE": f"{p}{a}SCALE" for a in "XYZ"}
    names |= {f"{a}ODIAG": f"{p}{a}ODIAG" for a in "XYZ"}
    names |= {k: p + k for k in ("ROT", "ROLL", "PITCH", "YAW", "ID")}
    return names


def to_px4(
    D_inv: np.ndarray,
    o: np.ndarray,
    field_gauss: float,
    Rot0: np.ndarray | None = None,
    *,
    index: int = 0,
    allow_custom: bool = False,
    max_rotation_index: int = rotations.PX4_MAX_COMMON_INDEX,
    inclination_deg: float = DEFAULT_INCLINATION_DEG,
    rotation_sigma_deg: np.ndarray | None = None,
    board_rotation: np.ndarray | None = None,
    motor_b: np.ndarray | None = None,
    motor_input: str = "current",
) -> AutopilotParams:
    """PX4 parameters for ``B = F · D⁻¹ (y − o − b·u)``, ``y = Rot0 · raw`` (gauss).

    D_inv : (3, 3) unit-field calibration, per gauss;  o : (3,) offset in gauss (y frame)
    field_gauss : F;  Rot0 : (3, 3) rotation already applied to y (default: y is raw)
    index : n in CAL_MAGn_*;  allow_custom : write ROT = 100 with CAL_MAGn_ROLL/PITCH/YAW
    (only for a vehicle that has those: newer releases); rotation_sigma_deg : as for
    :func:`to_ardupilot`; board_rotation : an internal compass (CAL_MAGn_ROT −1): the
    rotation PX4 turns it with (SENS_BOARD_ROT's), kept: CAL_MAGn_ROT is not written and a
    misalignment beyond it is left out (noted).
    motor_b : (3,) b in y, gauss per unit of ``motor_input`` (A or throttle 0…1), or None.
        PX4 adds ``power·comp`` to the raw sensor-frame field before the offset
        (Magnetometer.hpp ``Correct``), so ``comp = −Rot0ᵀ·b`` per unit of power: per kA for
        the current (gauss/kA: ×1000 of gauss/A), per unit throttle; CAL_MAG_COMP_TYP 2
        (battery 0's current) or 1 (throttle)
    """
    A = _check_calibration(D_inv, field_gauss, "PX4 mapping")
    o = np.asarray(o, dtype=float)
    Rot0 = np.eye(3) if Rot0 is None else np.asarray(Rot0, dtype=float)
    U, P = polar_right(A)
    R_want = U @ Rot0
    names = px4_param_names(index)
    params: dict[str, float] = {}
    notes: list[str] = []
    snapped = False  # left out within its own uncertainty
    near = rotations.nearest(R_want, "px4", max_rotation_index)
    if board_rotation is not None:
        R_new = np.asarray(board_rotation, dtype=float)
        angle = rotations.rotation_angle_deg(R_want, R_new)
        if angle < 1e-6:
            pass
        elif snapped := within_uncertainty(R_want, R_new, rotation_sigma_deg):
            notes.append(
                f"the estimated rotation is {angle:.2f}° from the board rotation (SENS_BOARD_ROT) "
                "that PX4 turns this internal compass with, within its uncertainty: kept"
            )
        else:
            notes.append(
                "misalignment not represented (an internal compass: PX4 turns it with the board "
                f"rotation SENS_BOARD_ROT only): the estimate is {angle:.2f}° from it"
            )
    elif near.angle_deg < 1e-6:
        R_new = near.matrix
        params[names["ROT"]] = float(near.index)
    elif snapped := within_uncertainty(R_want, near.matrix, rotation_sigma_deg):
        R_new = near.matrix
        params[names["ROT"]] = float(near.index)
        notes.append(_snapped_note(near))
    elif allow_custom:
        R_new = R_want
        roll, pitch, yaw = rotations.matrix_to_euler_deg(R_want)
        params[names["ROT"]] = float(PX4_CUSTOM_ROT)
        params |= {names["ROLL"]: roll, names["PITCH"]: pitch, names["YAW"]: yaw}
    else:
        R_new = near.matrix
        params[names["ROT"]] = float(near.index)
        notes.append(
            f"misalignment not represented (custom rotation not allowed): nearest enumerated "
            f"rotation {near.index} {near.name} is {near.angle_deg:.2f}° from the estimate"
        )
    S = Rot0.T @ P @ Rot0
    off = Rot0.T @ o
    for i, a in enumerate("XYZ"):
        if not PX4_SCALE_MIN <= S[i, i] <= PX4_SCALE_MAX:
            raise AutopilotMappingError(
                f"PX4 CAL_MAG{index}_{a}SCALE = {S[i, i]:.3f} outside "
                f"{PX4_SCALE_MIN}–{PX4_SCALE_MAX}: check the field strength and the raw "
                "units (gauss)"
            )
        if abs(off[i]) > PX4_OFFSET_WARN_GAUSS:
            notes.append(
                f"CAL_MAG{index}_{a}OFF = {off[i]:.2f} G is beyond {PX4_OFFSET_WARN_GAUSS} G: "
                "PX4 warns the sensor may saturate"
            )
    params |= {names[f"{a}OFF"]: float(off[i]) for i, a in enumerate("XYZ")}
    params |= {names[f"{a}SCALE"]: float(S[i, i]) for i, a in enumerate("XYZ")}
    params |= {
        names["XODIAG"]: float(S[0, 1]),
        names["YODIAG"]: float(S[0, 2]),
        names["ZODIAG"]: float(S[1, 2]),
    }
    if motor_b is not None:
        kind = _motor_input(motor_input)
        comp = -(Rot0.T @ np.asarray(motor_b, dtype=float)) / PX4_POWER_PER_INPUT_UNIT[kind]
        params |= {n: float(v) for n, v in zip(px4_motor_names(index), comp, strict=True)}
        params[PX4_COMP_TYP_NAME] = float(PX4_COMP_TYP[kind])
    residual = rotations.rotation_angle_deg(R_want, R_new)
    heading = 0.0
    if residual >= 1e-6:
        # y-frame correction applied: R_new S Rot0ᵀ (y − o) = R_new Rot0ᵀ P (y − o)
        heading = _heading_rms_deg(A, R_new @ Rot0.T @ P, inclination_deg)
        if not snapped:
            notes.append(f"leaving it out costs {heading:.2f}° RMS heading error")
    return AutopilotParams(params, R_new, residual, heading, tuple(notes), snapped)


def ardupilot_rotation(
    params: dict[str, float], compass: int = 1, naming: str = AP_NAMING_LEGACY
) -> np.ndarray:
    """(3, 3) rotation selected by COMPASS_ORIENTn (0–43, or 101/102 with CUST_ROTn_*)."""
    orient = int(params[_ap_names(compass, naming)["ORIENT"]])
    if orient in AP_CUSTOM_ORIENT:
        k = orient - 100
        return rotations.euler_deg_to_matrix(
            params[f"CUST_ROT{k}_ROLL"], params[f"CUST_ROT{k}_PITCH"], params[f"CUST_ROT{k}_YAW"]
        )
    return rotations.ardupilot_matrix(orient)


def ardupilot_correct(
    raw: np.ndarray, params: dict[str, float], compass: int = 1, naming: str = AP_NAMING_LEGACY
) -> np.ndarray:
    """ArduPilot's rotate_field + correct_field (no motor compensation) on raw (N, 3) mG."""
    raw = np.atleast_2d(np.asarray(raw, dtype=float))
    mag = raw @ ardupilot_rotation(params, compass, naming).T  # rotate_field
    ofs, Ms = _ap_scale_matrix(params, compass, naming)
    return (mag + ofs) @ Ms.T


def _ap_scale_matrix(
    params: dict[str, float], compass: int, naming: str = AP_NAMING_LEGACY
) -> tuple[np.ndarray, np.ndarray]:
    """(OFS, M·s) of correct_field, with the all-zero-diagonal and scale-factor rules."""
    n = _ap_names(compass, naming)
    ofs = np.array([params[n[f"OFS_{a}"]] for a in "XYZ"])
    dia = np.array([params[n[f"DIA_{a}"]] for a in "XYZ"])
    odi = np.array([params[n[f"ODI_{a}"]] for a in "XYZ"])
    if np.all(dia == 0):
        dia = np.ones(3)
    s = params.get(n["SCALE"], 0.0)
    if not AP_SCALE_MIN <= s <= AP_SCALE_MAX:  # have_scale_factor() is false: no scaling
        s = 1.0
    M = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    return ofs, s * M


def ardupilot_undo_correct_field(
    corrected: np.ndarray,
    params: dict[str, float],
    compass: int = 1,
    naming: str = AP_NAMING_LEGACY,
) -> np.ndarray:
    """``y = R_old · raw`` (N, 3) mG behind ArduPilot's corrected field (RAW_IMU,
    SCALED_IMU2/3, DataFlash MAG): correct_field undone, ``(M·s)⁻¹ B − OFS``, the field as
    rotate_field left it (the y of :func:`to_ardupilot`). Needs no rotation, so it holds for an
    internal compass too (rotated by AHRS_ORIENTATION and the board, not COMPASS_ORIENT)."""
    ofs, Ms = _ap_scale_matrix(params, compass, naming)
    corrected = np.atleast_2d(np.asarray(corrected, dtype=float))
    if np.linalg.cond(Ms) > 1e12:
        raise AutopilotMappingError(
            f"the compass {compass} scale matrix in force is singular: its correction cannot "
            "be undone to recover the raw field"
        )
    return np.linalg.solve(Ms, corrected.T).T - ofs


def ardupilot_correct_field(
    y: np.ndarray, params: dict[str, float], compass: int = 1, naming: str = AP_NAMING_LEGACY
) -> np.ndarray:
    """correct_field alone, ``M·s·(y + OFS)`` on y (N, 3) mG as rotate_field left it: the
    inverse of :func:`ardupilot_undo_correct_field`."""
    ofs, Ms = _ap_scale_matrix(params, compass, naming)
    return (np.atleast_2d(np.asarray(y, dtype=float)) + ofs) @ Ms.T


def ardupilot_uncorrect(
    corrected: np.ndarray,
    params: dict[str, float],
    compass: int = 1,
    naming: str = AP_NAMING_LEGACY,
) -> np.ndarray:
    """The raw sensor-frame field (N, 3) mG behind ArduPilot's corrected field (RAW_IMU,
    SCALED_IMU2/3, DataFlash MAG): the inverse of :func:`ardupilot_correct` with the
    parameters that were in force, as MAVProxy's magfit recovers raw data. (An external
    compass only: an internal one is rotated by AHRS_ORIENTATION, not COMPASS_ORIENT.)"""
    body = ardupilot_undo_correct_field(corrected, params, compass, naming)
    # Rᵀ on the right of row vectors: rotation matrices are orthogonal
    return body @ ardupilot_rotation(params, compass, naming)


def px4_rotation(params: dict[str, float], index: int = 0) -> np.ndarray:
    """(3, 3) rotation selected by CAL_MAGn_ROT (0–47, or 100 with CAL_MAGn_ROLL/PITCH/YAW;
    −1, an internal compass: SENS_BOARD_ROT's, when ``params`` hold it)."""
    n = px4_param_names(index)
    rot_value = int(params[n["ROT"]])
    if rot_value < 0 and "SENS_BOARD_ROT" in params:
        # internal: PX4 uses the board rotation (Magnetometer::set_rotation, GetBoardRotation)
        return rotations.px4_matrix(int(params["SENS_BOARD_ROT"]))
    if rot_value == PX4_CUSTOM_ROT:
        return rotations.euler_deg_to_matrix(
            params[n["ROLL"]], params[n["PITCH"]], params[n["YAW"]]
        )
    return rotations.px4_matrix(rot_value)


def _px4_offset_scale(params: dict[str, float], index: int) -> tuple[np.ndarray, np.ndarray]:
    n = px4_param_names(index)
    off = np.array([params[n[f"{a}OFF"]] for a in "XYZ"])
    d = [params[n[f"{a}SCALE"]] for a in "XYZ"]
    od = [params[n[f"{a}ODIAG"]] for a in "XYZ"]
    S = np.array([[d[0], od[0], od[1]], [od[0], d[1], od[2]], [od[1], od[2], d[2]]])
    return off, S


def px4_vector(params: dict[str, float], index: int, group: str) -> np.ndarray:
    """(3,) CAL_MAG{index}_X/Y/Z{group} (group "OFF", "SCALE" or "ODIAG")."""
    n = px4_param_names(index)
    return np.array([params[n[f"{a}{group}"]] for a in "XYZ"], dtype=float)


def px4_unapplied(params: dict[str, float], index: int = 0) -> tuple[str, ...]:
    """The groups ("OFF", "SCALE", "ODIAG") PX4 does not apply after a boot with ``params``:
    within PX4_UPDATE_THRESHOLD of the reset value but not equal to it (pure)."""
    out = []
    for g, reset in PX4_RESET_VALUES.items():
        d = float(np.linalg.norm(px4_vector(params, index, g) - np.array(reset)))
        if 0.0 < d <= PX4_UPDATE_THRESHOLD:
            out.append(g)
    return tuple(out)


def px4_as_applied(params: dict[str, float], index: int = 0) -> dict[str, float]:
    """``params`` as a PX4 Magnetometer uses them after a boot (see PX4_UPDATE_THRESHOLD):
    each vector within the threshold of its reset value replaced by that value."""
    out = dict(params)
    n = px4_param_names(index)
    for g in px4_unapplied(params, index):
        out |= {n[f"{a}{g}"]: v for a, v in zip("XYZ", PX4_RESET_VALUES[g], strict=True)}
    return out


def px4_unapplied_heading_rms_deg(
    params: dict[str, float],
    index: int,
    field_gauss: float,
    inclination_deg: float = DEFAULT_INCLINATION_DEG,
) -> float:
    """RMS heading error (deg) of PX4's correction as applied (:func:`px4_as_applied`) on
    the field that ``params``' full correction makes exact (the same SO(3) grid metric as
    :func:`_heading_rms_deg`, offsets included)."""
    R = px4_rotation(params, index)
    off_i, S_i = _px4_offset_scale(params, index)
    off_a, S_a = _px4_offset_scale(px4_as_applied(params, index), index)
    m_n = frames.field_direction(np.deg2rad(inclination_deg))
    # y = F (R S)⁻¹ m + off is what the full correction turns into the field F m exactly
    D_i = field_gauss * np.linalg.inv(R @ S_i)
    D_a = field_gauss * np.linalg.inv(R @ S_a)
    return quality.rms_deg(quality.calibration_heading_errors(D_i, off_i, m_n, D_a, off_a))


def px4_correct(
    raw: np.ndarray, params: dict[str, float], index: int = 0, *, as_applied: bool = False
) -> np.ndarray:
    """PX4 Magnetometer::Correct (no power compensation) on raw (N, 3) gauss: the formula
    with ``params``, or with ``as_applied`` the correction a vehicle booted with them uses
    (:func:`px4_as_applied`)."""
    raw = np.atleast_2d(np.asarray(raw, dtype=float))
    if as_applied:
        params = px4_as_applied(params, index)
    off, S = _px4_offset_scale(params, index)
    return (raw - off) @ S.T @ px4_rotation(params, index).T


def px4_uncorrect(
    corrected: np.ndarray, params: dict[str, float], index: int = 0, *, as_applied: bool = False
) -> np.ndarray:
    """The raw sensor-frame field (N, 3) gauss behind PX4's corrected field (HIGHRES_IMU,
    the ``vehicle_magnetometer`` topic): the inverse of :func:`px4_correct` (``as_applied``
    as there)."""
    if as_applied:
        params = px4_as_applied(params, index)
    off, S = _px4_offset_scale(params, index)
    corrected = np.atleast_2d(np.asarray(corrected, dtype=float))
    if np.linalg.cond(S) > 1e12:
        raise AutopilotMappingError(
            f"the CAL_MAG{index} scale matrix in force is singular: its correction cannot be "
            "undone to recover the raw field"
        )
    sensor = corrected @ px4_rotation(params, index)  # Rotᵀ
    return np.linalg.solve(S, sensor.T).T + off
