# SPDX-License-Identifier: Apache-2.0
"""The end-to-end demo (``make demo``): an emulated device with a random distortion, tumbled
by the world simulator while the real command line collects, calibrates, flashes and
verifies; then the heading error and the field-norm spread before and after, against the
simulator's truth.

    python -m magcal_evaluation.demo [--out out/demo] [--seed N] [--speedup X] [--duration S]

Steps (each one printed as it starts, with the wall-clock time):

1. start ``build/sil/magcal-sil`` (TCP) on a fresh flash file; draw a sensor with a random
   distortion (soft iron x misalignment D, hard iron o, noise: ``magcal.sim``'s MEMS or
   hand-held sampler, from the seed) in a 50 uT field, and a tumbling motion;
2. feed the sensors from a thread (:class:`magcal_evaluation.world.WorldFeeder`, real time or sped
   up: the device's clock is the feed's) while ``magcal collect`` records the session;
3. ``magcal calibrate --method ml`` (with the plots), ``magcal flash`` (with a backup),
   ``magcal verify``, each fed likewise; the feeder pauses in between, so the device's time
   stands still while the host computes;
4. the device's own corrected stream of the same motion read without noise (so what is left
   is the calibration's error, and the counts' rounding), each sample matched by its time to
   the attitude the world fed it with.

The figures (:class:`DemoReport`):

- the calibration-induced heading error (``magcal_evaluation.accuracy.heading_rms_deg``
  over the SO(3) grid, noise-free) of no calibration (identity, zero offset) and of the ML
  result. The truth is in the session's field unit (|m| = 1); the device reads
  ``k (D R m + o)`` counts (k counts per field unit, :attr:`World.counts_per_unit`), and the
  session holds those counts times its unit's size u (found by matching the session's rows
  to the fed counts); both are compared in raw counts: truth ``(k D, k o)``, result
  ``(D/u, o/u)``;
- from the device's corrected stream: heading error of each sample rotated to north with the
  true attitude (raw counts as "before", the device's output as "after"), and the spread of
  the field norm (std / mean), raw and corrected;
- the device's fixed-point output against the host's float64 correction ``D_inv (y - o)``
  of the result file (unquantised D_inv and o), in output LSBs, unrounded: at most 1 LSB,
  which the default output exponent of ``fixed_point.from_calibration`` guarantees (output
  rounding 1/2 LSB plus the parameters' quantisation at most 1/2 LSB).

Everything is written under the output directory: session.csv, result.json, backup.json,
plots/, flash.bin, device.csv (the corrected stream) and report.json.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import secrets
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from magcal.calib import frames
from magcal.calib.diagnostics import quality
from magcal.device.client import (
    ClientConfig,
    Corrected,
    DeviceClient,
    DeviceInfo,
    StreamKind,
)
from magcal.errors import MagcalError
from magcal.io.result import read_result
from magcal.io.session import Session, read_session
from magcal.link import LINK_OPEN_TIMEOUT_S, open_link
from magcal_evaluation.accuracy import heading_rms_deg
from magcal_evaluation.sil import (
    REPO_ROOT,
    SIL_BINARY,
    SIL_BINARY_ENV,
    SilProcess,
    build_sil,
    default_binary,
    start_sil,
)
from magcal_evaluation.world import (
    FIELD_STRENGTH_T,
    FeedClient,
    World,
    WorldFeeder,
    make_world,
    tumbling_session,
)

MAGCAL = REPO_ROOT / "host" / "magcal"
#: Margin on a step's expected wall time before it is declared hung, s.
STEP_TIMEOUT_MARGIN_S = 60.0
#: Wait for one streamed sample while the world feeds, s.
STREAM_SAMPLE_TIMEOUT_S = 5.0
#: Extra motion beyond the steps' own samples, for the start-up latency of each fed command
#: while the world already feeds: this many device seconds plus this many wall seconds.
WORLD_SLACK_S = 20.0
WORLD_SLACK_WALL_S = 8.0

Log = Callable[[str], None]


class DemoError(MagcalError):
    """A step of the demo failed (the message names it)."""


@dataclass(frozen=True)
class DemoConfig:
    """out_dir: where everything goes; seed: the sensor, motion and noise (None: random);
    kind: "mems" or "handheld"; collect_s, verify_s, check_s: device seconds of each
    step; speedup: device seconds per wall second; field_t: the field, tesla."""

    out_dir: Path = REPO_ROOT / "out" / "demo"
    seed: int | None = None
    kind: str = "mems"
    collect_s: float = 40.0
    verify_s: float = 5.0
    check_s: float = 10.0
    speedup: float = 2.0
    field_t: float = FIELD_STRENGTH_T
    sil_binary: Path = field(default_factory=default_binary)


@dataclass
class DemoReport:
    """The demo's figures (degrees, percent, LSB) and what they came from."""

    seed: int
    kind: str
    steps: dict[str, str] = field(default_factory=dict)  # step -> "cli": ran host/magcal
    session_samples: int = 0
    session_unit_per_count: float = 0.0
    heading_grid_identity_deg: float = math.nan
    heading_grid_ml_deg: float = math.nan
    device_samples: int = 0
    heading_device_raw_deg: float = math.nan
    heading_device_corrected_deg: float = math.nan
    norm_spread_raw_pct: float = math.nan
    norm_spread_corrected_pct: float = math.nan
    max_lsb_diff: float = math.nan  # |device - host float|, unrounded
    max_lsb_diff_rounded: float = math.nan  # |device - host float rounded to an LSB|
    seconds: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------- helpers


