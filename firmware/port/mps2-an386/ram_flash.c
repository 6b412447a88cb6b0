/* SPDX-License-Identifier: Apache-2.0 */
/* RAM-backed NOR flash. See ram_flash.h. */
#include "ram_flash.h"

#include <stddef.h>

#define RAM_FLASH_SIZE (MC_RAM_FLASH_PAGES * MC_RAM_FLASH_PAGE_SIZE)

static mc_status_t ram_erase_page(void *ctx, uint32_t page)
{
    mc_ram_flash_store_t *st = (mc_ram_flash_store_t *)ctx;
    if (page >= MC_RAM_FLASH_PAGES) {
        return MC_E_RANGE;
    }
    for (uint32_t i = 0; i < MC_RAM_FLASH_PAGE_SIZE; ++i) {
        st->bytes[page * MC_RAM_FLASH_PAGE_SIZE + i] = 0xFFu;
    }
    return MC_OK;
}

static mc_status_t ram_program_word(void *ctx, uint32_t addr, uint32_t word)
{
    mc_ram_flash_store_t *st = (mc_ram_flash_store_t *)ctx;
    if (addr % MC_FLASH_WORD_SIZE != 0u) {
        return MC_E_ARG;
    }
    if (addr > RAM_FLASH_SIZE - MC_FLASH_WORD_SIZE) {
        return MC_E_RANGE;
    }
    for (uint32_t i = 0; i < MC_FLASH_WORD_SIZE; ++i) {
        st->bytes[addr + i] &= (uint8_t)(word >> (8u * i)); /* NOR: clears bits only */
    }
    return MC_OK;
}

static mc_status_t ram_read(void *ctx, uint32_t addr, uint8_t *buf, size_t len)
{
    const mc_ram_flash_store_t *st = (const mc_ram_flash_store_t *)ctx;
    if (buf == NULL && len != 0u) {
        return MC_E_ARG;
    }
    if (addr > RAM_FLASH_SIZE || len > RAM_FLASH_SIZE - addr) {
        return MC_E_RANGE;
    }
    for (size_t i = 0; i < len; ++i) {
        buf[i] = st->bytes[addr + i];
    }
    return MC_OK;
}

static const mc_flash_ops_t k_ram_flash_ops = {ram_erase_page, ram_program_word, ram_read};

int mc_ram_flash_init(mc_flash_t *flash, mc_ram_flash_store_t *store)
{
    int kept = store->magic == MC_RAM_FLASH_MAGIC && store->magic_inv == ~MC_RAM_FLASH_MAGIC;
    flash->ops = &k_ram_flash_ops;
    flash->ctx = store;
    flash->page_size = MC_RAM_FLASH_PAGE_SIZE;
    flash->page_count = MC_RAM_FLASH_PAGES;
    if (!kept) {
        for (uint32_t p = 0; p < MC_RAM_FLASH_PAGES; ++p) {
            (void)ram_erase_page(store, p);
        }
        store->boots = 0u;
        store->reserved = 0u;
        store->magic = MC_RAM_FLASH_MAGIC;
        store->magic_inv = ~MC_RAM_FLASH_MAGIC;
    }
    ++store->boots;
    return kept;
}
