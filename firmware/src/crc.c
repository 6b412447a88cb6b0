/* SPDX-License-Identifier: Apache-2.0 */
/* CRC-16/CCITT-FALSE and CRC-32/ISO-HDLC, bitwise. See crc.h. */
#include "magcal/crc.h"

uint16_t mc_crc16_ccitt_false_update(uint16_t crc, const uint8_t *data, size_t len)
{
    if (data == NULL) {
        return crc;
    }
    for (size_t i = 0; i < len; ++i) {
        crc = (uint16_t)(crc ^ (uint16_t)((uint16_t)data[i] << 8));
        for (int bit = 0; bit < 8; ++bit) {
            crc = (crc & 0x8000u) ? (uint16_t)((uint16_t)(crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

uint16_t mc_crc16_ccitt_false(const uint8_t *data, size_t len)
{
    return mc_crc16_ccitt_false_update(MC_CRC16_CCITT_FALSE_INIT, data, len);
}

uint32_t mc_crc32_iso_hdlc_update(uint32_t state, const uint8_t *data, size_t len)
{
    if (data == NULL) {
        return state;
    }
    for (size_t i = 0; i < len; ++i) {
        state ^= data[i];
        for (int bit = 0; bit < 8; ++bit) {
            state = (state & 1u) ? (state >> 1) ^ 0xEDB88320u : state >> 1;
        }
    }
    return state;
}

uint32_t mc_crc32_iso_hdlc_final(uint32_t state)
{
    return state ^ 0xFFFFFFFFu;
}

uint32_t mc_crc32_iso_hdlc(const uint8_t *data, size_t len)
{
    return mc_crc32_iso_hdlc_final(mc_crc32_iso_hdlc_update(MC_CRC32_ISO_HDLC_INIT, data, len));
}
