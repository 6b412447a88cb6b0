"""The cross-built firmware (library + firmware/port/mps2-an386) on QEMU's mps2-an386.

Boot: the banner names the firmware, the library revision and the board; the self-test
checks the library's CRC check values and the SysTick time source on the Cortex-M4.
Session: until the protocol endpoint is linked in, the firmware echoes bytes, so the link
is checked for every byte value. The protocol session (info, stream, parameter write,
read-back, commit, corrected output) replaces ``test_echo_*`` and keeps the boot tests.
"""

from __future__ import annotations

import re

import pytest

from tests.target.qemu import TargetTimeoutError

BOOT_LINE_TIMEOUT_S = 10.0
ECHO_TIMEOUT_S = 10.0
# Bounds for boot_us, microseconds: the self-test waits 20 ms on SysTick, and
# on QEMU the whole boot takes milliseconds of guest time (seconds would mean a runaway clock).
SELFTEST_WAIT_US = 20_000
BOOT_US_MAX = 5_000_000

BANNER_RE = re.compile(
    r"magcal-target fw=(?P<fw>\d+\.\d+\.\d+) lib=(?P<lib>\S+) "
    r"board=mps2-an386 cpu=cortex-m4"
)
SELFTEST_RE = re.compile(
    r"selftest crc16=(?P<crc16>[0-9A-F]{4}) crc32=(?P<crc32>[0-9A-F]{8}) "
    r"time=(?P<time>\w+) boot_us=(?P<boot_us>\d+) result=(?P<result>PASS|FAIL)"
)


@pytest.fixture(scope="module")
def boot(target):
    """The three lines the firmware prints at boot: banner, self-test, mode."""
    lines = [target.read_line(BOOT_LINE_TIMEOUT_S) for _ in range(3)]
    print(f"QEMU boot (start until the UART was open): {target.boot_s:.3f} s")
    return lines


def test_banner_names_firmware_library_and_board(boot):
    match = BANNER_RE.fullmatch(boot[0])
    assert match, f"unexpected banner {boot[0]!r}"
    assert match["lib"] != "unknown"


def test_selftest_crc_check_values_and_time_source(boot):
    match = SELFTEST_RE.fullmatch(boot[1])
    assert match, f"unexpected self-test line {boot[1]!r}"
    # The catalogue check values for "123456789" (crc.h), computed on the Cortex-M4.
    assert match["crc16"] == "29B1"
    assert match["crc32"] == "CBF43926"
    assert match["time"] == "ok"
    assert SELFTEST_WAIT_US <= int(match["boot_us"]) <= BOOT_US_MAX
    assert match["result"] == "PASS"


def test_echo_mode_announced(boot):
    assert boot[2] == "echo"


def test_echo_returns_every_byte_value(target, boot):
    assert boot[2] == "echo"
    data = bytes(range(256)) * 4
    target.write(data)
    assert target.read_exact(len(data), ECHO_TIMEOUT_S) == data


def test_echo_is_silent_without_input(target, boot):
    with pytest.raises(TargetTimeoutError, match="0 arrived within"):
        target.read_exact(1, 0.3)
