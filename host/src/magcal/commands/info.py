"""``magcal info --port URL``: what the device says about itself; ``--mavlink URL``: the
autopilot, its firmware and each compass with its parameters in force."""

from __future__ import annotations

import sys

from magcal.commands.common import (
    add_link_arguments,
    check_link_options,
    open_device,
    scale_text,
)
from magcal.device.collect import SI_UNIT_TEXT as SI_UNIT


def add_parser(sub) -> None:
    p = sub.add_parser(
        "info", help="show the device's (or autopilot's) firmware, sensors and compass parameters"
    )
    add_link_arguments(p)
    p.set_defaults(run=run)


def run(args, out=None) -> int:
    check_link_options(args)
    if args.mavlink:
        from magcal.commands import autopilot

        return autopilot.run_info(args, out)
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
