/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Microsecond time from the Cortex-M SysTick timer: SysTick counts the core clock and
 * interrupts once per millisecond; mc_systick_time_us adds the elapsed part of the current
 * millisecond to 1000 times the interrupt count.
 *
 * The result is a uint32_t that wraps every 2^32 us (71.6 minutes); differences taken with
 * unsigned subtraction are right across the wrap. Resolution is 1 us (the core clock must
 * be a whole number of MHz). A SysTick interrupt that is pending but not yet taken is
 * counted, so the time is monotonic even from a higher-priority handler or with
 * interrupts masked, as long as they are not masked for more than a millisecond.
 */
#ifndef MAGCAL_PORT_SYSTICK_TIME_H
#define MAGCAL_PORT_SYSTICK_TIME_H

#include <stdint.h>

#include "magcal/status.h"

/* Start SysTick on the core clock (core_hz a multiple of 1 MHz, at most 16.7 GHz so one
 * millisecond fits SysTick's 24-bit reload). MC_E_RANGE otherwise. Time starts at 0. */
mc_status_t mc_systick_time_init(uint32_t core_hz);

/* Microseconds since mc_systick_time_init, modulo 2^32. */
uint32_t mc_systick_time_us(void);

/* The SysTick exception handler (placed in the vector table by startup.c). */
void SysTick_Handler(void);

#endif /* MAGCAL_PORT_SYSTICK_TIME_H */
