#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""Cut a small excerpt of the real-data set, for the quick check `make test` runs.

    python -m magcal_evaluation.real_excerpt --data ../shared/realdata \\
        --out evaluation/data/real --seconds 20 broad08_fast_rotation_breaks broad36_magnet5cm

For each named case (scored on its own recording: one trial with the session's samples) it
keeps the first --seconds of the session and of its truth, the same samples, and writes the
same layout as the full set (``cases.json``, ``sessions/CASE.csv``, ``truth/CASE.npz``), so
:mod:`magcal_evaluation.real` reads either. Session values are written as read (the shortest
text that gives the same float64); the truth is stored compressed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from magcal.io.session import Session, write_session
from magcal_evaluation import real


def write_excerpt(data_dir: str | Path, out_dir: str | Path, name: str, seconds: float) -> dict:
    """Write the first ``seconds`` of case ``name`` from ``data_dir`` into ``out_dir``;
    returns its ``cases.json`` entry. Raises :class:`real.RealDataError` for a case that is
    not scored on its own recording (its truth is other recordings: no span to cut)."""
    case = real.load_case(data_dir, name)
    if not real.scored_on_own_recording(case):
        raise real.RealDataError(
            f"excerpt of {name}: it is scored on other recordings, not on its own; "
            "choose a case scored on the recording itself"
        )
    s = case.session
    keep = s.t < s.t[0] + seconds
    n = int(keep.sum())
    meta = dict(s.meta)
    meta["excerpt"] = f"first {seconds:g} s ({n} samples) of the session {name}"
    out_dir = Path(out_dir)
    (out_dir / "sessions").mkdir(parents=True, exist_ok=True)
    (out_dir / "truth").mkdir(parents=True, exist_ok=True)
    write_session(
        out_dir / "sessions" / f"{name}.csv",
        Session(t=s.t[keep], gyr=s.gyr[keep], acc=s.acc[keep], mag=s.mag[keep], meta=meta),
    )
    tr = case.trials[0]
    np.savez_compressed(
        out_dir / "truth" / f"{name}.npz",
        trial_names=np.array([tr.name]),
        declination_deg=np.array([case.declination_deg]),
        t_0=tr.t[:n],
        mag_0=tr.mag[:n],
        quat_wxyz_0=tr.q_wb[:n],
        valid_0=tr.valid[:n],
    )
    info = dict(case.info)
    info.update(
        samples=n,
        seconds=round(float(s.t[n - 1] - s.t[0]), 2),
        excerpt=f"the first {seconds:g} s of the full case",
    )
    return info


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--data", default=str(real.DEFAULT_DATA_DIR), help="the full data set")
    ap.add_argument("--out", required=True, help="the excerpt's folder")
    ap.add_argument("--seconds", type=float, default=20.0, help="length kept (default 20 s)")
    ap.add_argument("cases", nargs="+", help="cases to cut")
    args = ap.parse_args(argv)
    try:
        known = real.case_names(args.data)
        unknown = [c for c in args.cases if c not in known]
        if unknown:
            ap.error(f"unknown case(s) {', '.join(unknown)}; known: {', '.join(known)}")
        index = {
            name: write_excerpt(args.data, args.out, name, args.seconds) for name in args.cases
        }
    except real.RealDataError as exc:
        print(f"magcal_evaluation.real_excerpt: {exc}", file=sys.stderr)
        return 2
    with open(Path(args.out) / "cases.json", "w", encoding="utf-8") as f:
        json.dump(index, f, indent=1, ensure_ascii=False)
        f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
