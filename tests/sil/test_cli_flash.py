# SPDX-License-Identifier: Apache-2.0
"""``magcal flash`` against the SIL device (build/sil/magcal-sil over TCP), run in-process
through :func:`magcal.cli.main`:

- a result JSON of a known calibration (in uT) becomes the device's active set, equal bit for
  bit to ``fixed_point.from_calibration`` with the device's exact count scale; the backup holds
  the set before; a second flash's backup holds the first set; ``--restore`` puts it back;
  ``--dry-run``, an unrepresentable calibration, an unknown unit, an existing backup path and
  another parameter format change nothing on the device and write no backup;
- a link cut at every byte of a flash (a TCP forwarder between the CLI and the SIL that closes
  both sides after N bytes, N = 0 .. all the bytes of an uncut run; reconnections pass): the
  device then holds exactly the old or the new set, and the CLI's last words say which. And
  a cut at the start, middle and end of every frame with reconnection refused too (the CLI
  cannot ask the device afterwards and says what it can: "OLD" before the commit was sent,
  "unknown" after).
"""

from __future__ import annotations

import re
import shutil
import socket
import threading
import types
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from serial.urlhandler import protocol_socket

from magcal import cli
from magcal.calib.frames import field_direction
from magcal.device import fixed_point
from magcal.device.client import DeviceClient, DeviceError, ParamWhich
from magcal.device.flash import read_backup
from magcal.device.framing import Deframer, Frame, crc32_iso_hdlc
from magcal.device.generated import MessageId, Status
from magcal.io.result import CalibrationResult, write_result
from magcal.link import LINK_OPEN_TIMEOUT_S, open_link
from magcal_evaluation.sil import REPO_ROOT, SIL_BINARY

PROXY_JOIN_TIMEOUT_S = 5.0

pytestmark = pytest.mark.skipif(
    not SIL_BINARY.exists()
    and not ((REPO_ROOT / "mk" / "sil.mk").exists() and shutil.which("make")),
    reason="the SIL executable build/sil/magcal-sil is missing and cannot be built",
)

# Two known calibrations, uT: a 50 uT field through a skewed soft iron and a hard iron.
D_A = np.array([[48.0, 1.5, -0.7], [0.3, 52.0, 0.9], [-1.1, 0.4, 50.0]])
O_A = np.array([12.0, -7.0, 30.0])
D_B = np.array([[51.0, -0.8, 0.2], [1.2, 47.5, -0.6], [0.5, 0.9, 49.0]])
O_B = np.array([-20.0, 15.5, -4.25])
DIP_DEG = 60.0
SIL_UID = "c0ffee"
# The SIL's magnetometer (LIS3MDL at ±4 G): one count is 1/6842 gauss = 100/6842 uT, exactly.
LIS3MDL_UT_PER_COUNT = Fraction(1, 6842) * Fraction(1, 10**4) * 10**6

_HOLDS = re.compile(r"device holds (the OLD set|the NEW set|an unknown set)")
_CLAIM = {"the OLD set": "old", "the NEW set": "new", "an unknown set": "unknown"}


@pytest.fixture(autouse=True)
def no_close_pause(monkeypatch):
    """pyserial's socket:// close() sleeps 0.3 s ("give the server some time in case of quick
    reconnects"); the SIL needs none, and the sweep closes ~2 000 links."""
    monkeypatch.setattr(protocol_socket, "time", types.SimpleNamespace(sleep=lambda s: None))


def write_cal(path: Path, D, o, mag_unit: str | None = "uT") -> Path:
    extra = {} if mag_unit is None else {"mag_unit": mag_unit}
    r = CalibrationResult("ml", D, o, field_direction(np.deg2rad(DIP_DEG)), DIP_DEG, extra=extra)
    write_result(path, r)
    return path


def expected_blob(D, o) -> bytes:
    """The set magcal flash must write: from_calibration with one count in uT."""
    upc = float(LIS3MDL_UT_PER_COUNT)
    return fixed_point.encode(fixed_point.from_calibration(np.linalg.inv(D), o, unit_per_count=upc))


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = cli.main(["flash", *argv])
    out, err = capsys.readouterr()
    return rc, out, err


