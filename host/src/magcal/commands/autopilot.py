"""The device commands with ``--mavlink URL``: an ArduPilot or PX4 autopilot instead of a device
running magcal's firmware. ``info``, ``collect``, ``flash`` and ``verify`` call the ``run_*``
here when ``--mavlink`` is given; the work is in :mod:`magcal.autopilot`.

Nothing here imports pymavlink at module level: the command line loads this module for its
help text, and ``simulate`` or ``calibrate`` must not pay for the MAVLink stack.
"""

from __future__ import annotations

import datetime as dt
import sys
from pathlib import Path

from magcal.errors import MagcalError


def _say(command: str, text: str) -> None:
    print(f"magcal {command}: {text}", file=sys.stderr, flush=True)


def _compass_params(ap, compass: int, **kw):
    from magcal.autopilot import vehicle

    return vehicle.read_compass_params(ap.read, ap.autopilot, compass, **kw)


# ------------------------------------------------------------------------------ info
def run_info(args, out=None) -> int:
    from magcal.autopilot import mapping, params, rotations, vehicle
    from magcal.autopilot.connection import open_autopilot

    out = out or sys.stdout
    with open_autopilot(args.mavlink) as ap:
        fw = ap.firmware()
        print(f"autopilot  {ap.name} {fw or '(firmware version not reported)'}", file=out)
        print(f"vehicle    {ap.describe()}, {args.mavlink}", file=out)
        compasses = [args.compass] if args.compass else [1, 2, 3]
        shared: dict[str, tuple[float, int | None]] = {}
        naming = mapping.AP_NAMING_LEGACY if ap.autopilot == vehicle.ARDUPILOT else ""
        for n in compasses:
            try:
                cp = _compass_params(ap, n)
            except vehicle.AutopilotError as exc:
                print(f"compass {n}  {exc}", file=out)
                continue
            naming = cp.naming
            own = set(vehicle.compass_param_names(ap.autopilot, n, naming))
            print(f"compass {n}  {_compass_line(cp, rotations, mapping)}", file=out)
            for name, value in cp.values.items():
                t = cp.types.get(name)
                if name not in own:
                    shared[name] = (value, t)
                    continue
                kind = params.TYPE_NAMES.get(t, str(t))
                print(f"  {name:<18} {params.value_text(value, t):>14}  {kind}", file=out)
        owned = {
            name for n in (1, 2, 3) for name in vehicle.compass_param_names(ap.autopilot, n, naming)
        }
        shared = {k: v for k, v in shared.items() if k not in owned}
        if shared:
            print("shared", file=out)
            for name, (value, t) in sorted(shared.items()):
                kind = params.TYPE_NAMES.get(t, str(t))
                print(f"  {name:<18} {params.value_text(value, t):>14}  {kind}", file=out)
    return 0


def _ap_rotation_name(index: int, rotations) -> str:
    if 0 <= index <= rotations.ARDUPILOT_MAX_INDEX:
        return rotations.ARDUPILOT_TABLE[index][0]
    return "not enumerated"


def _compass_line(cp, rotations, mapping) -> str:
    """One line on a compass: where its rotation comes from, its device, stream and unit."""
    from magcal.autopilot import vehicle

    n = cp.compass
    if cp.autopilot == vehicle.ARDUPILOT:
        orient = int(cp.values[mapping.ap_param_names(n, cp.naming)["ORIENT"]])
        if not cp.external:
            rot = "internal: turned by AHRS_ORIENTATION and the board"
        elif orient in mapping.AP_CUSTOM_ORIENT:
            rot = f"external, rotation {orient} (custom, CUST_ROT{orient - 100}_*)"
        else:
            rot = f"external, rotation {orient} ({_ap_rotation_name(orient, rotations)})"
        naming = f", parameter naming {cp.naming}"
    else:
        rot_value = int(cp.values[f"CAL_MAG{n - 1}_ROT"])
        rot = (
            "internal: turned by SENS_BOARD_ROT"
            if not cp.external
            else f"external, CAL_MAG{n - 1}_ROT {rot_value}"
        )
        naming = ""
    # read_compass_params refuses a compass whose device id is 0: this one is present
    dev = int(cp.values[vehicle.dev_id_name(cp.autopilot, n, cp.naming)])
    present = f", device id {dev}"
    stream = vehicle.collect_stream(cp.autopilot, n)
    return f"{rot}{present}{naming}; stream {stream}, field in {cp.unit}"


