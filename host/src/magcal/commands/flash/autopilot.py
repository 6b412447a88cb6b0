# SPDX-License-Identifier: Apache-2.0
"""``magcal flash RESULT.json --mavlink URL``: a calibration result as ArduPilot or PX4 compass
parameters (:mod:`magcal.autopilot.flash`: mapping, limits, a backup of every parameter touched
first, each write confirmed by the vehicle's echo). ``--restore BACKUP`` writes a backup back.

Nothing here imports pymavlink at module level.
"""

from __future__ import annotations

import datetime as dt
import sys
from pathlib import Path

import numpy as np

from magcal.commands.common import compass_params
from magcal.errors import MagcalError
from magcal.ui import EXIT_INTERRUPTED, EXIT_MISALIGNMENT_LEFT_OUT, ProgressBar, refusal, say


def _say(text: str) -> None:
    say("flash", text)


class WriteProgress:
    """``progress(text)`` for :func:`magcal.autopilot.flash.write_and_confirm`: in a log each
    parameter's line as the writer words it ("magcal flash: 3/12 COMPASS_OFS_Z = 12.5
    confirmed"); on a terminal a progress bar of the parameters written, the last one named
    beside it, and a parameter not confirmed on a line of its own above the bar. ``close()``
    (idempotent) after the writes."""

    def __init__(self, total: int, stream=None) -> None:
        self.bar = ProgressBar("flash: writing parameters", total, stream or sys.stderr)

    def __call__(self, text: str) -> None:
        if not self.bar.live:
            say("flash", text, self.bar.stream)
            return
        if "NOT confirmed" in text:
            self.bar.message(f"magcal flash: {text}")
        self.bar.advance(note=text.split(" ", 1)[-1])

    def close(self) -> None:
        self.bar.close()


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


def _recorded(args, result, cp, session, further: bool = False) -> dict[str, float] | None:
    """The compass parameters in force when the result's session was recorded: from
    ``--session``'s metadata (``session``, read), else the result's copy (``session_meta``)
    when it has one. ``further``: ``cp`` is one of the result's further compasses
    (``compasses``), not the session's own."""
    from magcal.autopilot import vehicle

    meta = None
    where = ""
    if session is not None:
        meta, where = session.meta, args.session
    elif isinstance(result_meta := result.extra.get("session_meta"), dict):
        meta, where = {str(k): str(v) for k, v in result_meta.items()}, args.result
    if meta is None:
        return None
    if meta.get("autopilot") not in (None, cp.autopilot) or (
        meta.get("compass") not in (None, str(cp.compass)) and not further
    ):
        raise MagcalError(
            f"flash: {where} was recorded from {meta.get('autopilot')} compass "
            f"{meta.get('compass')}, this is {cp.autopilot} compass {cp.compass}: nothing was "
            "written (use --compass, or the session of this compass)"
        )
    external = None if further else meta.get("compass_external")
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


#: A misalignment left out that costs at least this much heading (degrees) ends the flash
#: with EXIT_MISALIGNMENT_LEFT_OUT (the values are in force; the warning says what it costs).
LEFT_OUT_WARN_DEG = 0.5
#: Largest floor the corrected field's norm spread puts under the rotation's σ, degrees. The
#: floor stands for model errors the curvature does not know (on SITL it turned a 0.05° custom
#: rotation of an aligned compass into an enumerated one); capped so that on a sensor whose
#: field norm scatters by percents it never hides a real misalignment of degrees (the
#: largest rotation it can write as an enumerated one is about 0.35°).
SIGMA_FLOOR_MAX_DEG = 0.1


