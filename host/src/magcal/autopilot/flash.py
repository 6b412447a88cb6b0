# SPDX-License-Identifier: Apache-2.0
"""Writing a calibration to an ArduPilot or PX4 vehicle: plan, back up, write, confirm.

1. **Plan** (:func:`plan_flash`, pure): the result's ``D⁻¹``, ``o`` in the autopilot's unit,
   times the local field strength, mapped with :func:`magcal.autopilot.mapping.to_ardupilot`
   or :func:`~magcal.autopilot.mapping.to_px4` (polar decomposition; enumerated rotation, or a
   custom one when allowed; a rotation that cannot be represented is reported with the
   heading error of leaving it out). Limits are checked there: nothing is written when a
   value is refused. The writes are ordered so that no intermediate state uses half a
   rotation: ArduPilot's CUST_ROT_ENABLE (when set to 1) and custom angles first, the
   compass's rotation last (CUST_ROT_ENABLE when set to 0 after it).
2. **Back up** (:func:`back_up`): every parameter the plan touches is read from the vehicle
   and saved to a new QGroundControl ``.params`` file (with a Mission Planner ``.parm`` twin)
   *before anything is written*. ArduPilot hides CUST_ROTn_* while CUST_ROT_ENABLE is 0: they
   are not in the backup, and restoring CUST_ROT_ENABLE = 0 hides them again.
3. **Write and confirm** (:func:`write_and_confirm`): PARAM_SET, then the vehicle's
   PARAM_VALUE echo must carry the value (float32 equality; integers exact, PX4's bytewise
   encoding decoded); a lost or different echo is retried, up to PARAM_WRITE_TRIES sends per
   parameter. The outcome lists every parameter confirmed or not.

What holds after a failure: PARAM_SET sets a whole value, so each parameter holds either its
old value (in the backup) or the new one; the ones not confirmed are named with the last value
the vehicle echoed (if any). ``magcal flash --restore BACKUP`` writes the backup back the same
way (after backing up the values it replaces).

Some changes take effect only after a reboot (:attr:`Plan.reboot_reasons`): ArduPilot builds
a custom rotation's matrix when it is first used and marks CUST_ROT_ENABLE "reboot required";
PX4's Magnetometer takes a new offset, scale or off-diagonal only when it differs from the one
in use by more than 0.01 (:data:`magcal.autopilot.mapping.PX4_UPDATE_THRESHOLD`). A vector
within 0.01 of its reset value (offset 0, scale 1, off-diagonal 0) is never applied, not even
after a reboot: the plan says so with the heading error it costs
(:attr:`Plan.never_applied`), and does not count it as a reason to reboot.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from magcal.autopilot import mapping, params, rotations, vehicle, wmm
from magcal.autopilot.connection import Autopilot
from magcal.errors import MagcalError
from magcal.io.result import CalibrationResult, CompassCalibration, MotorInterference

log = logging.getLogger(__name__)

#: PARAM_SET sends per parameter before it is reported unconfirmed.
PARAM_WRITE_TRIES = 10
#: After this many parameters in a row without a single echo the link is taken for dead and
#: the remaining parameters are not sent (they keep their old values).
DEAD_LINK_PARAMS = 3
PX4_UPDATE_THRESHOLD = mapping.PX4_UPDATE_THRESHOLD


class AutopilotFlashError(MagcalError):
    """Writing the parameters failed; ``unconfirmed`` lists them, ``backup_path`` the backup."""

    def __init__(
        self,
        message: str,
        unconfirmed: tuple[Unconfirmed, ...] = (),
        backup_path: Path | None = None,
    ) -> None:
        super().__init__(message)
        self.unconfirmed = unconfirmed
        self.backup_path = backup_path


class WriteInterrupted(MagcalError):
    """The write phase stopped part-way: Ctrl-C (``by_user``), a link error or an OS error
    (``cause``). The message accounts for every parameter: confirmed, unconfirmed, the one
    in flight (old or new value) and the ones never sent (old values)."""

    def __init__(self, account: str, cause: BaseException) -> None:
        self.by_user = isinstance(cause, KeyboardInterrupt)
        what = "Ctrl-C" if self.by_user else f"{type(cause).__name__}: {cause}"
        super().__init__(f"interrupted by {what} while writing; {account}")
        self.account = account
        self.cause = cause


@dataclass(frozen=True)
class Unconfirmed:
    """A parameter whose new value was not confirmed: wanted, the last value echoed (None when
    no echo came), and whether it was sent at all (not after the link was taken for dead:
    then it certainly holds its old value)."""

    name: str
    wanted: float
    echoed: float | None
    sent: bool = True


@dataclass(frozen=True)
class Plan:
    """What flash will write, in order, and what it means.

    writes : the parameters to set (value as the vehicle will hold it, MAV_PARAM_TYPE)
    unchanged : parameters of the mapping the vehicle already holds (not written)
    mapped : the mapping's output (notes, residual rotation, its heading cost)
    field : the field strength used; unit : the autopilot's unit
    reboot_reasons : why a reboot is needed before every value is in use (empty: none)
    never_applied : PX4 parameter groups ("OFF", "SCALE", "ODIAG") the vehicle will not use,
        even after a reboot (within PX4_UPDATE_THRESHOLD of the reset value); notes say why
    """

    autopilot: str
    compass: int
    writes: tuple[params.ParamEntry, ...]
    unchanged: tuple[params.ParamEntry, ...]
    mapped: mapping.AutopilotParams
    field: wmm.Field
    unit: str
    reboot_reasons: tuple[str, ...] = field(default_factory=tuple)
    never_applied: tuple[str, ...] = field(default_factory=tuple)

    @property
    def all_entries(self) -> tuple[params.ParamEntry, ...]:
        return order_writes(self.autopilot, self.writes + self.unchanged, {})


# ------------------------------------------------------------------------------ units
def result_in_unit(
    result: CalibrationResult, unit: str, flag_unit: str | None, where: str
) -> tuple[np.ndarray, np.ndarray, str]:
    """(D_inv, o) of ``result`` converted to the autopilot's ``unit``, and the result's unit.

    The result's unit is its ``mag_unit`` (the session's ``# mag_unit:``) or ``--mag-unit``;
    a known magnetic unit is converted (y_ap = c·y: D_inv/c, c·o), anything else refused."""
    stored = result.extra.get("mag_unit")
    known = wmm.canonical_unit(stored) if isinstance(stored, str) else None
    flag = wmm.canonical_unit(flag_unit) if flag_unit else None
    if flag_unit and flag is None:
        raise MagcalError(f"flash: --mag-unit {flag_unit!r} is not a magnetic unit (mG, gauss, uT)")
    if flag and known and flag != known:
        raise MagcalError(
            f"flash: {where} says its magnetometer unit is {stored!r} but --mag-unit is "
            f"{flag_unit!r}; nothing was written: drop --mag-unit or give the result's unit"
        )
    res_unit = flag or known
    if res_unit is None:
        said = f"mag_unit {stored!r}" if stored is not None else "no mag_unit"
        raise MagcalError(
            f"flash: {where} has {said}, so the unit of its D and o is unknown; nothing was "
            f"written: calibrate a session recorded by magcal collect --mavlink (it says "
            f"{unit}), or pass --mag-unit"
        )
    c = wmm.convert(1.0, res_unit, unit)
    D_inv = np.linalg.inv(result.D) / c
    return D_inv, c * np.asarray(result.o, dtype=float), res_unit


def calibration_in_unit(cal: CompassCalibration, factor: float) -> CompassCalibration:
    """``cal`` for ``y_ap = factor·y`` (a unit change, :func:`result_in_unit`'s c): D, o and the
    motor vector times ``factor``."""
    motor = cal.motor
    if motor is not None:
        motor = dataclasses.replace(motor, vector=factor * np.asarray(motor.vector, dtype=float))
    return dataclasses.replace(
        cal,
        D=factor * np.asarray(cal.D, dtype=float),
        o=factor * np.asarray(cal.o, dtype=float),
        motor=motor,
    )


# ------------------------------------------------------------------------------ planning
def order_writes(
    autopilot: str, entries: tuple[params.ParamEntry, ...], current: dict[str, float]
) -> tuple[params.ParamEntry, ...]:
    """The order to write ``entries`` in (module docstring, step 1)."""

    def rank(e: params.ParamEntry) -> int:
        n = e.name
        if autopilot == vehicle.ARDUPILOT:
            if n == "CUST_ROT_ENABLE":
                return 0 if e.value != 0 else 4
            if n.startswith("CUST_ROT"):
                return 1
            if "ORIENT" in n:
                return 3
            return 2
        if n.endswith(("_ROLL", "_PITCH", "_YAW")):
            return 1
        return 3 if n.endswith("_ROT") else 2

    return tuple(sorted(entries, key=rank))


def _type_of(name: str, types: dict[str, int]) -> int:
    if name in types:
        return types[name]
    # parameters not read yet (ArduPilot's hidden CUST_ROTn_*): their declared types
    if name in ("CUST_ROT_ENABLE", mapping.AP_MOTCT_NAME) or "ORIENT" in name:
        return params.INT8
    if name == mapping.PX4_COMP_TYP_NAME:
        return params.INT32
    if name.endswith("_ROT"):
        return params.INT32
    return params.REAL32


def _ardupilot_slot(cp: vehicle.CompassParams) -> tuple[int | None, bool]:
    """(custom rotation slot to use or None, whether reusing it needs a reboot).

    A slot used by AHRS_ORIENTATION or another compass is never taken; a slot nobody uses
    is preferred (its matrix is built at first use); the slot this compass already uses is
    reused only when the other one is taken (its angles then apply after a reboot)."""
    v = cp.values
    own_name = mapping.ap_param_names(cp.compass, cp.naming)["ORIENT"]
    own = int(v.get(own_name, 0)) if cp.external else None
    others = {int(v.get("AHRS_ORIENTATION", 0))}
    for k in range(1, vehicle.MAX_COMPASSES + 1):
        name = mapping.ap_param_names(k, cp.naming)["ORIENT"]
        if k != cp.compass and name in v:
            others.add(int(v[name]))
    for slot in (1, 2):
        if 100 + slot not in others and own != 100 + slot:
            return slot, False
    for slot in (1, 2):
        if 100 + slot not in others:
            return slot, True
    return None, False


def require_px4_custom_angles(cp: vehicle.CompassParams) -> None:
    """Refuse a custom rotation on a PX4 without CAL_MAGn_ROLL/PITCH/YAW (older firmware)."""
    index = vehicle.px4_index(cp.compass)
    if not vehicle.px4_has_custom_angles(cp.values, index):
        raise MagcalError(
            f"flash: --px4-custom-rotation, but this PX4 has no CAL_MAG{index}_ROLL/PITCH/YAW "
            "(older firmware): drop the option; nothing was written"
        )


def plan_flash(
    result_D_inv: np.ndarray,
    result_o: np.ndarray,
    cp: vehicle.CompassParams,
    fld: wmm.Field,
    *,
    recorded: dict[str, float] | None = None,
    allow_custom: bool = True,
    rotation_sigma_deg: np.ndarray | None = None,
    motor: MotorInterference | None = None,
) -> Plan:
    """The parameters for a calibration (pure; module docstring, step 1).

    result_D_inv, result_o : the result in the autopilot's unit (:func:`result_in_unit`)
    cp : the compass parameters in force now
    fld : the local field
    recorded : the compass parameters in force when the session was recorded (ArduPilot:
        the rotation the session's y went through; needed for an external compass)
    allow_custom : ArduPilot: may write a custom rotation; PX4: may write CAL_MAGn_ROT = 100
        with CAL_MAGn_ROLL/PITCH/YAW (an external compass of a vehicle without those is
        refused: :func:`require_px4_custom_angles`)
    rotation_sigma_deg : (3,) the result's misalignment σ, degrees (None: unknown): a rotation
        within it of an enumerated one is written as that one
        (:func:`magcal.autopilot.mapping.within_uncertainty`)
    motor : the motor interference in the autopilot's unit (:func:`calibration_in_unit`):
        when kept, the compass's motor compensation and the vehicle's compensation type are
        planned too (ArduPilot COMPASS_MOTn_X/Y/Z and COMPASS_MOTCT, PX4 CAL_MAGn_X/Y/ZCOMP
        and CAL_MAG_COMP_TYP); absent or not kept, they are left as they are."""
    unit = cp.unit
    motor_kw = {}
    if motor is not None and motor.kept:
        motor_kw = {"motor_b": np.asarray(motor.vector, dtype=float), "motor_input": motor.input}
    F = fld.strength(unit)
    incl = (
        fld.inclination_deg if fld.inclination_deg is not None else mapping.DEFAULT_INCLINATION_DEG
    )
    reboot: list[str] = []
    if cp.autopilot == vehicle.ARDUPILOT:
        R_old = np.eye(3)
        if cp.external:
            if recorded is None:
                raise MagcalError(
                    "flash: ArduPilot rotates the session's magnetometer with the compass "
                    "rotation in force when it was recorded (y = R_old·raw), and the result "
                    "does not say which that was: pass --session SESSION.csv (the session the "
                    "result was calibrated from); nothing was written"
                )
            R_old = mapping.ardupilot_rotation(recorded, cp.compass, cp.naming)
        slot, reuse = _ardupilot_slot(cp)
        custom_ok = allow_custom and "CUST_ROT_ENABLE" in cp.values and slot is not None
        mapped = mapping.to_ardupilot(
            result_D_inv,
            result_o,
            F,
            R_old,
            compass=cp.compass,
            naming=cp.naming,
            external=cp.external,
            allow_custom=custom_ok,
            custom_slot=slot or 1,
            offs_max_mG=cp.values.get("COMPASS_OFFS_MAX", mapping.AP_OFFS_MAX_DEFAULT_MG),
            inclination_deg=incl,
            rotation_sigma_deg=rotation_sigma_deg,
            **motor_kw,
        )
        new = dict(mapped.params)
        scale_name = mapping.ap_param_names(cp.compass, cp.naming)["SCALE"]
        if scale_name not in cp.values:
            if new.get(scale_name, 1.0) != 1.0:
                raise MagcalError(
                    f"flash: the calibration needs {scale_name} = {new[scale_name]:.3f}, which "
                    "this firmware does not have (a diagonal outside 0.2–5 otherwise); "
                    "nothing was written: check the field strength and the result's unit"
                )
            new.pop(scale_name, None)
        notes = list(mapped.notes)
        if allow_custom and "CUST_ROT_ENABLE" not in cp.values and cp.external:
            notes.append("this firmware has no custom rotations (no CUST_ROT_ENABLE)")
        if "CUST_ROT_ENABLE" in new and cp.values.get("CUST_ROT_ENABLE", 0.0) == 0.0:
            reboot.append("ArduPilot marks CUST_ROT_ENABLE 'reboot required'")
        if reuse and any(k.startswith(f"CUST_ROT{slot}_") for k in new):
            reboot.append(
                f"compass {cp.compass} already uses custom rotation {100 + slot}, whose matrix "
                "ArduPilot rebuilds only at boot"
            )
        mapped = dataclasses.replace(mapped, params=new, notes=tuple(notes))
    else:
        index = vehicle.px4_index(cp.compass)
        board = None
        if not cp.external:
            if vehicle.PX4_BOARD_ROT not in cp.values:
                raise MagcalError(
                    f"flash: PX4 compass {cp.compass} is internal (CAL_MAG{index}_ROT = -1): PX4 "
                    "turns it with the board rotation SENS_BOARD_ROT, which the vehicle did not "
                    "report; nothing was written"
                )
            # PX4 ignores CAL_MAGn_ROT and CAL_MAGn_ROLL/PITCH/YAW for an internal compass
            board = rotations.px4_matrix(int(cp.values[vehicle.PX4_BOARD_ROT]))
            allow_custom = False
        if allow_custom:
            require_px4_custom_angles(cp)
        # PX4 applies Dcmf(Eulerf(SENS_BOARD_X/Y/Z_OFF)) to every magnetometer's rotation too
        L = rotations.euler_deg_to_matrix(
            cp.values["SENS_BOARD_X_OFF"],
            cp.values["SENS_BOARD_Y_OFF"],
            cp.values["SENS_BOARD_Z_OFF"],
        )
        mapped = mapping.to_px4(
            L.T @ result_D_inv,
            result_o,
            F,
            None,
            index=index,
            allow_custom=allow_custom,
            inclination_deg=incl,
            rotation_sigma_deg=rotation_sigma_deg,
            board_rotation=board,
            **motor_kw,
        )
    entries = []
    unchanged = []
    for name, value in mapped.params.items():
        t = _type_of(name, cp.types)
        e = params.ParamEntry(name, params.held_value(value, t, name), t)
        if name in cp.values and params.confirmed(e.value, cp.values[name], t):
            unchanged.append(e)
        else:
            entries.append(e)
    writes = order_writes(cp.autopilot, tuple(entries), cp.values)
    never: tuple[str, ...] = ()
    if cp.autopilot == vehicle.PX4:
        index = vehicle.px4_index(cp.compass)
        reboot += px4_reboot_reasons(cp.values, writes, index)
        final = dict(cp.values) | {e.name: e.value for e in (*writes, *unchanged)}
        never = mapping.px4_unapplied(final, index)
        if never:
            cost = mapping.px4_unapplied_heading_rms_deg(final, index, F, incl)
            mapped = dataclasses.replace(
                mapped, notes=(*mapped.notes, px4_never_applied_note(final, index, never, cost))
            )
    return Plan(
        cp.autopilot,
        cp.compass,
        writes,
        tuple(unchanged),
        mapped,
        fld,
        unit,
        tuple(reboot),
        never,
    )


def px4_never_applied_note(
    final: dict[str, float], index: int, groups: tuple[str, ...], cost_deg: float
) -> str:
    """The note on vectors PX4 will not use (pure)."""
    p = f"CAL_MAG{index}_"
    parts = []
    for g in groups:
        v = mapping.px4_vector(final, index, g)
        reset = ", ".join(f"{x:g}" for x in mapping.PX4_RESET_VALUES[g])
        parts.append(
            f"{p}X/Y/Z{g} = ({', '.join(f'{x:.4g}' for x in v)}) is within "
            f"{PX4_UPDATE_THRESHOLD} of its reset value ({reset})"
        )
    return (
        f"{'; '.join(parts)}: PX4's Magnetometer never applies such a small change "
        "(Magnetometer.cpp set_offset/set_scale/set_offdiagonal), not even after a reboot, and "
        f"keeps the reset value; that costs {cost_deg:.2f}° RMS heading error"
    )


def px4_reboot_reasons(
    in_force: dict[str, float], writes: tuple[params.ParamEntry, ...], index: int
) -> list[str]:
    """Why PX4 would not use every new value before a reboot, when a reboot would (pure).

    PX4's Magnetometer::ParametersUpdate (each parameter change) takes an offset, scale or
    off-diagonal vector from the parameters only when it differs from the one in use by more
    than PX4_UPDATE_THRESHOLD (mapping.PX4_UPDATE_THRESHOLD). The vehicle is taken to use
    what a boot with ``in_force`` gives (mapping.px4_as_applied). Written one at a time, the
    vectors pass through intermediate states; this replays the writes in order, assuming the
    vehicle acts on each (the worst case), and also flags a whole change within the threshold
    (an update that sees all writes at once). A reason is given only when a reboot puts a
    different vector in use; one within the threshold of its reset value is never applied,
    reboot or not (plan_flash's note)."""
    p = f"CAL_MAG{index}_"
    stored = dict(in_force)
    groups = tuple(mapping.PX4_RESET_VALUES)
    booted = mapping.px4_as_applied(in_force, index)
    in_use = {g: mapping.px4_vector(booted, index, g) for g in groups}
    first = dict(in_use)
    for e in writes:
        stored[e.name] = e.value
        for g in groups:
            candidate = mapping.px4_vector(stored, index, g)
            if np.linalg.norm(candidate - in_use[g]) > PX4_UPDATE_THRESHOLD:
                in_use[g] = candidate
    after_boot = mapping.px4_as_applied(stored, index)
    out = []
    for g in groups:
        final = mapping.px4_vector(after_boot, index, g)
        whole = float(np.linalg.norm(final - first[g]))
        if np.any(in_use[g] != final) or 0.0 < whole <= PX4_UPDATE_THRESHOLD:
            out.append(
                f"PX4 ignores a change of {p}*{g} up to {PX4_UPDATE_THRESHOLD} until a reboot, "
                "and the values written one by one leave the last of them unused"
            )
    return out


# ------------------------------------------------------------------------------ offline
def recorded_compass_params(
    meta: dict[str, str], compass: int, values: dict[str, float]
) -> tuple[vehicle.CompassParams | None, list[str]]:
    """Compass ``compass`` (1-based) as the session's metadata recorded it (pure): the
    CompassParams a vehicle with the parameters ``values`` would report (``values``: the
    session's ``param.NAME`` lines, with what is planned for other compasses already in), or
    None and what is missing: the parameters the correction in force needs (the rotation,
    whether the compass is external, its offsets and scales, its device id)."""
    autopilot = meta.get("autopilot", "")
    if autopilot == vehicle.ARDUPILOT:
        naming = meta.get("param_naming") or mapping.AP_NAMING_LEGACY
        required = vehicle.ardupilot_required(compass, naming)
    else:
        naming = ""
        required = vehicle.px4_required(vehicle.px4_index(compass))
    missing = [n for n in required if n not in values]
    if missing:
        return None, missing
    if values[vehicle.dev_id_name(autopilot, compass, naming)] == 0.0:
        return None, [
            f"compass {compass} itself ({vehicle.dev_id_name(autopilot, compass, naming)} = 0)"
        ]
    if autopilot == vehicle.ARDUPILOT:
        external = values[mapping.ap_external_name(compass, naming)] != 0.0
    else:
        external = values[f"CAL_MAG{vehicle.px4_index(compass)}_ROT"] >= 0
    return vehicle.CompassParams(autopilot, compass, dict(values), {}, naming, external), []


def offline_problems(meta: object) -> list[str]:
    """What a result's ``session_meta`` lacks for a parameter file without a vehicle (pure;
    empty: nothing)."""
    if not isinstance(meta, dict):
        return [
            "it holds no session metadata ('session_meta'): it was not calibrated by magcal "
            "calibrate from a session file"
        ]
    problems = []
    if meta.get("autopilot") not in vehicle.AUTOPILOT_NAMES:
        said = meta.get("autopilot")
        problems.append(
            "its session did not come from an autopilot (no 'autopilot' in session_meta)"
            if said is None
            else f"its session's autopilot {said!r} is neither ardupilot nor px4"
        )
    if not vehicle.params_from_meta({str(k): str(v) for k, v in meta.items()}):
        problems.append(
            "its session recorded none of the compass parameters in force ('param.NAME' "
            "metadata, which magcal collect --mavlink and magcal import write)"
        )
    if meta.get("autopilot") in vehicle.AUTOPILOT_NAMES and "compass" not in meta:
        problems.append("its session does not say which compass it recorded ('compass')")
    return problems


def plan_param_file(
    calibrations: list[CompassCalibration],
    meta: dict[str, str],
    fld: wmm.Field,
    *,
    allow_custom: bool = True,
    where: str = "result",
) -> tuple[Plan, ...]:
    """The plans of every compass in ``calibrations`` (in the autopilot's unit:
    :func:`calibration_in_unit`) for a vehicle whose parameters are the ones the session
    recorded (``meta``'s ``param.NAME``), one after the other: each sees what the ones before
    it plan (a custom rotation slot taken, the motor compensation type set), so that their
    writes together make one consistent set (pure). MagcalError, naming what is missing, when
    the session lacks a compass's parameters; and when the compasses' motor interferences
    follow different inputs (one COMPASS_MOTCT / CAL_MAG_COMP_TYP for the vehicle)."""
    recorded = vehicle.params_from_meta(meta)
    inputs = {c.motor.input for c in calibrations if c.motor is not None and c.motor.kept}
    if len(inputs) > 1:
        parts = ", ".join(
            f"compass {c.compass}: {c.motor.input}"
            for c in calibrations
            if c.motor is not None and c.motor.kept
        )
        raise MagcalError(
            f"flash: {where}'s motor interferences follow different inputs ({parts}), and the "
            "vehicle has one compensation type for every compass (ArduPilot COMPASS_MOTCT, PX4 "
            "CAL_MAG_COMP_TYP); nothing was written: write one compass with --compass N"
        )
    values = dict(recorded)
    plans: list[Plan] = []
    missing: list[str] = []
    for cal in calibrations:
        cp, lacking = recorded_compass_params(meta, cal.compass, values)
        if cp is None:
            missing.append(f"compass {cal.compass}: {', '.join(lacking)}")
            continue
        custom = allow_custom
        if cp.autopilot == vehicle.PX4:
            custom = custom and vehicle.px4_has_custom_angles(
                values, vehicle.px4_index(cal.compass)
            )
        plan = plan_flash(
            np.linalg.inv(cal.D),
            cal.o,
            cp,
            fld,
            recorded=recorded,
            allow_custom=custom,
            motor=cal.motor,
        )
        values |= {e.name: e.value for e in plan.writes}
        plans.append(plan)
    if missing:
        raise MagcalError(
            f"flash: {where}'s session did not record the parameters in force that a parameter "
            f"file without a vehicle needs ({'; '.join(missing)}): calibrate a session that "
            "records them (magcal collect --mavlink, magcal import), or flash with --mavlink URL; "
            "nothing was written"
        )
    return tuple(plans)


def param_file_entries(plans: tuple[Plan, ...]) -> tuple[params.ParamEntry, ...]:
    """Every plan's writes in one file, in write order (the same order a vehicle is written
    in: custom angles first, rotations last)."""
    if not plans:
        return ()
    entries: dict[str, params.ParamEntry] = {}
    for plan in plans:
        entries |= {e.name: e for e in plan.writes}
    return order_writes(plans[0].autopilot, tuple(entries.values()), {})


# ------------------------------------------------------------------------------ backup
def default_backup_path(result_path: Path, autopilot: str, system: int) -> Path:
    """``RESULT.backup-<autopilot>-sys<N>-<UTC time>.params`` next to the result, new."""
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    base = result_path.with_name(f"{result_path.stem}.backup-{autopilot}-sys{system}-{stamp}")
    k = 1
    while True:
        p = Path(f"{base}{'' if k == 1 else f'-{k}'}{params.QGC_SUFFIX}")
        if not p.exists() and not p.with_suffix(params.PARM_SUFFIX).exists():
            return p
        k += 1


@dataclass(frozen=True)
class Backup:
    """A backup written: its files (.params first), the values saved, the names not saved
    (hidden by the vehicle, with why)."""

    paths: tuple[Path, ...]
    saved: params.ParamFile
    hidden: tuple[str, ...]

    @property
    def path(self) -> Path:
        return self.paths[0]


def back_up(
    ap: Autopilot,
    names: list[str],
    path: Path,
    *,
    what: str,
    known: dict[str, params.ParamEntry] | None = None,
    twin: bool = True,
) -> Backup:
    """Read every parameter of ``names`` from the vehicle and save them to ``path`` (a new
    ``.params`` file; with ``twin`` also the ``.parm`` next to it). ArduPilot's CUST_ROTn_*
    are skipped while CUST_ROT_ENABLE is 0 (they cannot be read); any other parameter that does
    not answer refuses the flash before anything is written.

    known : values just read (not asked again)."""
    known = known or {}
    entries: list[params.ParamEntry] = []
    hidden: list[str] = []
    unreadable: list[str] = []
    enable_off = False
    if ap.autopilot == vehicle.ARDUPILOT and any(n.startswith("CUST_ROT") for n in names):
        e = known.get("CUST_ROT_ENABLE") or vehicle.read_optional(ap.read, "CUST_ROT_ENABLE")
        enable_off = e is not None and e.value == 0.0
    for name in names:
        e = known.get(name) or vehicle.read_optional(ap.read, name)
        if e is None:
            if enable_off and name.startswith("CUST_ROT") and name != "CUST_ROT_ENABLE":
                hidden.append(name)
                continue
            unreadable.append(name)
            continue
        entries.append(e)
    if unreadable:
        raise MagcalError(
            f"flash: no answer for {', '.join(unreadable)} while backing up: the vehicle does "
            "not have them or the link lost every reply; nothing was written"
        )
    hb = ap.heartbeat
    stamp = datetime.now(timezone.utc).isoformat(timespec="seconds")
    comments = [
        f"magcal backup: {ap.name} system {hb.system}, {what}, read {stamp} from {ap.url}",
        "restore with: magcal flash --restore THIS_FILE --mavlink URL",
    ]
    if hidden:
        comments.append(
            f"not saved: {', '.join(hidden)} (hidden while CUST_ROT_ENABLE = 0; restoring "
            "CUST_ROT_ENABLE = 0 hides them again)"
        )
    pf = params.ParamFile(tuple(entries), hb.system, hb.component, tuple(comments))
    header = {"stack": ap.name, "vehicle": vehicle.vehicle_type_name(hb.vehicle_type)}
    written = [params.write_new_file(path, params.render_param_file(path, pf, **header))]
    if twin:
        other = path.with_suffix(
            params.PARM_SUFFIX
            if params.file_format(path) == params.QGC_SUFFIX
            else params.QGC_SUFFIX
        )
        if not other.exists():
            written.append(
                params.write_new_file(other, params.render_param_file(other, pf, **header))
            )
    return Backup(tuple(written), pf, tuple(hidden))


# ------------------------------------------------------------------------------ writing
Progress = Callable[[str], None]


def write_and_confirm(
    ap: Autopilot,
    writes: tuple[params.ParamEntry, ...],
    progress: Progress | None = None,
    tries: int = PARAM_WRITE_TRIES,
    old: dict[str, float] | None = None,
) -> tuple[Unconfirmed, ...]:
    """PARAM_SET each entry until its echo confirms it (module docstring, step 3); returns the
    ones not confirmed after ``tries`` sends (empty: all confirmed). After DEAD_LINK_PARAMS
    parameters in a row without any echo the rest are not sent.

    Ctrl-C, a link error (MagcalError) or an OSError part-way raises WriteInterrupted with
    the account of every parameter (``old``: the values in force, for that account)."""
    for e in writes:
        if e.param_type is None:
            raise MagcalError(f"flash: no parameter type for {e.name}; nothing was written")
    failed: list[Unconfirmed] = []
    confirmed: list[params.ParamEntry] = []
    in_flight: list[params.ParamEntry] = []  # the parameter whose PARAM_SET may have gone out
    try:
        _write_all(ap, writes, progress, tries, failed, confirmed, in_flight)
    except (KeyboardInterrupt, MagcalError, OSError) as exc:
        raise WriteInterrupted(
            interrupted_text(writes, confirmed, failed, in_flight, old or {}), exc
        ) from exc
    return tuple(failed)


def interrupted_text(
    writes: tuple[params.ParamEntry, ...],
    confirmed: list[params.ParamEntry],
    failed: list[Unconfirmed],
    in_flight: list[params.ParamEntry],
    old: dict[str, float],
) -> str:
    """What each parameter holds after the writes stopped part-way (pure)."""
    parts = []
    if confirmed:
        parts.append(
            f"{len(confirmed)} confirmed with their new values: "
            + ", ".join(f"{e.name} = {params.value_text(e.value, e.param_type)}" for e in confirmed)
        )
    else:
        parts.append("none confirmed")
    if failed:
        parts.append(f"not confirmed: {unconfirmed_text(tuple(failed))}")
    flying = {e.name for e in in_flight}
    for e in in_flight:
        was = old.get(e.name)
        was_text = "" if was is None else f" {params.value_text(was, e.param_type)}"
        parts.append(
            f"{e.name} was being written: it holds its old value{was_text} or the new "
            f"{params.value_text(e.value, e.param_type)}"
        )
    done = {e.name for e in confirmed} | {u.name for u in failed} | flying
    untouched = [e.name for e in writes if e.name not in done]
    if untouched:
        parts.append(f"not sent (old values): {', '.join(untouched)}")
    return "; ".join(parts)


def _write_all(
    ap: Autopilot,
    writes: tuple[params.ParamEntry, ...],
    progress: Progress | None,
    tries: int,
    failed: list[Unconfirmed],
    confirmed: list[params.ParamEntry],
    in_flight: list[params.ParamEntry],
) -> None:
    """write_and_confirm's loop; the lists say how far it got when it stops part-way."""
    silent = 0
    for k, e in enumerate(writes, start=1):
        if silent >= DEAD_LINK_PARAMS:
            failed.append(Unconfirmed(e.name, e.value, None, sent=False))
            continue
        echoed: float | None = None
        in_flight[:] = [e]
        for attempt in range(tries):
            echo = ap.write_once(e.name, e.value, e.param_type)
            if echo is not None:
                echoed = echo.value
                if params.confirmed(e.value, echo.value, e.param_type):
                    break
            log.info("%s: %s not confirmed (try %d, echo %s)", ap.url, e.name, attempt + 1, echoed)
        else:
            silent = silent + 1 if echoed is None else 0
            failed.append(Unconfirmed(e.name, e.value, echoed))
            in_flight.clear()
            if progress:
                progress(f"{k}/{len(writes)} {e.name}: NOT confirmed after {tries} tries")
            continue
        silent = 0
        confirmed.append(e)
        in_flight.clear()
        if progress:
            text = params.value_text(e.value, e.param_type)
            progress(f"{k}/{len(writes)} {e.name} = {text} confirmed")


def unconfirmed_text(failed: tuple[Unconfirmed, ...]) -> str:
    """The unconfirmed parameters and what is known of each, for an error message."""
    sent = [u for u in failed if u.sent]
    parts = []
    for u in sent:
        got = "no echo" if u.echoed is None else f"vehicle echoed {u.echoed:.9g}"
        parts.append(f"{u.name} (wanted {u.wanted:.9g}, {got})")
    text = ", ".join(parts)
    unsent = [u.name for u in failed if not u.sent]
    if unsent:
        text += (
            f"; not sent after {DEAD_LINK_PARAMS} parameters in a row got no answer (they hold "
            f"their old values): {', '.join(unsent)}"
        )
    return text


def restore_entries(
    pf: params.ParamFile, current: dict[str, params.ParamEntry], autopilot: str
) -> tuple[params.ParamEntry, ...]:
    """A backup's entries with their types (the file's, else the vehicle's), in write order.
    Parameters the vehicle hides now (ArduPilot CUST_ROTn_* while CUST_ROT_ENABLE is 0) keep
    the file's type or their declared one."""
    out = []
    types = {n: e.param_type for n, e in current.items() if e.param_type is not None}
    for e in pf.entries:
        t = e.param_type if e.param_type is not None else _type_of(e.name, types)
        out.append(params.ParamEntry(e.name, params.held_value(e.value, t, e.name), t))
    return order_writes(autopilot, tuple(out), {})