# ------------------------------------------------------------------------------ collect
def run_collect(args, out=None) -> int:
    from magcal.autopilot.collect import collect
    from magcal.autopilot.connection import open_autopilot
    from magcal.calib.diagnostics import observability
    from magcal.commands.collect import collect_saving_partial, finish_collect, progress_printer
    from magcal.io.session import check_writable

    out = out or sys.stdout
    if args.duration is None and args.coverage is None and args.max_samples is None:
        raise MagcalError("collect: --coverage off needs --duration or --max-samples")
    check_writable(args.output, "writing session")
    compass = args.compass or 1
    min_samples = observability.MIN_SAMPLES
    progress = progress_printer()
    with open_autopilot(args.mavlink) as ap:
        fw = ap.firmware()
        cp = _compass_params(ap, compass)
        _say(
            "collect",
            f"{ap.describe()}, firmware {fw or 'unknown'}; compass {compass} "
            f"({'external' if cp.external else 'internal'}), field in {cp.unit}",
        )
        result = collect_saving_partial(
            lambda: collect(
                ap,
                cp,
                rate_hz=args.rate,
                duration_s=args.duration,
                coverage_target=None if args.coverage is None else args.coverage / 100.0,
                max_samples=args.max_samples,
                min_samples=min_samples,
                progress=progress,
                firmware=fw,
            ),
            args.output,
            progress,
        )
    return finish_collect(
        args,
        result,
        min_samples,
        f"on {args.mavlink}",
        "check that the vehicle streams its IMU",
        out,
    )


# ------------------------------------------------------------------------------ flash
def _field(args):
    from magcal.autopilot import wmm

    if args.field and args.location:
        raise MagcalError("flash: give --field or --location, not both")
    if args.date and not args.location:
        raise MagcalError("flash: --date goes with --location (the World Magnetic Model's date)")
    if args.field:
        return wmm.parse_field(args.field)
    if args.location:
        lat, lon, alt = wmm.parse_location(args.location)
        try:
            day = dt.date.fromisoformat(args.date) if args.date else dt.date.today()
        except ValueError:
            raise MagcalError(f"flash: --date {args.date!r} is not a date YYYY-MM-DD") from None
        return wmm.wmm_field(lat, lon, alt, day)
    raise MagcalError(
        "flash: the autopilot wants the field in its unit, so magcal needs the local field "
        "strength: give --location LAT,LON[,ALT_KM] (World Magnetic Model) or --field VALUE "
        "with its unit (e.g. 48.5uT); nothing was written"
    )


def _recorded(args, result, cp) -> dict[str, float] | None:
    """The compass parameters in force when the result's session was recorded: from
    ``--session``'s metadata, else the result's copy (``session_meta``) when it has one."""
    from magcal.autopilot import vehicle
    from magcal.io.session import read_session

    meta = None
    where = ""
    if args.session:
        meta, where = read_session(args.session).meta, args.session
    elif isinstance(result_meta := result.extra.get("session_meta"), dict):
        meta, where = {str(k): str(v) for k, v in result_meta.items()}, args.result
    if meta is None:
        return None
    if meta.get("autopilot") not in (None, cp.autopilot) or meta.get("compass") not in (
        None,
        str(cp.compass),
    ):
        raise MagcalError(
            f"flash: {where} was recorded from {meta.get('autopilot')} compass "
            f"{meta.get('compass')}, this is {cp.autopilot} compass {cp.compass}: nothing was "
            "written (use --compass, or the session of this compass)"
        )
    external = meta.get("compass_external")
    if external is not None and (external == "1") != cp.external:
        raise MagcalError(
            f"flash: {where} was recorded with compass {cp.compass} "
            f"{'external' if external == '1' else 'internal'}, the vehicle now says otherwise; "
            "nothing was written"
        )
    recorded = vehicle.params_from_meta(meta)
    if not recorded:
        raise MagcalError(
            f"flash: {where} holds no compass parameters (no 'param.NAME' metadata): it was not "
            "recorded by magcal collect --mavlink; nothing was written"
        )
    return recorded


