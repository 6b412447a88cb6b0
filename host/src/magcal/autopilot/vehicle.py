# SPDX-License-Identifier: Apache-2.0
"""What magcal knows about an ArduPilot or PX4 vehicle on a MAVLink link.

Identity. The HEARTBEAT's ``autopilot`` field: MAV_AUTOPILOT_ARDUPILOTMEGA (3) is ArduPilot,
MAV_AUTOPILOT_PX4 (12) is PX4; anything else is refused (:func:`autopilot_of`).

Compass numbering. ``--compass N`` counts from 1 as ArduPilot does:

======================  ==========================================  ==============================
                        ArduPilot                                   PX4
======================  ==========================================  ==============================
parameters              COMPASS_OFS_X… (N = 1), COMPASS_OFS2_X… (2)  CAL_MAG{N−1}_XOFF…
stream (collect)        RAW_IMU (1), SCALED_IMU2 (2), SCALED_IMU3    SCALED_IMU (1), SCALED_IMU2…
stream (verify)         the same (its field is corrected)           HIGHRES_IMU (N = 1), else the
                                                                    raw stream corrected here
magnetometer unit       mG (corrected, body frame)                  mG on the wire = raw gauss×1000
======================  ==========================================  ==============================

ArduPilot streams its compasses in priority order (``get_field(i)`` is the i-th priority,
AP_Compass.h) and names parameters in detection order; they agree unless COMPASS_PRIOn_ID
lists the devices in another order than COMPASS_DEV_ID…, which ArduPilot undoes at boot
(``_reorder_compass_params``). PX4 finds a sensor's calibration slot by CAL_MAGn_ID; magcal
assumes SCALED_IMU{N}'s magnetometer uses CAL_MAG{N−1}, which holds for the usual order.

Streams, from the sources (GCS_Common.cpp ``send_raw_imu`` / ``send_scaled_imu``; PX4
``streams/SCALED_IMU.hpp``, ``HIGHRES_IMU.hpp``): accelerometer mG of standard gravity
(``accel·1000/GRAVITY_MSS``), gyroscope mrad/s, both calibrated and in the body frame;
magnetometer in mG: ArduPilot's ``compass.get_field(i)`` (the corrected field), PX4's
``sensor_mag`` ×1000 (the raw field in the driver's frame, before CAL_MAGn_*). Timestamps:
RAW_IMU ``time_usec`` (µs; ``micros64`` now, 32-bit ``micros`` in older ArduPilot, which wraps
after 71.6 minutes), SCALED_IMU* ``time_boot_ms`` (ms, uint32), HIGHRES_IMU ``time_usec``.
ArduPilot stamps the time of sending, PX4 the sample's.

The session's magnetometer (what :func:`session_mag` makes of a message's field):

- ArduPilot: ``y = (M·s)⁻¹ B − OFS`` with the compass parameters in force, the field as
  ``rotate_field`` left it (``y = R_old · raw``, :func:`magcal.autopilot.mapping.to_ardupilot`'s
  y): the body-aligned frame of the rotation in force, before offsets and scaling. Motor
  compensation is not undone (zero on the ground with motors off).
- PX4: the raw sensor-frame field in gauss (``Rot0 = I`` for
  :func:`~magcal.autopilot.mapping.to_px4`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from magcal.autopilot import mapping, params, rotations
from magcal.errors import MagcalError
from magcal.link.mavlink import MavlinkTimeoutError

ARDUPILOT, PX4 = "ardupilot", "px4"
AUTOPILOT_NAMES = {ARDUPILOT: "ArduPilot", PX4: "PX4"}
MAV_AUTOPILOT = {3: ARDUPILOT, 12: PX4}
MAG_UNIT = {ARDUPILOT: "mG", PX4: "gauss"}
#: Session magnetometer units per milligauss.
UNIT_PER_MG = {ARDUPILOT: 1.0, PX4: 1e-3}
ENCODING = {ARDUPILOT: params.C_CAST, PX4: params.BYTEWISE}
#: ArduPilot GRAVITY_MSS and PX4 CONSTANTS_ONE_G, m/s².
STANDARD_GRAVITY = 9.80665
MAX_COMPASSES = 3
#: Message ids of the streams (common.xml).
MESSAGE_IDS = {"SCALED_IMU": 26, "RAW_IMU": 27, "HIGHRES_IMU": 105, "SCALED_IMU2": 116}
MESSAGE_IDS["SCALED_IMU3"] = 129
#: Tries for a parameter that may not exist on this firmware (each costs a reply time-out).
OPTIONAL_READ_TRIES = 6
#: Prefix of the session metadata keys holding the compass parameters in force.
SESSION_PARAM_PREFIX = "param."


class AutopilotError(MagcalError):
    """The vehicle is not one magcal can work with, or lacks what is needed."""


def autopilot_of(mav_autopilot: int, where: str) -> str:
    """ARDUPILOT or PX4 from HEARTBEAT.autopilot; AutopilotError for any other."""
    if mav_autopilot in MAV_AUTOPILOT:
        return MAV_AUTOPILOT[mav_autopilot]
    raise AutopilotError(
        f"{where}: the vehicle's autopilot is MAV_AUTOPILOT {mav_autopilot} "
        f"({_enum_name('MAV_AUTOPILOT', mav_autopilot)}); magcal works with ArduPilot (3) and "
        "PX4 (12) only"
    )


def _enum_name(enum: str, value: int) -> str:
    from pymavlink import mavutil

    entry = mavutil.mavlink.enums.get(enum, {}).get(value)
    return entry.name if entry is not None else "unknown"


def vehicle_type_name(mav_type: int) -> str:
    """ "QUADROTOR" for MAV_TYPE_QUADROTOR (2)."""
    return _enum_name("MAV_TYPE", mav_type).removeprefix("MAV_TYPE_")


def firmware_text(flight_sw_version: int) -> str:
    """AUTOPILOT_VERSION.flight_sw_version (major<<24 | minor<<16 | patch<<8 | type) as
    "4.5.7 official" (FIRMWARE_VERSION_TYPE: dev 0, alpha 64, beta 128, rc 192, official 255)."""
    v = int(flight_sw_version)
    kind = {0: "dev", 64: "alpha", 128: "beta", 192: "rc", 255: "official"}.get(v & 0xFF, "")
    text = f"{(v >> 24) & 0xFF}.{(v >> 16) & 0xFF}.{(v >> 8) & 0xFF}"
    return f"{text} {kind}".strip()


def check_compass(compass: int) -> None:
    if not 1 <= compass <= MAX_COMPASSES:
        raise AutopilotError(
            f"--compass {compass}: give 1, 2 or 3 (the streams carry three compasses at most)"
        )


def collect_stream(autopilot: str, compass: int) -> str:
    """The message carrying compass N's field with its IMU (module docstring's table)."""
    check_compass(compass)
    if compass == 1:
        return "RAW_IMU" if autopilot == ARDUPILOT else "SCALED_IMU"
    return f"SCALED_IMU{compass}"


def px4_index(compass: int) -> int:
    """n of CAL_MAGn_* for ``--compass N``."""
    check_compass(compass)
    return compass - 1


# ----------------------------------------------------------------- compass parameter sets
@dataclass(frozen=True)
class CompassParams:
    """The parameters of one compass in force, as the vehicle reported them.

    values : name → value (decoded); types : name → MAV_PARAM_TYPE; naming : ArduPilot's
    AP_NAMING_* (PX4: ""); external : whether the compass is external (ArduPilot:
    COMPASS_EXTERNn ≠ 0; PX4: CAL_MAGn_ROT ≥ 0)
    """

    autopilot: str
    compass: int
    values: dict[str, float]
    types: dict[str, int]
    naming: str = ""
    external: bool = True
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def unit(self) -> str:
        return MAG_UNIT[self.autopilot]

    def session_meta(self) -> dict[str, str]:
        """The parameters as session metadata lines (``param.NAME: value``)."""
        return {
            SESSION_PARAM_PREFIX + n: params.value_text(v, self.types.get(n))
            for n, v in self.values.items()
        }


def params_from_meta(meta: dict[str, str]) -> dict[str, float]:
    """The ``param.NAME: value`` entries of session metadata (or a result's copy of it)."""
    out: dict[str, float] = {}
    for key, text in meta.items():
        if key.startswith(SESSION_PARAM_PREFIX):
            try:
                out[key[len(SESSION_PARAM_PREFIX) :]] = float(text)
            except ValueError:
                raise AutopilotError(f"session metadata {key}: {text!r} is not a number") from None
    return out


def ardupilot_required(compass: int, naming: str) -> list[str]:
    """What ArduPilot's correct_field and rotate_field need for ``compass``, and its device id
    (0: no such compass)."""
    n = mapping.ap_param_names(compass, naming)
    roles = [f"{g}_{a}" for g in ("OFS", "DIA", "ODI") for a in "XYZ"] + ["ORIENT", "DEV_ID"]
    return [n[r] for r in roles] + [mapping.ap_external_name(compass, naming)]


def ardupilot_optional(compass: int, naming: str) -> list[str]:
    """Parameters used when present: the scale factor (newer firmware), the offset limit,
    custom rotations and the rotations that may already use a custom slot."""
    n = mapping.ap_param_names(compass, naming)
    others = [
        mapping.ap_param_names(k, naming)["ORIENT"]
        for k in range(1, MAX_COMPASSES + 1)
        if k != compass
    ]
    return [n["SCALE"], "COMPASS_OFFS_MAX", "CUST_ROT_ENABLE", "AHRS_ORIENTATION", *others]


def compass_param_names(autopilot: str, compass: int, naming: str = "") -> list[str]:
    """The parameters that belong to one compass alone (not shared with others)."""
    if autopilot == ARDUPILOT:
        n = mapping.ap_param_names(compass, naming)
        return [*ardupilot_required(compass, naming), n["SCALE"]]
    index = px4_index(compass)
    return [*px4_required(index)[:10], dev_id_name(PX4, compass), *px4_custom_angles(index)]


def dev_id_name(autopilot: str, compass: int, naming: str = "") -> str:
    """The parameter holding compass N's device id: COMPASS_DEV_ID, COMPASS_DEV_ID2, ...
    (ArduPilot), CAL_MAG{N−1}_ID (PX4). 0 means no such compass."""
    if autopilot == ARDUPILOT:
        return mapping.ap_param_names(compass, naming or mapping.AP_NAMING_LEGACY)["DEV_ID"]
    return mapping.px4_param_names(px4_index(compass))["ID"]


def ardupilot_custom_angles(slot: int) -> list[str]:
    return [f"CUST_ROT{slot}_{a}" for a in ("ROLL", "PITCH", "YAW")]


def px4_required(index: int) -> list[str]:
    p = f"CAL_MAG{index}_"
    names = [f"{p}{a}{k}" for k in ("OFF", "SCALE", "ODIAG") for a in "XYZ"]
    # the level adjustment PX4 applies to every magnetometer's rotation (Magnetometer.cpp)
    board = ["SENS_BOARD_X_OFF", "SENS_BOARD_Y_OFF", "SENS_BOARD_Z_OFF"]
    return [*names, p + "ROT", *board, p + "ID"]


#: PX4's board rotation, which turns an internal compass (CAL_MAGn_ROT −1).
PX4_BOARD_ROT = "SENS_BOARD_ROT"


def px4_custom_angles(index: int) -> list[str]:
    return [f"CAL_MAG{index}_{a}" for a in ("ROLL", "PITCH", "YAW")]


def px4_has_custom_angles(values: dict[str, float], index: int) -> bool:
    """Whether ``values`` hold CAL_MAGn_ROLL/PITCH/YAW: only firmware that has them takes a
    custom rotation (CAL_MAGn_ROT = 100)."""
    return all(n in values for n in px4_custom_angles(index))


#: read(name, tries) → the decoded parameter; raises MavlinkTimeoutError when the vehicle
#: never answered (tries None: the reader's default).
ReadParam = Callable[[str, "int | None"], "params.ParamEntry"]


def read_optional(read: ReadParam, name: str, tries: int | None = None) -> params.ParamEntry | None:
    """``read(name, tries)``, or None for a parameter that may not exist (no answer)."""
    try:
        return read(name, tries)
    except MavlinkTimeoutError:
        return None


def read_compass_params(
    read: ReadParam, autopilot: str, compass: int, *, custom_angles: bool = False
) -> CompassParams:
    """The compass parameters in force, read one by one with ``read(name, tries)`` (a
    decoded ParamEntry; MavlinkTimeoutError when the vehicle never answered).

    ArduPilot: the naming is detected first (COMPASS_OFS_X, else COMPASS1_OFS_X); the custom
    angles of the slots in use are read when CUST_ROT_ENABLE is 1. PX4: the CAL_MAG{N−1}
    set, and its custom angles when ``custom_angles``. AutopilotError lists what is missing,
    and refuses a compass whose device id is 0 (not on this vehicle: its stream would carry
    zeros), naming the compasses that are."""
    check_compass(compass)
    values: dict[str, float] = {}
    types: dict[str, int] = {}
    missing: list[str] = []
    notes: list[str] = []

    def get(names: list[str], tries: int | None = None, required: bool = True) -> None:
        for name in names:
            if name in values:
                continue
            e = read_optional(read, name, tries)
            if e is None:
                if required:
                    missing.append(name)
                continue
            values[name] = e.value
            types[name] = e.param_type if e.param_type is not None else params.REAL32

    if autopilot == ARDUPILOT:
        naming = _ardupilot_naming(read)
        get(ardupilot_required(compass, naming))
        get(ardupilot_optional(compass, naming), OPTIONAL_READ_TRIES, required=False)
        if values.get("CUST_ROT_ENABLE", 0.0) != 0.0:
            get([a for s in (1, 2) for a in ardupilot_custom_angles(s)], OPTIONAL_READ_TRIES, False)
        _raise_missing(missing, autopilot, compass)
        _refuse_absent(read, values, autopilot, compass, naming)
        external = values[mapping.ap_external_name(compass, naming)] != 0.0
        orient = int(values[mapping.ap_param_names(compass, naming)["ORIENT"]])
        if external and orient in mapping.AP_CUSTOM_ORIENT:
            angles = ardupilot_custom_angles(orient - 100)
            if any(a not in values for a in angles):
                raise AutopilotError(
                    f"ArduPilot compass {compass} uses custom rotation {orient} but "
                    f"{', '.join(angles)} could not be read: check the link and try again"
                )
        return CompassParams(autopilot, compass, values, types, naming, external, tuple(notes))
    index = px4_index(compass)
    get(px4_required(index))
    if custom_angles:
        get(px4_custom_angles(index), OPTIONAL_READ_TRIES, required=False)
    _raise_missing(missing, autopilot, compass)
    _refuse_absent(read, values, autopilot, compass, "")
    external = values[f"CAL_MAG{index}_ROT"] >= 0
    if not external:
        # PX4 turns an internal compass with the board rotation instead of CAL_MAGn_ROT
        get([PX4_BOARD_ROT], OPTIONAL_READ_TRIES, required=False)
    return CompassParams(autopilot, compass, values, types, "", external, tuple(notes))


def _ardupilot_naming(read: ReadParam) -> str:
    """AP_NAMING_LEGACY when the vehicle answers COMPASS_OFS_X, per-instance when it answers
    COMPASS1_OFS_X; both are asked alternately, so a lossy link decides as soon as either
    answers."""
    legacy = mapping.ap_param_names(1, mapping.AP_NAMING_LEGACY)["OFS_X"]
    per_instance = mapping.ap_param_names(1, mapping.AP_NAMING_PER_INSTANCE)["OFS_X"]
    for _ in range(OPTIONAL_READ_TRIES):
        if read_optional(read, legacy, 1) is not None:
            return mapping.AP_NAMING_LEGACY
        if read_optional(read, per_instance, 1) is not None:
            return mapping.AP_NAMING_PER_INSTANCE
    raise AutopilotError(
        f"ArduPilot: neither {legacy} nor {per_instance} answered: the vehicle has no compass "
        "parameters, or the link loses every reply (check it and try again)"
    )


def _refuse_absent(
    read: ReadParam, values: dict[str, float], autopilot: str, compass: int, naming: str
) -> None:
    """AutopilotError when compass N's device id is 0: no such compass on this vehicle. The
    device ids of the others are read (only then) to say which compasses it has."""
    name = dev_id_name(autopilot, compass, naming)
    if values[name] != 0.0:
        return
    present = []
    for k in range(1, MAX_COMPASSES + 1):
        if k == compass:
            continue
        e = read_optional(read, dev_id_name(autopilot, k, naming), OPTIONAL_READ_TRIES)
        if e is not None and e.value != 0.0:
            present.append(k)
    if present:
        which = " and ".join(map(str, present))
        has = f"this vehicle has compass{'es' if len(present) > 1 else ''} {which}"
        hint = f"use --compass {present[0]}"
    else:
        has, hint = "this vehicle reports no compass", "check its compass wiring and set-up"
    raise AutopilotError(
        f"{AUTOPILOT_NAMES[autopilot]} compass {compass} is absent ({name} = 0); {has}: "
        f"{hint}; nothing was read or written"
    )


def _raise_missing(missing: list[str], autopilot: str, compass: int) -> None:
    if missing:
        raise AutopilotError(
            f"{AUTOPILOT_NAMES[autopilot]} compass {compass}: no answer for parameter(s) "
            f"{', '.join(missing)}: this firmware does not have them (another compass number?) "
            "or the link lost every reply; nothing was written"
        )


# ----------------------------------------------------------------- stream samples
def acc_mg_to_si(a_mg: np.ndarray) -> np.ndarray:
    """Accelerometer mG of standard gravity → m/s²."""
    return np.asarray(a_mg, dtype=float) * (STANDARD_GRAVITY / 1000.0)


#: The stream's gyroscope unit: mrad/s per rad/s.
GYRO_MRAD_PER_RAD = 1000.0


def gyro_mrad_to_si(w_mrad: np.ndarray) -> np.ndarray:
    """Gyroscope mrad/s → rad/s."""
    return np.asarray(w_mrad, dtype=float) / GYRO_MRAD_PER_RAD


def mag_wire_to_unit(m_mG: np.ndarray, autopilot: str) -> np.ndarray:
    """The magnetometer fields' mG in the autopilot's unit (ArduPilot mG, PX4 gauss)."""
    return np.asarray(m_mG, dtype=float) * UNIT_PER_MG[autopilot]


def session_mag(wire_mG: np.ndarray, cp: CompassParams) -> np.ndarray:
    """The session's magnetometer (N, 3) from the streamed field (N, 3) mG (module docstring):
    ArduPilot ``(M·s)⁻¹ B − OFS`` in mG, PX4 the raw field in gauss."""
    m = mag_wire_to_unit(wire_mG, cp.autopilot)
    if cp.autopilot == ARDUPILOT:
        return mapping.ardupilot_undo_correct_field(m, cp.values, cp.compass, cp.naming)
    return m


def onboard_correction(
    y: np.ndarray, cp: CompassParams, recorded: dict[str, float] | None = None
) -> np.ndarray:
    """What the vehicle makes of a session's magnetometer y (N, 3) with the parameters in
    force now (``cp``): ArduPilot ``M·s·(R_now R_recᵀ y + OFS)`` (R_rec: the rotation in
    force when y was recorded, from ``recorded``; an internal compass is not turned by its
    parameters), PX4 ``L · Rot · S · (y − off)`` (L: SENS_BOARD_X/Y/Z_OFF) with S and off as
    a booted PX4 applies them (:func:`magcal.autopilot.mapping.px4_as_applied`)."""
    y = np.atleast_2d(np.asarray(y, dtype=float))
    if cp.autopilot == ARDUPILOT:
        if cp.external:
            if recorded is None:
                raise AutopilotError(
                    "the session does not record the compass parameters it was recorded with"
                )
            R_rec = mapping.ardupilot_rotation(recorded, cp.compass, cp.naming)
            return mapping.ardupilot_correct(y @ R_rec, cp.values, cp.compass, cp.naming)
        return mapping.ardupilot_correct_field(y, cp.values, cp.compass, cp.naming)
    v = cp.values
    L = rotations.euler_deg_to_matrix(
        v["SENS_BOARD_X_OFF"], v["SENS_BOARD_Y_OFF"], v["SENS_BOARD_Z_OFF"]
    )
    # as a booted vehicle applies them: a vector within 0.01 of its reset value is not
    return mapping.px4_correct(y, v, px4_index(cp.compass), as_applied=True) @ L.T


def mag_frame_text(cp: CompassParams) -> str:
    """The frame of the session's magnetometer, for its metadata."""
    if cp.autopilot == ARDUPILOT:
        which = "COMPASS_ORIENT" if cp.external else "AHRS_ORIENTATION and the board's rotation"
        return (
            "ArduPilot rotate_field output, y = R_old·raw (the rotation in force: "
            f"{which}), corrected field with OFS and DIA/ODI/SCALE undone"
        )
    return "PX4 sensor_mag: raw sensor frame (driver's rotation), before CAL_MAGn_* (Rot0 = I)"


@dataclass(frozen=True)
class TimeBase:
    """How a stream message is stamped: ``field`` in ticks of ``tick_s`` seconds, wrapping at
    ``modulus`` ticks (a 32-bit counter) or never (None)."""

    field: str
    tick_s: float
    modulus: int | None


#: RAW_IMU/HIGHRES_IMU time_usec may come from a 32-bit micros() (older ArduPilot).
TIME_BASES = {
    "RAW_IMU": TimeBase("time_usec", 1e-6, 2**32),
    "HIGHRES_IMU": TimeBase("time_usec", 1e-6, 2**32),
    "SCALED_IMU": TimeBase("time_boot_ms", 1e-3, 2**32),
    "SCALED_IMU2": TimeBase("time_boot_ms", 1e-3, 2**32),
    "SCALED_IMU3": TimeBase("time_boot_ms", 1e-3, 2**32),
}
#: A backward step that a counter wrap turns into a forward step of at most this much is a
#: wrap; any other backward step is a restart of the vehicle's clock (a reboot), s.
MAX_WRAP_STEP_S = 60.0
#: A time step longer than this many nominal (median) steps is a gap: messages were lost.
GAP_STEPS = 1.5


@dataclass(frozen=True)
class Timeline:
    """t : (N,) s from the first sample, strictly increasing over the kept samples (NaN for
    dropped ones); keep : (N,) bool (False: a repeated timestamp); wraps, resets : counts;
    missing : samples missing by the time steps (steps over GAP_STEPS median steps)."""

    t: np.ndarray
    keep: np.ndarray
    wraps: int
    resets: int
    missing: int


def tick_step(previous: int, tick: int, base: TimeBase) -> int:
    """Ticks from ``previous`` to ``tick``: a backward step that ``base.modulus`` explains as a
    counter wrap within MAX_WRAP_STEP_S is that wrap's forward step; any other backward step
    stays negative (a clock restart)."""
    step = tick - previous
    if step < 0 and base.modulus is not None:
        if 0 < step + base.modulus <= MAX_WRAP_STEP_S / base.tick_s:
            step += base.modulus
    return step


def unwrap_times(ticks: np.ndarray, base: TimeBase, host_s: np.ndarray) -> Timeline:
    """Monotonic session time from a stream's timestamps (pure).

    ticks : (N,) int, the messages' timestamp field; host_s : (N,) host receive times, s.
    A backward step that ``base.modulus`` explains as a counter wrap within MAX_WRAP_STEP_S is
    one; any other backward step is a clock restart (a reboot): the time then continues from
    the previous sample by the host's receive interval. A repeated timestamp (an autopilot
    that sends faster than the value changes, or PX4's ms resolution) drops the sample.
    """
    ticks = np.asarray(ticks, dtype=np.int64)
    host_s = np.asarray(host_s, dtype=float)
    n = ticks.size
    t = np.full(n, np.nan)
    keep = np.zeros(n, dtype=bool)
    wraps = resets = 0
    if n == 0:
        return Timeline(t, keep, 0, 0, 0)
    t[0], keep[0] = 0.0, True
    last = 0  # index of the last kept sample
    for i in range(1, n):
        raw = int(ticks[i] - ticks[last])
        step = tick_step(int(ticks[last]), int(ticks[i]), base)
        wraps += raw < 0 <= step
        if step == 0:
            continue
        if step < 0:
            resets += 1
            dt = max(host_s[i] - host_s[last], base.tick_s)
        else:
            dt = step * base.tick_s
        t[i] = t[last] + dt
        keep[i] = True
        last = i
    kept = t[keep]
    missing = 0
    if kept.size > 2:
        steps = np.diff(kept)
        median = float(np.median(steps))
        if median > 0:
            big = steps > GAP_STEPS * median
            missing = int(np.sum(np.rint(steps[big] / median) - 1))
    return Timeline(t, keep, wraps, resets, missing)
