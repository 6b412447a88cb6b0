# SPDX-License-Identifier: Apache-2.0
"""The autopilots' own magnetometer corrections, re-implemented from their sources.

This module is deliberately independent of ``magcal.autopilot.mapping`` (the tests compare
the two readings of the sources); it shares only the enumerated rotation tables of
``magcal.autopilot.rotations``, which have their own tests against the sources.

ArduPilot, ``libraries/AP_Compass/AP_Compass_Backend.cpp`` (``accumulate_sample`` →
``rotate_field`` → ``correct_field``), per sample, in mG:

1. ``rotate_field``: the driver's own rotation (none here), then for an *internal* compass
   the board orientation ``AHRS_ORIENTATION``, for an *external* one ``COMPASS_ORIENTn``;
   ROTATION_CUSTOM_1/2 (101/102) use the matrix of ``CUST_ROT1_*``/``CUST_ROT2_*``
   (``AP_CustomRotations.cpp``: ``from_euler(roll, pitch, yaw)``, degrees, "euler 321"),
   built when the rotation is first used and rebuilt only at a reboot (RebootRequired);
2. ``correct_field``: all-zero ``COMPASS_DIAn`` are replaced by (1, 1, 1) *in the parameter*;
   ``mag += OFS``; ``mag *= COMPASS_SCALEn`` only when ``have_scale_factor`` (``AP_Compass.cpp``:
   within [COMPASS_MIN_SCALE_FACTOR, COMPASS_MAX_SCALE_FACTOR] = [0.85, 1.4] of
   ``CompassCalibrator.h``, bounds included); ``mag = M · mag`` with
   ``M = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]``;
   motor compensation (``COMPASS_MOTCT`` = 0 here: none).

PX4, ``src/lib/sensor_calibration/Magnetometer.cpp`` / ``.hpp`` (gauss):

- ``Correct(data) = _rotation · (_scale · (data − _offset))`` (power compensation 0);
- ``ParametersUpdate``: an external ``CAL_MAGn_ROT`` outside [0, ROTATION_MAX) is reset to 0
  (the parameter is rewritten), an internal one must be −1 (rewritten otherwise) and the
  board rotation ``SENS_BOARD_ROT`` is used; ``_rotation = Dcmf(Eulerf(SENS_BOARD_X_OFF,
  SENS_BOARD_Y_OFF, SENS_BOARD_Z_OFF)) · get_rot_matrix(rot)``;
- ``set_offset`` / ``set_scale`` / ``set_offdiagonal`` take a new value only when it differs
  from the one in use by more than 0.01 (vector length of the difference) and is finite
  (scales also > 0): a smaller change stays unused until a reboot (``Reset`` then
  ``ParametersUpdate``). There is no custom rotation (no ``CAL_MAGn_ROLL/PITCH/YAW``).

Arithmetic here is float64 on the stored (float32-rounded) parameter values; the autopilots
compute in float32, a difference of ~1e-7 relative, far below the 1 mG step of the int16
message fields.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.autopilot import rotations

AP_SCALE_FACTOR_MIN = 0.85
AP_SCALE_FACTOR_MAX = 1.4
AP_CUSTOM_ROTATIONS = (101, 102)
#: PX4 ``enum Rotation`` ROTATION_MAX (rotation.h: 48 entries, 0–47).
PX4_ROTATION_MAX = len(rotations.PX4_TABLE)
#: PX4 Magnetometer::set_offset/set_scale/set_offdiagonal: changes up to this are ignored.
PX4_UPDATE_THRESHOLD = 0.01


def ap_suffix(compass: int) -> str:
    """ArduPilot's parameter suffix for compass 1, 2, 3: "", "2", "3"."""
    return "" if compass == 1 else str(compass)


def ap_external_name(compass: int) -> str:
    return "COMPASS_EXTERNAL" if compass == 1 else f"COMPASS_EXTERN{compass}"


