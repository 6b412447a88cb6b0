# SPDX-License-Identifier: Apache-2.0
"""Undo the autopilot's on-board compass correction along a log's parameter timeline.

ArduPilot logs (DataFlash ``MAG``) and streams (``RAW_IMU``, ``SCALED_IMU2/3``) the
*corrected* field. ``libraries/AP_Compass/AP_Compass_Logging.cpp`` writes
``get_field(i)``, ``get_offsets(i)`` and ``get_motor_offsets(i)``, each cast to ``int16_t``
(whole mG, truncated towards zero); ``AP_Compass_Backend::accumulate_sample`` makes that field
as ``rotate_field`` (board and ``COMPASS_ORIENTn`` rotation) then ``correct_field``:
``mag = M · s · (mag + OFS) + motor_offset`` (checked at commit 20172681; the motor
offset is added *after* the matrix there). Here only ``correct_field`` is undone
(:func:`magcal.autopilot.mapping.ardupilot_undo_correct_field`, after subtracting the logged
motor offset): the result stays in the frame ``rotate_field`` gave it, ``y = R_old · raw``,
which is what :func:`~magcal.autopilot.mapping.to_ardupilot` takes (with ``R_old`` the
rotation in force) and what ``magcal collect`` records. That frame is also the only one that
can be recovered for an internal compass, whose rotation (``AHRS_ORIENTATION`` and the
board's own) is not in the compass parameters.

PX4's ``vehicle_magnetometer`` topic is ``L · Rot · S · (raw − off)`` (L: the board level
adjustment); undoing it gives the raw sensor-frame field (``Rot0 = I`` for
:func:`~magcal.autopilot.mapping.to_px4`).

A change of parameters mid-log is honoured: each sample is undone with the parameters in
force at its time, and the samples in the :data:`MIXED_WINDOW_S` after a change are dropped
(the autopilot averages several sensor readings into one logged sample, so the first ones
after a change mix old and new corrections).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magcal.autopilot import mapping, rotations, vehicle
from magcal.logs.streams import LogImportError, ParamTimeline

#: Samples this long after a compass-parameter change are dropped, s: ArduPilot averages the
#: readings since its last compass read (10–100 Hz) into one logged field, PX4 publishes
#: within a sensor period; half a second covers both with margin.
MIXED_WINDOW_S = 0.5
#: A logged offset (whole mG, truncated) may differ from the parameter by less than 1 mG;
#: more than this means the offsets in use were not the parameters the log recorded.
LOGGED_OFFSET_TOLERANCE_MG = 1.0 + 1e-6

# PX4's CAL_MAGn_* names are mapping.py's (one place for them).
px4_param_names = mapping.px4_param_names


@dataclass(frozen=True)
class Undone:
    """The raw field and which samples survived.

    mag            : (K, 3) float, raw field (see the module docstring for the frame)
    keep           : (N,) bool over the input samples; ``mag`` holds the kept ones
    notes          : remarks for the user
    suspect        : (K,) bool, samples whose logged offsets contradict the parameters
    suspect_reason : why such a sample cannot be used (for the error if one is imported)
    param_compass  : the parameter set used (ArduPilot: 1-based compass of COMPASS_OFSn_X;
                     PX4: n of CAL_MAGn_*)
    naming         : ArduPilot's parameter naming (mapping.AP_NAMING_*); PX4: ""
    meta           : session metadata about the correction (e.g. one taken as the identity)
    """

    mag: np.ndarray
    keep: np.ndarray
    notes: tuple[str, ...]
    suspect: np.ndarray
    suspect_reason: str
    param_compass: int
    naming: str = ""
    meta: dict[str, str] = field(default_factory=dict)


#: The session's ``mag_frame`` for PX4's raw field (as ``magcal collect`` describes it).
PX4_RAW_FRAME = "PX4 sensor_mag: raw sensor frame (driver's rotation), before CAL_MAGn_* (Rot0 = I)"


def ardupilot_frame(motor: bool) -> str:
    """The session's ``mag_frame`` for ArduPilot data (as ``magcal collect`` describes it)."""
    undone = "OFS, DIA/ODI/SCALE and motor compensation" if motor else "OFS and DIA/ODI/SCALE"
    return (
        "ArduPilot rotate_field output, y = R_old·raw (the rotation in force: COMPASS_ORIENT "
        "for an external compass, AHRS_ORIENTATION and the board's rotation for an internal "
        f"one), corrected field with {undone} undone"
    )


