/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Reset and exception entry for the Cortex-M4 on mps2-an386, in C: the vector table,
 * Reset_Handler (copy .data from its load address, zero .bss, call main) and a default
 * handler for every other exception. The symbols come from mps2_an386.ld.
 */
#include <stdint.h>

#include "startup.h"

extern uint32_t __data_load__[];
extern uint32_t __data_start__[];
extern uint32_t __data_end__[];
extern uint32_t __bss_start__[];
extern uint32_t __bss_end__[];
extern uint32_t __stack_top__[];

int main(void);
void SysTick_Handler(void);

typedef void (*mc_handler_t)(void);

/* ARMv7-M: 16 system entries (initial SP, reset, 14 exceptions) then the external
 * interrupts; the AN386 image has 32 of them (QEMU: num-irq 32). */
#define MC_STARTUP_NUM_IRQ 32

typedef struct {
    uint32_t *initial_sp;
    mc_handler_t system[15];
    mc_handler_t irq[MC_STARTUP_NUM_IRQ];
} mc_vector_table_t;

void Reset_Handler(void);
void Default_Handler(void);

__attribute__((section(".isr_vector"), used)) const mc_vector_table_t mc_vector_table = {
    .initial_sp = __stack_top__,
    .system = {
        Reset_Handler,
        Default_Handler, /* NMI */
        Default_Handler, /* HardFault */
        Default_Handler, /* MemManage */
        Default_Handler, /* BusFault */
        Default_Handler, /* UsageFault */
        0,
        0,
        0,
        0,
        Default_Handler, /* SVCall */
        Default_Handler, /* DebugMonitor */
        0,
        Default_Handler, /* PendSV */
        SysTick_Handler,
    },
    .irq = {
        Default_Handler, Default_Handler, Default_Handler, Default_Handler,
        Default_Handler, Default_Handler, Default_Handler, Default_Handler,
        Default_Handler, Default_Handler, Default_Handler, Default_Handler,
        Default_Handler, Default_Handler, Default_Handler, Default_Handler,
        Default_Handler, Default_Handler, Default_Handler, Default_Handler,
        Default_Handler, Default_Handler, Default_Handler, Default_Handler,
        Default_Handler, Default_Handler, Default_Handler, Default_Handler,
        Default_Handler, Default_Handler, Default_Handler, Default_Handler,
    },
};

void Reset_Handler(void)
{
    /* Word loops (the linker script aligns all four symbols to 4 bytes). */
    const uint32_t *src = __data_load__;
    for (uint32_t *dst = __data_start__; dst < __data_end__; ++dst) {
        *dst = *src++;
    }
    for (uint32_t *dst = __bss_start__; dst < __bss_end__; ++dst) {
        *dst = 0u;
    }
    (void)main();
    for (;;) {
    }
}

__attribute__((weak)) void mc_startup_on_fault(uint32_t exception)
{
    (void)exception;
}

void Default_Handler(void)
{
    uint32_t ipsr;
    __asm__ volatile("mrs %0, ipsr" : "=r"(ipsr));
    mc_startup_on_fault(ipsr & 0x1FFu);
    for (;;) {
    }
}