def _rotation_sigma_deg(args, result, session):
    """The result's misalignment σ per axis (degrees) from the ML cost's curvature on the
    session it was fitted on (``--session``, read), or None without one or when it cannot be
    had (then a rotation is written as an enumerated one only when it is one)."""
    if session is None:
        return None
    from magcal.calib.diagnostics import replay, uncertainty
    from magcal.errors import CalibrationError

    try:
        unc = uncertainty.calibration_uncertainty(result, session)
    except (replay.ModelUnavailableError, CalibrationError) as exc:
        _say(f"note: no uncertainty of the rotation ({exc}): it is written as estimated")
        return None
    sigma = np.asarray(unc.sigma["misalignment_deg"], dtype=float)
    # The curvature knows only the noise model; the corrected field's own norm spread (std /
    # mean) bounds how well any direction is held, whatever the model says: a floor.
    after = (result.extra.get("field_norm") or {}).get("after") or {}
    floor = 0.0
    if after.get("mean"):
        floor = min(float(np.degrees(after["std"] / after["mean"])), SIGMA_FLOOR_MAX_DEG)
    sigma = np.sqrt(sigma**2 + floor**2)
    _say(
        "misalignment σ "
        + ", ".join(f"{v:.3f}" for v in sigma)
        + f"° (roll, pitch, yaw axes; the curvature on {args.session}, at least the corrected "
        f"field's norm spread up to {SIGMA_FLOOR_MAX_DEG}°: {floor:.3f}°)"
    )
    return sigma


def _print_plan(plan, cp, out) -> None:
    from magcal.autopilot import params

    m = plan.mapped
    for note in m.notes:
        _say(f"note: {note}")
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


def run(args) -> int:
    from magcal.autopilot import flash as apflash
    from magcal.autopilot import params, vehicle, wmm
    from magcal.autopilot.connection import open_autopilot
    from magcal.io.result import read_result, result_compasses
    from magcal.io.session import read_session

    if args.restore:  # flash.run has checked that exactly one of the two is given
        return _run_restore(args)
    result_path = Path(args.result)
    result = read_result(result_path)
    fld = _field(args)
    if args.param_file:
        params.file_format(args.param_file)
    if args.backup:
        params.file_format(args.backup)
        if Path(args.backup).exists():
            raise MagcalError(f"flash: backup file {args.backup} exists; give a new path")
    # one compass: --compass, default the result's first (its session's); the result's
    # further compasses (``compasses``) each with their own calibration
    calibrations = result_compasses(result, f"reading result {args.result}")
    compass = args.compass or calibrations[0].compass or 1
    chosen = next((c for c in calibrations if c.compass == compass), calibrations[0])
    further = chosen is not calibrations[0]
    # The session and the rotation's σ (a Hessian of the ML cost) before the link is open.
    session = read_session(args.session) if args.session else None
    rotation_sigma_deg = None if further else _rotation_sigma_deg(args, result, session)
    with open_autopilot(args.mavlink) as ap:
        # PX4: CAL_MAGn_ROLL/PITCH/YAW are read (and used) unless --no-custom-rotation
        cp = compass_params(
            ap, compass, custom_angles=ap.autopilot == vehicle.PX4 and not args.no_custom_rotation
        )
        _say(f"vehicle {ap.describe()}; compass {compass}, unit {cp.unit}")
        _, _, res_unit = apflash.result_in_unit(result, cp.unit, args.mag_unit, args.result)
        cal = apflash.calibration_in_unit(chosen, wmm.convert(1.0, res_unit, cp.unit))
        D_inv, o = np.linalg.inv(cal.D), cal.o
        conv = "" if res_unit == cp.unit else f" (converted from {res_unit})"
        _say(f"{args.result}: method {result.method}, D and o in {cp.unit}{conv}")
        _say(
            f"field {fld.strength(cp.unit):.6g} {cp.unit} from {fld.source}"
            + (
                f", inclination {fld.inclination_deg:.2f}°"
                if fld.inclination_deg is not None
                else ""
            ),
        )
        allow_custom = not args.no_custom_rotation
        if ap.autopilot == vehicle.PX4:
            # --px4-custom-rotation refuses older firmware even for an internal compass (whose
            # rotation plan_flash never makes custom); without it the angles are used whenever
            # the vehicle reports them
            if args.px4_custom_rotation:
                apflash.require_px4_custom_angles(cp)
            index = vehicle.px4_index(compass)
            allow_custom = allow_custom and vehicle.px4_has_custom_angles(cp.values, index)
        plan = apflash.plan_flash(
            D_inv,
            o,
            cp,
            fld,
            recorded=_recorded(args, result, cp, session, further),
            allow_custom=allow_custom,
            rotation_sigma_deg=rotation_sigma_deg,
            motor=cal.motor,
        )
        _print_plan(plan, cp, sys.stdout)
        if args.param_file:
            _say(
                f"parameter file written: {_export(plan, Path(args.param_file), ap, args.result)}",
            )
        if args.dry_run:
            if not args.param_file:
                suffix = (
                    params.PARM_SUFFIX if ap.autopilot == vehicle.ARDUPILOT else params.QGC_SUFFIX
                )
                path = result_path.with_name(f"{result_path.stem}.{ap.autopilot}{suffix}")
                _say(f"parameter file written: {_export(plan, path, ap, args.result)}")
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
        _say(f"backup of the values in force: {', '.join(map(str, backup.paths))}")
        writing = WriteProgress(len(plan.writes))
        try:
            failed = apflash.write_and_confirm(ap, plan.writes, writing, old=cp.values)
        except apflash.WriteInterrupted as exc:
            writing.close()
            return _interrupted(
                exc,
                f"flash: {exc}. The old values are in {backup.path}: run flash again, or "
                f"restore with magcal flash --restore {backup.path} --mavlink URL",
                backup.path,
            )
        writing.close()
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
    return _left_out(plan)