def ardupilot_naming(names: set[str]) -> str:
    """The log's ArduPilot parameter naming: per-instance (COMPASS1_OFS_X) when only that is
    there, else the legacy one (COMPASS_OFS_X, COMPASS_OFS2_X)."""
    if "COMPASS1_OFS_X" in names and "COMPASS_OFS_X" not in names:
        return mapping.AP_NAMING_PER_INSTANCE
    return mapping.AP_NAMING_LEGACY


def ardupilot_required(compass: int, naming: str = mapping.AP_NAMING_LEGACY) -> list[str]:
    """The parameters whose values ``correct_field`` needs for ``compass`` (1-based state
    index). COMPASS_SCALEn is optional (older firmware has none: no scaling)."""
    n = mapping.ap_param_names(compass, naming)
    return [n[f"{k}_{a}"] for k in ("OFS", "DIA", "ODI") for a in "XYZ"]


def ardupilot_recorded(compass: int, naming: str, names: set[str]) -> tuple[str, ...]:
    """The compass parameters a session records (those the log has): the same set
    ``magcal collect`` records, which ``flash`` and ``verify`` read back."""
    wanted = vehicle.ardupilot_required(compass, naming) + vehicle.ardupilot_optional(
        compass, naming
    )
    for slot in (1, 2):
        wanted += vehicle.ardupilot_custom_angles(slot)
    return tuple(dict.fromkeys(n for n in wanted if n in names))


def flight_recorded_ardupilot(compass: int, naming: str, names: set[str]) -> tuple[str, ...]:
    """What a flight session records of ``compass`` (1-based state index): the parameters
    :func:`ardupilot_recorded` gives, its motor compensation (COMPASS_MOTn_X/Y/Z), whether it
    is used and its priority, and the shared motor-compensation settings; those the log has."""
    k = "" if compass == 1 else str(compass)
    if naming == mapping.AP_NAMING_PER_INSTANCE:
        motor = [f"COMPASS{compass}_MOT_{a}" for a in "XYZ"] + [f"COMPASS{compass}_USE"]
    else:
        motor = [f"COMPASS_MOT{k}_{a}" for a in "XYZ"] + [f"COMPASS_USE{k}"]
    shared = ["COMPASS_MOTCT", "COMPASS_PMOT_EN", f"COMPASS_PRIO{compass}_ID", "COMPASS_DEC"]
    wanted = [*ardupilot_recorded(compass, naming, names), *motor, *shared]
    return tuple(dict.fromkeys(n for n in wanted if n in names))


def ardupilot_state_index(params: dict[str, float], instance: int) -> int:
    """The parameter set (1-based state index) of logged compass ``instance`` (1-based).

    ArduPilot logs and streams compasses in *priority* order (``get_field(i)`` is
    ``_get_state(Priority(i))`` in AP_Compass.h), while COMPASS_OFS_X, COMPASS_OFS2_X, ...
    belong to the detection order. The two differ when COMPASS_PRIOn_ID lists the device ids
    in another order than COMPASS_DEV_ID, _ID2, _ID3; without those parameters they agree.
    """
    prio = params.get(f"COMPASS_PRIO{instance}_ID")
    if not prio:
        return instance
    for state in (1, 2, 3):
        if params.get(mapping.ap_param_names(state)["DEV_ID"]) == prio:
            return state
    return instance


