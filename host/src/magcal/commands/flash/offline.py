# SPDX-License-Identifier: Apache-2.0
"""``magcal flash RESULT.json --param-file OUT.parm`` without a vehicle: the compass parameters
a MAVLink flash would write, in a parameter file for Mission Planner, MAVProxy (``param load``)
or QGroundControl.

Everything a MAVLink flash reads from the vehicle comes from what the result's session
recorded of it (``session_meta``: ``autopilot``, ``compass``, ``mag_unit``, ``param_naming``
and ``param.NAME``, every compass parameter in force while it was recorded), and the plan is
the same (:func:`magcal.autopilot.flash.plan_param_file`). Every compass of the result is
written (``compasses``), each with its own parameter names, and the motor compensation of
each whose interference the calibration kept (``motor``). The file holds only the
parameters whose values change.

Nothing here imports pymavlink.
"""

from __future__ import annotations

import datetime as dt
import sys
from pathlib import Path

from magcal.errors import MagcalError
from magcal.ui import say

#: Options that need a vehicle: refused without --mavlink.
VEHICLE_ONLY = ("session", "reboot", "backup", "px4_custom_rotation", "force")


def _say(text: str) -> None:
    say("flash", text)


def _day(text: str, what: str) -> dt.date:
    try:
        return dt.date.fromisoformat(text.strip()[:10])
    except ValueError:
        raise MagcalError(f"flash: {what} {text!r} is not a date YYYY-MM-DD") from None


def field_for(args, meta: dict[str, str], where: str):
    """The field strength: ``--field``, or the World Magnetic Model at ``--location`` (else
    the session's ``location``) on ``--date`` (else the session's ``date``, else today)."""
    from magcal.autopilot import wmm

    if args.field and args.location:
        raise MagcalError("flash: give --field or --location, not both")
    if args.field:
        if args.date:
            raise MagcalError(
                "flash: --date goes with --location (the World Magnetic Model's date)"
            )
        return wmm.parse_field(args.field)
    location = args.location or meta.get("location")
    if not location:
        raise MagcalError(
            f"flash: the autopilot wants the field in its unit, so magcal needs the local field "
            f"strength, and {where}'s session has no location: give --location LAT,LON[,ALT_KM] "
            "(World Magnetic Model) or --field VALUE with its unit (e.g. 48.5uT); nothing was "
            "written"
        )
    if args.location:
        lat, lon, alt = wmm.parse_location(location)
    else:
        try:
            lat, lon, alt = wmm.parse_location(location)
        except wmm.FieldError as exc:
            raise MagcalError(
                f"flash: {where}'s session location {location!r} is unusable ({exc}); give "
                "--location or --field; nothing was written"
            ) from exc
    if args.date:
        day = _day(args.date, "--date")
    elif meta.get("date") and not args.location:
        day = _day(meta["date"], f"{where}'s session date")
    else:
        day = dt.date.today()
    return wmm.wmm_field(lat, lon, alt, day)


def _check_options(args) -> None:
    used = [
        "--" + n.replace("_", "-")
        for n in VEHICLE_ONLY
        if getattr(args, n, None) not in (None, False)
    ]
    if args.restore:
        used.append("--restore")
    if used:
        raise MagcalError(
            f"flash: {', '.join(used)} need{'s' if len(used) == 1 else ''} a vehicle: add "
            "--mavlink URL (a parameter file alone is written from the result's session)"
        )
    if not args.result:
        raise MagcalError("flash: give a calibration result (RESULT.json) to write to --param-file")


def _header(args, plans, meta, where: str) -> tuple[str, ...]:
    from magcal.autopilot import vehicle

    first = plans[0]
    names = vehicle.AUTOPILOT_NAMES[first.autopilot]
    which = ", ".join(str(p.compass) for p in plans)
    stamp = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    lines = [
        f"magcal flash: {names} compass{'es' if len(plans) > 1 else ''} {which} from {where}, "
        f"written {stamp}",
        f"field {first.field.strength(first.unit):.6g} {first.unit} from {first.field.source}",
        "only the compass parameters that change, for the parameters in force when the "
        f"session was recorded ({meta.get('source', 'source not recorded')})",
    ]
    if any(e.name == "CUST_ROT_ENABLE" and e.value != 0 for p in plans for e in p.writes):
        lines.append(
            "ArduPilot shows CUST_ROTn_* only after a reboot with CUST_ROT_ENABLE = 1: load this "
            "file, reboot, and load it again"
        )
    reasons = sorted({r for p in plans for r in p.reboot_reasons})
    if reasons:
        lines.append(f"reboot after loading: {'; '.join(reasons)}")
    return tuple(lines)


