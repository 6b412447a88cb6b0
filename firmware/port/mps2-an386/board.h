/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The MPS2 board with the AN386 FPGA image (Cortex-M4), as Arm's Application Note AN386
 * documents it and QEMU's `-M mps2-an386` models it (hw/arm/mps2.c; checked with the QEMU
 * monitor's `info mtree` on QEMU 7.2):
 *
 *   0x00000000 - 0x003FFFFF  ZBT SSRAM1, 4 MB: code and read-only data (the "flash" here)
 *   0x20000000 - 0x203FFFFF  ZBT SSRAM2&3, 4 MB: data, bss and the stack
 *   0x40000000               CMSDK APB timer 0 (not used: SysTick is the time source)
 *   0x40004000               CMSDK APB UART0: the device protocol's serial link
 *   0xE000E010               SysTick (in the Cortex-M4's System Control Space)
 *
 * Every peripheral and the core run from one 25 MHz clock (SYSCLK = PCLK).
 */
#ifndef MAGCAL_PORT_MPS2_AN386_BOARD_H
#define MAGCAL_PORT_MPS2_AN386_BOARD_H

#define MC_BOARD_NAME "mps2-an386"
#define MC_BOARD_CPU "cortex-m4"

/* Core clock and APB clock, Hz (SYSCLK_FRQ in QEMU's mps2.c; the FPGA's 25 MHz on hardware). */
#define MC_BOARD_SYSCLK_HZ 25000000u

#define MC_BOARD_UART0_BASE 0x40004000u
/* 115200 baud: BAUDDIV = 25 MHz / 115200 = 217 (QEMU ignores the rate but needs >= 16). */
#define MC_BOARD_UART_BAUD 115200u

#endif /* MAGCAL_PORT_MPS2_AN386_BOARD_H */