def _left_out(plan) -> int:
    """0, or EXIT_MISALIGNMENT_LEFT_OUT with a warning when the values written leave out a
    misalignment costing at least LEFT_OUT_WARN_DEG of heading."""

    m = plan.mapped
    if m.heading_rms_deg < LEFT_OUT_WARN_DEG or m.snapped:
        return 0
    print(
        f"magcal flash: warning: the values written leave out a misalignment of "
        f"{m.residual_angle_deg:.2f}°, costing {m.heading_rms_deg:.2f}° RMS heading error "
        "(see the notes): allow a custom rotation (ArduPilot: without --no-custom-rotation; "
        "PX4: a firmware with CAL_MAGn_ROLL/PITCH/YAW) or mount the compass along an "
        "enumerated rotation",
        file=sys.stderr,
    )
    return EXIT_MISALIGNMENT_LEFT_OUT


def _interrupted(exc, message: str, backup_path: Path) -> int:
    """A write phase stopped part-way: Ctrl-C prints the account and exits with
    EXIT_INTERRUPTED (130, as any interrupted command); any other cause is an
    AutopilotFlashError carrying the same account and the backup path."""
    from magcal.autopilot import flash as apflash

    if exc.by_user:
        print(refusal("flash", message), file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    raise apflash.AutopilotFlashError(message, backup_path=backup_path) from exc


def _reboot(ap, reasons: tuple[str, ...], reboot: bool, never: tuple[str, ...] = ()) -> None:
    if not reasons:
        return
    if reboot:
        _say(f"rebooting the vehicle ({'; '.join(reasons)})")
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
        _say(f"restoring {len(pf.entries)} parameters from {src} to {ap.describe()}")
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
        _say(f"values in force saved in {backup.path}")
        writing = WriteProgress(len(writes))
        try:
            failed = apflash.write_and_confirm(
                ap,
                writes,
                writing,
                old={n: e.value for n, e in current.items()},
            )
        except apflash.WriteInterrupted as exc:
            writing.close()
            return _interrupted(
                exc,
                f"flash --restore: {exc}. The values before the restore are in {backup.path}; "
                f"run the restore of {src} again",
                backup.path,
            )
        writing.close()
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
