/* SPDX-License-Identifier: Apache-2.0 */
/*
 * A RAM NOR flash for the native tests, with power-cut and fault injection. Header-only
 * (static functions) because each tests/native/test_fw_*.c is compiled alone with the
 * library sources.
 *
 * Power-loss model. Every change to flash is a sequence of byte STEPS, counted in `steps`:
 *   - program_word = 4 steps, bytes in ascending address order;
 *   - erase_page = page_size steps, one byte each, in the order `erase_order` (forward,
 *     reverse, or a stride permutation that scatters erased bytes across the page).
 * With cut_at = k >= 0, step k is where power fails: steps 0 .. k-1 are complete; the byte of
 * step k is left as `tear` says (FLASH_SIM_TEAR_NONE: unchanged; FLASH_SIM_TEAR_PARTIAL:
 * half its bits done, i.e. a program cleared only the low nibble's bits and an erase set only
 * the low nibble's bits); then the sim is dead: every later call (reads too) fails with
 * MC_E_FLASH and changes nothing, as a CPU without power would do nothing. flash_sim_power_on
 * "reboots": clears dead and disarms the cut, keeping the contents.
 *
 * It also enforces the driver contract of flash.h: programming a word that is not erased
 * (a second program without erase), a misaligned or out-of-range access, counts as a
 * violation (and fails), so a test can assert the library never does it.
 * flip_reads_from = k >= 0 makes reads from the k-th on return a flipped bit (flaky reads).
 * lie_after = k >= 0 makes every program step from step k on silently do nothing while
 * reporting MC_OK (a flash that fails without telling): read-back must catch it.
 */
#ifndef MAGCAL_TEST_FLASH_SIM_H
#define MAGCAL_TEST_FLASH_SIM_H

#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "magcal/flash.h"

#define FLASH_SIM_MAX_BYTES 4096u

enum { FLASH_SIM_TEAR_NONE = 0, FLASH_SIM_TEAR_PARTIAL = 1 };
enum { FLASH_SIM_ERASE_FORWARD = 0, FLASH_SIM_ERASE_REVERSE = 1, FLASH_SIM_ERASE_STRIDE = 2 };

/* Odd, so i * stride mod page_size is a permutation for power-of-two page sizes. */
#define FLASH_SIM_STRIDE 37u

typedef struct {
    uint8_t mem[FLASH_SIM_MAX_BYTES];
    uint32_t page_size, page_count;
    long steps;      /* byte steps done (program and erase) */
    long cut_at;     /* step at which power fails; -1: never */
    int tear;        /* FLASH_SIM_TEAR_* for the step that is cut */
    int erase_order; /* FLASH_SIM_ERASE_* */
    int dead;        /* power is off */
    long lie_after;  /* program steps from here on are silently dropped; -1: never */
    long violations; /* contract violations by the caller */
    long erases, programs, reads;
    int fail_erase;  /* erase_page returns MC_E_FLASH without erasing */
    long flip_reads_from; /* reads numbered from here on return byte 0 with bit 0 flipped
                           * (a flaky read; the flash itself is unchanged); -1: never */
} flash_sim_t;

/* One byte step. Returns 0 if done, -1 if power failed here (the sim is now dead). */
static int flash_sim_step(flash_sim_t *sim, uint8_t *byte, uint8_t target, int is_erase)
{
    if (sim->cut_at >= 0 && sim->steps == sim->cut_at) {
        if (sim->tear == FLASH_SIM_TEAR_PARTIAL) {
            *byte = is_erase ? (uint8_t)(*byte | 0x0Fu) : (uint8_t)(*byte & (target | 0xF0u));
        }
        sim->dead = 1;
        return -1;
    }
    if (is_erase) {
        *byte = 0xFFu;
    } else if (sim->lie_after < 0 || sim->steps < sim->lie_after) {
        *byte = (uint8_t)(*byte & target); /* NOR: programming only clears bits */
    }
    ++sim->steps;
    return 0;
}