def _print_plan(plan, cp, out) -> None:
    from magcal.autopilot import params

    m = plan.mapped
    for note in m.notes:
        _say("flash", f"note: {note}")
    print(f"{'parameter':<18} {'in force':>14} {'new':>14}", file=out)
    for e in plan.writes:
        old = cp.values.get(e.name)
        old_text = "(hidden)" if old is None else params.value_text(old, e.param_type)
        print(
            f"{e.name:<18} {old_text:>14} {params.value_text(e.value, e.param_type):>14}", file=out
        )
    for e in plan.unchanged:
        print(
            f"{e.name:<18} {params.value_text(e.value, e.param_type):>14} {'(same)':>14}", file=out
        )


def _export(plan, path: Path, ap, result_path: str) -> Path:
    from magcal.autopilot import params, vehicle

    hb = ap.heartbeat
    pf = params.ParamFile(
        plan.all_entries,
        hb.system,
        hb.component,
        (f"magcal flash: {ap.name} compass {plan.compass} from {result_path}", plan.field.source),
    )
    header = {"stack": ap.name, "vehicle": vehicle.vehicle_type_name(hb.vehicle_type)}
    return params.write_new_file(path, params.render_param_file(path, pf, **header), overwrite=True)


def run_flash(args) -> int:
    from magcal.autopilot import flash as apflash
    from magcal.autopilot import params, vehicle
    from magcal.autopilot.connection import open_autopilot
    from magcal.io.result import read_result

    if args.restore:
        if args.result:
            raise MagcalError("flash: give either RESULT.json or --restore BACKUP, not both")
        return _run_restore(args)
    if not args.result:
        raise MagcalError("flash: give a calibration result (RESULT.json) or --restore BACKUP")
    result_path = Path(args.result)
    result = read_result(result_path)
    fld = _field(args)
    if args.param_file:
        params.file_format(args.param_file)
    if args.backup:
        params.file_format(args.backup)
        if Path(args.backup).exists():
            raise MagcalError(f"flash: backup file {args.backup} exists; give a new path")
    compass = args.compass or 1
    with open_autopilot(args.mavlink) as ap:
        cp = _compass_params(
            ap, compass, custom_angles=args.px4_custom_rotation and ap.autopilot == vehicle.PX4
        )
        _say("flash", f"vehicle {ap.describe()}; compass {compass}, unit {cp.unit}")
        D_inv, o, res_unit = apflash.result_in_unit(result, cp.unit, args.mag_unit, args.result)
        conv = "" if res_unit == cp.unit else f" (converted from {res_unit})"
        _say("flash", f"{args.result}: method {result.method}, D and o in {cp.unit}{conv}")
        _say(
            "flash",
            f"field {fld.strength(cp.unit):.6g} {cp.unit} from {fld.source}"
            + (
                f", inclination {fld.inclination_deg:.2f}°"
                if fld.inclination_deg is not None
                else ""
            ),
        )
        allow_custom = (
            not args.no_custom_rotation
            if ap.autopilot == vehicle.ARDUPILOT
            else bool(args.px4_custom_rotation)
        )
        plan = apflash.plan_flash(
            D_inv, o, cp, fld, recorded=_recorded(args, result, cp), allow_custom=allow_custom
        )
        _print_plan(plan, cp, sys.stdout)
        if args.param_file:
            _say(
                "flash",
                f"parameter file written: {_export(plan, Path(args.param_file), ap, args.result)}",
            )
        if args.dry_run:
            if not args.param_file:
                suffix = (
                    params.PARM_SUFFIX if ap.autopilot == vehicle.ARDUPILOT else params.QGC_SUFFIX
                )
                path = result_path.with_name(f"{result_path.stem}.{ap.autopilot}{suffix}")
                _say("flash", f"parameter file written: {_export(plan, path, ap, args.result)}")
            print("dry run: nothing was written to the vehicle")
            return 0
        if not plan.writes:
            print(f"the vehicle already holds these {len(plan.unchanged)} values; nothing to write")
            return 0
        backup_path = (
            Path(args.backup)
            if args.backup
            else apflash.default_backup_path(result_path, ap.autopilot, ap.heartbeat.system)
        )
        known = {n: params.ParamEntry(n, v, cp.types.get(n)) for n, v in cp.values.items()}
        backup = apflash.back_up(
            ap,
            [e.name for e in plan.all_entries],
            backup_path,
            what=f"before magcal flash {args.result}",
            known=known,
        )
        _say("flash", f"backup of the values in force: {', '.join(map(str, backup.paths))}")
        try:
            failed = apflash.write_and_confirm(
                ap, plan.writes, lambda t: _say("flash", t), old=cp.values
            )
        except apflash.WriteInterrupted as exc:
            return _interrupted(
                exc,
                f"flash: {exc}. The old values are in {backup.path}: run flash again, or "
                f"restore with magcal flash --restore {backup.path} --mavlink URL",
                backup.path,
            )
        if failed:
            raise apflash.AutopilotFlashError(
                f"flash: {len(failed)} of {len(plan.writes)} parameters not confirmed: "
                f"{apflash.unconfirmed_text(failed)}. Each holds its old value or the new one "
                f"(the others are confirmed new); the old values are in {backup.path}: run "
                f"flash again, or restore with magcal flash --restore {backup.path} --mavlink URL",
                failed,
                backup.path,
            )
        print(
            f"all {len(plan.writes)} parameters written and confirmed by the vehicle "
            f"({len(plan.unchanged)} already held their value)"
        )
        print(f"previous values saved in {backup.path} (magcal flash --restore to put them back)")
        _reboot(ap, plan.reboot_reasons, args.reboot, plan.never_applied)
    return 0


