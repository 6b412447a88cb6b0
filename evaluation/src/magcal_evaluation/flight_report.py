#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""The flight-log report: magcal on flight logs beside magfit_WMM, `make flight`.

    python -m magcal_evaluation.flight_report --flights ../shared/flightlogs --out bench/flight.md

Every flight log with a known error (``NAME.bin`` with ``NAME.truth.json``) goes through
``magcal import``, ``calibrate`` and ``flash --param-file`` with default options, and the
parameter file is scored with the folder's ``tools/score_flight.py`` beside the parameters in
force, the truth and pymavlink's magfit_WMM.py (four option sets; their fits cached under
--cache). Every real log of --reallogs goes through ``import`` and ``calibrate``. The Markdown
report (--out) has the command, date, machine and commit, the scores with the wall time of
each step, the acceptance criteria, and the real logs' outcomes and consistency figures; every
figure goes to --raw as JSON (:mod:`magcal_evaluation.flight` describes the measures). Exits 1
when a criterion fails or a step crashed, after writing.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from magcal_evaluation import flight
from magcal_evaluation.accuracy_report import _git_description, run_record


def _f(x: float | None, fmt: str = "{:.2f}") -> str:
    return "–" if x is None or not math.isfinite(x) else fmt.format(x)


def _cell(text: str) -> str:
    """Text for a table cell: no pipes or line breaks."""
    return " ".join(str(text).replace("|", "/").split())


# ----------------------------------------------------------------------------- running
def flight_logs(folder: Path) -> list[Path]:
    """The DataFlash logs of a flight-log folder, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() == ".bin" and p.is_file())


def real_logs(folder: Path) -> list[Path]:
    """Every log under a real-log folder (its README and other text left out), sorted."""
    return sorted(
        p
        for p in folder.rglob("*")
        if p.is_file() and p.suffix.lower() in (".bin", ".log", ".tlog", ".ulg")
    )


def truth_path(log: Path) -> Path:
    return log.with_name(log.stem + ".truth.json")


def score(log: Path, tools: Path, candidates: dict[str, str], out: Path, cache: Path) -> dict:
    """``score_flight.py LOG SPEC… --label L… --json OUT``: label → the scorer's row, plus
    ``_meta`` (the Earth field, the lag, sample counts) and ``_seconds``."""
    argv = [sys.executable, str(tools / "score_flight.py"), str(log), *candidates.values()]
    for label in candidates:
        argv += ["--label", label]
    argv += ["--json", str(out)]
    step = flight.run_step(
        argv, out.parent, flight.SCORE_TIMEOUT_S, env={"FLIGHTLOG_CACHE": str(cache)}
    )
    if step["rc"] != 0 or not out.exists():
        return {"_error": f"score_flight.py exited with {step['rc']}: {step['stderr'][-300:]}"}
    data = json.loads(out.read_text(encoding="utf-8"))
    rows = {r["label"]: r for r in data["rows"] if "label" in r}
    for r in data["rows"]:
        if "error" in r:
            rows.setdefault(r["spec"], {"error": r["error"]})
    meta = {k: v for k, v in data.items() if k != "rows"}
    return {**rows, "_meta": meta, "_seconds": step["seconds"]}


def compass2(result_path: str, param_file: str, truth: dict, field_ned) -> dict:
    """Compass 2 of magcal's parameter file against the calibration in force, which is right
    for the flight logs' compass 2 (their README): SO(3) heading error and motor vector."""
    import numpy as np

    res = json.loads(Path(result_path).read_text(encoding="utf-8"))
    listed = (res.get("extra") or {}).get("compasses") or res.get("compasses") or []
    if not any(int(c.get("compass", 0)) == 2 for c in listed):
        return {"missing": "the result has no compass 2"}
    inforce = {k.upper(): float(v) for k, v in truth.get("in_force", {}).items()}
    cand = flight.ap_correction({**inforce, **flight.read_param_file(param_file)}, 2)
    ref = flight.ap_correction(inforce, 2)
    out = flight.so3_against(cand, ref, np.asarray(field_ned, float), flight.random_attitudes())
    out["mot_err"] = flight.motor_error(cand, ref)
    return out


