# SPDX-License-Identifier: Apache-2.0
"""``magcal info --port URL``: what the device says about itself; ``--mavlink URL``: the
autopilot, its firmware and each compass with its parameters in force.

Each half loads what it needs when it runs, not when the parser is built (the device client;
the ``--mavlink`` half :mod:`magcal.autopilot` and pymavlink).
"""

from __future__ import annotations

import sys

from magcal.commands.common import (
    add_link_arguments,
    check_link_options,
    compass_params,
    open_device,
    scale_text,
)


def add_parser(sub) -> None:
    p = sub.add_parser(
        "info",
        help="show the device's (or autopilot's) firmware, sensors and compass parameters",
        description="Show what a device running magcal's firmware says about itself: its "
        "firmware, protocol version, parameter format, sample rate and sensors with their exact "
        "scales. With --mavlink: the autopilot, its firmware and each compass with its "
        "parameters in force. It only reads: nothing is written to the device or the vehicle.",
        epilog="examples:\n"
        "  magcal info --port /dev/ttyACM0\n"
        "  magcal info --mavlink udpin:0.0.0.0:14550\n"
        "  magcal info --mavlink /dev/ttyACM0,115200 --compass 2",
    )
    add_link_arguments(p)
    p.set_defaults(run=run)


def run(args, out=None) -> int:
    from magcal.device.collect import SI_UNIT_TEXT as SI_UNIT

    check_link_options(args)
    if args.mavlink:
        return run_autopilot(args, out)
    out = out or sys.stdout
    with open_device(args.port) as dev:
        i = dev.info
        print(f"device     {args.port}, uid {i.uid_hex}", file=out)
        print(f"firmware   {i.fw_version_str} (build {i.fw_build:08x})", file=out)
        print(
            f"protocol   version {dev.hello.version} "
            f"(device supports {dev.hello.device_min_version}..{dev.hello.device_max_version})",
            file=out,
        )
        print(
            f"parameters format {i.params_format_version}, {i.params_size} bytes; "
            f"sample rate {i.sample_rate_hz:g} Hz",
            file=out,
        )
        for s in i.sensors:
            full = scale_text(s.full_scale)
            count = f"{scale_text(s.count_scale)} = {s.count_scale.si:.6g} {SI_UNIT[s.kind]}"
            print(
                f"{s.kind:<10} {s.name} (id 0x{s.sensor_id:02x}): full scale ±{full}, "
                f"one count = {count}",
                file=out,
            )
    return 0


# ---------------------------------------------------------------- --mavlink: an autopilot


def run_autopilot(args, out=None) -> int:
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
                cp = compass_params(ap, n)
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
        if cp.external:
            rot = f"external, CAL_MAG{n - 1}_ROT {rot_value}"
        elif vehicle.PX4_BOARD_ROT in cp.values:
            board = int(cp.values[vehicle.PX4_BOARD_ROT])
            name = rotations.PX4_TABLE[board][0] if 0 <= board < len(rotations.PX4_TABLE) else "?"
            rot = f"internal: turned by SENS_BOARD_ROT {board} ({name})"
        else:
            rot = "internal: turned by SENS_BOARD_ROT (not reported)"
        naming = ""
    # read_compass_params refuses a compass whose device id is 0: this one is present
    dev = int(cp.values[vehicle.dev_id_name(cp.autopilot, n, cp.naming)])
    present = f", device id {dev}"
    stream = vehicle.collect_stream(cp.autopilot, n)
    return f"{rot}{present}{naming}; stream {stream}, field in {cp.unit}"