def ap_enumerated_matrix(index: int) -> np.ndarray:
    """(3, 3) ArduPilot rotation 0–43; anything else (Vector3::rotate's default) is none."""
    if 0 <= index <= rotations.ARDUPILOT_MAX_INDEX:
        return rotations.ardupilot_matrix(index)
    return np.eye(3)


def ap_custom_matrix(params: dict[str, float], slot: int) -> np.ndarray:
    """(3, 3) matrix of CUST_ROT{slot}_ROLL/PITCH/YAW (degrees, Euler 3-2-1)."""
    p = f"CUST_ROT{slot}_"
    return rotations.euler_deg_to_matrix(
        params.get(p + "ROLL", 0.0), params.get(p + "PITCH", 0.0), params.get(p + "YAW", 0.0)
    )


def ap_rotation_index(params: dict[str, float], compass: int) -> int:
    """The rotation rotate_field applies: COMPASS_ORIENTn (external) or AHRS_ORIENTATION."""
    if params.get(ap_external_name(compass), 0.0) != 0.0:
        return int(params[f"COMPASS_ORIENT{ap_suffix(compass)}"])
    return int(params.get("AHRS_ORIENTATION", 0.0))


def ap_rotation(
    params: dict[str, float], compass: int, custom: dict[int, np.ndarray] | None = None
) -> np.ndarray:
    """(3, 3) sensor→body rotation of rotate_field. ``custom`` holds the custom matrices as
    built at first use (slot → matrix); missing slots are built from the parameters now."""
    index = ap_rotation_index(params, compass)
    if index in AP_CUSTOM_ROTATIONS:
        slot = index - 100
        if custom is not None and slot in custom:
            return custom[slot]
        return ap_custom_matrix(params, slot)
    return ap_enumerated_matrix(index)


def ap_scale_and_matrix(params: dict[str, float], compass: int) -> tuple[np.ndarray, np.ndarray]:
    """(OFS (3,), s·M (3, 3)) of correct_field with its all-zero-diagonal and scale rules."""
    k = ap_suffix(compass)
    ofs = np.array([params[f"COMPASS_OFS{k}_{a}"] for a in "XYZ"])
    dia = np.array([params[f"COMPASS_DIA{k}_{a}"] for a in "XYZ"])
    odi = np.array([params[f"COMPASS_ODI{k}_{a}"] for a in "XYZ"])
    if np.all(dia == 0.0):
        dia = np.ones(3)
    scale = params.get(f"COMPASS_SCALE{k}", 0.0)
    if not AP_SCALE_FACTOR_MIN <= scale <= AP_SCALE_FACTOR_MAX:
        scale = 1.0
    M = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    return ofs, scale * M


def ardupilot_correct(
    raw_mG: np.ndarray,
    params: dict[str, float],
    compass: int = 1,
    custom: dict[int, np.ndarray] | None = None,
) -> np.ndarray:
    """ArduPilot's corrected field (N, 3) mG, body frame, from the raw sensor field (N, 3) mG:
    ``M·s·(R·raw + OFS)`` (rotate_field, then correct_field)."""
    raw = np.atleast_2d(np.asarray(raw_mG, dtype=float))
    body = raw @ ap_rotation(params, compass, custom).T
    ofs, sM = ap_scale_and_matrix(params, compass)
    return (body + ofs) @ sM.T


