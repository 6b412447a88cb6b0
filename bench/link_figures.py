#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""Link figures: what the device protocol sustains on a 921600-baud serial line, its overhead
per sample, and how long a parameter flash takes.

    .venv/bin/python bench/link_figures.py --out bench/link.json

The SIL device (``build/sil/magcal-sil``, built with ``make -s sil``) serves the protocol on a
pseudo-terminal, which the host opens at 921600 baud like a USB-serial adapter. A pty moves
bytes as fast as both ends go: the baud rate is only a setting. So the stream figures come
three ways, each labelled in the table and the JSON:

(a) ``pty``: the pty read as fast as the host can; the rate the device and the host's client
    (magcal.device.client, pure Python framing) sustain with no line limit;
(b) ``paced 921600``: the same, but the host reads at most 92160 bytes/s (921600 baud, 8N1:
    10 bits per byte; a token bucket of 64 bytes), so the pty's buffer and then the device's
    transmit queue fill as on a real UART: the device drops samples it cannot send and counts
    them (``dropped``), as the firmware would;
(c) ``wire bound``: the arithmetic: a ``sample`` frame's bytes on the wire × 10 bits / 921600
    baud gives the most samples per second the line can carry, and the loss it must have
    above that rate.

For each target rate (simulated time paced in real time), the sensor feed (S lines, raw
counts) gets one sample per 1/rate s of wall time, for ``--seconds`` s; the host streams raw
samples and counts what arrives; the received rate is over the arrivals (first to last
sample). Loss = (fed - received) / fed; it is split into the device's
``dropped`` count (stream_stop_resp) and sequence gaps seen by the host (drops after the last
sample received are not gaps); received + dropped = fed is checked (``accounted``).