def run_cli(args: list[str], timeout_s: float, log: Log) -> None:
    """Run ``host/magcal ARGS`` as a user would, its output logged line by line (indented);
    DemoError when it exits non-zero or takes longer than timeout_s (then it is killed)."""
    cmd = [str(MAGCAL), *args]
    log("  $ magcal " + " ".join(args))
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    tail: list[str] = []

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            line = line.rstrip("\n").split("\r")[-1]
            tail.append(line)
            del tail[:-20]
            log("    " + line)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        status = proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5.0)
        raise DemoError(f"magcal {args[0]} did not finish within {timeout_s:.0f} s") from None
    finally:
        reader.join(5.0)
        if proc.stdout is not None:
            proc.stdout.close()
    if status != 0:
        raise DemoError(f"magcal {args[0]} exited with status {status}:\n" + "\n".join(tail))


def _client(url: str) -> DeviceClient:
    return DeviceClient(open_link(url, LINK_OPEN_TIMEOUT_S), ClientConfig())


def _read_stream(client: DeviceClient, duration_s: float, kind: type) -> list:
    """Stream messages of ``kind`` until they span duration_s of device time."""
    out: list = []
    while True:
        s = client.read_stream(STREAM_SAMPLE_TIMEOUT_S)
        if not isinstance(s, kind):
            continue
        out.append(s)
        if s.t_us - out[0].t_us >= duration_s * 1e6:
            return out


# ------------------------------------------------------------------------- figures


#: Sizes of one unit in tesla that a session's magnetometer column may be written in.
_UNIT_IN_T = {"T": 1.0, "mT": 1e-3, "uT": 1e-6, "nT": 1e-9, "G": 1e-4, "mG": 1e-7}


def match_session(session: Session, world: World, info: DeviceInfo) -> tuple[float, np.ndarray]:
    """The size u of one raw magnetometer count in the session's unit, and the world index
    of every session row, found by matching the session's magnetometer rows to the counts
    the world fed (raw counts, or counts times the count's size in one of T, mT, uT, nT, G,
    mG). DemoError when no unit makes every row a fed sample."""
    count_t = info.sensor("mag").count_scale.si
    mag = np.asarray(session.mag, dtype=np.float64)
    candidates = [1.0] + [count_t / size for size in _UNIT_IN_T.values()]
    for u in candidates:
        counts = mag / u
        if np.max(np.abs(counts - np.rint(counts))) > 1e-6 * max(1.0, np.max(np.abs(counts))):
            continue
        c = np.rint(counts).astype(np.int64)
        first = np.flatnonzero(np.all(world.mag == c[0], axis=1))
        for k0 in first:
            # Times: the session's t minus its first row's, plus the world's time there.
            t_us = world.t_us[k0] + np.rint((session.t - session.t[0]) * 1e6).astype(np.int64)
            try:
                idx = world.indices(t_us)
            except MagcalError:
                continue
            if np.array_equal(world.mag[idx], c):
                return u, idx
    raise DemoError(
        "the session's magnetometer rows do not match the samples the world fed in any known "
        "unit (raw counts, T, mT, uT, nT, G, mG): cannot compare the result with the truth"
    )


