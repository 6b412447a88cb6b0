# SPDX-License-Identifier: Apache-2.0
"""The firmware's CRCs agree with Python's (binascii) on the catalogue check value and on
random data. binascii.crc_hqx with init 0xFFFF is CRC-16/CCITT-FALSE; binascii.crc32 is
CRC-32/ISO-HDLC."""

from __future__ import annotations

import binascii
import ctypes

import numpy as np
import pytest


@pytest.fixture
def crcs(fwlib):
    fwlib.mc_crc16_ccitt_false.restype = ctypes.c_uint16
    fwlib.mc_crc16_ccitt_false.argtypes = [ctypes.c_char_p, ctypes.c_size_t]
    fwlib.mc_crc32_iso_hdlc.restype = ctypes.c_uint32
    fwlib.mc_crc32_iso_hdlc.argtypes = [ctypes.c_char_p, ctypes.c_size_t]
    return fwlib.mc_crc16_ccitt_false, fwlib.mc_crc32_iso_hdlc


def test_catalogue_check_values(crcs):
    crc16, crc32 = crcs
    assert crc16(b"123456789", 9) == 0x29B1 == binascii.crc_hqx(b"123456789", 0xFFFF)
    assert crc32(b"123456789", 9) == 0xCBF43926 == binascii.crc32(b"123456789")


def test_random_data_agrees_with_binascii(crcs):
    crc16, crc32 = crcs
    rng = np.random.default_rng(3)
    for n in [0, 1, 2, 7, 64, 255, 1000]:
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert crc16(data, n) == binascii.crc_hqx(data, 0xFFFF)
        assert crc32(data, n) == binascii.crc32(data)
