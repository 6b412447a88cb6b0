/* SPDX-License-Identifier: Apache-2.0 */
/* Polled CMSDK APB UART. See uart_cmsdk.h. */
#include "uart_cmsdk.h"

mc_status_t mc_uart_cmsdk_init(mc_uart_cmsdk_t *uart, uintptr_t base, uint32_t pclk_hz,
                               uint32_t baud)
{
    if (uart == NULL || base == 0u) {
        return MC_E_ARG;
    }
    if (baud == 0u || pclk_hz / baud < MC_UART_CMSDK_BAUDDIV_MIN) {
        return MC_E_RANGE;
    }
    uart->regs = (mc_uart_cmsdk_regs_t *)base;
    uart->rx_overruns = 0u;
    uart->regs->ctrl = 0u;
    uart->regs->bauddiv = pclk_hz / baud;
    /* Clear stale overrun flags (write one to clear), then enable both directions. */
    uart->regs->state = MC_UART_CMSDK_STATE_TXOVERRUN | MC_UART_CMSDK_STATE_RXOVERRUN;
    uart->regs->ctrl = MC_UART_CMSDK_CTRL_TX_EN | MC_UART_CMSDK_CTRL_RX_EN;
    return MC_OK;
}

mc_status_t mc_uart_cmsdk_write(mc_uart_cmsdk_t *uart, const uint8_t *data, size_t len)
{
    if (uart == NULL || uart->regs == NULL || (data == NULL && len != 0u)) {
        return MC_E_ARG;
    }
    for (size_t i = 0; i < len; ++i) {
        while ((uart->regs->state & MC_UART_CMSDK_STATE_TXFULL) != 0u) {
        }
        uart->regs->data = data[i];
    }
    return MC_OK;
}

size_t mc_uart_cmsdk_try_write(mc_uart_cmsdk_t *uart, const uint8_t *data, size_t len)
{
    size_t n = 0;
    if (uart == NULL || uart->regs == NULL || data == NULL) {
        return 0;
    }
    while (n < len && (uart->regs->state & MC_UART_CMSDK_STATE_TXFULL) == 0u) {
        uart->regs->data = data[n];
        ++n;
    }
    return n;
}

int mc_uart_cmsdk_tx_full(const mc_uart_cmsdk_t *uart)
{
    if (uart == NULL || uart->regs == NULL) {
        return 0;
    }
    return (uart->regs->state & MC_UART_CMSDK_STATE_TXFULL) != 0u;
}

mc_status_t mc_uart_cmsdk_puts(mc_uart_cmsdk_t *uart, const char *s)
{
    if (s == NULL) {
        return MC_E_ARG;
    }
    size_t len = 0;
    while (s[len] != '\0') {
        ++len;
    }
    return mc_uart_cmsdk_write(uart, (const uint8_t *)s, len);
}

mc_status_t mc_uart_cmsdk_read_byte(mc_uart_cmsdk_t *uart, uint8_t *byte)
{
    if (uart == NULL || uart->regs == NULL || byte == NULL) {
        return MC_E_ARG;
    }
    uint32_t state = uart->regs->state;
    if ((state & MC_UART_CMSDK_STATE_RXOVERRUN) != 0u) {
        uart->regs->state = MC_UART_CMSDK_STATE_RXOVERRUN;
        if (uart->rx_overruns != UINT32_MAX) {
            ++uart->rx_overruns;
        }
    }
    if ((state & MC_UART_CMSDK_STATE_RXFULL) == 0u) {
        return MC_E_EMPTY;
    }
    *byte = (uint8_t)(uart->regs->data & 0xFFu);
    return MC_OK;
}