def device_figures(
    cor: list[Corrected], world: World, result_path: Path, unit_per_count: float
) -> dict[str, float]:
    """Heading errors (true attitude), norm spreads and the LSB difference from the device's
    corrected stream ``cor`` (fed by ``world``)."""
    idx = world.indices([s.t_us for s in cor])
    raw = np.array([s.mag for s in cor], dtype=np.int64)
    if not np.array_equal(raw, world.mag[idx]):
        raise DemoError("the device's raw counts differ from what the world fed at those times")
    out_exp = np.array([s.out_exp for s in cor])
    got = np.array([s.m_b for s in cor], dtype=np.float64)
    m_dev = np.ldexp(got, out_exp[:, None] - 31)
    R_nb = frames.quat_to_matrix(world.truth.q_nb[idx])

    def heading_rms(v_b: np.ndarray) -> float:
        v_n = np.einsum("kij,kj->ki", R_nb, v_b)
        return quality.rms_deg(frames.wrap_angle(frames.heading_of(v_n)))

    def spread_pct(v: np.ndarray) -> float:
        n = np.linalg.norm(v, axis=1)
        return float(100.0 * n.std() / n.mean())

    # The host's float64 correction of the same counts from the result file, in output LSBs.
    result = read_result(result_path)
    y = raw.astype(np.float64) * unit_per_count
    host = (y - result.o) @ np.asarray(result.D_inv, dtype=np.float64).T
    host_lsb = np.ldexp(host, 31 - out_exp[:, None])
    return {
        "device_samples": len(cor),
        "heading_device_raw_deg": heading_rms(raw.astype(np.float64)),
        "heading_device_corrected_deg": heading_rms(m_dev),
        "norm_spread_raw_pct": spread_pct(raw.astype(np.float64)),
        "norm_spread_corrected_pct": spread_pct(m_dev),
        "max_lsb_diff": float(np.max(np.abs(got - host_lsb))),
        "max_lsb_diff_rounded": float(np.max(np.abs(got - np.rint(host_lsb)))),
    }


def write_device_csv(path: Path, cor: list[Corrected]) -> None:
    rows = [(s.seq, s.t_us, *s.mag, s.out_exp, *s.m_b) for s in cor]
    header = "seq,t_us,mag_x,mag_y,mag_z,out_exp,m_x,m_y,m_z"
    np.savetxt(path, np.array(rows, dtype=np.int64), fmt="%d", delimiter=",", header=header)


def format_report(r: DemoReport) -> str:
    """The before/after table."""
    rows = [
        ("heading error, SO(3) grid, deg", r.heading_grid_identity_deg,
         r.heading_grid_ml_deg, "{:.3f}"),
        (f"heading error, device stream ({r.device_samples} samples), deg",
         r.heading_device_raw_deg, r.heading_device_corrected_deg, "{:.3f}"),
        ("field norm spread (std/mean), device stream, %", r.norm_spread_raw_pct,
         r.norm_spread_corrected_pct, "{:.3f}"),
    ]  # fmt: skip
    w = max(len(name) for name, *_ in rows)
    lines = [f"{'':{w}}  {'before (raw)':>13}  {'after (ML)':>11}"]
    for name, before, after, fmt in rows:
        lines.append(f"{name:{w}}  {fmt.format(before):>13}  {fmt.format(after):>11}")
    verdict = "within 1 LSB" if r.max_lsb_diff <= 1.0 else "BEYOND 1 LSB"
    lines.append(
        f"device fixed-point output vs the host's float64 D_inv (y - o) of result.json in "
        f"output LSBs, {r.device_samples} samples: max {r.max_lsb_diff:.3f} LSB unrounded "
        f"({verdict}), {r.max_lsb_diff_rounded:.0f} LSB with the host value rounded to the LSB"
    )
    return "\n".join(lines)


# --------------------------------------------------------------------------------- demo


