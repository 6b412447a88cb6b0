/* SPDX-License-Identifier: Apache-2.0 */
/* The firmware CRCs against their catalogue check values, whole and in pieces. */
#include "check.h"
#include "magcal/crc.h"

#include <string.h>

int main(void)
{
    const uint8_t check_input[] = "123456789";
    const size_t n = strlen((const char *)check_input);

    CHECK_EQ_INT(mc_crc16_ccitt_false(check_input, n), 0x29B1);
    CHECK_EQ_INT(mc_crc32_iso_hdlc(check_input, n), 0xCBF43926u);
    /* Empty input: the init value (CRC-16, no xorout) and 0 (CRC-32, xorout = init). */
    CHECK_EQ_INT(mc_crc16_ccitt_false(NULL, 0), 0xFFFF);
    CHECK_EQ_INT(mc_crc32_iso_hdlc(NULL, 0), 0);

    /* In pieces: every split point gives the same CRC. */
    for (size_t k = 0; k <= n; ++k) {
        uint16_t c16 = mc_crc16_ccitt_false_update(MC_CRC16_CCITT_FALSE_INIT, check_input, k);
        c16 = mc_crc16_ccitt_false_update(c16, check_input + k, n - k);
        CHECK_EQ_INT(c16, 0x29B1);
        uint32_t c32 = mc_crc32_iso_hdlc_update(MC_CRC32_ISO_HDLC_INIT, check_input, k);
        c32 = mc_crc32_iso_hdlc_update(c32, check_input + k, n - k);
        CHECK_EQ_INT(mc_crc32_iso_hdlc_final(c32), 0xCBF43926u);
    }
    /* A single flipped bit changes both. */
    uint8_t flipped[9];
    memcpy(flipped, check_input, n);
    flipped[4] ^= 0x10u;
    CHECK(mc_crc16_ccitt_false(flipped, n) != 0x29B1);
    CHECK(mc_crc32_iso_hdlc(flipped, n) != 0xCBF43926u);
    return check_summary("test_fw_crc");
}