def _segments(t: np.ndarray, changes: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges [i0, i1) of ``t`` between consecutive change times."""
    cuts = np.searchsorted(t, np.unique(changes), side="left")
    edges = np.concatenate([[0], cuts, [t.size]])
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def _mixed(t: np.ndarray, changes: np.ndarray) -> np.ndarray:
    """(N,) bool: samples within MIXED_WINDOW_S after a change."""
    mixed = np.zeros(t.size, dtype=bool)
    for c in np.unique(changes):
        mixed |= (t > c) & (t <= c + MIXED_WINDOW_S)
    return mixed


def undo_ardupilot(
    source: str,
    t: np.ndarray,
    corrected: np.ndarray,
    params: ParamTimeline,
    instance: int,
    motor: np.ndarray | None = None,
    logged_offsets: np.ndarray | None = None,
    params_complete: bool = False,
    params_note: str = "",
) -> Undone:
    """ArduPilot's ``correct_field`` undone for logged compass ``instance`` (1-based).

    source         : the log's name, for messages
    t              : (N,) s;  corrected : (N, 3) mG, the logged (corrected) field
    params         : the parameters over time
    motor          : (N, 3) mG, logged motor-interference offsets (DataFlash MOX/MOY/MOZ);
                     None when not logged (telemetry: zero while disarmed)
    logged_offsets : (N, 3) mG, the offsets the log says were in use (MAG OfsX/Y/Z); samples
                     where they contradict the parameters are marked ``suspect``
    params_complete: the log holds every parameter the firmware has (DataFlash writes them
                     all when a log opens; a ground station that received every index of
                     PARAM_VALUE). Then soft-iron parameters that are absent do not exist in
                     that firmware (ArduPilot before COMPASS_DIA/ODI): the identity is used
    params_note    : why the parameters may be incomplete, for the error
    returns        : the field after rotate_field, before correct_field, mG
    """
    naming = ardupilot_naming(params.names())
    state = ardupilot_state_index(params.at(float(t[0]) if t.size else 0.0), instance)
    required = ardupilot_required(state, naming)
    missing = [n for n in required if n not in params.names()]
    names = mapping.ap_param_names(state, naming)
    # the soft-iron parameters, each with the value correct_field acts as if it had when the
    # firmware has none: diagonal 1, off-diagonal 0
    soft_iron = {names[f"{k}_{a}"]: v for k, v in (("DIA", 1.0), ("ODI", 0.0)) for a in "XYZ"}
    identity = params_complete and bool(missing) and set(missing) <= set(soft_iron)
    if missing and not identity:
        raise LogImportError(
            f"{source} has no value for {', '.join(missing)}: without the compass "
            "parameters in force its corrected field cannot be undone; "
            + (
                params_note
                or "log the parameters (ArduPilot writes PARM messages when a log opens; a "
                "ground station fetches PARAM_VALUE when it connects)"
            )
        )
    meta: dict[str, str] = {}
    defaults = {n: v for n, v in soft_iron.items() if n in missing}
    if identity:
        meta["onboard_soft_iron"] = (
            f"the firmware has no {', '.join(missing)} (its log holds every parameter and "
            "not these): its correction was the offsets alone, so the soft-iron matrix was "
            "taken as the identity"
        )
    watched = set(required) | {names["SCALE"]}
    changes = params.change_times(watched)
    mixed = _mixed(t, changes)
    mag = np.empty_like(np.asarray(corrected, dtype=float))
    suspect = np.zeros(t.size, dtype=bool)
    notes: list[str] = []
    if state != instance:
        notes.append(
            f"compass {instance} (priority order) uses the parameter set of compass {state} "
            "(COMPASS_PRIOn_ID)"
        )
    for i0, i1 in _segments(t, changes):
        p = defaults | params.at(float(t[i0]))
        p.setdefault(names["SCALE"], 0.0)  # no COMPASS_SCALE (older firmware): no scaling
        field = np.asarray(corrected[i0:i1], dtype=float)
        if motor is not None:
            field = field - motor[i0:i1]
        if logged_offsets is not None:
            suspect[i0:i1] = _offsets_disagree(logged_offsets[i0:i1], p, names)
        mag[i0:i1] = mapping.ardupilot_undo_correct_field(field, p, state, naming)
    if changes.size:
        notes.append(
            f"compass parameters changed {changes.size} time(s) in the log; each sample was "
            f"undone with those in force, and {int(mixed.sum())} sample(s) within "
            f"{MIXED_WINDOW_S} s after a change were dropped"
        )
    reason = (
        f"compass {instance} was corrected with other offsets than {names['OFS_X']}/_Y/_Z in "
        "force (the logged OfsX/Y/Z differ): they changed without a parameter record "
        "(in-flight learning, COMPASS_LEARN), so the correction cannot be undone there"
    )
    return Undone(mag[~mixed], ~mixed, tuple(notes), suspect[~mixed], reason, state, naming, meta)


def _offsets_disagree(logged: np.ndarray, p: dict[str, float], names: dict[str, str]) -> np.ndarray:
    """(N,) bool: the logged offsets are not the parameters' (truncated like the log's
    ``int16_t`` cast, so a fraction of a mG is no disagreement)."""
    ofs = np.array([p[names[f"OFS_{a}"]] for a in "XYZ"])
    diff = np.abs(np.asarray(logged, dtype=float) - np.trunc(ofs))
    return (diff > LOGGED_OFFSET_TOLERANCE_MG).any(axis=1)


def px4_required(index: int) -> list[str]:
    """CAL_MAGn_* parameters PX4's correction needs for calibration slot ``index`` (0-based)."""
    n = px4_param_names(index)
    return [n[k] for k in ("XOFF", "YOFF", "ZOFF", "XSCALE", "YSCALE", "ZSCALE")] + [
        n[k] for k in ("XODIAG", "YODIAG", "ZODIAG", "ROT")
    ]


