/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Polled driver for the Arm CMSDK APB UART (Cortex-M System Design Kit TRM, DDI0479):
 * 8N1, one byte of buffering in each direction, no FIFO and no flow control.
 *
 *   0x00 DATA       write: byte to send; read: received byte (clears RXFULL)
 *   0x04 STATE      bit 0 TX buffer full, bit 1 RX buffer full, bits 2/3 TX/RX overrun (W1C)
 *   0x08 CTRL       bit 0 TX enable, bit 1 RX enable, bits 2-5 interrupt enables
 *   0x0C INTSTATUS  interrupt status / clear (W1C)
 *   0x10 BAUDDIV    PCLK / baud, at least 16
 *
 * No interrupts are used: the caller polls mc_uart_cmsdk_read_byte often enough that the
 * one-byte receive buffer does not overrun (overruns are counted, see rx_overruns).
 * Transmit either waits (mc_uart_cmsdk_write, for the boot text) or never waits
 * (mc_uart_cmsdk_try_write, for the protocol: the link reports full instead).
 *
 * Under QEMU the transmit buffer is "full" only while the host side (the pty) does not take
 * bytes, and the receiver holds further input back while RXFULL is set, so nothing received
 * is lost there; on hardware TXFULL is set for one character time (87 us at 115200 baud).
 */
#ifndef MAGCAL_PORT_UART_CMSDK_H
#define MAGCAL_PORT_UART_CMSDK_H

#include <stddef.h>
#include <stdint.h>

#include "magcal/status.h"

typedef struct {
    volatile uint32_t data;
    volatile uint32_t state;
    volatile uint32_t ctrl;
    volatile uint32_t intstatus;
    volatile uint32_t bauddiv;
} mc_uart_cmsdk_regs_t;

#define MC_UART_CMSDK_STATE_TXFULL 0x1u
#define MC_UART_CMSDK_STATE_RXFULL 0x2u
#define MC_UART_CMSDK_STATE_TXOVERRUN 0x4u
#define MC_UART_CMSDK_STATE_RXOVERRUN 0x8u
#define MC_UART_CMSDK_CTRL_TX_EN 0x1u
#define MC_UART_CMSDK_CTRL_RX_EN 0x2u
#define MC_UART_CMSDK_BAUDDIV_MIN 16u

typedef struct {
    mc_uart_cmsdk_regs_t *regs;
    uint32_t rx_overruns; /* receive overruns seen (a byte was lost), saturates */
} mc_uart_cmsdk_t;

/* Program the baud divider (pclk_hz / baud, at least 16) and enable TX and RX.
 * MC_E_ARG for a NULL pointer, MC_E_RANGE when the divider would be below 16 or zero. */
mc_status_t mc_uart_cmsdk_init(mc_uart_cmsdk_t *uart, uintptr_t base, uint32_t pclk_hz,
                               uint32_t baud);

/* Send len bytes, waiting while the transmit buffer is full. */
mc_status_t mc_uart_cmsdk_write(mc_uart_cmsdk_t *uart, const uint8_t *data, size_t len);

/* Send what fits now without waiting: bytes are written while the transmit buffer is not
 * full, and the count written (0 .. len) is returned. 0 for a NULL pointer. */
size_t mc_uart_cmsdk_try_write(mc_uart_cmsdk_t *uart, const uint8_t *data, size_t len);

/* 1 while the transmit buffer holds a byte not yet taken by the shifter (TXFULL), else 0. */
int mc_uart_cmsdk_tx_full(const mc_uart_cmsdk_t *uart);

/* Send a NUL-terminated string. */
mc_status_t mc_uart_cmsdk_puts(mc_uart_cmsdk_t *uart, const char *s);

/* Take the received byte if there is one: MC_OK and *byte set, or MC_E_EMPTY. Never waits. */
mc_status_t mc_uart_cmsdk_read_byte(mc_uart_cmsdk_t *uart, uint8_t *byte);

#endif /* MAGCAL_PORT_UART_CMSDK_H */
