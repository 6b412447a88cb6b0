# SPDX-License-Identifier: Apache-2.0
"""``magcal flash RESULT.json --port URL``: write a calibration to the device.

1. convert the result's ``D_inv`` and ``o`` to the device's fixed-point parameter set
   (:func:`magcal.device.fixed_point.from_calibration`) and check it is representable;
2. read the device's current set and save it to a backup file (never overwriting one);
3. write it, read it back and compare bit for bit, commit;
4. reset the device and confirm the new set is active, bit for bit.

Steps 2-4 are :func:`magcal.device.flash.flash_parameters` (SPEC §5). Progress goes to stderr,
one line per step; the outcome names the set the device holds: "new parameters active
(crc32 ...)" on stdout, or, on failure, a message ending "device holds the OLD set", "the NEW
set" or "an unknown set", with the backup's path, and a non-zero exit status.

``magcal flash --restore BACKUP --port URL`` writes a backup back the same way (the set it
replaces is backed up first). ``--dry-run`` converts and checks only and prints the parameter
set; it reads the device's description (hello, info) and writes nothing, not even a backup.

Units: the result's ``D`` and ``o`` are in the session's magnetometer unit, the device
corrects raw counts. The unit comes from ``--mag-unit`` or the result's optional ``mag_unit``
key; the size of one count from the device (info's exact magnetometer count scale).
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from datetime import datetime, timezone
from fractions import Fraction
from pathlib import Path

import numpy as np

from magcal.commands.common import open_device, scale_text
from magcal.commands.flash import MAG_UNIT_TESLA
from magcal.device import fixed_point
from magcal.device.client import DeviceClient, DeviceInfo, Scale
from magcal.device.flash import (
    FlashError,
    FlashResult,
    Progress,
    before_restore_path,
    flash_parameters,
    restorable_backup,
    restore,
)
from magcal.device.framing import crc32_iso_hdlc
from magcal.device.generated import Status, Unit
from magcal.errors import MagcalError
from magcal.io.result import CalibrationResult, read_result
from magcal.link import LINK_OPEN_TIMEOUT_S, open_link
from magcal.ui import say

#: Other spellings of MAG_UNIT_TESLA's units (as a session's ``# mag_unit:`` may write them).
_UNIT_ALIASES = {"µT": "uT", "μT": "uT", "microtesla": "uT", "tesla": "T", "G": "gauss"}
_MAG_SCALE_TESLA = {Unit.TESLA: Fraction(1), Unit.GAUSS: Fraction(1, 10**4)}

OLD, NEW, UNKNOWN = "OLD", "NEW", "unknown"


class FlashCommandError(MagcalError):
    """magcal flash failed; the message ends by saying which set the device holds."""


def _say(text: str) -> None:
    say("flash", text)


# ---------------------------------------------------------------- conversion


def canonical_mag_unit(text: str) -> str | None:
    """``text`` as one of MAG_UNIT_TESLA's keys, or None when it names no known unit."""
    t = text.strip()
    t = _UNIT_ALIASES.get(t, t)
    return t if t in MAG_UNIT_TESLA else None


def result_mag_unit(result: CalibrationResult, flag: str | None, path: str) -> str:
    """The unit of the result's D and o: ``--mag-unit`` or the result's ``mag_unit`` key
    (they must agree when both are given)."""
    stored = result.extra.get("mag_unit")
    known = canonical_mag_unit(stored) if isinstance(stored, str) else None
    if flag is not None:
        if known is not None and known != flag:
            raise MagcalError(
                f"flash: {path} says its magnetometer unit is {stored!r} but --mag-unit is "
                f"{flag!r}; nothing was written: drop --mag-unit or give the result's unit"
            )
        return flag
    if known is not None:
        return known
    said = f"mag_unit {stored!r}, not a known unit" if stored is not None else "no mag_unit key"
    raise MagcalError(
        f"flash: the unit of {path}'s D and o is unknown (the result has {said}); nothing was "
        f"written: pass --mag-unit ({', '.join(sorted(MAG_UNIT_TESLA))}) with the session's "
        "magnetometer unit (its '# mag_unit:' line)"
    )


def unit_per_count(scale: Scale, mag_unit: str) -> float:
    """Size of one magnetometer count in ``mag_unit``, from the device's exact count scale
    (one rounding, from the exact rational); 1 for ``counts``."""
    unit_t = MAG_UNIT_TESLA[mag_unit]
    if unit_t is None:
        return 1.0
    if scale.unit not in _MAG_SCALE_TESLA or scale.den <= 0:
        raise MagcalError(
            f"flash: the device's magnetometer count scale {scale.num}/{scale.den}e"
            f"{scale.exp10} has unit {scale.unit.name}, not a magnetic unit; nothing was "
            "written: check the firmware's sensor table"
        )
    tesla = Fraction(scale.num, scale.den) * Fraction(10) ** scale.exp10
    return float(tesla * _MAG_SCALE_TESLA[scale.unit] / unit_t)


