# SPDX-License-Identifier: Apache-2.0
"""The firmware's parameter storage (storage.h) through ctypes, over a flash held in a Python
bytearray: a second, independent implementation of the on-flash record (struct + binascii)
reads what the C code writes and writes what the C code must read.

The power-loss sweep itself is native (tests/native/test_fw_storage.c); here the point is the
documented layout and the API seen from Python.
"""

from __future__ import annotations

import binascii
import ctypes
import struct

import pytest

PAGE_SIZE = 128
PAGE_COUNT = 6
SLOT_PAGES = (0, 3)
PAGES_PER_SLOT = 2
MAGIC = 0x5350434D
LAYOUT_VERSION = 1
COMMIT_MARKER = 0xC0DE600D
PAYLOAD_MAX = 128  # MC_STORAGE_PAYLOAD_MAX, the default of config.h

MC_OK = 0
MC_E_ARG = -1
MC_E_RANGE = -2
MC_E_NO_PARAMS = -7
MC_E_FLASH = -9
MC_E_NO_SPACE = -17

ERASE = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_uint32)
PROGRAM = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32)
READ = ctypes.CFUNCTYPE(
    ctypes.c_int, ctypes.c_void_p, ctypes.c_uint32, ctypes.POINTER(ctypes.c_uint8), ctypes.c_size_t
)


class FlashOps(ctypes.Structure):
    _fields_ = [("erase_page", ERASE), ("program_word", PROGRAM), ("read", READ)]


class Flash(ctypes.Structure):
    """mc_flash_t of flash.h."""

    _fields_ = [
        ("ops", ctypes.POINTER(FlashOps)),
        ("ctx", ctypes.c_void_p),
        ("page_size", ctypes.c_uint32),
        ("page_count", ctypes.c_uint32),
    ]


class BytearrayFlash:
    """A NOR flash in a bytearray: erase to 0xFF, program ANDs a little-endian word into an
    erased word only. Counts contract violations instead of raising inside a C callback."""

    def __init__(self) -> None:
        self.mem = bytearray(b"\xff" * (PAGE_SIZE * PAGE_COUNT))
        self.violations = 0
        # The callbacks must stay referenced as long as C may call them.
        self._ops = FlashOps(ERASE(self._erase), PROGRAM(self._program), READ(self._read))
        self.flash = Flash(ctypes.pointer(self._ops), None, PAGE_SIZE, PAGE_COUNT)

    def _erase(self, _ctx, page):
        if page >= PAGE_COUNT:
            self.violations += 1
            return MC_E_RANGE
        self.mem[page * PAGE_SIZE : (page + 1) * PAGE_SIZE] = b"\xff" * PAGE_SIZE
        return MC_OK

    def _program(self, _ctx, addr, word):
        if addr % 4 or addr + 4 > len(self.mem) or self.mem[addr : addr + 4] != b"\xff" * 4:
            self.violations += 1
            return MC_E_FLASH
        self.mem[addr : addr + 4] = struct.pack("<I", word)
        return MC_OK

    def _read(self, _ctx, addr, buf, n):
        if addr + n > len(self.mem):
            self.violations += 1
            return MC_E_RANGE
        ctypes.memmove(buf, bytes(self.mem[addr : addr + n]), n)
        return MC_OK

    def slot(self, i: int) -> bytearray:
        start = SLOT_PAGES[i] * PAGE_SIZE
        return self.mem[start : start + PAGES_PER_SLOT * PAGE_SIZE]

    def put_slot(self, i: int, record: bytes) -> None:
        start = SLOT_PAGES[i] * PAGE_SIZE
        self.mem[start : start + len(record)] = record


def encode_record(sequence: int, fmt: int, payload: bytes, marker: int = COMMIT_MARKER) -> bytes:
    """The record of storage.h's table."""
    padded = payload + b"\xff" * (-len(payload) % 4)
    body = struct.pack("<IHHII", MAGIC, LAYOUT_VERSION, fmt, sequence, len(payload)) + padded
    return body + struct.pack("<II", binascii.crc32(body), marker)


def decode_record(slot: bytes) -> tuple[int, int, bytes] | None:
    """(sequence, format version, payload) of a valid record, else None."""
    magic, layout, fmt, sequence, n = struct.unpack_from("<IHHII", slot)
    if magic != MAGIC or layout != LAYOUT_VERSION or not 0 < n <= len(slot) - 24:
        return None
    end = 16 + n + (-n % 4)
    crc, marker = struct.unpack_from("<II", slot, end)
    if marker != COMMIT_MARKER or crc != binascii.crc32(slot[:end]):
        return None
    return sequence, fmt, bytes(slot[16 : 16 + n])