Overhead: the bytes a sample costs on the wire, measured (bytes read during the stream /
samples received) and from SPEC §1 (3 header + 30 payload + 2 CRC + 1 COBS + 1 delimiter =
37). What counts as payload: the 18 bytes of raw int16 counts (mag, acc, gyr) plus the 8-byte
timestamp t_us = 26 bytes; the rest (the 4-byte acquisition seq, framing, CRC, COBS) is
overhead: 11 bytes, 42 % of the payload. Also given against the 30-byte message payload (7
bytes, SPEC's "19 %" of the frame) and against the 18 data bytes alone.

Flash: ``flash_parameters`` (SPEC §5) over the pty, ``--flash-runs`` times alternating two
sets; the median of (1) param_set + param_get(staged) read-back + param_commit, (2) reset +
hello + param_get(active) confirmation, (3) the whole flow (info, param_get(active), the
backup file written and fsynced, 1 and 2). With the wire time of the bytes exchanged in (1)
and (1 + 2) at 921600 and 115200 baud, which a real UART adds. The SIL's flash is a file and
its reset in-process, so a board also adds its flash erase/write time and its boot time.

Prints a Markdown table and writes the figures as JSON.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import random
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from magcal.device import fixed_point
from magcal.device.client import DeviceClient, DeviceTimeoutError, Sample, StreamKind
from magcal.device.flash import flash_parameters
from magcal.device.framing import encode_message
from magcal.link import open_link
from magcal_evaluation.sil import build_sil, start_sil

FORMAT = "magcal-link-figures/1"
BAUD = 921_600
BITS_PER_BYTE = 10  # 8N1: start bit, 8 data bits, stop bit
PACED_BUCKET_BYTES = 64  # a UART FIFO's worth: the most the paced reader takes at once
DEFAULT_RATES_HZ = (1000, 2000, 5000)
DEFAULT_SECONDS = 3.0
DEFAULT_FLASH_RUNS = 10
TARGET_RATE_HZ = 1000.0
TARGET_LOSS = 0.001  # < 0.1 %
FEED_TICK_S = 0.001  # the feeder sends what is due every millisecond
DRAIN_IDLE_S = 0.3  # the stream has ended when no sample came for this long
STREAM_READ_TIMEOUT_S = 0.05
FEED_CONNECT_TIMEOUT_S = 5.0
LINK_OPEN_TIMEOUT_S = 5.0
RAW_DATA_BYTES = 18  # mag, acc, gyr: 9 int16
TIMESTAMP_BYTES = 8  # t_us u64
SEQ_BYTES = 4  # the acquisition seq u32


class MeteredLink:
    """A Link wrapper that counts bytes each way; with ``bytes_per_s`` its reads are paced
    to that rate (a token bucket of PACED_BUCKET_BYTES), as a UART delivers them."""

    def __init__(self, link, bytes_per_s: float | None = None) -> None:
        self.link = link
        self.url = link.url
        self.bytes_per_s = bytes_per_s
        self.rx = 0
        self.tx = 0
        self._tokens = float(PACED_BUCKET_BYTES)
        self._last = time.monotonic()

    def _refill(self) -> None:
        now = time.monotonic()
        self._tokens = min(
            float(PACED_BUCKET_BYTES), self._tokens + (now - self._last) * self.bytes_per_s
        )
        self._last = now

    def read(self, timeout_s: float, max_bytes: int = 4096) -> bytes:
        if self.bytes_per_s:
            self._refill()
            if self._tokens < 1.0:
                time.sleep((1.0 - self._tokens) / self.bytes_per_s)
                self._refill()
            max_bytes = max(1, min(max_bytes, int(self._tokens)))
        data = self.link.read(timeout_s, max_bytes)
        if self.bytes_per_s:
            self._tokens -= len(data)
        self.rx += len(data)
        return data

    def write(self, data: bytes, timeout_s: float | None = None) -> None:
        self.link.write(data, timeout_s)
        self.tx += len(data)

    def close(self) -> None:
        self.link.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def sample_lines(n: int, rate_hz: float, t0_us: int, seed: int) -> list[bytes]:
    """n S lines (raw counts, pseudo-random) 1/rate_hz apart, starting at t0_us."""
    rng = random.Random(seed)
    out = []
    for k in range(n):
        t = t0_us + (k * 1_000_000) // int(rate_hz)
        counts = " ".join(str(rng.randint(-30000, 30000)) for _ in range(9))
        out.append(f"S {t} {counts}\n".encode("ascii"))
    return out


class Feeder(threading.Thread):
    """Sends lines to the feed socket, line k at k / rate_hz s after start (batched each
    FEED_TICK_S)."""

    def __init__(self, sock: socket.socket, lines: list[bytes], rate_hz: float) -> None:
        super().__init__(daemon=True)
        self.sock, self.lines, self.rate_hz = sock, lines, rate_hz
        self.sent = 0
        self.seconds = 0.0
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            t0 = time.monotonic()
            n = len(self.lines)
            while self.sent < n:
                due = min(n, int((time.monotonic() - t0) * self.rate_hz) + 1)
                if due > self.sent:
                    self.sock.sendall(b"".join(self.lines[self.sent : due]))
                    self.sent = due
                time.sleep(FEED_TICK_S)
            self.seconds = time.monotonic() - t0
        except BaseException as exc:  # reported by the main thread
            self.error = exc


def stream_run(
    client: DeviceClient, link: MeteredLink, feed: socket.socket, rate_hz: float, seconds: float
) -> dict:
    """Feed ``rate_hz`` samples/s for ``seconds`` and stream them raw; the figures."""
    n = int(round(rate_hz * seconds))
    t0_us = stream_run.t_us
    lines = sample_lines(n, rate_hz, t0_us, seed=int(rate_hz))
    stream_run.t_us = t0_us + (n + 1) * 1_000_000 // int(rate_hz) + 1_000_000
    client.stream_start(StreamKind.RAW)
    rx0 = link.rx
    feeder = Feeder(feed, lines, rate_hz)
    seqs: list[int] = []
    first = last = None
    feeder.start()
    idle_since = None
    while True:
        try:
            s = client.read_stream(STREAM_READ_TIMEOUT_S)
        except DeviceTimeoutError:
            if feeder.is_alive():
                continue
            idle_since = idle_since or time.monotonic()
            if time.monotonic() - idle_since >= DRAIN_IDLE_S:
                break
            continue
        idle_since = None
        now = time.monotonic()
        first = first or now
        last = now
        assert isinstance(s, Sample)
        seqs.append(s.seq)
    feeder.join()
    if feeder.error is not None:
        raise feeder.error
    rx_bytes = link.rx - rx0
    stats = client.stream_stop()
    received = len(seqs)
    gaps = sum(b - a - 1 for a, b in zip(seqs, seqs[1:], strict=False) if b - a > 1)
    span = (seqs[-1] - seqs[0] + 1) if seqs else 0
    return {
        "target_rate_hz": rate_hz,
        "fed": n,
        "feed_rate_hz": round(n / feeder.seconds, 1) if feeder.seconds else None,
        "received": received,
        # Over the arrivals (first to last): a backlog drained after the feed ended counts at
        # the rate it came, not as if it had arrived while feeding.
        "received_rate_hz": round((received - 1) / (last - first), 1) if received > 1 else None,
        "device_sent": stats.sent,
        "device_dropped": stats.dropped,
        "seq_gaps": gaps,
        "seq_span": span,
        "loss": (n - received) / n,
        "accounted": stats.sent + stats.dropped == n and stats.sent >= received,
        "host_queue_dropped": client.stats.stream_queue_dropped,
        "bytes_per_sample_measured": round(rx_bytes / received, 3) if received else None,
        "stream_seconds": round(last - first, 3) if first else 0.0,
    }


stream_run.t_us = 1_000_000


def wire_bound(bytes_per_sample: int, baud: int = BAUD) -> float:
    """Samples per second a line of ``baud`` carries at most (8N1)."""
    return baud / (BITS_PER_BYTE * bytes_per_sample)


def two_sets() -> tuple[bytes, bytes]:
    """Two valid, different parameter sets (counts in, unit-norm field out)."""
    out = []
    for scale, off in ((1 / 3400.0, (120.0, -80.0, 300.0)), (1 / 3300.0, (-40.0, 55.0, 10.0))):
        d_inv = np.array([[1.0, 0.02, -0.01], [0.0, 0.97, 0.015], [0.01, -0.02, 1.03]]) * scale
        out.append(fixed_point.encode(fixed_point.from_calibration(d_inv, np.array(off))))
    return out[0], out[1]


def flash_runs(client: DeviceClient, link: MeteredLink, runs: int, tmp: Path) -> dict:
    """``runs`` flashes alternating two sets; medians of the phases (seconds)."""
    sets = two_sets()
    phases: dict[str, list[float]] = {"write_readback_commit": [], "reset_confirm": [], "total": []}
    wire_bytes: dict[str, list[int]] = {"write_readback_commit": [], "write_to_confirm": []}
    for k in range(runs):
        marks: dict[str, tuple[float, int]] = {}

        def progress(text: str, marks=marks) -> None:
            marks.setdefault(text.split(":", 1)[0], (time.perf_counter(), link.rx + link.tx))

        t0 = time.perf_counter()
        flash_parameters(
            client,
            sets[k % 2],
            fixed_point.FORMAT_VERSION,
            tmp / f"backup-{k}.json",
            progress=progress,
        )
        t1, b1 = time.perf_counter(), link.rx + link.tx
        ts, bs = marks["param_set"]
        tr, br = marks["reset"]
        phases["write_readback_commit"].append(tr - ts)
        phases["reset_confirm"].append(t1 - tr)
        phases["total"].append(t1 - t0)
        wire_bytes["write_readback_commit"].append(br - bs)
        wire_bytes["write_to_confirm"].append(b1 - bs)
    med = {f"{k}_s_median": statistics.median(v) for k, v in phases.items()}
    out = {
        "runs": runs,
        **{k: round(v, 6) for k, v in med.items()},
        **{f"{k}_s_max": round(max(v), 6) for k, v in phases.items()},
    }
    for k, v in wire_bytes.items():
        b = statistics.median(v)
        out[f"{k}_bytes"] = b
        out[f"{k}_wire_s_921600"] = round(b * BITS_PER_BYTE / BAUD, 6)
        out[f"{k}_wire_s_115200"] = round(b * BITS_PER_BYTE / 115_200, 6)
    return out


def measure(rates: list[float], seconds: float, runs: int) -> dict:
    build_sil()
    with tempfile.TemporaryDirectory(prefix="magcal-link-") as tmp_name:
        tmp = Path(tmp_name)
        with start_sil(tmp / "flash.bin", pty=True) as sil:
            print(f"link figures: magcal-sil on {sil.pty} at {BAUD} baud", file=sys.stderr)
            feed = socket.create_connection(("127.0.0.1", sil.feed_port), FEED_CONNECT_TIMEOUT_S)
            feed.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            streams = []
            with open_link(sil.pty, LINK_OPEN_TIMEOUT_S, baudrate=BAUD) as raw_link:
                for mode, pace in (("pty", None), ("paced 921600", BAUD / BITS_PER_BYTE)):
                    link = MeteredLink(raw_link, pace)
                    client = DeviceClient(link)
                    client.hello()
                    for rate in rates:
                        r = {"mode": mode, **stream_run(client, link, feed, rate, seconds)}
                        print(
                            f"  {mode:>13} {rate:6.0f} Hz: received {r['received']} of "
                            f"{r['fed']}, dropped {r['device_dropped']}, loss "
                            f"{100 * r['loss']:.3f} %",
                            file=sys.stderr,
                        )
                        streams.append(r)
                link = MeteredLink(raw_link)
                client = DeviceClient(link)
                client.hello()
                flash = flash_runs(client, link, runs, tmp)
            feed.close()
    return {"streams": streams, "flash": flash}


def overhead() -> dict:
    """Bytes of a sample frame on the wire (encoded here, as the device does) vs payload."""
    frame = encode_message(
        "sample",
        0,
        {"seq": 1, "t_us": 1_000_000, "mag": [1, 2, 3], "acc": [4, 5, 6], "gyr": [7, 8, 9]},
    )
    wire = len(frame)
    payload = RAW_DATA_BYTES + TIMESTAMP_BYTES
    return {
        "sample_frame_wire_bytes": wire,
        "message_payload_bytes": RAW_DATA_BYTES + TIMESTAMP_BYTES + SEQ_BYTES,
        "payload_bytes": payload,
        "payload_definition": "raw int16 counts (18 bytes: mag, acc, gyr) + t_us (8 bytes)",
        "overhead_bytes": wire - payload,
        "overhead_vs_payload": round((wire - payload) / payload, 4),
        "overhead_vs_message_payload_bytes": wire - (payload + SEQ_BYTES),
        "overhead_vs_raw_data_bytes": wire - RAW_DATA_BYTES,
        "wire_bound_hz_921600": round(wire_bound(wire), 1),
        "wire_bound_hz_115200": round(wire_bound(wire, 115_200), 1),
    }


def table(doc: dict) -> str:
    ov = doc["overhead"]
    bound = ov["wire_bound_hz_921600"]
    lines = [
        f"## Link figures ({doc['date']}, {doc['machine']})",
        "",
        "| mode | target Hz | fed | received | received Hz | device dropped | seq gaps | loss "
        "| bytes/sample |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in doc["streams"]:
        lines.append(
            f"| {r['mode']} | {r['target_rate_hz']:.0f} | {r['fed']} | {r['received']} | "
            f"{r['received_rate_hz']} | {r['device_dropped']} | {r['seq_gaps']} | "
            f"{100 * r['loss']:.3f} % | {r['bytes_per_sample_measured']} |"
        )
    for rate in sorted({r["target_rate_hz"] for r in doc["streams"]}):
        loss = max(0.0, 1.0 - bound / rate)
        lines.append(
            f"| wire bound 921600 | {rate:.0f} | | | {min(rate, bound):.0f} | | | "
            f"{100 * loss:.3f} % | {ov['sample_frame_wire_bytes']} |"
        )
    t = doc["target"]
    lines += [
        "",
        f"Target: ≥ {t['rate_hz']:.0f} Hz with < {100 * t['loss']:.1f} % loss at 921600 baud: "
        f"{'PASS' if t['met'] else 'FAIL'} ({t['why']}).",
        "",
        f"Overhead: a sample is {ov['sample_frame_wire_bytes']} bytes on the wire for "
        f"{ov['payload_bytes']} bytes of payload ({ov['payload_definition']}): "
        f"{ov['overhead_bytes']} bytes ({100 * ov['overhead_vs_payload']:.0f} % of the payload); "
        f"{ov['overhead_vs_message_payload_bytes']} bytes over the 30-byte message payload "
        f"(which also has the 4-byte seq), {ov['overhead_vs_raw_data_bytes']} over the 18 data "
        f"bytes alone. Wire bound: {bound:.0f} samples/s at 921600 baud, "
        f"{ov['wire_bound_hz_115200']:.0f} at 115200.",
        "",
    ]
    f = doc["flash"]
    ms = 1000.0
    lines += [
        f"| flash ({f['runs']} runs over the pty) | median ms | max ms | wire ms at 921600 "
        "| wire ms at 115200 |",
        "| --- | ---: | ---: | ---: | ---: |",
        f"| param_set + read-back + commit | {ms * f['write_readback_commit_s_median']:.2f} | "
        f"{ms * f['write_readback_commit_s_max']:.2f} | "
        f"{ms * f['write_readback_commit_wire_s_921600']:.2f} | "
        f"{ms * f['write_readback_commit_wire_s_115200']:.2f} |",
        f"| reset + hello + confirm | {ms * f['reset_confirm_s_median']:.2f} | "
        f"{ms * f['reset_confirm_s_max']:.2f} | | |",
        f"| whole flow (info, backup, all above) | {ms * f['total_s_median']:.2f} | "
        f"{ms * f['total_s_max']:.2f} | {ms * f['write_to_confirm_wire_s_921600']:.2f} "
        f"(write to confirm) | {ms * f['write_to_confirm_wire_s_115200']:.2f} |",
        "",
        "The SIL's flash is a file and its reset is in-process: a board adds its flash erase "
        "and write (a sector erase can take 1-2 s) to the commit, its boot time to the reset, "
        "and the wire time of the bytes to both.",
    ]
    return "\n".join(lines)


def target_verdict(streams: list[dict], ov: dict) -> dict:
    """≥ 1 kHz with < 0.1 % loss: met when the paced-921600 run at 1 kHz lost < 0.1 % and the
    wire bound is above 1 kHz."""
    paced = [
        r for r in streams if r["mode"] == "paced 921600" and r["target_rate_hz"] == TARGET_RATE_HZ
    ]
    bound = ov["wire_bound_hz_921600"]
    if not paced:
        return {"rate_hz": TARGET_RATE_HZ, "loss": TARGET_LOSS, "met": False, "why": "not run"}
    loss = paced[0]["loss"]
    met = loss < TARGET_LOSS and bound >= TARGET_RATE_HZ
    return {
        "rate_hz": TARGET_RATE_HZ,
        "loss": TARGET_LOSS,
        "met": met,
        "why": f"paced 921600 at 1 kHz lost {100 * loss:.3f} %, wire bound {bound:.0f} Hz",
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, help="write the figures as JSON here")
    ap.add_argument(
        "--rates",
        default=",".join(str(r) for r in DEFAULT_RATES_HZ),
        help="target sample rates, Hz, comma-separated",
    )
    ap.add_argument("--seconds", type=float, default=DEFAULT_SECONDS, help="per rate and mode")
    ap.add_argument("--flash-runs", type=int, default=DEFAULT_FLASH_RUNS)
    args = ap.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",") if r.strip()]
    t0 = time.perf_counter()
    m = measure(rates, args.seconds, args.flash_runs)
    ov = overhead()
    doc = {
        "format": FORMAT,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {platform.system()}, python {platform.python_version()}",
        "baud": BAUD,
        "seconds_per_rate": args.seconds,
        "modes": {
            "pty": "the pty read as fast as the host can: no line limit (a pty ignores baud)",
            "paced 921600": "host reads paced to 92160 bytes/s (921600 baud 8N1), so the "
            "device's transmit queue fills as on a UART and it drops and counts samples",
            "wire bound 921600": "computed: 921600 / (10 bits x sample frame bytes)",
        },
        "overhead": ov,
        "streams": m["streams"],
        "target": target_verdict(m["streams"], ov),
        "flash": m["flash"],
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    print(table(doc))
    if args.out:
        args.out.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