def active_set(port: int, reset: bool = False) -> bytes | None:
    """The device's active set (None: it has none), read over a direct link; with reset, after
    a restart (what a committed set becomes)."""
    with open_link(f"socket://127.0.0.1:{port}", LINK_OPEN_TIMEOUT_S) as link:
        c = DeviceClient(link)
        c.hello()
        if reset:
            c.reset()
            c.hello()
        try:
            p = c.param_get(ParamWhich.ACTIVE)
        except DeviceError as exc:
            if exc.status == Status.E_NO_PARAMS:
                return None
            raise
        assert p.format_version == fixed_point.FORMAT_VERSION
        assert p.crc32 == crc32_iso_hdlc(p.blob)
        return p.blob


def claim(text: str) -> str:
    """Which set the CLI said the device holds: "old", "new" or "unknown" (its last claim)."""
    found = _HOLDS.findall(text)
    assert found, f"the CLI did not say which set the device holds:\n{text}"
    return _CLAIM[found[-1]]


def test_flash_restore_and_refusals(start_sil, tmp_path, capsys, monkeypatch):
    sil = start_sil(tmp_path / "flash.bin", "--uid", SIL_UID)
    url = f"socket://127.0.0.1:{sil.proto_port}"
    a = write_cal(tmp_path / "a.json", D_A, O_A)
    b = write_cal(tmp_path / "b.json", D_B, O_B, mag_unit=None)
    blob_a, blob_b = expected_blob(D_A, O_A), expected_blob(D_B, O_B)
    assert blob_a != blob_b
    files = lambda: sorted(p.name for p in tmp_path.iterdir())  # noqa: E731

    # --dry-run: the set printed, nothing written (the device has no set yet), no backup.
    before = files()
    rc, out, err = run_cli(capsys, str(a), "--port", url, "--dry-run")
    assert rc == 0, err
    assert f"crc32 0x{crc32_iso_hdlc(blob_a):08x}" in out and blob_a.hex() in out
    assert "nothing was written" in out
    assert active_set(sil.proto_port, reset=True) is None and files() == before

    # Flash A: the active set is from_calibration's bit for bit; the backup holds "no set".
    rc, out, err = run_cli(capsys, str(a), "--port", url)
    assert rc == 0, err
    assert f"new parameters active (crc32 0x{crc32_iso_hdlc(blob_a):08x})" in out
    assert claim(out) == "new"
    assert active_set(sil.proto_port) == blob_a
    assert active_set(sil.proto_port, reset=True) == blob_a
    backups = sorted(tmp_path.glob(f"a.backup-{SIL_UID:0>8}{'0' * 16}-*Z.json"))
    assert len(backups) == 1, files()
    assert str(backups[0]) in err and str(backups[0]) in out  # said before writing, and after
    assert err.index(str(backups[0])) < err.index("param_set")
    assert read_backup(backups[0])["blob"] is None

    # Flash B (no unit in the result: --mag-unit): its backup holds A, the first set.
    rc, out, err = run_cli(capsys, str(b), "--port", url)
    assert rc == 2 and "--mag-unit" in err and "nothing was written" in err
    b2 = tmp_path / "b2.json"
    rc, out, err = run_cli(capsys, str(b), "--port", url, "--mag-unit", "uT", "--backup", str(b2))
    assert rc == 0, err
    assert active_set(sil.proto_port, reset=True) == blob_b
    assert read_backup(b2)["blob"] == blob_a

    # An existing backup path is never overwritten: refused, device unchanged.
    kept = b2.read_bytes()
    rc, out, err = run_cli(capsys, str(a), "--port", url, "--backup", str(b2))
    assert rc == 2 and re.search(r"backup file .*b2\.json exists; nothing was written", err)
    assert claim(err) == "old" and b2.read_bytes() == kept
    assert active_set(sil.proto_port, reset=True) == blob_b

    # --restore puts A back, with a backup of B first (default: next to the restored file).
    before = set(files())
    rc, out, err = run_cli(capsys, "--restore", str(b2), "--port", url)
    assert rc == 0, err
    assert claim(out) == "new"
    assert active_set(sil.proto_port, reset=True) == blob_a
    (new,) = set(files()) - before
    assert new.startswith("b2.before-restore-") and new in out
    assert read_backup(tmp_path / new)["blob"] == blob_b

    # Refused before anything is written (device unchanged, no backup file): unrepresentable
    # offset (600 uT is 41 000 counts, beyond ±32 768), unknown unit, another format.
    before = files()
    far = write_cal(tmp_path / "far.json", D_A, np.array([600.0, 0.0, 0.0]))
    rc, out, err = run_cli(capsys, str(far), "--port", url)
    assert rc == 2
    assert re.search(r"cannot be represented.*offset o\[0\] = 4105\d\.?\d* counts.*±32768", err)
    assert "no backup was made" in err and claim(err) == "old"
    odd = write_cal(tmp_path / "odd.json", D_A, O_A, mag_unit="simulated (field magnitude 1)")
    rc, out, err = run_cli(capsys, str(odd), "--port", url)
    assert rc == 2 and "mag_unit 'simulated (field magnitude 1)', not a known unit" in err
    with monkeypatch.context() as m:  # a device of another parameter format
        m.setattr(fixed_point, "ENCODED_SIZE", fixed_point.ENCODED_SIZE + 4)
        rc, out, err = run_cli(capsys, str(a), "--port", url)
    assert (
        rc == 2 and "takes parameter format 1 of 52 bytes; this magcal writes format 1 of 56" in err
    )
    assert active_set(sil.proto_port, reset=True) == blob_a
    assert files() == sorted([*before, "far.json", "odd.json"])


