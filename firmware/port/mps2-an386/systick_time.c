/* SPDX-License-Identifier: Apache-2.0 */
/* Microsecond time from SysTick. See systick_time.h. */
#include "systick_time.h"

/* SysTick registers (ARMv7-M ARM, B3.3). */
#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define SYST_CSR_ENABLE 0x1u
#define SYST_CSR_TICKINT 0x2u
#define SYST_CSR_CLKSOURCE_CORE 0x4u
#define SYST_RVR_MAX 0x00FFFFFFu
/* Interrupt Control and State Register: PENDSTSET, SysTick pending (B3.2.4). */
#define SCB_ICSR (*(volatile uint32_t *)0xE000ED04u)
#define SCB_ICSR_PENDSTSET (1u << 26)

static volatile uint32_t s_ms;
static uint32_t s_ticks_per_ms;
static uint32_t s_ticks_per_us;

void SysTick_Handler(void)
{
    s_ms = s_ms + 1u;
}

mc_status_t mc_systick_time_init(uint32_t core_hz)
{
    if (core_hz == 0u || core_hz % 1000000u != 0u || core_hz / 1000u - 1u > SYST_RVR_MAX) {
        return MC_E_RANGE;
    }
    s_ticks_per_ms = core_hz / 1000u;
    s_ticks_per_us = core_hz / 1000000u;
    SYST_CSR = 0u;
    s_ms = 0u;
    SYST_RVR = s_ticks_per_ms - 1u;
    SYST_CVR = 0u; /* any write clears the counter; it reloads on the next clock */
    SYST_CSR = SYST_CSR_CLKSOURCE_CORE | SYST_CSR_TICKINT | SYST_CSR_ENABLE;
    return MC_OK;
}

uint32_t mc_systick_time_us(void)
{
    uint32_t ms_seen;
    uint32_t ms;
    uint32_t val;
    /* The counter counts down from RVR to 0 and reloads. Two races:
     * - the interrupt runs between reading s_ms and the counter: s_ms changed, read again;
     * - the counter has reloaded but the interrupt has not run yet (it is pending; QEMU
     *   takes interrupts only between translated blocks, hardware while a higher-priority
     *   handler runs): the millisecond is not counted yet, so count it here and take the
     *   counter again, now certainly after the reload. */
    do {
        ms_seen = s_ms;
        ms = ms_seen;
        val = SYST_CVR;
        if ((SCB_ICSR & SCB_ICSR_PENDSTSET) != 0u) {
            val = SYST_CVR;
            ms = ms_seen + 1u;
        }
    } while (ms_seen != s_ms);
    uint32_t elapsed_ticks = (s_ticks_per_ms - 1u) - val;
    /* ms * 1000 wraps modulo 2^32 like the result is documented to. */
    return ms * 1000u + elapsed_ticks / s_ticks_per_us;
}