def px4_recorded(index: int, names: set[str]) -> tuple[str, ...]:
    """The CAL_MAGn_* parameters a session records (those the log has), as ``magcal
    collect`` records them."""
    wanted = vehicle.px4_required(index) + vehicle.px4_custom_angles(index)
    wanted += [f"CAL_MAG{index}_ID", f"CAL_MAG{index}_PRIO", "SENS_BOARD_ROT"]
    return tuple(dict.fromkeys(n for n in wanted if n in names))


def flight_recorded_px4(index: int, names: set[str]) -> tuple[str, ...]:
    """What a flight session records of CAL_MAG``index``: :func:`px4_recorded`'s parameters,
    its motor compensation (CAL_MAGn_XCOMP/YCOMP/ZCOMP) and the compensation type; those the
    log has."""
    wanted = [*px4_recorded(index, names), *(f"CAL_MAG{index}_{a}COMP" for a in "XYZ")]
    wanted.append("CAL_MAG_COMP_TYP")
    return tuple(dict.fromkeys(n for n in wanted if n in names))


def px4_calibration_index(params: dict[str, float], device_id: int) -> int | None:
    """The n of the CAL_MAGn_ID equal to ``device_id``, or None."""
    for n in range(8):
        if params.get(f"CAL_MAG{n}_ID") == device_id:
            return n
    return None


def px4_level_adjustment(params: dict[str, float]) -> np.ndarray:
    """(3, 3) PX4's board level adjustment from SENS_BOARD_X/Y/Z_OFF (degrees; identity when
    not logged): newer PX4 applies it to every magnetometer's rotation
    (``Magnetometer::set_rotation``: ``Dcmf(GetSensorLevelAdjustment()) * get_rot_matrix``)."""
    angles = [params.get(f"SENS_BOARD_{a}_OFF", 0.0) for a in "XYZ"]
    return rotations.euler_deg_to_matrix(*angles)


def undo_px4(
    source: str,
    t: np.ndarray,
    corrected: np.ndarray,
    params: ParamTimeline,
    index: int,
    params_complete: bool = False,
) -> Undone:
    """PX4's ``L · Rot · S · (raw − off)`` undone with the parameters in force at each time.

    t : (N,) s;  corrected : (N, 3) gauss (vehicle_magnetometer);  returns raw gauss, sensor
    frame. ``Rot`` is CAL_MAG``index``_ROT, or for an internal magnetometer (ROT = −1) the
    board rotation SENS_BOARD_ROT; ``L`` is :func:`px4_level_adjustment`. With
    ``params_complete`` (a ULog holds every parameter), absent off-diagonal terms
    (CAL_MAGn_xODIAG, PX4 before 1.12) are zero: that firmware has none.
    """
    required = px4_required(index)
    missing = [n for n in required if n not in params.names()]
    names = px4_param_names(index)
    odiag = {names[f"{a}ODIAG"] for a in "XYZ"}
    defaults = {n: 0.0 for n in missing if n in odiag} if params_complete else {}
    missing = [n for n in missing if n not in defaults]
    if missing:
        raise LogImportError(
            f"{source} has no value for {', '.join(missing)}: without the calibration in force "
            "the corrected field cannot be undone; log sensor_mag (raw) instead"
        )
    rot = px4_param_names(index)["ROT"]
    watched = set(required) | {"SENS_BOARD_ROT"} | {f"SENS_BOARD_{a}_OFF" for a in "XYZ"}
    changes = params.change_times(watched)
    mixed = _mixed(t, changes)
    mag = np.empty_like(np.asarray(corrected, dtype=float))
    for i0, i1 in _segments(t, changes):
        p = defaults | params.at(float(t[i0]))
        if p[rot] < 0:
            if "SENS_BOARD_ROT" not in p:
                raise LogImportError(
                    f"{source}: magnetometer calibration {index} is an internal one ({rot} = "
                    "-1), rotated with the board (SENS_BOARD_ROT), which the log does not hold; "
                    "log the raw sensor_mag topic instead"
                )
            p[rot] = p["SENS_BOARD_ROT"]
        # row vectors: c @ L is Lᵀ c
        field = np.asarray(corrected[i0:i1], dtype=float) @ px4_level_adjustment(p)
        # as PX4 applies them after a boot: a vector within 0.01 of its reset value is not
        mag[i0:i1] = mapping.px4_uncorrect(field, p, index, as_applied=True)
    notes = []
    if changes.size:
        notes.append(
            f"CAL_MAG{index} parameters changed {changes.size} time(s); each sample was undone "
            f"with those in force, and {int(mixed.sum())} sample(s) right after a change dropped"
        )
    keep = ~mixed
    return Undone(mag[keep], keep, tuple(notes), np.zeros(int(keep.sum()), bool), "", index)