def check_device_format(info: DeviceInfo, url: str) -> None:
    """Refuse a device whose parameter format is not the one fixed_point writes."""
    fmt, size = info.params_format_version, info.params_size
    if fmt != fixed_point.FORMAT_VERSION or size != fixed_point.ENCODED_SIZE:
        raise MagcalError(
            f"flash: the device on {url} takes parameter format {fmt} of {size} bytes; this "
            f"magcal writes format {fixed_point.FORMAT_VERSION} of "
            f"{fixed_point.ENCODED_SIZE} bytes; nothing was written: update magcal or the "
            "firmware so that they match"
        )


def convert(result: CalibrationResult, upc: float, path: str) -> fixed_point.DeviceParams:
    """The device parameter set of ``result`` (``upc``: one count in the result's unit);
    MagcalError naming the entry and the range when it is not representable."""
    d_inv = result.D_inv
    try:
        return fixed_point.from_calibration(d_inv, result.o, unit_per_count=upc)
    except fixed_point.FixedPointError as exc:
        where = ""
        if exc.status == Status.E_EXPONENT:
            i, j = np.unravel_index(int(np.argmax(np.abs(d_inv))), (3, 3))
            where = f" (the largest is D_inv[{i}][{j}] = {d_inv[i, j]:.6g} per result unit)"
        raise MagcalError(
            f"flash: the calibration in {path} cannot be represented in the device's "
            f"parameter format: {exc}{where}; nothing was written"
        ) from exc


def describe_params(params: fixed_point.DeviceParams, out) -> None:
    """The parameter set as stored: exponents, mantissas with their values, CRC-32."""
    blob = fixed_point.encode(params)
    d = params.d_inv_matrix()
    o = params.offset_counts()
    print(
        f"device parameter set: format {params.version}, {len(blob)} bytes, "
        f"crc32 0x{crc32_iso_hdlc(blob):08x}",
        file=out,
    )
    print(
        f"  D_inv exponent E_d = {params.d_inv_exp} (D_inv = mantissa × 2^{params.d_inv_exp - 30})",
        file=out,
    )
    for i in range(3):
        m = params.d_inv[3 * i : 3 * i + 3]
        print(
            "  D_inv row {}: {:>11d} {:>11d} {:>11d}   = {:.9g} {:.9g} {:.9g}".format(i, *m, *d[i]),
            file=out,
        )
    print(
        "  offset (Q16.15): {:>11d} {:>11d} {:>11d}   = {:.6f} {:.6f} {:.6f} counts".format(
            *params.offset, *o
        ),
        file=out,
    )
    print(
        f"  output exponent E_m = {params.out_exp} (one output LSB = 2^{params.out_exp - 31}"
        f" = {params.out_lsb:.6g}), shift {params.shift}",
        file=out,
    )
    print(f"  blob {blob.hex()}", file=out)


# ---------------------------------------------------------------- backup paths


def _stamp() -> str:
    return datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")


def _free_path(base: Path) -> Path:
    """``base``, or ``base`` with -2, -3, ... before the suffix when it exists."""
    if not base.exists():
        return base
    k = 2
    while True:
        p = base.with_name(f"{base.stem}-{k}{base.suffix}")
        if not p.exists():
            return p
        k += 1


def default_backup_path(result_path: Path, uid_hex: str) -> Path:
    """``RESULT.backup-<uid>-<UTC time>.json`` next to the result, never an existing file."""
    return _free_path(result_path.with_name(f"{result_path.stem}.backup-{uid_hex}-{_stamp()}.json"))


def _chosen_backup(arg: str | None, default: Path) -> Path:
    if arg is None:
        return default
    p = Path(arg)
    if p.exists():
        raise MagcalError(
            f"flash: backup file {p} exists; nothing was written: give a new path (an earlier "
            "backup is worth keeping)"
        )
    return p


# ---------------------------------------------------------------- the flow


def _reconnect(url: str):
    def reconnect() -> DeviceClient:
        return DeviceClient(open_link(url, LINK_OPEN_TIMEOUT_S))

    return reconnect


def _holds(state: str, backup: Path | None) -> str:
    if backup is None:
        return f"device holds the {state} set, untouched (no backup was made)"
    where = f" — backup at {backup}"
    if state == UNKNOWN:
        return (
            f"device holds an unknown set (either the OLD or the NEW one){where}: check it "
            "with magcal verify"
        )
    return f"device holds the {state} set{where}"