def run_flights(logs: list[Path], work: Path, cache: Path, tools: Path, workers: int) -> list:
    """Every flight: magcal's three steps one log after another (a quiet machine: their wall
    times are a criterion), then the magfit fits ``workers`` at a time, then the scores."""
    results = []
    for log in logs:
        print(f"flight {log.name}: magcal import, calibrate, flash", file=sys.stderr)
        truth = truth_path(log)
        r = {
            "name": log.stem,
            "log": str(log),
            "sha256": flight.file_sha256(log),
            "truth": str(truth) if truth.exists() else None,
            "magcal": flight.magcal_pipeline(log, work / "flights" / log.stem),
        }
        if truth.exists():
            t = json.loads(truth.read_text(encoding="utf-8"))
            r["truth_sim"] = t.get("sim")
        results.append(r)
    jobs = [(r, label) for r in results if r["truth"] for label in flight.MAGFIT_FITS]

    def fit(job):
        r, label = job
        return flight.magfit_fit(Path(r["log"]), r["sha256"], label, cache, tools)

    print(
        f"magfit_WMM: {len(jobs)} fits ({workers} at a time; cached ones are read)", file=sys.stderr
    )
    with ThreadPoolExecutor(max_workers=workers) as pool:
        fits = list(pool.map(fit, jobs))
    for (r, label), rec in zip(jobs, fits, strict=True):
        r.setdefault("magfit", {})[label] = rec
    for r in results:
        if not r["truth"]:
            continue
        print(f"flight {r['name']}: scoring", file=sys.stderr)
        cands = {"in force": "inforce", "ideal": "ideal"}
        if r["magcal"].get("param_file"):
            cands["magcal"] = r["magcal"]["param_file"]
        for label, rec in r.get("magfit", {}).items():
            if rec.get("param_file"):
                cands[label] = rec["param_file"]
        rows = score(
            Path(r["log"]),
            tools,
            cands,
            work / "flights" / r["name"] / "scores.json",
            cache / "scorer",
        )
        r["scores"] = {k: v for k, v in rows.items() if not k.startswith("_")}
        r["score_meta"] = rows.get("_meta")
        r["score_seconds"] = rows.get("_seconds")
        r["score_error"] = rows.get("_error")
        if r["magcal"].get("param_file") and r["score_meta"]:
            truth = json.loads(Path(r["truth"]).read_text(encoding="utf-8"))
            r["compass2"] = compass2(
                r["magcal"]["result"],
                r["magcal"]["param_file"],
                truth,
                r["score_meta"]["earth_field"],
            )
    return results


def run_reallogs(logs: list[Path], root: Path, work: Path) -> list[dict]:
    """Every real log: import, calibrate (and flash --param-file where it calibrated), then
    the consistency figures of what was imported."""
    out = []
    for log in logs:
        rel = log.relative_to(root)
        name = str(rel)
        print(f"real log {name}", file=sys.stderr)
        mc = flight.magcal_pipeline(log, work / "reallogs" / "_".join(rel.parts))
        r = {"name": name, **mc}
        if mc.get("session"):
            try:
                r["consistency"] = flight.session_consistency(mc["session"], mc.get("param_file"))
            except Exception as exc:  # a figure that fails must not hide the others
                r["consistency"] = {"skipped": f"{type(exc).__name__}: {exc}"}
        out.append(r)
    return out


# ----------------------------------------------------------------------------- rendering
def outcome_line(r: dict) -> str:
    """What became of a log, in one line: calibrated (which compasses, motor), refused (the
    first sentence, at which step) or failed."""
    if r.get("error"):
        return "**failed**: " + r["error"]
    if r.get("refused"):
        return f"{r['refused_at']} refused: {r['refused']}"
    if r.get("result"):
        res = json.loads(Path(r["result"]).read_text(encoding="utf-8"))
        extra = res.get("extra") or {}
        comps = [1] + [
            int(c["compass"]) for c in (extra.get("compasses") or res.get("compasses") or [])
        ]
        motor = extra.get("motor") or res.get("motor")
        mtxt = ""
        if motor:
            mtxt = f"; motor ({motor.get('input')}) {'kept' if motor.get('kept') else 'not kept'}"
        return f"calibrated ({res.get('method')}): compass(es) {', '.join(map(str, comps))}{mtxt}"
    return "no result"