def run_demo(cfg: DemoConfig, log: Log = print) -> DemoReport:
    """The whole demo (see the module docstring); returns its figures."""
    seed = cfg.seed if cfg.seed is not None else secrets.randbelow(2**31)
    report = DemoReport(seed=seed, kind=cfg.kind)
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()

    def step(text: str) -> None:
        log(f"[{time.monotonic() - t_start:6.1f} s] {text}")

    flash_file = out / "flash.bin"
    flash_file.unlink(missing_ok=True)  # a fresh, uncalibrated device every run
    backup = out / "backup.json"
    backup.unlink(missing_ok=True)
    binary = Path(cfg.sil_binary).resolve()
    shown = binary.relative_to(REPO_ROOT) if binary.is_relative_to(REPO_ROOT) else binary
    step(f"starting {shown} (TCP) on {flash_file}")
    with start_sil(flash_file, binary=cfg.sil_binary) as sil:
        report = _run_on_device(cfg, sil, report, out, backup, step, log)
        step("stopping magcal-sil")
        status = sil.stop()
        if status != 0:
            raise DemoError(f"magcal-sil exited with status {status}: {sil.stderr_text()}")
    report.seconds["total"] = time.monotonic() - t_start
    (out / "report.json").write_text(json.dumps(asdict(report), indent=2) + "\n")
    return report


