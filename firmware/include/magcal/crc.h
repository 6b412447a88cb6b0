/* SPDX-License-Identifier: Apache-2.0 */
/*
 * CRCs, named by their catalogue names (Greg Cook's CRC catalogue, "reveng"):
 *
 *   CRC-16/CCITT-FALSE (a.k.a. CRC-16/IBM-3740): poly 0x1021, init 0xFFFF, no reflection,
 *       xorout 0. Check ("123456789"): 0x29B1. Used on protocol frames.
 *   CRC-32/ISO-HDLC (the zlib/Ethernet CRC-32): poly 0x04C11DB7 reflected (0xEDB88320),
 *       init 0xFFFFFFFF, xorout 0xFFFFFFFF. Check: 0xCBF43926. Used on stored parameters.
 *
 * Both are bitwise (no tables): 1 KB of table per CRC is not worth it for a few hundred
 * bytes per frame or per parameter commit. The *_update forms continue a running CRC so a
 * record can be checked in pieces: start from the *_INIT value and finish with *_final.
 */
#ifndef MAGCAL_CRC_H
#define MAGCAL_CRC_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define MC_CRC16_CCITT_FALSE_INIT 0xFFFFu
#define MC_CRC32_ISO_HDLC_INIT 0xFFFFFFFFu

/*
 * NULL data. data may be NULL only when len is 0 (the CRC of nothing). NULL with len > 0 is a
 * caller error that these functions cannot report (they return a CRC, not a status): they
 * read nothing and return the unchanged state, i.e. the CRC of nothing (the *_INIT value for
 * an _update, the empty-input CRC for the one-shot forms: 0xFFFF and 0x00000000). So a CRC
 * computed over NULL never matches one over real bytes of that length except by chance; the
 * library's callers never pass NULL with len > 0 (they check their own arguments first).
 */

/* CRC-16/CCITT-FALSE of len bytes at data (see NULL data above). */
uint16_t mc_crc16_ccitt_false(const uint8_t *data, size_t len);
uint16_t mc_crc16_ccitt_false_update(uint16_t crc, const uint8_t *data, size_t len);

/* CRC-32/ISO-HDLC of len bytes at data (see NULL data above). */
uint32_t mc_crc32_iso_hdlc(const uint8_t *data, size_t len);
uint32_t mc_crc32_iso_hdlc_update(uint32_t state, const uint8_t *data, size_t len);
uint32_t mc_crc32_iso_hdlc_final(uint32_t state);

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_CRC_H */