def magfit_source(rec: dict) -> str:
    if rec.get("error"):
        return "fit failed: " + rec["error"][:120]
    when = "from the cache, measured " + rec["measured_on"] if rec.get("cached") else "measured now"
    return f"fit {rec['seconds']:.0f} s ({when})"


def score_row(label: str, s: dict | None, time_txt: str, source: str) -> str:
    if not s or "error" in s:
        why = source if not s else s["error"]
        return f"| {label} | – | – | – | – | – | {time_txt} | {_cell(why)} |"
    mot = s.get("mot_err")
    return (
        f"| {label} | {s['so3_rms']:.3f} | {s['so3_max']:.2f} | {s['flight_rms']:.3f} | "
        f"{s['flight_p95']:.2f} | {_f(mot, '{:.3f}')} | {time_txt} | {_cell(source)} |"
    )


def flight_section(r: dict) -> list[str]:
    mc = r["magcal"]
    sec = mc["seconds"]
    lines = [f"### {r['name']}", ""]
    sim = r.get("truth_sim") or {}
    if sim:
        rot = sim.get("ROT")
        lines += [
            f"Error of compass 1: offsets {sim.get('OFS')} mG, DIA {sim.get('DIA')}, ODI "
            f"{sim.get('ODI')}, motor {sim.get('MOT')} mG/A, rotation "
            f"{'none' if not rot else f'{rot}° (custom)'}. Log SHA-256 `{r['sha256'][:16]}…`.",
            "",
        ]
    if r.get("score_error"):
        lines += [f"Scoring failed: {r['score_error']}", ""]
    lines += [
        "| parameters | SO(3) RMS ° | SO(3) max ° | in flight RMS ° | in flight p95 ° | "
        "motor error mG/A | wall time s | source |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    scores = r.get("scores") or {}
    lines.append(score_row("in force", scores.get("in force"), "–", "the log's PARM values"))
    lines.append(score_row("truth", scores.get("ideal"), "–", "the truth's ideal parameters"))
    steps = " + ".join(f"{k} {v:.1f}" for k, v in sec.items())
    if mc.get("param_file"):
        lines.append(
            score_row(
                "magcal", scores.get("magcal"), f"{sum(sec.values()):.1f}", f"measured now: {steps}"
            )
        )
    else:
        why = outcome_line(mc)
        why = why.rstrip(".")
        lines.append(
            f"| magcal | – | – | – | – | – | {sum(sec.values()):.1f} | measured now: {steps}; "
            f"{_cell(why)}: nothing to score |"
        )
    for label, rec in (r.get("magfit") or {}).items():
        t = "–" if rec.get("seconds") is None else f"{rec['seconds']:.0f}"
        lines.append(score_row(label, scores.get(label), t, magfit_source(rec)))
    c2 = r.get("compass2")
    if c2:
        lines += [
            "",
            (
                "Compass 2 (magcal, against its right calibration in force): "
                + (
                    c2["missing"]
                    if c2.get("missing")
                    else f"SO(3) RMS {c2['so3_rms']:.3f}° (max "
                    f"{c2['so3_max']:.2f}°), motor error {_f(c2.get('mot_err'), '{:.3f}')} mG/A"
                )
            ),
        ]
    lines += [
        "",
        "magcal's steps:",
        "",
        "| step | command | exit | wall time s |",
        "|---|---|---:|---:|",
    ]
    for name, s in mc["steps"].items():
        lines.append(f"| {name} | `{flight.user_command(s)}` | {s['rc']} | {s['seconds']:.2f} |")
    lines.append("")
    return lines


def consistency_rows(r: dict) -> list[str]:
    c = r.get("consistency")
    if not c:
        return []
    if c.get("skipped"):
        return [f"| {r['name']} | – | – | {_cell(c['skipped'])} | | | |"]
    out = []
    for when in ("before", "after"):
        fig = c.get(when)
        if not fig:
            continue
        label = "in force" if when == "before" else "magcal"
        for n, v in fig["compasses"].items():
            h = fig["heading_vs_first_deg"].get(n)
            htxt = "–" if h is None else f"{h['rms']:.1f} (median {h['median']:+.1f})"
            out.append(
                f"| {r['name']} | {label} | {n} | {v['strength_ratio']:.3f} | "
                f"{100 * v['strength_spread']:.1f} % | {v['dip_error_deg']:+.1f} | {htxt} |"
            )
    return out


def render_markdown(flights: list[dict], reals: list[dict], verdicts: list, meta: dict) -> str:
    fits = [rec for r in flights for rec in (r.get("magfit") or {}).values()]
    cached = sum(1 for rec in fits if rec.get("cached"))
    lines = [
        "# magcal on flight logs",
        "",
        f"Generated by `{meta['command']}`",
        f"on {meta['date']} in {meta['wall_s']:.0f} s wall time; machine: {meta['cores']} cores "
        f"({meta['workers']} magfit fits at a time), Python {meta['python']}, pymavlink "
        f"{meta['pymavlink']}, magcal at {meta['commit']}. Flights: `{meta['flights']}`; real "
        f"logs: `{meta['reallogs']}` (see their README.md). magfit_WMM fits: {len(fits) - cached} "
        f"measured in this run, {cached} from the cache `{meta['cache']}`.",
        "",
        "Each flight log goes through `magcal import LOG -o s.csv`, `magcal calibrate s.csv -o "
        "r.json` and `magcal flash r.json --param-file p.parm`, default options, and the "
        "parameter file is scored with the flight folder's `tools/score_flight.py` against the "
        "log's truth: *SO(3)*, the heading error of ArduPilot's correction with those "
        "parameters over 3,000 random attitudes, motor interference left out (the calibration "
        "itself); *in flight*, the log's raw field corrected with the parameters (motor "
        "compensation × current), rotated by the true attitude, against the true field's "
        "heading over the airborne samples (the true parameters score about 0.3° here: the "
        "harness's floor); *motor error*, |COMPASS_MOT + SIM_MAG_MOT|. Beside it: the "
        "parameters in force during the flight (a stale calibration), the truth, and "
        "pymavlink's `magfit_WMM.py` with its four option sets, each run as "
        "`MPLBACKEND=Agg magfit_WMM.py OPTIONS --save-params m0.bin` on a copy of the log that "
        "keeps compass 1 only (`tools/keep_mag_instance.py LOG m0.bin --mag 0`). A magfit fit "
        "takes minutes, so its parameter file and wall time are cached under a key of the "
        "log's SHA-256, the options and pymavlink's version; the table says which figures "
        "were measured in this run and which come from the cache. Where magcal refuses, the "
        "first sentence of its refusal stands in its row and nothing is scored for it.",
        "",
        "## Summary",
        "",
        "| log | criterion | measured | result |",
        "|---|---|---|---|",
    ]
    for c in verdicts:
        res = "n/a" if c.passed is None else ("pass" if c.passed else "**FAIL**")
        lines.append(f"| {c.log} | {_cell(c.text)} | {_cell(c.measured)} | {res} |")
    lines += ["", "## Flights with a known error", ""]
    for r in flights:
        lines += flight_section(r)
    lines += [
        "## Real logs",
        "",
        "Each log of the real-log folder through `magcal import LOG -o s.csv` and `magcal "
        "calibrate s.csv -o r.json` (and `flash r.json --param-file p.parm` where it "
        "calibrated): what was calibrated, or the first sentence of the refusal and the step "
        "that refused. A traceback or another exit status than 0 or 2 is a failure.",
        "",
        "| log | outcome | import s | calibrate s |",
        "|---|---|---:|---:|",
    ]
    for r in reals:
        sec = r["seconds"]
        lines.append(
            f"| {r['name']} | {_cell(outcome_line(r))} | {_f(sec.get('import'))} | "
            f"{_f(sec.get('calibrate'))} |"
        )
    cons = [row for r in reals for row in consistency_rows(r)]
    lines += [
        "",
        "### Physical consistency of the imported logs",
        "",
        "For every log that imported (ArduPilot): each compass's field corrected as ArduPilot "
        "corrects it, with the parameters in force (*in force*) and, where magcal "
        "calibrated, with its parameter file over them (*magcal*), against the World Magnetic "
        "Model at the session's location and date: the field strength's median over the "
        "model's (*strength/WMM*) and its spread (std/mean), the dip below the horizontal "
        "(from the accelerometer's down, so a flight's accelerations add noise) minus the "
        "model's inclination, and the heading difference between compass n and the first "
        "compass (RMS and median, degrees, on rows where both measured). A right calibration "
        "gives a strength ratio near 1 with a small spread, a dip error near 0 and compasses "
        "that agree.",
        "",
        "| log | parameters | compass | strength/WMM | spread | dip − WMM ° | heading vs first "
        "compass ° |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    lines += cons or ["| (no log imported) | | | | | | |"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--flights", default=str(flight.DEFAULT_FLIGHTLOGS), help="flight-log folder")
    ap.add_argument("--reallogs", default=str(flight.DEFAULT_REALLOGS), help="real-log folder")
    ap.add_argument("--out", default="bench/flight.md", help="Markdown report path")
    ap.add_argument("--raw", default="out/flight.json", help="every figure as JSON")
    ap.add_argument("--work", default="out/flight", help="sessions, results, parameter files")
    ap.add_argument("--cache", default=None, help="magfit cache (default WORK/cache)")
    ap.add_argument("--workers", type=int, default=2, help="magfit fits at a time (default 2)")
    args = ap.parse_args(argv)
    if args.workers < 1:
        ap.error("--workers must be at least 1")
    # absolute: each step runs in its own work directory
    flights_dir, reals_dir = Path(args.flights).resolve(), Path(args.reallogs).resolve()
    if not flights_dir.is_dir():
        print(f"{__spec__.name}: no flight-log folder at {flights_dir}", file=sys.stderr)
        return 2
    work = Path(args.work).resolve()
    cache = Path(args.cache).resolve() if args.cache else work / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    tools = flights_dir / "tools"

    commit_at_start = _git_description()
    t0 = time.perf_counter()
    flights = run_flights(flight_logs(flights_dir), work, cache, tools, args.workers)
    reals = run_reallogs(real_logs(reals_dir), reals_dir, work) if reals_dir.is_dir() else []
    wall = time.perf_counter() - t0

    verdicts = [c for r in flights if r["truth"] for c in flight.flight_criteria(r)]
    if reals:
        verdicts.append(flight.reallog_criterion(reals))
    meta = {
        **run_record(__spec__.name, argv, args.workers, commit_at_start),
        "wall_s": wall,
        "flights": args.flights,
        "reallogs": args.reallogs,
        "cache": args.cache or str(Path(args.work) / "cache"),
        "pymavlink": flight.pymavlink_version(),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(render_markdown(flights, reals, verdicts, meta) + "\n", encoding="utf-8")
    raw = Path(args.raw)
    raw.parent.mkdir(parents=True, exist_ok=True)
    raw.write_text(
        json.dumps(
            {
                "meta": meta,
                "flights": flights,
                "reallogs": reals,
                "criteria": [c.__dict__ for c in verdicts],
            },
            indent=1,
            default=float,
        )
        + "\n",
        encoding="utf-8",
    )
    for c in verdicts:
        res = "n/a" if c.passed is None else ("pass" if c.passed else "FAIL")
        print(f"{res:>4}  {c.log}: {c.text}: {c.measured}", file=sys.stderr)
    print(f"wrote {out} and {raw} in {wall:.0f} s", file=sys.stderr)
    crashed = [r["name"] for r in flights if r["magcal"].get("error") or r.get("score_error")]
    if crashed:
        print(f"logs whose steps failed: {', '.join(crashed)}", file=sys.stderr)
    return 1 if crashed or any(c.passed is False for c in verdicts) else 0


if __name__ == "__main__":
    sys.exit(main())