static mc_status_t flash_sim_erase_page(void *ctx, uint32_t page)
{
    flash_sim_t *sim = (flash_sim_t *)ctx;
    if (sim->dead) {
        return MC_E_FLASH;
    }
    if (page >= sim->page_count) {
        ++sim->violations;
        return MC_E_RANGE;
    }
    if (sim->fail_erase) {
        return MC_E_FLASH;
    }
    ++sim->erases;
    uint8_t *p = sim->mem + (size_t)page * sim->page_size;
    for (uint32_t i = 0; i < sim->page_size; ++i) {
        uint32_t j = i;
        if (sim->erase_order == FLASH_SIM_ERASE_REVERSE) {
            j = sim->page_size - 1u - i;
        } else if (sim->erase_order == FLASH_SIM_ERASE_STRIDE) {
            j = (i * FLASH_SIM_STRIDE) % sim->page_size;
        }
        if (flash_sim_step(sim, &p[j], 0xFFu, 1) != 0) {
            return MC_E_FLASH;
        }
    }
    return MC_OK;
}

static mc_status_t flash_sim_program_word(void *ctx, uint32_t addr, uint32_t word)
{
    flash_sim_t *sim = (flash_sim_t *)ctx;
    if (sim->dead) {
        return MC_E_FLASH;
    }
    const uint64_t size = (uint64_t)sim->page_size * sim->page_count;
    if (addr % MC_FLASH_WORD_SIZE != 0 || (uint64_t)addr + MC_FLASH_WORD_SIZE > size) {
        ++sim->violations;
        return MC_E_RANGE;
    }
    uint8_t *p = sim->mem + addr;
    if ((p[0] & p[1] & p[2] & p[3]) != 0xFFu) {
        ++sim->violations; /* programmed twice without an erase */
        return MC_E_FLASH;
    }
    ++sim->programs;
    for (unsigned i = 0; i < MC_FLASH_WORD_SIZE; ++i) {
        if (flash_sim_step(sim, &p[i], (uint8_t)((word >> (8u * i)) & 0xFFu), 0) != 0) {
            return MC_E_FLASH;
        }
    }
    return MC_OK;
}

static mc_status_t flash_sim_read(void *ctx, uint32_t addr, uint8_t *buf, size_t len)
{
    flash_sim_t *sim = (flash_sim_t *)ctx;
    if (sim->dead) {
        return MC_E_FLASH;
    }
    const uint64_t size = (uint64_t)sim->page_size * sim->page_count;
    if (buf == NULL || (uint64_t)addr + len > size) {
        ++sim->violations;
        return MC_E_RANGE;
    }
    memcpy(buf, sim->mem + addr, len);
    if (sim->flip_reads_from >= 0 && sim->reads >= sim->flip_reads_from && len > 0) {
        buf[0] ^= 0x01u;
    }
    ++sim->reads;
    return MC_OK;
}

static const mc_flash_ops_t flash_sim_ops = {
    flash_sim_erase_page,
    flash_sim_program_word,
    flash_sim_read,
};

/* A blank (all 0xFF) flash of page_count pages of page_size bytes, described by *flash. */
static void flash_sim_init(flash_sim_t *sim, mc_flash_t *flash, uint32_t page_size,
                           uint32_t page_count)
{
    if ((uint64_t)page_size * page_count > FLASH_SIM_MAX_BYTES) {
        abort(); /* a test bug: make FLASH_SIM_MAX_BYTES larger */
    }
    memset(sim, 0, sizeof *sim);
    memset(sim->mem, 0xFF, sizeof sim->mem);
    sim->page_size = page_size;
    sim->page_count = page_count;
    sim->cut_at = -1;
    sim->lie_after = -1;
    sim->flip_reads_from = -1;
    flash->ops = &flash_sim_ops;
    flash->ctx = sim;
    flash->page_size = page_size;
    flash->page_count = page_count;
}

/* Power fails at step `steps_from_now` from now (counting from the current step count). */
static void flash_sim_arm_cut(flash_sim_t *sim, long steps_from_now, int tear, int erase_order)
{
    sim->cut_at = sim->steps + steps_from_now;
    sim->tear = tear;
    sim->erase_order = erase_order;
}

/* Reboot: power back, no cut armed, contents kept. */
static void flash_sim_power_on(flash_sim_t *sim)
{
    sim->dead = 0;
    sim->cut_at = -1;
    sim->lie_after = -1;
}

#endif /* MAGCAL_TEST_FLASH_SIM_H */
