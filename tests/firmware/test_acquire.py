# SPDX-License-Identifier: Apache-2.0
"""The acquisition's data structures through ctypes: the sample record's layout (what the
protocol streams), the ring's drop-newest counting, the sensor descriptions the C check accepts
and refuses, and the exact conversion of counts to SI units that sensor_hal.h documents,
with fractions.Fraction. Also: no floating point in the acquisition path."""

from __future__ import annotations

import ctypes
import math
import shutil
import subprocess
from fractions import Fraction
from pathlib import Path

import pytest

from magcal.device.generated import Status

REPO_ROOT = Path(__file__).resolve().parents[2]

# mc_unit_t (sensor_hal.h) and the exact SI factor of each. Degrees per second: pi/180, kept
# as the rational 1/180 times pi.
TESLA, GAUSS, METRE_PER_S2, STANDARD_GRAVITY, RAD_PER_S, DEG_PER_S = range(1, 7)
SI_FACTOR = {
    TESLA: Fraction(1),
    GAUSS: Fraction(1, 10_000),
    METRE_PER_S2: Fraction(1),
    STANDARD_GRAVITY: Fraction(980_665, 100_000),
    RAD_PER_S: Fraction(1),
    DEG_PER_S: Fraction(1, 180),  # times pi
}
MAG, ACC, GYR = range(3)


class McScale(ctypes.Structure):
    _fields_ = [
        ("num", ctypes.c_int32),
        ("den", ctypes.c_uint32),
        ("exp10", ctypes.c_int8),
        ("unit", ctypes.c_uint8),
    ]


class McSensorInfo(ctypes.Structure):
    _fields_ = [
        ("kind", ctypes.c_uint8),
        ("id", ctypes.c_uint8),
        ("name", ctypes.c_char * 12),
        ("full_scale", McScale),
        ("count_scale", McScale),
    ]


class McSample(ctypes.Structure):
    _fields_ = [
        ("t_us", ctypes.c_uint64),
        ("seq", ctypes.c_uint32),
        ("mag", ctypes.c_int16 * 3),
        ("acc", ctypes.c_int16 * 3),
        ("gyr", ctypes.c_int16 * 3),
    ]


class McRing(ctypes.Structure):
    _fields_ = [
        ("buf", ctypes.POINTER(McSample)),
        ("mask", ctypes.c_uint32),
        ("head", ctypes.c_uint32),
        ("tail", ctypes.c_uint32),
        ("overflow", ctypes.c_uint32),
    ]


def count_to_si(count: int, scale: McScale) -> Fraction:
    """The exact SI value of `count` counts (for DEG_PER_S: the value divided by pi)."""
    return (
        count * Fraction(scale.num, scale.den) * Fraction(10) ** scale.exp10 * SI_FACTOR[scale.unit]
    )


# The examples of sensor_hal.h: (kind, name, count_scale, full_scale).
EXAMPLES = [
    (MAG, b"LIS3MDL", (1, 6842, 0, GAUSS), (4, 1, 0, GAUSS)),
    (MAG, b"AK8963", (15, 100, -6, TESLA), (4912, 1, -6, TESLA)),
    (ACC, b"MPU-6050", (1, 16384, 0, STANDARD_GRAVITY), (2, 1, 0, STANDARD_GRAVITY)),
    (GYR, b"MPU-6050", (10, 164, 0, DEG_PER_S), (2000, 1, 0, DEG_PER_S)),
    (GYR, b"LSM6DSO", (70, 1, -3, DEG_PER_S), (2000, 1, 0, DEG_PER_S)),
]


def make_info(kind, name, count_scale, full_scale) -> McSensorInfo:
    return McSensorInfo(kind, 0x42, name, McScale(*full_scale), McScale(*count_scale))


@pytest.fixture
def lib(fwlib):
    fwlib.mc_sensor_info_check.restype = ctypes.c_int
    fwlib.mc_sensor_info_check.argtypes = [ctypes.POINTER(McSensorInfo), ctypes.c_int]
    fwlib.mc_ring_init.restype = ctypes.c_int
    fwlib.mc_ring_init.argtypes = [
        ctypes.POINTER(McRing),
        ctypes.POINTER(McSample),
        ctypes.c_uint32,
    ]
    fwlib.mc_ring_push.restype = ctypes.c_int
    fwlib.mc_ring_push.argtypes = [ctypes.POINTER(McRing), ctypes.POINTER(McSample)]
    fwlib.mc_ring_pop.restype = ctypes.c_int
    fwlib.mc_ring_pop.argtypes = [ctypes.POINTER(McRing), ctypes.POINTER(McSample)]
    for name in ("mc_ring_count", "mc_ring_overflow", "mc_ring_capacity"):
        getattr(fwlib, name).restype = ctypes.c_uint32
        getattr(fwlib, name).argtypes = [ctypes.POINTER(McRing)]
    return fwlib


def test_sample_record_layout():
    # 30 bytes of fields, no inner padding, 32 with the tail padding (ring.h).
    assert ctypes.sizeof(McSample) == 32
    assert [getattr(McSample, f).offset for f in ("t_us", "seq", "mag", "acc", "gyr")] == [
        0,
        8,
        12,
        18,
        24,
    ]
    assert ctypes.sizeof(McSensorInfo) == 14 + 2 + 2 * 12