# --------------------------------------------------------------------- disconnect sweep


class CutProxy:
    """A TCP forwarder 127.0.0.1:port -> the SIL. The first connection is cut after ``budget``
    bytes (both directions counted): the first ``budget`` bytes pass, and when more would,
    both sides are shut down and closed (``cut``). Later connections are forwarded whole
    (``reconnect=True``) or accepted and closed at once. ``chunks`` records what the first
    connection forwarded: (direction "h2d"/"d2h", bytes)."""

    def __init__(self, target_port: int, budget: int | None, reconnect: bool) -> None:
        self.target_port = target_port
        self.budget = budget
        self.reconnect = reconnect
        self.cut = False
        self.chunks: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._socks: list[socket.socket] = []
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://127.0.0.1:{self.port}"
        self._spawn(self._accept_loop)

    def _spawn(self, fn, *args) -> None:
        t = threading.Thread(target=fn, args=args, daemon=True)
        t.start()
        self._threads.append(t)

    def _accept_loop(self) -> None:
        first = True
        while True:
            try:
                host, _ = self._listener.accept()
            except OSError:
                return  # closed
            if not first and not self.reconnect:
                host.close()
                continue
            dev = socket.create_connection(("127.0.0.1", self.target_port))
            pair = [host, dev]
            self._socks += pair
            left = [self.budget if first else None]
            self._spawn(self._forward, host, dev, pair, left, "h2d", first)
            self._spawn(self._forward, dev, host, pair, left, "d2h", first)
            first = False

    @staticmethod
    def _close(pair) -> None:
        for s in pair:
            try:
                s.shutdown(socket.SHUT_RDWR)  # wakes the other direction's recv
            except OSError:
                pass
            s.close()

    def _forward(self, src, dst, pair, left, direction, record) -> None:
        while True:
            try:
                data = src.recv(4096)
            except OSError:
                data = b""
            with self._lock:
                if not data:
                    self._close(pair)
                    return
                cut = left[0] is not None and len(data) > left[0]
                if left[0] is not None:
                    data = data[: left[0]]
                    left[0] -= len(data)
                if record and data:
                    self.chunks.append((direction, data))
                try:
                    dst.sendall(data)
                except OSError:
                    cut = False
                if cut:  # byte budget + 1 would pass now: it never does
                    self.cut = self.cut or record
                    self._close(pair)
                    return

    def close(self) -> None:
        try:
            self._listener.shutdown(socket.SHUT_RDWR)  # wakes accept() (close alone does not)
        except OSError:
            pass
        self._listener.close()
        with self._lock:
            self._close(self._socks)
        for t in self._threads:
            t.join(PROXY_JOIN_TIMEOUT_S)


