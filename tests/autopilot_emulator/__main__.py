# SPDX-License-Identifier: Apache-2.0
"""``python -m tests.autopilot_emulator``: run an emulated autopilot until Ctrl-C."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from tests.autopilot_emulator import AutopilotEmulator


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.autopilot_emulator", description=__doc__)
    ap.add_argument("--personality", choices=("ardupilot", "px4"), default="ardupilot")
    ap.add_argument("--port", type=int, default=14550, help="UDP port the client listens on")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speedup", type=float, default=1.0)
    ap.add_argument("--compasses", type=int, default=1)
    ap.add_argument("--motion", default="tumble", choices=("tumble", "yaw-only", "small"))
    ap.add_argument("--param-value-loss", type=float, default=0.0)
    ap.add_argument("--misalignment-deg", type=float, default=None)
    ap.add_argument(
        "--duration", type=float, default=None, help="stop after this many wall seconds"
    )
    args = ap.parse_args(argv)
    emu = AutopilotEmulator(
        args.personality,
        seed=args.seed,
        port=args.port,
        speedup=args.speedup,
        param_value_loss=args.param_value_loss,
        compasses=args.compasses,
        motion=args.motion,
        misalignment_deg=args.misalignment_deg,
    )
    np.set_printoptions(precision=4, suppress=True)
    print(f"{args.personality} emulator: connect with {emu.url}", file=sys.stderr)
    print(f"field {emu.field_strength} {emu.unit}", file=sys.stderr)
    for n in range(1, args.compasses + 1):
        c = emu.truth.compass(n)
        print(
            f"compass {n}: D =\n{c.D}\no = {c.o}\nmisalignment {c.misalignment_deg} deg, "
            f"heading error now {emu.heading_error_deg(n):.2f} deg",
            file=sys.stderr,
        )
    deadline = None if args.duration is None else time.monotonic() + args.duration
    with emu:
        try:
            while deadline is None or time.monotonic() < deadline:
                left = 1.0 if deadline is None else deadline - time.monotonic()
                time.sleep(min(1.0, max(0.0, left)))
                emu.check()
                print(
                    f"\rsim {emu.sim_time_s:8.1f} s  heading error "
                    f"{emu.heading_error_deg(1):6.2f} deg",
                    end="",
                    file=sys.stderr,
                )
        except KeyboardInterrupt:
            print(file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