def _flash(write: Callable[[Progress], FlashResult]) -> FlashResult:
    """Run ``write`` (flash_parameters or restore, given the progress printer); on failure
    raise FlashCommandError saying which set the device holds, as the library found out."""
    try:
        return write(_say)
    except FlashError as exc:
        state = {"old": OLD, "new": NEW}.get(exc.active, UNKNOWN)
        raise FlashCommandError(f"{exc}; {_holds(state, exc.backup_path)}") from exc


def _finish(result: FlashResult, first: DeviceClient) -> int:
    if result.recovered_from:
        _say(
            f"the flow was interrupted ({result.recovered_from}); the new set was then read back "
            "and verified"
        )
    if result.client is not None and result.client is not first:
        result.client.close()
    print(f"new parameters active (crc32 0x{result.crc32:08x}); device holds the NEW set")
    if result.backup_path is None:
        print(
            "no backup was made: the device already held this set before anything was written "
            "(found after reconnecting)"
        )
    else:
        print(f"previous set saved in {result.backup_path} (magcal flash --restore to put it back)")
    return 0


def run(args) -> int:
    """``magcal flash --port``: a refusal or failure says which set the device holds."""
    try:
        return _run(args)
    except FlashCommandError:
        raise
    except MagcalError as exc:
        # Refused or failed before the flow's first write (result, unit, link, hello, info,
        # format, conversion, backup path): the device was not written to.
        raise FlashCommandError(f"{exc}; {_holds(OLD, None)}") from exc


def _run(args) -> int:
    if args.restore:  # flash.run has checked that exactly one of the two is given
        return _run_restore(args)
    if args.force:
        raise MagcalError("flash: --force is for --restore only")
    result_path = Path(args.result)
    result = read_result(result_path)
    unit = result_mag_unit(result, args.mag_unit, args.result)
    with open_device(args.port) as dev:
        info = dev.info
        _say(
            f"device {args.port}: uid {info.uid_hex}, firmware {info.fw_version_str}, "
            f"parameter format {info.params_format_version} ({info.params_size} bytes)"
        )
        check_device_format(info, args.port)
        scale = info.sensor("mag").count_scale
        upc = unit_per_count(scale, unit)
        _say(
            f"{args.result}: method {result.method}, D and o in {unit}; one count = "
            f"{scale_text(scale)} = {upc:.9g} {unit}"
        )
        params = convert(result, upc, args.result)
        blob = fixed_point.encode(params)
        crc = crc32_iso_hdlc(blob)
        _say(
            f"converted: E_d {params.d_inv_exp}, E_m {params.out_exp}, crc32 0x{crc:08x}; "
            "representable, and the device's checks pass"
        )
        if args.dry_run:
            describe_params(params, sys.stdout)
            print("dry run: nothing was written to the device")
            return 0
        backup = _chosen_backup(args.backup, default_backup_path(result_path, info.uid_hex))
        _say(f"backup of the current set goes to {backup}")
        url = args.port
        result_ = _flash(
            lambda progress: flash_parameters(
                dev.client,
                blob,
                fixed_point.FORMAT_VERSION,
                backup,
                reconnect=_reconnect(url),
                progress=progress,
            ),
        )
        return _finish(result_, dev.client)


def _run_restore(args) -> int:
    if args.mag_unit:
        raise MagcalError("flash: --mag-unit has no meaning with --restore (a backup is counts)")
    src = Path(args.restore)
    doc = restorable_backup(src)
    blob: bytes = doc["blob"]
    _say(
        f"backup {src}: device {doc.get('device_uid')}, taken {doc.get('time')}, "
        f"crc32 0x{crc32_iso_hdlc(blob):08x}"
    )
    with open_device(args.port) as dev:
        info = dev.info
        _say(
            f"device {args.port}: uid {info.uid_hex}, firmware {info.fw_version_str}, "
            f"parameter format {info.params_format_version} ({info.params_size} bytes)"
        )
        check_device_format(info, args.port)
        if args.dry_run:
            try:
                describe_params(fixed_point.decode(blob), sys.stdout)
            except fixed_point.FixedPointError as exc:
                raise MagcalError(f"flash: backup {src} holds no readable set ({exc})") from exc
            print("dry run: nothing was written to the device")
            return 0
        backup = _chosen_backup(args.backup, before_restore_path(src))
        _say(f"backup of the current set goes to {backup}")
        url = args.port
        result_ = _flash(
            lambda progress: restore(
                dev.client,
                src,
                new_backup_path=backup,
                reconnect=_reconnect(url),
                force=args.force,
                progress=progress,
            ),
        )
        return _finish(result_, dev.client)