def frame_layout(chunks) -> list[tuple[int, int, str]]:
    """(start, end, message name) of every frame forwarded, byte offsets in the whole run."""
    out, pos = [], 0
    deframers = {"h2d": Deframer(), "d2h": Deframer()}
    for direction, data in chunks:
        start = pos
        for ev in deframers[direction].feed(data):
            if isinstance(ev, Frame):
                out.append((start, pos + len(data), MessageId(ev.id).name.lower()))
        pos += len(data)
    return out


def one_flash(capsys, sil, tmp_path, n, budget, reconnect, paths, blobs, holds):
    """Flash the set the device does not hold through a CutProxy; check the outcome."""
    target = "b" if holds == "a" else "a"
    proxy = CutProxy(sil.proto_port, budget, reconnect)
    backup = tmp_path / f"sweep-{n}-{int(reconnect)}.json"
    try:
        rc, out, err = run_cli(
            capsys, str(paths[target]), "--port", proxy.url, "--backup", str(backup)
        )
    finally:
        proxy.close()
    said = claim(out + err)
    after = active_set(sil.proto_port, reset=True)
    assert after in (blobs[holds], blobs[target]), "the device holds neither complete set"
    actual = "new" if after == blobs[target] else "old"
    if said == "unknown":
        assert not reconnect, f"cut at {budget}: 'unknown' although reconnecting was possible"
        assert "either its old or the new complete set" in err
    else:
        assert said == actual, f"cut at {budget}: the CLI said {said}, the device holds {actual}"
    assert (rc == 0) == (said == "new"), (rc, out, err)
    if backup.exists():  # written only once about to write; it holds the old set
        assert read_backup(backup)["blob"] == blobs[holds]
        assert str(backup) in (out + err)
    else:
        assert actual == "old" and "no backup was made" in err
    return proxy, said, target if actual == "new" else holds


def test_disconnect_at_every_byte_of_flash(start_sil, tmp_path, capsys):
    sil = start_sil(tmp_path / "flash.bin", "--uid", SIL_UID)
    paths = {
        "a": write_cal(tmp_path / "a.json", D_A, O_A),
        "b": write_cal(tmp_path / "b.json", D_B, O_B),
    }
    blobs = {"a": expected_blob(D_A, O_A), "b": expected_blob(D_B, O_B)}
    rc, _, err = run_cli(capsys, str(paths["a"]), "--port", f"socket://127.0.0.1:{sil.proto_port}")
    assert rc == 0, err
    holds = "a"

    # Every byte count, reconnection allowed: the CLI recovers and says what it verified.
    outcomes: dict[str, int] = {}
    n = 0
    while True:
        proxy, said, holds = one_flash(capsys, sil, tmp_path, n, n, True, paths, blobs, holds)
        if not proxy.cut:
            layout = frame_layout(proxy.chunks)
            total = n
            break
        outcomes[said] = outcomes.get(said, 0) + 1
        n += 1
    names = [name for _, _, name in layout]
    assert names[names.index("reset") :] == [
        "reset",
        "reset_resp",
        "hello",
        "hello_resp",
        "param_get",
        "param_get_resp",
    ]
    assert total == layout[-1][1] and total > 600
    assert outcomes.get("old", 0) > 0 and outcomes.get("new", 0) > 0
    with capsys.disabled():
        print(
            f"\ncut after each of 0..{total - 1} of {total} bytes (reconnect allowed): {outcomes}"
        )

    # Reconnection refused: cuts at the start, middle and end of every frame, except those
    # where the first request to fail is the hello after the reset (the CLI then tries to
    # reconnect for RESET_RECOVERY_TIMEOUT_S, 5 s each).
    reset_end = next(e for s, e, name in layout if name == "reset_resp")
    hello2_end = next(e for s, e, name in layout if name == "hello_resp" and s >= reset_end)
    cuts = sorted(
        {c for s, e, _ in layout for c in (s, (s + e) // 2, e - 1)}
        - set(range(reset_end, hello2_end))
    )
    refused: dict[str, int] = {}
    for c in cuts:
        _, said, holds = one_flash(capsys, sil, tmp_path, c, c, False, paths, blobs, holds)
        refused[said] = refused.get(said, 0) + 1
    assert refused.get("old", 0) > 0 and refused.get("unknown", 0) > 0
    with capsys.disabled():
        print(f"{len(cuts)} cuts at frame starts/middles/ends (no reconnect): {refused}")
