/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The flash abstraction the parameter storage (storage.h) runs on: a NOR flash region of
 * page_count pages of page_size bytes, addressed by byte offset from the start of the region
 * (page p starts at p * page_size). A port fills in an mc_flash_ops_t and an mc_flash_t; the
 * library never touches flash any other way.
 *
 * What a driver must provide (NOR semantics):
 *   - erase_page(ctx, page): sets every byte of the page to 0xFF. Returns MC_OK, or MC_E_FLASH
 *     when the hardware reports an error, MC_E_RANGE for a page >= page_count.
 *   - program_word(ctx, addr, word): programs the 4 bytes at addr (addr a multiple of
 *     MC_FLASH_WORD_SIZE) to `word` stored little-endian, i.e. byte addr + i holds
 *     (word >> (8 * i)) & 0xFF whatever the CPU's byte order. Programming can only clear
 *     bits. Returns MC_OK, MC_E_FLASH on a hardware error, MC_E_RANGE / MC_E_ARG for an
 *     address outside the region or misaligned.
 *   - read(ctx, addr, buf, len): copies len bytes starting at any byte address into buf.
 *     Returns MC_OK, MC_E_FLASH, or MC_E_RANGE when [addr, addr + len) leaves the region.
 *
 * What the library promises the driver (so drivers for flashes with ECC or "program once"
 * rules work unchanged): it programs a word only after erasing its page, at most once per
 * erase, in ascending address order within a commit, and always whole aligned words. It
 * reads back everything it programs, so a driver need not verify.
 *
 * What the library does NOT assume: that an interrupted erase or program leaves anything
 * sensible. After a power cut, a page being erased may hold any mix of 0xFF and old bytes
 * (and bytes with only some bits set), and a word being programmed may have only some of its
 * bits cleared. storage.c is built so that neither matters (see storage.h).
 *
 * The ctx pointer is the driver's own state (a file descriptor, a RAM array, registers); the
 * library passes it through unchanged. Operations are synchronous: each returns when done.
 */
#ifndef MAGCAL_FLASH_H
#define MAGCAL_FLASH_H

#include <stddef.h>
#include <stdint.h>

#include "magcal/status.h"

#ifdef __cplusplus
extern "C" {
#endif

/* The programming unit in bytes. Fixed, not a config knob: program_word takes a uint32_t. */
#define MC_FLASH_WORD_SIZE 4u

typedef struct mc_flash_ops {
    mc_status_t (*erase_page)(void *ctx, uint32_t page);
    mc_status_t (*program_word)(void *ctx, uint32_t addr, uint32_t word);
    mc_status_t (*read)(void *ctx, uint32_t addr, uint8_t *buf, size_t len);
} mc_flash_ops_t;

/* One flash region. page_size must be a non-zero multiple of MC_FLASH_WORD_SIZE and
 * page_size * page_count must fit in uint32_t; users of the region (mc_storage_init) check. */
typedef struct mc_flash {
    const mc_flash_ops_t *ops;
    void *ctx;
    uint32_t page_size;  /* bytes */
    uint32_t page_count; /* pages */
} mc_flash_t;

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_FLASH_H */
