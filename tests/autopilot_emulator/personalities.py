# SPDX-License-Identifier: Apache-2.0
"""ArduPilot and PX4 personalities: parameters, hidden compass errors, on-board state.

Each compass ``n`` (1-based) reads ``raw = A m_b + c + σ e`` in the autopilot's raw units
(ArduPilot mG, PX4 gauss), sensor frame, with ``m_b`` the unit field in the body and ``e``
standard normal: in magcal's model ``y = D R^bn m^n + o`` that is ``D = A``, ``o = c`` for
``y`` = the raw sensor-frame vector (:class:`CompassTruth`).

ArduPilot, like SITL (``libraries/AP_Compass/AP_Compass_SITL.cpp``, ``_timer``):
``raw = SCALING · R_misᵀ · R(SIM_MAGn_ORIENT)ᵀ · (E⁻¹ · F m_b − SIM_MAGn_OFS)`` with
``E = [[DIA_X, ODI_X, ODI_Y], …]`` of ``SIM_MAGn_DIA/ODI`` (all-zero diagonal → 1; singular →
identity), so the SIM_MAGn_* parameters are live as in SITL (writing them changes the sensor).
``R_mis`` is a hidden misalignment SITL does not have: a rotation by ``misalignment_deg``
about a random axis for external compasses (compass 1), none for the internal ones (2, 3,
which sit on the flight controller board with the IMU). Noise σ = ``SIM_MAG_RND`` mG (SITL's
is uniform; here Gaussian, added in the sensor frame).

PX4 has no simulated-compass parameters: the same kind of errors are hidden:
``raw = W · R_misᵀ · R(mount)ᵀ · F m_b + o`` (gauss), W symmetric positive definite (a few %),
o a few hundred mG, R(mount) an enumerated rotation for the external compass (identity for
internal ones), and no misalignment by default (PX4 cannot represent one: CAL_MAGn_ROT is
enumerated only, see :mod:`.onboard`).

The parameters in force at start are an older, imperfect calibration: right rotation, but
offsets off by up to ~80 mG and scale/cross terms off by a few %, so a client must undo the
correction in force to get raw data, and the heading error starts large.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from magcal.autopilot import rotations
from tests.autopilot_emulator import onboard
from tests.autopilot_emulator.params import INT8, INT16, INT32, REAL32, ParamSpec, ParamStore
from tests.autopilot_emulator.world import FIELD_STRENGTH_GAUSS, random_rotation_deg

MAX_COMPASSES = 3
#: Enumerated rotations an external compass is mounted with (same matrices in both).
EXTERNAL_MOUNTS = (0, 2, 4, 6, 8, 10, 14)
#: Hidden misalignment of external compasses by default, deg.
DEFAULT_MISALIGNMENT_DEG = {"ardupilot": 3.0, "px4": 0.0}
AP_MAG_NOISE_MG = 2.0
PX4_MAG_NOISE_GAUSS = 0.002
AP_DEV_IDS = (97539, 131874, 263178)  # SITL's SIM_MAGn_DEVID defaults
PX4_DEV_IDS = (396825, 2260994, 2261002)


@dataclass(frozen=True)
class CompassTruth:
    """One compass's true errors. ``y = D m_b + o`` with y the raw sensor-frame field
    (raw units) and m_b the unit field in the body; for a ``y`` taken after a rotation R
    (``y' = R y``) use ``R D``, ``R o``.

    R_sensor_to_body : (3, 3) true mounting, enumerated rotation × misalignment
    """

    compass: int
    present: bool
    external: bool
    D: np.ndarray
    o: np.ndarray
    R_sensor_to_body: np.ndarray
    misalignment_deg: float
    noise_sigma: float


@dataclass(frozen=True)
class EmulatorTruth:
    """What the emulator simulates. field_strength in the personality's unit (mG or gauss);
    m_n the unit field in n (x north, z up); compasses[n − 1] is compass n."""

    personality: str
    unit: str
    field_strength: float
    dip_deg: float
    m_n: np.ndarray
    compasses: tuple[CompassTruth, ...]

    def compass(self, n: int) -> CompassTruth:
        if not 1 <= n <= len(self.compasses):
            raise ValueError(f"compass {n} is not simulated (1–{len(self.compasses)})")
        return self.compasses[n - 1]


def _symmetric(diag: np.ndarray, odi: np.ndarray) -> np.ndarray:
    return np.array(
        [[diag[0], odi[0], odi[1]], [odi[0], diag[1], odi[2]], [odi[1], odi[2], diag[2]]]
    )


def _axes(template: str, values: np.ndarray) -> list[ParamSpec]:
    """REAL32 parameters for the X, Y, Z components: template holds ``{a}`` for the axis."""
    return [
        ParamSpec(template.format(a=a), REAL32, float(v))
        for a, v in zip("XYZ", values, strict=True)
    ]


def _signed_uniform(rng: np.random.Generator, lo: float, hi: float, n: int = 3) -> np.ndarray:
    return rng.uniform(lo, hi, n) * rng.choice((-1.0, 1.0), n)


class ArduPilot:
    """ArduPilot Copter (SITL-like) personality. Field unit mG."""

    name = "ardupilot"
    autopilot = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    unit = "mG"

    def __init__(self, rng: np.random.Generator, compasses: int, misalignment_deg: float):
        self.field_strength = FIELD_STRENGTH_GAUSS * 1000.0
        self.compasses = compasses
        self._misalignment_deg = [misalignment_deg if n == 1 else 0.0 for n in (1, 2, 3)]
        self._R_mis = [random_rotation_deg(rng, a) for a in self._misalignment_deg]
        self.specs = self._specs(rng)
        self._custom: dict[int, np.ndarray] = {}  # custom rotation matrices, built at first use

    def _specs(self, rng: np.random.Generator) -> list[ParamSpec]:
        s: list[ParamSpec] = [
            ParamSpec("FORMAT_VERSION", INT16, 120),
            ParamSpec("SYSID_THISMAV", INT16, 1),
            ParamSpec("FRAME_CLASS", INT8, 1),
            ParamSpec("AHRS_EKF_TYPE", INT8, 3),
            ParamSpec("AHRS_ORIENTATION", INT8, 0),
            ParamSpec("CUST_ROT_ENABLE", INT8, 0),
        ]
        s += [
            ParamSpec(f"CUST_ROT{k}_{a}", REAL32, 0.0)
            for k in (1, 2)
            for a in ("ROLL", "PITCH", "YAW")
        ]
        s += [
            ParamSpec("COMPASS_ENABLE", INT8, 1),
            ParamSpec("COMPASS_AUTODEC", INT8, 1),
            ParamSpec("COMPASS_DEC", REAL32, 0.0),
            ParamSpec("COMPASS_LEARN", INT8, 0),
            ParamSpec("COMPASS_MOTCT", INT8, 0),
            ParamSpec("COMPASS_OFFS_MAX", INT16, 1800),
            ParamSpec("COMPASS_CAL_FIT", REAL32, 16.0),
            ParamSpec("COMPASS_AUTO_ROT", INT8, 2),
            ParamSpec("COMPASS_TYPEMASK", INT32, 0),
            ParamSpec("COMPASS_FLTR_RNG", INT8, 0),
        ]
        sim: list[ParamSpec] = [ParamSpec("SIM_MAG_RND", REAL32, AP_MAG_NOISE_MG)]
        for n in (1, 2, 3):
            k = onboard.ap_suffix(n)
            present = n <= self.compasses
            external = n == 1
            # hidden truth in SITL's terms
            ofs = _signed_uniform(rng, 100.0, 300.0)
            dia = rng.uniform(0.94, 1.06, 3)
            odi = rng.uniform(-0.04, 0.04, 3)
            scaling = rng.uniform(0.97, 1.03)
            orient = int(rng.choice(EXTERNAL_MOUNTS)) if external else 0
            # the calibration in force: an older, imperfect one
            E = _symmetric(dia, odi)
            cal_ofs = scaling * ofs + rng.uniform(-80.0, 80.0, 3)
            M = E / scaling
            cal_dia = np.diag(M) * (1.0 + rng.uniform(-0.03, 0.03, 3))
            cal_odi = np.array([M[0, 1], M[0, 2], M[1, 2]]) + rng.uniform(-0.02, 0.02, 3)
            if not present:
                cal_ofs, cal_dia, cal_odi = np.zeros(3), np.zeros(3), np.zeros(3)
            dev_id = AP_DEV_IDS[n - 1] if present else 0
            s += _axes(f"COMPASS_OFS{k}_{{a}}", cal_ofs)
            s += _axes(f"COMPASS_DIA{k}_{{a}}", cal_dia)
            s += _axes(f"COMPASS_ODI{k}_{{a}}", cal_odi)
            s += [
                ParamSpec(f"COMPASS_SCALE{k}", REAL32, 1.0 if present else 0.0),
                ParamSpec(f"COMPASS_ORIENT{k}", INT8, orient),
                ParamSpec(onboard.ap_external_name(n), INT8, 1 if external else 0),
                ParamSpec(f"COMPASS_DEV_ID{k}", INT32, dev_id),
                ParamSpec(f"COMPASS_USE{k}", INT8, 1),
                ParamSpec(f"COMPASS_PRIO{n}_ID", INT32, dev_id),
            ]
            s += [ParamSpec(f"COMPASS_MOT{k}_{a}", REAL32, 0.0) for a in "XYZ"]
            sim += _axes(f"SIM_MAG{n}_OFS_{{a}}", ofs)
            sim += _axes(f"SIM_MAG{n}_DIA_{{a}}", dia)
            sim += _axes(f"SIM_MAG{n}_ODI_{{a}}", odi)
            sim += [
                ParamSpec(f"SIM_MAG{n}_ORIENT", INT8, orient),
                ParamSpec(f"SIM_MAG{n}_SCALING", REAL32, scaling),
                ParamSpec(f"SIM_MAG{n}_DEVID", INT32, AP_DEV_IDS[n - 1]),
            ]
        s += [ParamSpec(f"INS_ACCOFFS_{a}", REAL32, 0.0) for a in "XYZ"]
        s += [ParamSpec(f"INS_ACCSCAL_{a}", REAL32, 1.0) for a in "XYZ"]
        s += [ParamSpec(f"INS_GYROFFS_{a}", REAL32, 0.0) for a in "XYZ"]
        return s + sim

    # -- the sensor ------------------------------------------------------------------------
    def compass_model(self, params: dict[str, float], n: int) -> tuple[np.ndarray, np.ndarray]:
        """(A (3, 3), c (3,)) of ``raw = A m_b + c``, mG, from the SIM_MAGn_* in force."""
        p = f"SIM_MAG{n}_"
        dia = np.array([params[f"{p}DIA_{a}"] for a in "XYZ"])
        odi = np.array([params[f"{p}ODI_{a}"] for a in "XYZ"])
        if np.all(dia == 0.0):
            dia = np.ones(3)
        E = _symmetric(dia, odi)
        try:
            E_inv = np.linalg.inv(E)
        except np.linalg.LinAlgError:  # SITL: "if (!_eliptical_corr.invert()) identity"
            E_inv = np.eye(3)
        ofs = np.array([params[f"{p}OFS_{a}"] for a in "XYZ"])
        s = params[f"{p}SCALING"]
        Rt = (onboard.ap_enumerated_matrix(int(params[f"{p}ORIENT"])) @ self._R_mis[n - 1]).T
        return self.field_strength * s * Rt @ E_inv, -s * Rt @ ofs

    def noise_sigma(self, params: dict[str, float]) -> float:
        return abs(params["SIM_MAG_RND"])

    def truth(self, params: dict[str, float], dip_deg: float, m_n: np.ndarray) -> EmulatorTruth:
        out = []
        for n in range(1, MAX_COMPASSES + 1):
            A, c = self.compass_model(params, n)
            R = onboard.ap_enumerated_matrix(int(params[f"SIM_MAG{n}_ORIENT"])) @ self._R_mis[n - 1]
            out.append(
                CompassTruth(
                    n,
                    n <= self.compasses,
                    n == 1,
                    A,
                    c,
                    R,
                    self._misalignment_deg[n - 1],
                    self.noise_sigma(params),
                )
            )
        return EmulatorTruth(self.name, self.unit, self.field_strength, dip_deg, m_n, tuple(out))

    # -- on board --------------------------------------------------------------------------
    def correct(self, raw: np.ndarray, params: dict[str, float], n: int) -> np.ndarray:
        """The field ArduPilot publishes (N, 3) mG for raw (N, 3) mG."""
        return onboard.ardupilot_correct(raw, params, n, self._custom)

    def after_params_changed(self, store: ParamStore) -> None:
        """What the next compass sample does with new parameters: builds a custom rotation's
        matrix at its first use (and sets CUST_ROT_ENABLE, as get_rotation does), replaces
        all-zero diagonals by 1 (correct_field)."""
        params = store.snapshot()
        for n in range(1, self.compasses + 1):
            index = onboard.ap_rotation_index(params, n)
            if index in onboard.AP_CUSTOM_ROTATIONS and index - 100 not in self._custom:
                self._custom[index - 100] = onboard.ap_custom_matrix(params, index - 100)
                store.force("CUST_ROT_ENABLE", 1.0)
            k = onboard.ap_suffix(n)
            if all(params[f"COMPASS_DIA{k}_{a}"] == 0.0 for a in "XYZ"):
                for a in "XYZ":
                    store.force(f"COMPASS_DIA{k}_{a}", 1.0)

    def reboot(self, store: ParamStore) -> None:
        self._custom.clear()
        self.after_params_changed(store)


class PX4:
    """PX4 multicopter personality. Field unit gauss."""

    name = "px4"
    autopilot = mavlink.MAV_AUTOPILOT_PX4
    unit = "gauss"

    def __init__(self, rng: np.random.Generator, compasses: int, misalignment_deg: float):
        self.field_strength = FIELD_STRENGTH_GAUSS
        self.compasses = compasses
        self.mag_noise_sigma = PX4_MAG_NOISE_GAUSS
        self._hidden = []
        specs: list[ParamSpec] = [
            ParamSpec("MAV_SYS_ID", INT32, 1),
            ParamSpec("SYS_AUTOSTART", INT32, 4001),
            ParamSpec("SYS_HAS_MAG", INT32, 1),
            ParamSpec("SENS_BOARD_ROT", INT32, 0),
            ParamSpec("SENS_BOARD_X_OFF", REAL32, 0.0),
            ParamSpec("SENS_BOARD_Y_OFF", REAL32, 0.0),
            ParamSpec("SENS_BOARD_Z_OFF", REAL32, 0.0),
            ParamSpec("SENS_MAG_MODE", INT32, 1),
            ParamSpec("CAL_MAG_SIDES", INT32, 63),
            ParamSpec("CAL_MAG_ROT_AUTO", INT32, 1),
            ParamSpec("CAL_MAG_COMP_TYP", INT32, 0),
            ParamSpec("EKF2_MAG_TYPE", INT32, 0),
            ParamSpec("EKF2_MAG_DECL", REAL32, 0.0),
            ParamSpec("CAL_ACC0_ID", INT32, 1310988),
            ParamSpec("CAL_GYRO0_ID", INT32, 1310988),
        ]
        for n in (1, 2, 3):
            i = n - 1
            present = n <= compasses
            external = n == 1
            mount = int(rng.choice(EXTERNAL_MOUNTS)) if external else 0
            mis = misalignment_deg if external else 0.0
            R_mis = random_rotation_deg(rng, mis)
            W = _symmetric(rng.uniform(0.94, 1.06, 3), rng.uniform(-0.04, 0.04, 3))
            o = _signed_uniform(rng, 0.1, 0.3)
            self._hidden.append((mount, mis, R_mis, W, o))
            S = np.linalg.inv(W)
            off = o + rng.uniform(-0.08, 0.08, 3)
            scale = np.diag(S) * (1.0 + rng.uniform(-0.03, 0.03, 3))
            odiag = np.array([S[0, 1], S[0, 2], S[1, 2]]) + rng.uniform(-0.02, 0.02, 3)
            rot = mount if external else -1
            if not present:
                off, scale, odiag, rot = np.zeros(3), np.ones(3), np.zeros(3), -1
            p = f"CAL_MAG{i}_"
            specs += [
                ParamSpec(p + "ID", INT32, PX4_DEV_IDS[i] if present else 0),
                ParamSpec(p + "PRIO", INT32, (75 if external else 50) if present else -1),
                ParamSpec(p + "ROT", INT32, rot),
                ParamSpec(p + "TEMP", REAL32, -1000.0),
            ]
            specs += _axes(f"{p}{{a}}OFF", off)
            specs += _axes(f"{p}{{a}}SCALE", scale)
            specs += _axes(f"{p}{{a}}ODIAG", odiag)
            specs += [ParamSpec(f"{p}{a}COMP", REAL32, 0.0) for a in "XYZ"]
        self.specs = specs
        self._cal: list[onboard.Px4MagCalibration] = []

    def compass_model(self, params: dict[str, float], n: int) -> tuple[np.ndarray, np.ndarray]:
        """(A (3, 3), c (3,)) of ``raw = A m_b + c``, gauss (hidden, fixed)."""
        mount, _, R_mis, W, o = self._hidden[n - 1]
        Rt = (rotations.px4_matrix(mount) @ R_mis).T
        return self.field_strength * W @ Rt, o.copy()

    def noise_sigma(self, params: dict[str, float]) -> float:
        return self.mag_noise_sigma

    def truth(self, params: dict[str, float], dip_deg: float, m_n: np.ndarray) -> EmulatorTruth:
        out = []
        for n in range(1, MAX_COMPASSES + 1):
            mount, mis, R_mis, _, _ = self._hidden[n - 1]
            A, c = self.compass_model(params, n)
            out.append(
                CompassTruth(
                    n,
                    n <= self.compasses,
                    n == 1,
                    A,
                    c,
                    rotations.px4_matrix(mount) @ R_mis,
                    mis,
                    self.mag_noise_sigma,
                )
            )
        return EmulatorTruth(self.name, self.unit, self.field_strength, dip_deg, m_n, tuple(out))

    def correct(self, raw: np.ndarray, params: dict[str, float], n: int) -> np.ndarray:
        """vehicle_magnetometer (N, 3) gauss: the calibration *in use* applied to raw."""
        return self._cal[n - 1].correct(raw)

    def after_params_changed(self, store: ParamStore) -> None:
        """Magnetometer::ParametersUpdate for each compass (parameter_update)."""
        if not self._cal:
            self.reboot(store)
            return
        for cal in self._cal:
            for name, value in cal.parameters_update(store.snapshot()).items():
                store.force(name, value)

    def reboot(self, store: ParamStore) -> None:
        params = store.snapshot()
        self._cal = [onboard.Px4MagCalibration.reset(n - 1, n == 1, params) for n in (1, 2, 3)]
        self.after_params_changed(store)


def make_personality(
    name: str, rng: np.random.Generator, compasses: int, misalignment_deg: float | None
) -> ArduPilot | PX4:
    if not 1 <= compasses <= MAX_COMPASSES:
        raise ValueError(f"compasses must be 1–{MAX_COMPASSES}, got {compasses}")
    if misalignment_deg is None:
        misalignment_deg = DEFAULT_MISALIGNMENT_DEG.get(name, 0.0)
    if name == "ardupilot":
        return ArduPilot(rng, compasses, misalignment_deg)
    if name == "px4":
        return PX4(rng, compasses, misalignment_deg)
    raise ValueError(f"unknown personality {name!r}: use 'ardupilot' or 'px4'")
