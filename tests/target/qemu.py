# SPDX-License-Identifier: Apache-2.0
"""The Cortex-M4 firmware image under QEMU (``-M mps2-an386``), its UART0 on a host pty.

QEMU starts halted (``-S``) with its monitor on stdin/stdout; ``QemuTarget.start`` reads
the pty QEMU names ("char device redirected to /dev/pts/N (label serial0)"), opens it and
only then lets the CPU run (monitor ``cont``): QEMU discards what the guest writes to a pty
nobody has open, so the first line would otherwise be lost. ``close`` asks the monitor to
``quit`` and kills QEMU if it does not exit in time.

Every wait has a timeout and a timeout raises ``TargetTimeoutError``.
"""

from __future__ import annotations

import re
import subprocess
import tempfile
import time
from pathlib import Path

import serial

from magcal.errors import MagcalError

REPO_ROOT = Path(__file__).resolve().parents[2]
TARGET_ELF = REPO_ROOT / "build" / "cortex-m4" / "magcal-target.elf"
QEMU = "qemu-system-arm"
QEMU_MACHINE = "mps2-an386"

# QEMU 7.2 on the CI machine names its pty in well under a second; the rest is margin for
# a loaded machine (2 shared cores).
QEMU_PTY_TIMEOUT_S = 15.0
QEMU_QUIT_TIMEOUT_S = 5.0
QEMU_KILL_TIMEOUT_S = 5.0
MONITOR_POLL_S = 0.02
# The UART's rate is ignored by QEMU's pty; 115200 matches the firmware's BAUDDIV.
UART_BAUD = 115200
SERIAL_READ_CHUNK_TIMEOUT_S = 0.05

_PTY_RE = re.compile(rb"char device redirected to (/dev/pts/\d+) \(label serial0\)")


class TargetError(MagcalError):
    """QEMU or the firmware under it did not behave: failed to start, exited, garbled."""


class TargetTimeoutError(TargetError):
    """The target did not answer in time."""


class QemuTarget:
    """One QEMU process running ``elf``; use as a context manager.

    ``serial`` is the open pty (pyserial), ``log_path`` QEMU's own stdout+stderr (monitor
    output and errors), quoted in every error message.
    """

    def __init__(self, elf: Path = TARGET_ELF, qemu: str = QEMU) -> None:
        self.elf = Path(elf)
        self.qemu = qemu
        self.proc: subprocess.Popen[bytes] | None = None
        self.serial: serial.Serial | None = None
        self.pty: str | None = None
        self.boot_s: float | None = None  # QEMU start until the pty was open, seconds
        self._logdir = tempfile.TemporaryDirectory(prefix="magcal-qemu-")
        self.log_path = Path(self._logdir.name) / "qemu.log"

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> QemuTarget:
        t0 = time.monotonic()
        cmd = [
            self.qemu,
            "-M",
            QEMU_MACHINE,
            "-nographic",
            "-S",
            "-monitor",
            "stdio",
            "-serial",
            "pty",
            "-kernel",
            str(self.elf),
        ]
        # QEMU's output goes to a file rather than a pipe nobody drains while the test runs.
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                cmd, stdin=subprocess.PIPE, stdout=log, stderr=subprocess.STDOUT
            )
        self.pty = self._wait_for_pty()
        self.serial = serial.Serial(self.pty, baudrate=UART_BAUD, timeout=0, write_timeout=5)
        self._monitor("cont")
        self.boot_s = time.monotonic() - t0
        return self

    def close(self) -> None:
        """Quit QEMU through its monitor; terminate, then kill it if it does not exit."""
        if self.serial is not None:
            self.serial.close()
            self.serial = None
        proc, self.proc = self.proc, None
        if proc is not None and proc.poll() is None:
            try:
                self._send_monitor(proc, "quit")
                proc.wait(timeout=QEMU_QUIT_TIMEOUT_S)
            except (OSError, subprocess.TimeoutExpired):
                proc.terminate()
                try:
                    proc.wait(timeout=QEMU_KILL_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout=QEMU_KILL_TIMEOUT_S)
        if proc is not None and proc.stdin is not None:
            proc.stdin.close()
        self._logdir.cleanup()

    def __enter__(self) -> QemuTarget:
        try:
            return self.start()
        except BaseException:
            self.close()
            raise

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ serial I/O
    def read_until(self, terminator: bytes, timeout_s: float) -> bytes:
        """Bytes up to and including ``terminator``; TargetTimeoutError after timeout_s."""
        deadline = time.monotonic() + timeout_s
        buf = bytearray()
        while not buf.endswith(terminator):
            self._check_running()
            if time.monotonic() > deadline:
                raise TargetTimeoutError(
                    f"reading the target's UART: no {terminator!r} within {timeout_s} s "
                    f"(got {bytes(buf)!r}){self._log_tail()}"
                )
            self.serial.timeout = SERIAL_READ_CHUNK_TIMEOUT_S
            buf += self.serial.read(1)
        return bytes(buf)

    def read_line(self, timeout_s: float) -> str:
        """One CR LF terminated line from the target, without the terminator."""
        raw = self.read_until(b"\r\n", timeout_s)
        try:
            return raw[:-2].decode("ascii")
        except UnicodeDecodeError as exc:
            raise TargetError(f"target printed a non-ASCII line {raw!r}") from exc

    def read_exact(self, n: int, timeout_s: float) -> bytes:
        """Exactly n bytes; TargetTimeoutError after timeout_s with what arrived."""
        deadline = time.monotonic() + timeout_s
        buf = bytearray()
        while len(buf) < n:
            self._check_running()
            left = deadline - time.monotonic()
            if left <= 0:
                raise TargetTimeoutError(
                    f"reading {n} bytes from the target's UART: {len(buf)} arrived within "
                    f"{timeout_s} s{self._log_tail()}"
                )
            self.serial.timeout = min(left, SERIAL_READ_CHUNK_TIMEOUT_S)
            buf += self.serial.read(n - len(buf))
        return bytes(buf)

    def write(self, data: bytes) -> None:
        self._check_running()
        self.serial.write(data)
        self.serial.flush()

    # ------------------------------------------------------------------ internals
    def _wait_for_pty(self) -> str:
        deadline = time.monotonic() + QEMU_PTY_TIMEOUT_S
        while time.monotonic() < deadline:
            match = _PTY_RE.search(self.log_path.read_bytes())
            if match:
                return match.group(1).decode()
            self._check_running()
            time.sleep(MONITOR_POLL_S)
        raise TargetTimeoutError(
            f"starting {self.qemu}: it named no pty within {QEMU_PTY_TIMEOUT_S} s{self._log_tail()}"
        )

    def _monitor(self, command: str) -> None:
        self._check_running()
        self._send_monitor(self.proc, command)

    @staticmethod
    def _send_monitor(proc: subprocess.Popen[bytes], command: str) -> None:
        proc.stdin.write(command.encode() + b"\n")
        proc.stdin.flush()

    def _check_running(self) -> None:
        if self.proc is None:
            raise TargetError("the QEMU target is not running (start() it first)")
        code = self.proc.poll()
        if code is not None:
            raise TargetError(f"{self.qemu} exited with status {code}{self._log_tail()}")

    def _log_tail(self, n_bytes: int = 2000) -> str:
        try:
            text = self.log_path.read_bytes()[-n_bytes:].decode(errors="replace")
        except OSError:
            return ""
        return f"\n--- {self.qemu} output ---\n{text}" if text.strip() else ""