@dataclass
class Px4MagCalibration:
    """The calibration a PX4 ``calibration::Magnetometer`` has in use (not the parameters).

    rotation : (3, 3) sensor→body; offset : (3,) gauss, sensor frame; scale : (3, 3)
    """

    index: int
    external: bool
    rotation: np.ndarray
    offset: np.ndarray
    scale: np.ndarray

    @classmethod
    def reset(cls, index: int, external: bool, params: dict[str, float]) -> Px4MagCalibration:
        """Magnetometer::Reset(): rotation none (external) or the board's, zero offset,
        identity scale."""
        rotation = _px4_level_adjustment(params) if external else _px4_board_rotation(params)
        return cls(index, external, rotation, np.zeros(3), np.eye(3))

    def parameters_update(self, params: dict[str, float]) -> dict[str, float]:
        """Magnetometer::ParametersUpdate() on the current parameters. Returns the parameters
        PX4 rewrites (an invalid CAL_MAGn_ROT), for the caller to store."""
        p = f"CAL_MAG{self.index}_"
        rewrites: dict[str, float] = {}
        rot = int(params[p + "ROT"])
        if self.external:
            if not 0 <= rot < PX4_ROTATION_MAX:
                rot = 0
                rewrites[p + "ROT"] = 0.0
            self.rotation = _px4_level_adjustment(params) @ rotations.px4_matrix(rot)
        else:
            if rot != -1:
                rewrites[p + "ROT"] = -1.0
            self.rotation = _px4_board_rotation(params)
        offset = np.array([params[f"{p}{a}OFF"] for a in "XYZ"])
        if _changed(self.offset, offset) and np.all(np.isfinite(offset)):
            self.offset = offset
        diag = np.array([params[f"{p}{a}SCALE"] for a in "XYZ"])
        if _changed(np.diag(self.scale), diag) and np.all(np.isfinite(diag) & (diag > 0)):
            self.scale[np.diag_indices(3)] = diag
        odiag = np.array([params[f"{p}{a}ODIAG"] for a in "XYZ"])
        in_use = np.array([self.scale[0, 1], self.scale[0, 2], self.scale[1, 2]])
        if _changed(in_use, odiag) and np.all(np.isfinite(odiag)):
            for (i, j), v in zip(((0, 1), (0, 2), (1, 2)), odiag, strict=True):
                self.scale[i, j] = self.scale[j, i] = v
        return rewrites

    def correct(self, raw_gauss: np.ndarray) -> np.ndarray:
        """Magnetometer::Correct: ``rotation · (scale · (raw − offset))``, (N, 3) gauss."""
        raw = np.atleast_2d(np.asarray(raw_gauss, dtype=float))
        return (raw - self.offset) @ self.scale.T @ self.rotation.T


def _changed(old: np.ndarray, new: np.ndarray) -> bool:
    # Vector3f(old - new).longerThan(0.01f)
    return bool(np.linalg.norm(np.asarray(old) - np.asarray(new)) > PX4_UPDATE_THRESHOLD)


def _px4_level_adjustment(params: dict[str, float]) -> np.ndarray:
    """GetSensorLevelAdjustment(): Dcmf(Eulerf(x_off, y_off, z_off)), degrees."""
    return rotations.euler_deg_to_matrix(
        params.get("SENS_BOARD_X_OFF", 0.0),
        params.get("SENS_BOARD_Y_OFF", 0.0),
        params.get("SENS_BOARD_Z_OFF", 0.0),
    )


def _px4_board_rotation(params: dict[str, float]) -> np.ndarray:
    """Level adjustment · GetBoardRotation() (SENS_BOARD_ROT; invalid → none)."""
    rot = int(params.get("SENS_BOARD_ROT", 0.0))
    board = rotations.px4_matrix(rot) if 0 <= rot < PX4_ROTATION_MAX else np.eye(3)
    return _px4_level_adjustment(params) @ board


def px4_correct(
    raw_gauss: np.ndarray, params: dict[str, float], index: int = 0, external: bool | None = None
) -> np.ndarray:
    """PX4's corrected field (N, 3) gauss from raw sensor_mag (N, 3) gauss, with the
    calibration a fresh boot takes from ``params`` (Reset, then ParametersUpdate).
    external : the device is external (default: CAL_MAGn_ROT ≥ 0, as PX4 stores it)."""
    if external is None:
        external = params.get(f"CAL_MAG{index}_ROT", 0.0) >= 0
    cal = Px4MagCalibration.reset(index, external, params)
    cal.parameters_update(params)
    return cal.correct(raw_gauss)