def run(args) -> int:
    from magcal.autopilot import flash as apflash
    from magcal.autopilot import mapping, params, vehicle, wmm
    from magcal.commands.flash.autopilot import _left_out
    from magcal.io.result import read_result, result_compasses

    _check_options(args)
    out_path = Path(args.param_file)
    fmt = params.file_format(out_path)
    result = read_result(args.result)
    where = args.result
    raw_meta = result.extra.get("session_meta")
    problems = apflash.offline_problems(raw_meta)
    if problems:
        raise MagcalError(
            f"flash: {where} cannot be written to a parameter file without a vehicle: "
            f"{'; '.join(problems)}. Calibrate a session that an autopilot recorded (magcal "
            "collect --mavlink, or magcal import of its log), or flash with --mavlink URL, "
            "which reads the vehicle; nothing was written"
        )
    meta = {str(k): str(v) for k, v in raw_meta.items()}
    autopilot = meta["autopilot"]
    unit = vehicle.MAG_UNIT[autopilot]
    # D and o of every compass in the autopilot's unit (the result's mag_unit or --mag-unit)
    _, _, res_unit = apflash.result_in_unit(result, unit, args.mag_unit, where)
    factor = wmm.convert(1.0, res_unit, unit)
    calibrations = result_compasses(result, f"reading result {where}")
    if args.compass is not None:
        chosen = [c for c in calibrations if c.compass == args.compass]
        if not chosen:
            have = ", ".join(str(c.compass) for c in calibrations)
            raise MagcalError(
                f"flash: {where} calibrates compass {have}, not compass {args.compass}: give "
                "one of those with --compass; nothing was written"
            )
        calibrations = chosen
    calibrations = [apflash.calibration_in_unit(c, factor) for c in calibrations]
    fld = field_for(args, meta, where)
    conv = "" if res_unit == unit else f" (converted from {res_unit})"
    _say(
        f"{where}: method {result.method}, {vehicle.AUTOPILOT_NAMES[autopilot]} compass "
        f"{', '.join(str(c.compass) for c in calibrations)} as its session recorded the vehicle; "
        f"D and o in {unit}{conv}"
    )
    _say(f"field {fld.strength(unit):.6g} {unit} from {fld.source}")
    for c in calibrations:
        if c.motor is not None:
            kept = (
                "kept" if c.motor.kept else "not kept: its compensation in force is left as it is"
            )
            _say(f"compass {c.compass}: motor interference ({c.motor.input}) {kept}")
    plans = apflash.plan_param_file(
        calibrations, meta, fld, allow_custom=not args.no_custom_rotation, where=where
    )
    recorded = vehicle.params_from_meta(meta)
    _print_table(plans, recorded, sys.stdout)
    entries = apflash.param_file_entries(plans)
    if not entries:
        print(
            f"the parameters the session recorded already hold these values; {out_path} was "
            "not written"
        )
        return 0
    for e in entries:
        if e.name not in (mapping.AP_MOTCT_NAME, mapping.PX4_COMP_TYP_NAME):
            continue
        _say(
            f"note: {e.name} = {params.value_text(e.value, e.param_type)} applies to every "
            "compass of the vehicle"
        )
    if args.dry_run:
        print(f"dry run: {len(entries)} parameters; {out_path} was not written")
        return 0
    system = int(meta.get("mavlink_system", "1") or 1)
    component = int(meta.get("mavlink_component", "1") or 1)
    pf = params.ParamFile(entries, system, component, _header(args, plans, meta, where))
    text = params.render_param_file(
        out_path,
        pf,
        stack=vehicle.AUTOPILOT_NAMES[autopilot],
        vehicle=meta.get("vehicle", ""),
    )
    params.write_new_file(out_path, text, overwrite=True)
    loader = "Mission Planner, MAVProxy" if fmt == params.PARM_SUFFIX else "QGroundControl"
    print(
        f"wrote {out_path} (for {loader}): "
        f"{len(entries)} parameters of compass{'es' if len(plans) > 1 else ''} "
        f"{', '.join(str(p.compass) for p in plans)}"
    )
    return max(_left_out(p) for p in plans)


def _print_table(plans, recorded: dict[str, float], out) -> None:
    from magcal.autopilot import params

    for p in plans:
        for note in p.mapped.notes:
            _say(f"note: compass {p.compass}: {note}")
    print(f"{'parameter':<18} {'recorded':>14} {'new':>14}", file=out)
    shown: set[str] = set()
    for p in plans:
        for e in p.writes:
            if e.name in shown:
                continue
            shown.add(e.name)
            old = recorded.get(e.name)
            old_text = "(not recorded)" if old is None else params.value_text(old, e.param_type)
            print(
                f"{e.name:<18} {old_text:>14} {params.value_text(e.value, e.param_type):>14}",
                file=out,
            )