def _interrupted(exc, message: str, backup_path: Path) -> int:
    """A write phase stopped part-way: Ctrl-C prints the account and exits with
    EXIT_INTERRUPTED (130, as any interrupted command); any other cause is an
    AutopilotFlashError carrying the same account and the backup path."""
    from magcal.autopilot import flash as apflash
    from magcal.cli import EXIT_INTERRUPTED, refusal

    if exc.by_user:
        print(refusal("flash", message), file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    raise apflash.AutopilotFlashError(message, backup_path=backup_path) from exc


def _reboot(ap, reasons: tuple[str, ...], reboot: bool, never: tuple[str, ...] = ()) -> None:
    if not reasons:
        return
    if reboot:
        _say("flash", f"rebooting the vehicle ({'; '.join(reasons)})")
        ap.reboot()
        if never:
            groups = ", ".join(f"*{g}" for g in never)
            print(f"vehicle rebooted: every value is in use except {groups} (see the note)")
        else:
            print("vehicle rebooted: every value is in use")
    else:
        print(f"reboot the vehicle before flying: {'; '.join(reasons)} (or pass --reboot)")


def _run_restore(args) -> int:
    from magcal.autopilot import flash as apflash
    from magcal.autopilot import params
    from magcal.autopilot.connection import open_autopilot

    for option in ("field", "location", "date", "session", "param_file", "mag_unit"):
        if getattr(args, option, None):
            raise MagcalError(f"flash: --{option.replace('_', '-')} has no meaning with --restore")
    src = Path(args.restore)
    pf = params.read_param_file(src)
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    with open_autopilot(args.mavlink) as ap:
        # a .parm says its system only in magcal's backup comment: unknown otherwise
        if pf.system_id is not None and pf.system_id != ap.heartbeat.system and not args.force:
            raise MagcalError(
                f"flash: {src} was saved from system {pf.system_id}, this vehicle is system "
                f"{ap.heartbeat.system}: nothing was written (--force writes it anyway)"
            )
        _say("flash", f"restoring {len(pf.entries)} parameters from {src} to {ap.describe()}")
        before = (
            Path(args.backup)
            if args.backup
            else src.with_name(f"{src.stem}.before-restore-{stamp}{params.QGC_SUFFIX}")
        )
        backup = apflash.back_up(
            ap, [e.name for e in pf.entries], before, what=f"before restoring {src}"
        )
        current = {e.name: e for e in backup.saved.entries}
        entries = apflash.restore_entries(pf, current, ap.autopilot)
        writes = tuple(
            e
            for e in entries
            if e.name not in current
            or not params.confirmed(e.value, current[e.name].value, e.param_type)
        )
        _say("flash", f"values in force saved in {backup.path}")
        try:
            failed = apflash.write_and_confirm(
                ap,
                writes,
                lambda t: _say("flash", t),
                old={n: e.value for n, e in current.items()},
            )
        except apflash.WriteInterrupted as exc:
            return _interrupted(
                exc,
                f"flash --restore: {exc}. The values before the restore are in {backup.path}; "
                f"run the restore of {src} again",
                backup.path,
            )
        if failed:
            raise apflash.AutopilotFlashError(
                f"flash --restore: {len(failed)} of {len(writes)} parameters not confirmed: "
                f"{apflash.unconfirmed_text(failed)}; each holds the value before the restore "
                f"(saved in {backup.path}) or the restored one: run the restore again",
                failed,
                backup.path,
            )
        print(
            f"restored: {len(writes)} parameters written and confirmed "
            f"({len(entries) - len(writes)} already held their value); the values replaced are "
            f"in {backup.path}"
        )
        if args.reboot:
            ap.reboot()
            print("vehicle rebooted")
        else:
            print("reboot the vehicle so that every restored value is in use (or pass --reboot)")
    return 0


# ------------------------------------------------------------------------------ verify
def run_verify(args, out=None) -> int:
    from magcal.autopilot import verify as apverify
    from magcal.autopilot.connection import open_autopilot
    from magcal.commands.verify import DEFAULT_MAX_SPREAD_PCT, EXIT_FAILED, heading_lines
    from magcal.io.session import read_session

    out = out or sys.stdout
    session = read_session(args.session) if args.session else None
    compass = args.compass or 1
    with open_autopilot(args.mavlink) as ap:
        cp = _compass_params(ap, compass)
        session_head = None
        if session is not None:
            session_head = apverify.heading_of_session(session, cp, args.session)
        r = apverify.verify(
            ap, cp, n_samples=args.samples, duration_s=args.duration, rate_hz=args.rate
        )
    n = r.norm
    who = (
        "corrected here with the parameters in force"
        if r.corrected_here
        else "corrected by the vehicle"
    )
    lines = [
        f"vehicle    {ap.describe()}, compass {compass}; stream {r.stream} ({who})",
        f"norm       mean {n.mean:.5g} {r.unit}, std {n.std:.4g} ({100 * n.rel_std:.3f} %), "
        f"min {n.min:.5g}, max {n.max:.5g}, (max-min)/mean {100 * n.rel_range:.3f} % "
        f"over {n.n} samples (missing {r.missing}, repeated timestamps {r.repeated})",
    ]
    if r.heading is not None:
        lines += heading_lines(r.heading, f"{r.stream} stream")
    else:
        lines.append("heading    not measurable: no sample with |acc| near g")
    if session is not None:
        if session_head is not None:
            lines += heading_lines(session_head, f"{args.session} (parameters in force)")
        else:
            lines.append(f"heading    {args.session}: not measurable (no sample with |acc| ≈ g)")
    for line in lines:
        print(line, file=out)
    max_spread = args.max_spread if args.max_spread is not None else DEFAULT_MAX_SPREAD_PCT
    if 100 * n.rel_std > max_spread:
        print(
            f"magcal verify: the norm's spread {100 * n.rel_std:.2f} % exceeds {max_spread:g} %: "
            "calibrate again (rotate through more orientations, away from magnetic objects) "
            "and flash the result",
            file=sys.stderr,
        )
        return EXIT_FAILED
    return 0