def test_ring_round_trip_and_drop_newest(lib):
    cap = 4
    storage = (McSample * cap)()
    ring = McRing()
    assert lib.mc_ring_init(ctypes.byref(ring), storage, 6) == Status.E_ARG
    assert lib.mc_ring_init(ctypes.byref(ring), storage, 0) == Status.E_ARG
    assert lib.mc_ring_init(ctypes.byref(ring), storage, cap) == Status.OK
    assert lib.mc_ring_capacity(ctypes.byref(ring)) == cap
    pushed = []
    for seq in range(7):
        s = McSample(2**40 + seq, (0xFFFFFFFE + seq) & 0xFFFFFFFF)
        s.mag[:] = [seq, -32768, 32767]
        s.acc[:] = [-seq, 1, 2]
        s.gyr[:] = [3, 4, -5 * seq]
        expected = Status.OK if seq < cap else Status.E_OVERFLOW
        assert lib.mc_ring_push(ctypes.byref(ring), ctypes.byref(s)) == expected
        pushed.append(s)
    assert lib.mc_ring_overflow(ctypes.byref(ring)) == 3
    assert lib.mc_ring_count(ctypes.byref(ring)) == cap
    out = McSample()
    for s in pushed[:cap]:  # the oldest were kept
        assert lib.mc_ring_pop(ctypes.byref(ring), ctypes.byref(out)) == Status.OK
        assert bytes(out) == bytes(s)
    assert lib.mc_ring_pop(ctypes.byref(ring), ctypes.byref(out)) == Status.E_EMPTY


@pytest.mark.parametrize("kind,name,count_scale,full_scale", EXAMPLES)
def test_documented_examples_are_valid(lib, kind, name, count_scale, full_scale):
    info = make_info(kind, name, count_scale, full_scale)
    assert lib.mc_sensor_info_check(ctypes.byref(info), kind) == Status.OK
    for other in {MAG, ACC, GYR} - {kind}:  # a unit of another sensor is refused
        assert lib.mc_sensor_info_check(ctypes.byref(info), other) == Status.E_RANGE


def test_invalid_descriptions_are_refused(lib):
    good = EXAMPLES[0]
    assert lib.mc_sensor_info_check(None, MAG) == Status.E_ARG
    info = make_info(*good)
    assert lib.mc_sensor_info_check(ctypes.byref(info), 3) == Status.E_ARG
    for field, value in [
        ("num", 0),
        ("num", -1),
        ("den", 0),
        ("exp10", 19),
        ("exp10", -19),
        ("unit", 0),
        ("unit", 7),
    ]:
        for which in ("count_scale", "full_scale"):
            info = make_info(*good)
            setattr(getattr(info, which), field, value)
            assert lib.mc_sensor_info_check(ctypes.byref(info), MAG) == Status.E_RANGE, (
                which,
                field,
            )
    info = make_info(*good)
    ctypes.memmove(ctypes.addressof(info) + McSensorInfo.name.offset, b"x" * 12, 12)  # no NUL
    assert lib.mc_sensor_info_check(ctypes.byref(info), MAG) == Status.E_RANGE


def test_exact_conversion_to_si():
    lis3mdl, ak8963, mpu_acc, mpu_gyr, lsm6dso = (McScale(*e[2]) for e in EXAMPLES)
    assert count_to_si(6842, lis3mdl) == Fraction(1, 10_000)  # 6842 counts = 1 G = 1e-4 T
    assert count_to_si(1, ak8963) == Fraction(3, 20_000_000)  # 0.15 uT
    assert count_to_si(16384, mpu_acc) == Fraction("9.80665")  # 1 g, exactly g0
    assert count_to_si(-32768, mpu_acc) == -2 * Fraction("9.80665")
    # 164 counts = 10 deg/s = pi/18 rad/s; 1 count of 70 mdps = 7e-2 * pi/180 rad/s.
    assert count_to_si(164, mpu_gyr) == Fraction(1, 18)
    assert count_to_si(1, lsm6dso) == Fraction(7, 18_000)
    # Rounding once at the end: the float is the correctly rounded value of the exact one.
    assert float(count_to_si(3 * 6842, lis3mdl)) == 3e-4  # the float nearest 0.0003 T
    assert float(count_to_si(100, lsm6dso)) * math.pi == pytest.approx(math.radians(7.0), rel=1e-15)


@pytest.mark.skipif(shutil.which("gcc") is None, reason="needs gcc")
def test_library_has_no_floating_point(tmp_path):
    # -mgeneral-regs-only makes any float or double operation a compile error (x86-64, AArch64).
    probe = subprocess.run(
        ["gcc", "-mgeneral-regs-only", "-x", "c", "-c", "-", "-o", str(tmp_path / "p.o")],
        input="int f(int x) { return x; }\n",
        text=True,
        capture_output=True,
        timeout=60,
    )
    if probe.returncode != 0:
        pytest.skip("gcc has no -mgeneral-regs-only on this machine")
    # The whole library: acquisition, correction, validation, storage and protocol. The SIL
    # port's sensor_feed.c plays the sensors' ADCs (it quantises the simulator's physical
    # values) and may use floating point; it is not part of the library.
    sources = sorted(
        str(p.relative_to(REPO_ROOT)) for p in (REPO_ROOT / "firmware/src").glob("*.c")
    )
    assert "firmware/src/correction.c" in sources and "firmware/src/acquire.c" in sources
    for src in sources:
        r = subprocess.run(
            [
                "gcc",
                "-std=c99",
                "-O2",
                "-mgeneral-regs-only",
                "-Ifirmware/include",
                "-c",
                src,
                "-o",
                str(tmp_path / "x.o"),
            ],
            cwd=REPO_ROOT,
            text=True,
            capture_output=True,
            timeout=60,
        )
        assert r.returncode == 0, f"{src} uses floating point:\n{r.stderr}"