class Storage:
    """mc_storage_t in a buffer larger than the struct: the caller owns it, and C never
    writes past sizeof(mc_storage_t)."""

    def __init__(self, lib: ctypes.CDLL, flash: BytearrayFlash) -> None:
        self.lib = lib
        self.flash = flash
        self.buf = (ctypes.c_uint64 * 32)()  # 256 bytes, 8-byte aligned

    def init(self) -> int:
        return self.lib.mc_storage_init(
            self.buf, ctypes.byref(self.flash.flash), SLOT_PAGES[0], SLOT_PAGES[1], PAGES_PER_SLOT
        )

    def commit(self, payload: bytes, fmt: int) -> int:
        return self.lib.mc_storage_commit(self.buf, payload, len(payload), fmt)

    def load(self, cap: int = PAYLOAD_MAX) -> tuple[int, bytes, int, int]:
        out = ctypes.create_string_buffer(max(cap, 1))
        n, fmt, seq = ctypes.c_size_t(), ctypes.c_uint16(), ctypes.c_uint32()
        status = self.lib.mc_storage_load(
            self.buf, out, cap, ctypes.byref(n), ctypes.byref(fmt), ctypes.byref(seq)
        )
        return status, out.raw[: n.value] if status == MC_OK else b"", fmt.value, seq.value

    def active(self) -> tuple[int, int, int]:
        slot, seq = ctypes.c_int(), ctypes.c_uint32()
        status = self.lib.mc_storage_active(self.buf, ctypes.byref(slot), ctypes.byref(seq))
        return status, slot.value, seq.value


@pytest.fixture
def lib(fwlib):
    fwlib.mc_storage_init.argtypes = [
        ctypes.c_void_p,
        ctypes.POINTER(Flash),
        ctypes.c_uint32,
        ctypes.c_uint32,
        ctypes.c_uint32,
    ]
    fwlib.mc_storage_commit.argtypes = [
        ctypes.c_void_p,
        ctypes.c_char_p,
        ctypes.c_size_t,
        ctypes.c_uint16,
    ]
    fwlib.mc_storage_load.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_size_t] + [
        ctypes.c_void_p
    ] * 3
    fwlib.mc_storage_active.argtypes = [ctypes.c_void_p] * 3
    for name in ("mc_storage_init", "mc_storage_commit", "mc_storage_load", "mc_storage_active"):
        getattr(fwlib, name).restype = ctypes.c_int
    return fwlib


def test_c_writes_what_python_decodes(lib):
    flash = BytearrayFlash()
    st = Storage(lib, flash)
    assert st.init() == MC_OK
    assert st.active() == (MC_E_NO_PARAMS, -1, 0)
    payloads = [bytes(range(n)) for n in (PAYLOAD_MAX, 37, 1, 100)]
    for k, payload in enumerate(payloads):
        assert st.commit(payload, 0x0200 + k) == MC_OK
        # Alternating slots A, B, A, B with sequences 1, 2, 3, 4.
        assert st.active() == (MC_OK, k % 2, k + 1)
        assert decode_record(flash.slot(k % 2)) == (k + 1, 0x0200 + k, payload)
        assert flash.slot(k % 2)[: 24 + len(payload) + (-len(payload) % 4)] == encode_record(
            k + 1, 0x0200 + k, payload
        )
    assert flash.violations == 0
    fresh = Storage(lib, flash)
    assert fresh.init() == MC_OK
    assert fresh.load() == (MC_OK, payloads[-1], 0x0203, 4)


def test_c_reads_what_python_encodes(lib):
    flash = BytearrayFlash()
    flash.put_slot(0, encode_record(41, 7, b"older"))
    flash.put_slot(1, encode_record(42, 9, b"newer, in slot B"))
    st = Storage(lib, flash)
    assert st.init() == MC_OK
    assert st.active() == (MC_OK, 1, 42)
    assert st.load() == (MC_OK, b"newer, in slot B", 9, 42)
    # The next commit goes to A (not the best) with sequence 43, B is untouched.
    before_b = bytes(flash.slot(1))
    assert st.commit(b"third", 1) == MC_OK
    assert decode_record(flash.slot(0)) == (43, 1, b"third")
    assert bytes(flash.slot(1)) == before_b


# Erased, zeroed, one bit not yet cleared, half the word programmed.
@pytest.mark.parametrize(
    "marker", [0xFFFFFFFF, 0x00000000, COMMIT_MARKER | 0x10, COMMIT_MARKER | 0xFFFF0000]
)
def test_record_without_its_marker_is_not_loaded(lib, marker):
    flash = BytearrayFlash()
    flash.put_slot(0, encode_record(1, 1, b"old"))
    flash.put_slot(1, encode_record(2, 1, b"new, but not committed", marker=marker))
    st = Storage(lib, flash)
    assert st.init() == MC_OK
    assert marker != COMMIT_MARKER
    assert st.load() == (MC_OK, b"old", 1, 1)


def test_errors(lib):
    flash = BytearrayFlash()
    st = Storage(lib, flash)
    assert st.init() == MC_OK
    assert st.load()[0] == MC_E_NO_PARAMS
    assert st.commit(b"", 1) == MC_E_ARG
    assert st.commit(b"x" * (PAYLOAD_MAX + 1), 1) == MC_E_ARG
    assert st.commit(b"x" * PAYLOAD_MAX, 1) == MC_OK
    status, _, fmt, seq = st.load(cap=PAYLOAD_MAX - 1)
    assert (status, fmt, seq) == (MC_E_NO_SPACE, 1, 1)
    # Slots that overlap or leave the region.
    bad = Storage(lib, flash)
    assert (
        lib.mc_storage_init(bad.buf, ctypes.byref(flash.flash), 0, 1, PAGES_PER_SLOT) == MC_E_RANGE
    )
    assert (
        lib.mc_storage_init(bad.buf, ctypes.byref(flash.flash), 0, 5, PAGES_PER_SLOT) == MC_E_RANGE
    )
    assert lib.mc_storage_init(bad.buf, None, 0, 3, PAGES_PER_SLOT) == MC_E_ARG
