/* SPDX-License-Identifier: Apache-2.0 */
/*
 * A RAM-backed NOR flash (flash.h) for the mps2-an386 target, which has no flash the
 * firmware may write: MC_RAM_FLASH_PAGES pages of MC_RAM_FLASH_PAGE_SIZE bytes, erase sets a
 * page to 0xFF, programming a word clears bits only (new = old & word), as NOR does.
 *
 * The store lives in the .noinit section (mps2_an386.ld: its own region at the start of
 * SSRAM2&3, outside every loaded segment, not zeroed by Reset_Handler), so it survives a
 * reset of the MCU (SYSRESETREQ, the protocol's reset) but NOT a power-off: the contents are
 * lost when the board (or QEMU) is started anew. A header (magic and its complement) tells a
 * store that was formatted by an earlier boot from the garbage (or, under QEMU, zeros) RAM
 * holds at power-on; mc_ram_flash_init erases the whole store when the header is wrong.
 */
#ifndef MAGCAL_PORT_RAM_FLASH_H
#define MAGCAL_PORT_RAM_FLASH_H

#include <stdint.h>

#include "magcal/flash.h"

#define MC_RAM_FLASH_PAGE_SIZE 1024u
#define MC_RAM_FLASH_PAGES 2u
#define MC_RAM_FLASH_MAGIC 0x4D43464Cu /* "MCFL" */

typedef struct {
    uint32_t magic;     /* MC_RAM_FLASH_MAGIC once formatted */
    uint32_t magic_inv; /* ~magic */
    uint32_t boots;     /* boots since it was formatted, this one included */
    uint32_t reserved;
    uint8_t bytes[MC_RAM_FLASH_PAGES * MC_RAM_FLASH_PAGE_SIZE];
} mc_ram_flash_store_t;

/* Fills *flash over *store. Returns 1 when the store's header was valid (contents kept
 * from an earlier boot), 0 when it was formatted now (every page erased). Counts the boot. */
int mc_ram_flash_init(mc_flash_t *flash, mc_ram_flash_store_t *store);

#endif /* MAGCAL_PORT_RAM_FLASH_H */
