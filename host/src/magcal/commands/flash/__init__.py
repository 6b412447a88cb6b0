# SPDX-License-Identifier: Apache-2.0
"""``magcal flash``: write a calibration where it is used, reading back every step.

``--port URL`` writes to a device running magcal's firmware (:mod:`.device`: fixed-point
conversion, a backup of the device's set first, write, read back bit for bit, commit, reset,
confirm). ``--mavlink URL`` sets an ArduPilot or PX4 autopilot's compass parameters
(:mod:`.autopilot`: mapping, limits, a backup of every parameter touched first, each write
confirmed by the vehicle's echo). Either takes ``--restore BACKUP`` to write a backup back and
``--dry-run`` to write nothing to the device or vehicle."""

from __future__ import annotations

from fractions import Fraction

from magcal.commands.common import add_link_arguments, check_link_options
from magcal.errors import MagcalError

#: The magnetometer units a result may be in, with their size in tesla (None: raw counts).
#: Here, not in :mod:`.device`, which converts with it: ``--mag-unit`` offers its keys, and
#: the parser is built without loading the device stack.
MAG_UNIT_TESLA: dict[str, Fraction | None] = {
    "uT": Fraction(1, 10**6),
    "T": Fraction(1),
    "gauss": Fraction(1, 10**4),
    "mG": Fraction(1, 10**7),
    "counts": None,
}


def add_parser(sub) -> None:
    p = sub.add_parser(
        "flash",
        help="write a calibration result to the device (backup first, every step read back)",
        description="Convert RESULT.json to the device's parameter format, save the device's "
        "current set to a backup file, write, read back bit for bit, commit, reset and "
        "confirm the new set is active. --restore BACKUP writes a backup back. With --mavlink: "
        "map it to ArduPilot or PX4 compass parameters (field strength from --location or "
        "--field), back up the values in force, write each and confirm it from the vehicle's "
        "echo. With --param-file and no link: write the parameters to that file from what the "
        "result's session recorded of the vehicle, without a vehicle.",
        epilog="examples:\n"
        "  magcal flash result.json --port /dev/ttyACM0\n"
        "  magcal flash result.json --mavlink udpin:0.0.0.0:14550 --location 52.1,5.2 --dry-run\n"
        "  magcal flash result.json --param-file compass.parm",
    )
    p.add_argument("result", nargs="?", help="calibration result JSON (magcal-result/1)")
    # --param-file alone writes a parameter file without a vehicle: neither link is required
    # (run() asks for one of the three)
    add_link_arguments(p, required=False)
    p.add_argument(
        "--restore",
        metavar="BACKUP",
        help="write this backup (of an earlier flash) back instead of a result",
    )
    p.add_argument(
        "--mag-unit",
        choices=sorted(MAG_UNIT_TESLA),
        help="the unit of the result's D and o (default: the result's mag_unit; needed "
        "when the result does not say)",
    )
    p.add_argument(
        "--backup",
        metavar="PATH",
        help="where to save the device's current set (default: next to the result, "
        "RESULT.backup-<uid>-<UTC time>.json); never overwritten",
    )
    p.add_argument(
        "--dry-run",
        action="store_true",
        help="convert and check only, print the parameter set; write nothing",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="with --restore: write a backup that was taken from another device",
    )
    ap = p.add_argument_group("with --mavlink (ArduPilot, PX4)")
    ap.add_argument(
        "--location",
        metavar="LAT,LON[,ALT_KM]",
        help="where the vehicle flies (degrees north, east; km): the field strength comes from "
        "the World Magnetic Model",
    )
    ap.add_argument(
        "--date",
        metavar="YYYY-MM-DD",
        help="the model's date (default today; for a parameter file alone, the session's date)",
    )
    ap.add_argument(
        "--field",
        metavar="VALUE",
        help="the local field strength with its unit instead of --location: 48.5uT, 485mG, "
        "0.485gauss",
    )
    ap.add_argument(
        "--session",
        metavar="SESSION.csv",
        help="the session the result was calibrated from: its compass parameters at recording "
        "time (ArduPilot needs the rotation that was in force)",
    )
    ap.add_argument(
        "--param-file",
        metavar="PATH",
        help="also export the parameters: .parm or .param (Mission Planner, MAVProxy) or "
        ".params (QGroundControl); with --dry-run the default is RESULT.<autopilot>.parm/.params. "
        "Without --mavlink: write, without a vehicle, the parameters that change for every "
        "compass of the result (--compass N: one), from the parameters its session recorded; the "
        "field from --field, --location or the session's location and date",
    )
    ap.add_argument(
        "--no-custom-rotation",
        action="store_true",
        help="do not write a custom rotation (ArduPilot CUST_ROTn_*, PX4 CAL_MAGn_ROT 100 with "
        "CAL_MAGn_ROLL/PITCH/YAW); a misalignment is then left out, its heading error "
        "reported, and one costing 0.5° or more exits with code 3",
    )
    ap.add_argument(
        "--px4-custom-rotation",
        action="store_true",
        help="PX4: require CAL_MAGn_ROLL/PITCH/YAW (refuse a firmware without them); they are "
        "used by default whenever the vehicle reports them",
    )
    ap.add_argument(
        "--reboot",
        action="store_true",
        help="reboot the vehicle after writing when some value takes effect only at boot",
    )
    p.set_defaults(run=run)


MAVLINK_ONLY = (
    "location",
    "date",
    "field",
    "session",
    "param_file",
    "no_custom_rotation",
    "px4_custom_rotation",
    "reboot",
)


def run(args) -> int:
    if not args.mavlink and not args.port:
        if args.param_file:
            from magcal.commands.flash import offline

            return offline.run(args)
        raise MagcalError(
            "flash: give --port URL (a device), --mavlink URL (an autopilot), or --param-file "
            "OUT.parm to write an autopilot's parameters to a file without a vehicle"
        )
    check_link_options(args, MAVLINK_ONLY)
    if args.restore and args.result:
        raise MagcalError("flash: give either RESULT.json or --restore BACKUP, not both")
    if not args.restore and not args.result:
        raise MagcalError("flash: give a calibration result (RESULT.json) or --restore BACKUP")
    if args.mavlink:
        from magcal.commands.flash import autopilot

        return autopilot.run(args)
    from magcal.commands.flash import device

    return device.run(args)