def _run_on_device(
    cfg: DemoConfig,
    sil: SilProcess,
    report: DemoReport,
    out: Path,
    backup: Path,
    step: Callable[[str], None],
    log: Log,
) -> DemoReport:
    url = sil.url
    with _client(url) as client:
        client.hello()
        info = client.info()
    rate = info.sample_rate_hz
    # verify streams corrected then raw samples: twice its length.
    slack_s = WORLD_SLACK_S + WORLD_SLACK_WALL_S * cfg.speedup
    total_s = cfg.collect_s + 2 * cfg.verify_s + cfg.check_s + slack_s
    session_sim, truth = tumbling_session(total_s, report.seed, kind=cfg.kind, rate_hz=rate)
    world = make_world(session_sim, truth, info, field_t=cfg.field_t, t0_us=1_000_000)
    ideal = make_world(session_sim, truth, info, field_t=cfg.field_t, noise=False, t0_us=1_000_000)
    D_c, o_c = world.calibration_counts()
    step(
        f"device at {url}, feed port {sil.feed_port}; world: {cfg.kind} sensor, seed "
        f"{report.seed}, {cfg.field_t * 1e6:g} uT field ({world.counts_per_unit:.1f} counts), "
        f"tumbling {len(world)} samples at {rate:g} Hz, speed-up {cfg.speedup:g}x"
    )
    with np.printoptions(precision=3, suppress=True):
        log(f"    true D (counts) {np.array2string(D_c, prefix=' ' * 20)}")
        log(f"    true o (counts) {o_c}")

    session_path = out / "session.csv"
    result_path = out / "result.json"
    wall = cfg.speedup
    timeout = STEP_TIMEOUT_MARGIN_S

    with (
        FeedClient("127.0.0.1", sil.feed_port) as feed,
        WorldFeeder(world, feed, speedup=cfg.speedup) as feeder,
    ):

        def fed_step(name: str, action: Callable[[], None]) -> None:
            t0 = time.monotonic()
            feeder.resume()
            try:
                action()
            except MagcalError as exc:
                if feeder.exhausted.is_set():
                    raise DemoError(
                        f"{name}: the world ran out of motion ({len(world)} samples fed); "
                        "a command waited longer than expected"
                    ) from exc
                raise
            finally:
                feeder.pause()
            report.seconds[name] = time.monotonic() - t0

        # collect
        report.steps["collect"] = "cli"
        step(f"collect: {cfg.collect_s:g} s of device time while the world tumbles")
        # --max-samples: collect_s of device time whatever the speed-up (--duration is the
        # host's clock).
        n_samples = round(cfg.collect_s * rate)
        args = ["collect", "--port", url, "-o", str(session_path)]
        args += ["--max-samples", str(n_samples), "--coverage", "off"]
        fed_step("collect", lambda: run_cli(args, cfg.collect_s / wall + timeout, log))
        session = read_session(session_path)
        u, rows = match_session(session, world, info)
        report.session_samples = len(session)
        report.session_unit_per_count = u
        log(
            f"    session: {len(session)} samples, world samples {rows[0]}..{rows[-1]}, "
            f"one count = {u:.6g} session units"
        )

        # calibrate
        report.steps["calibrate"] = "cli"
        step("calibrate: maximum likelihood")
        t0 = time.monotonic()
        run_cli(
            ["calibrate", str(session_path), "--method", "ml", "-o", str(result_path),
             "--plot", str(out / "plots")],
            timeout,
            log,
        )  # fmt: skip
        report.seconds["calibrate"] = time.monotonic() - t0
        result = read_result(result_path)
        truth_c = world.truth_counts()
        report.heading_grid_identity_deg = heading_rms_deg(truth_c, np.eye(3), np.zeros(3))
        report.heading_grid_ml_deg = heading_rms_deg(truth_c, result.D / u, result.o / u)

        # flash
        report.steps["flash"] = "cli"
        step(f"flash: {result_path.name}, backup {backup.name}")
        t0 = time.monotonic()
        args = ["flash", str(result_path), "--port", url, "--backup", str(backup)]
        if "mag_unit" in session.meta:  # the session's unit, as its header says
            args += ["--mag-unit", session.meta["mag_unit"]]
        run_cli(args, timeout, log)
        report.seconds["flash"] = time.monotonic() - t0

        # verify
        report.steps["verify"] = "cli"
        step(f"verify: {cfg.verify_s:g} s of the device's corrected output")
        # --samples: verify_s of device time whatever the speed-up.
        args = ["verify", "--port", url, "--samples", str(round(cfg.verify_s * rate))]
        fed_step("verify", lambda: run_cli(args, 2 * cfg.verify_s / wall + timeout, log))

        # the device's own corrected output, noise-free readings of the same motion
        step(f"check: {cfg.check_s:g} s of corrected output, noise-free, against the truth")
        feeder.switch(ideal)
        cor: list[Corrected] = []
        with _client(url) as client:
            client.hello()
            client.stream_start(StreamKind.CORRECTED)

            def read() -> None:
                cor.extend(_read_stream(client, cfg.check_s, Corrected))

            fed_step("check", read)
            stats = client.stream_stop()
        if stats.dropped:
            log(f"    (the device dropped {stats.dropped} stream messages: a slow host)")
        write_device_csv(out / "device.csv", cor)
    for key, value in device_figures(cor, ideal, result_path, u).items():
        setattr(report, key, value)
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m magcal_evaluation.demo", description=__doc__.split("\n")[0]
    )
    p.add_argument("--out", type=Path, default=DemoConfig.out_dir, help="output directory")
    p.add_argument("--seed", type=int, help="sensor, motion and noise (default: random)")
    p.add_argument("--kind", default="mems", choices=["mems", "handheld"])
    p.add_argument("--duration", type=float, default=DemoConfig.collect_s,
                   help="device seconds to collect")  # fmt: skip
    p.add_argument("--speedup", type=float, default=DemoConfig.speedup,
                   help="device seconds per wall-clock second (1: real time)")  # fmt: skip
    p.add_argument(
        "--sil",
        type=Path,
        metavar="PATH",
        help=f"the magcal-sil executable (default: ${SIL_BINARY_ENV}, else the checkout's "
        "build/sil/magcal-sil, brought up to date with make sil)",
    )
    p.add_argument("--no-build", action="store_true", help="do not run make sil first")
    args = p.parse_args(argv)
    binary = args.sil or default_binary()
    try:
        if not args.no_build and binary == SIL_BINARY:
            binary = build_sil()
        cfg = DemoConfig(
            out_dir=args.out,
            seed=args.seed,
            kind=args.kind,
            collect_s=args.duration,
            speedup=args.speedup,
            sil_binary=binary,
        )
        report = run_demo(cfg, log=lambda s: print(s, flush=True))
    except MagcalError as exc:
        print(f"magcal demo: {exc}", file=sys.stderr)
        return 1
    print()
    print(f"Before/after ({report.kind} sensor, seed {report.seed}; steps: "
          + ", ".join(f"{k} {v}" for k, v in report.steps.items()) + ")")  # fmt: skip
    print(format_report(report))
    print(f"wrote {cfg.out_dir}/ (session.csv, result.json, backup.json, plots/, device.csv, "
          f"report.json) in {report.seconds['total']:.0f} s")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
