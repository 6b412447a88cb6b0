/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The magcal firmware on mps2-an386 (Cortex-M4 under QEMU): the protocol endpoint
 * (mc_device_t, device.h; protocol/SPEC.md) on UART0, with synthetic sensors
 * (synthetic_sensors.h) and a RAM-backed parameter flash (ram_flash.h).
 * tests/target/test_qemu_target.py drives it.
 *
 * Boot: it prints three text lines (CR LF ended, key=value fields), then one 0x00 byte, the
 * protocol's frame delimiter, so the host's deframer starts clean at the first frame:
 *   magcal-target fw=<version> lib=<git revision> board=mps2-an386 cpu=cortex-m4
 *   selftest crc16=29B1 crc32=CBF43926 time=ok|backwards|stuck boot_us=<n> result=PASS|FAIL
 *   protocol flash=erased|kept boots=<n>
 *   FAULT exception=<n>       (only from the fault hook, at any time)
 * "flash=kept" means the RAM flash held a formatted store from an earlier boot (a reset of
 * the MCU), "boots" counts the boots since it was formatted. After the 0x00 only frames.
 *
 * Main loop (no interrupt but SysTick's millisecond tick):
 *   - mc_device_poll: pending output to the UART, a due reset, queued samples streamed;
 *   - the UART's received bytes into s_rx (MAIN_RX_SIZE), mc_device_rx_bytes on them, and
 *     what it did not use kept for the next pass (it stops while a response is pending);
 *   - mc_device_sample when the synthetic sensors have a sample due (every 10 ms of the
 *     SysTick clock, one per pass). The acquisition's producer is thus the main loop, which
 *     acquire.h allows; a late pass catches up, each sample with its own instant.
 *   tx is mc_uart_cmsdk_try_write: it takes what the UART takes now and never waits, so a
 *   full link drops (and counts) stream messages and holds responses (device.h).
 *
 * Reset: the protocol's reset (mc_device handles it) is followed by a real reboot: the reset
 * hook waits until the UART has sent reset_resp, then requests a system reset (AIRCR
 * SYSRESETREQ). QEMU resets the machine and reloads the image; the RAM flash is in .noinit,
 * so the committed set survives and the new boot loads it as the active set. Time and the
 * sample numbers start again from 0 after the reboot (both come from this boot).
 */
#include <stddef.h>
#include <stdint.h>

#include "board.h"
#include "magcal/crc.h"
#include "magcal/device.h"
#include "mc_target_version.h"
#include "ram_flash.h"
#include "startup.h"
#include "synthetic_sensors.h"
#include "systick_time.h"
#include "uart_cmsdk.h"

#define MC_STR_(x) #x
#define MC_STR(x) MC_STR_(x)
#define MC_TARGET_FW_MAJOR 0
#define MC_TARGET_FW_MINOR 1
#define MC_TARGET_FW_PATCH 0
#define MC_TARGET_FW_VERSION                                                                   \
    MC_STR(MC_TARGET_FW_MAJOR) "." MC_STR(MC_TARGET_FW_MINOR) "." MC_STR(MC_TARGET_FW_PATCH)
#ifndef MC_TARGET_FW_BUILD
#define MC_TARGET_FW_BUILD 0u
#endif
/* The device uid (info_resp), word 0 least significant: "MPS2" "AN386" as text, fixed since
 * the emulated board has none. */
#define MC_TARGET_UID0 0x36383341u /* "A386" */
#define MC_TARGET_UID1 0x0000004Eu /* "N" */
#define MC_TARGET_UID2 0x4D505332u /* "MPS2" */

/* The catalogue check values of crc.h for "123456789". */
#define SELFTEST_CRC16_CHECK 0x29B1u
#define SELFTEST_CRC32_CHECK 0xCBF43926u
/* The time source must advance this far, never stepping back, while we read it at most
 * SELFTEST_SPIN_LIMIT times (20 millisecond interrupts: each is a chance for a race). */
#define SELFTEST_TIME_STEP_US 20000u
#define SELFTEST_SPIN_LIMIT 100000000u

/* Received bytes the device has not used yet. */
#define MAIN_RX_SIZE 64u
/* After the UART's buffer has emptied, the shifter still sends the last byte: two character
 * times at 115200 baud (10 bits each) before the reboot cuts the line. */
#define RESET_DRAIN_US 200u
#define SCB_AIRCR (*(volatile uint32_t *)0xE000ED0Cu)
#define SCB_AIRCR_VECTKEY 0x05FA0000u
#define SCB_AIRCR_SYSRESETREQ 0x4u

static mc_uart_cmsdk_t s_uart;
static mc_synth_sensors_t s_synth;
static mc_sensor_hal_t s_hal;
static mc_flash_t s_flash;
/* Survives a reset of the MCU, not a power-off (ram_flash.h, mps2_an386.ld). */
__attribute__((section(".noinit"))) static mc_ram_flash_store_t s_flash_store;
static mc_sample_t s_ring[MC_RING_CAPACITY];
static mc_device_t s_dev;
static uint8_t s_rx[MAIN_RX_SIZE];
static size_t s_rx_len;

static void put_str(const char *s)
{
    (void)mc_uart_cmsdk_puts(&s_uart, s);
}

static void put_hex(uint32_t value, unsigned digits)
{
    static const char hex[] = "0123456789ABCDEF";
    char buf[9];
    if (digits > 8u) {
        digits = 8u;
    }
    for (unsigned i = 0; i < digits; ++i) {
        buf[digits - 1u - i] = hex[(value >> (4u * i)) & 0xFu];
    }
    buf[digits] = '\0';
    put_str(buf);
}

static void put_dec(uint32_t value)
{
    char buf[11];
    size_t i = sizeof buf - 1u;
    buf[i] = '\0';
    do {
        buf[--i] = (char)('0' + value % 10u);
        value /= 10u;
    } while (value != 0u);
    put_str(&buf[i]);
}

/* Reads the time source until it has advanced SELFTEST_TIME_STEP_US: "ok", or "backwards"
 * when a reading is below the one before, or "stuck" when it did not advance in time. */
static const char *time_check(void)
{
    uint32_t t0 = mc_systick_time_us();
    uint32_t prev = t0;
    for (uint32_t spin = 0; spin < SELFTEST_SPIN_LIMIT; ++spin) {
        uint32_t now = mc_systick_time_us();
        if (now - prev > UINT32_MAX / 2u) { /* negative step, modulo 2^32 */
            return "backwards";
        }
        if (now - t0 >= SELFTEST_TIME_STEP_US) {
            return "ok";
        }
        prev = now;
    }
    return "stuck";
}

/* Prints the selftest line; returns 1 when every check passed. */
static int run_selftest(void)
{
    static const uint8_t check_input[] = {'1', '2', '3', '4', '5', '6', '7', '8', '9'};
    uint16_t crc16 = mc_crc16_ccitt_false(check_input, sizeof check_input);
    uint32_t crc32 = mc_crc32_iso_hdlc(check_input, sizeof check_input);
    const char *time_result = time_check();
    int time_ok = time_result[0] == 'o';
    int pass = crc16 == SELFTEST_CRC16_CHECK && crc32 == SELFTEST_CRC32_CHECK && time_ok;

    put_str("selftest crc16=");
    put_hex(crc16, 4u);
    put_str(" crc32=");
    put_hex(crc32, 8u);
    put_str(" time=");
    put_str(time_result);
    put_str(" boot_us=");
    put_dec(mc_systick_time_us());
    put_str(pass ? " result=PASS\r\n" : " result=FAIL\r\n");
    return pass;
}

void mc_startup_on_fault(uint32_t exception)
{
    if (s_uart.regs != NULL) {
        put_str("FAULT exception=");
        put_dec(exception);
        put_str("\r\n");
    }
}

static int uart_tx(void *ctx, const uint8_t *bytes, size_t len)
{
    return (int)mc_uart_cmsdk_try_write((mc_uart_cmsdk_t *)ctx, bytes, len);
}

/* After reset_resp went out (device.h): drain the UART, then reboot the MCU. */
static void reboot(void *ctx)
{
    mc_uart_cmsdk_t *uart = (mc_uart_cmsdk_t *)ctx;
    uint32_t t0;
    while (mc_uart_cmsdk_tx_full(uart)) {
    }
    t0 = mc_systick_time_us();
    while (mc_systick_time_us() - t0 < RESET_DRAIN_US) {
    }
    __asm__ volatile("dsb" ::: "memory");
    SCB_AIRCR = SCB_AIRCR_VECTKEY | SCB_AIRCR_SYSRESETREQ;
    __asm__ volatile("dsb" ::: "memory");
    for (;;) {
    }
}

int main(void)
{
    if (mc_uart_cmsdk_init(&s_uart, MC_BOARD_UART0_BASE, MC_BOARD_SYSCLK_HZ,
                           MC_BOARD_UART_BAUD) != MC_OK) {
        return 1;
    }
    if (mc_systick_time_init(MC_BOARD_SYSCLK_HZ) != MC_OK) {
        put_str("FAULT systick\r\n");
        return 1;
    }
    put_str("magcal-target fw=" MC_TARGET_FW_VERSION " lib=" MC_TARGET_LIB_REV
            " board=" MC_BOARD_NAME " cpu=" MC_BOARD_CPU "\r\n");
    (void)run_selftest();
    {
        const int kept = mc_ram_flash_init(&s_flash, &s_flash_store);
        put_str(kept ? "protocol flash=kept boots=" : "protocol flash=erased boots=");
        put_dec(s_flash_store.boots);
        put_str("\r\n");
    }
    mc_synth_init(&s_synth);
    s_hal = mc_synth_hal(&s_synth);
    {
        mc_device_config_t cfg = {0};
        cfg.tx = uart_tx;
        cfg.tx_ctx = &s_uart;
        cfg.on_reset = reboot;
        cfg.reset_ctx = &s_uart;
        cfg.hal = &s_hal;
        cfg.ring = s_ring;
        cfg.ring_capacity = MC_RING_CAPACITY;
        cfg.flash = &s_flash;
        cfg.slot_a_page = 0u;
        cfg.slot_b_page = 1u;
        cfg.pages_per_slot = 1u;
        cfg.fw_version[0] = MC_TARGET_FW_MAJOR;
        cfg.fw_version[1] = MC_TARGET_FW_MINOR;
        cfg.fw_version[2] = MC_TARGET_FW_PATCH;
        cfg.fw_build = (uint32_t)(MC_TARGET_FW_BUILD);
        cfg.device_uid[0] = MC_TARGET_UID0;
        cfg.device_uid[1] = MC_TARGET_UID1;
        cfg.device_uid[2] = MC_TARGET_UID2;
        cfg.sample_rate_mhz = MC_SYNTH_SAMPLE_RATE_MHZ;
        if (mc_device_init(&s_dev, &cfg) != MC_OK) {
            put_str("FAULT device\r\n");
            return 1;
        }
    }
    {
        static const uint8_t delimiter = 0x00u;
        (void)mc_uart_cmsdk_write(&s_uart, &delimiter, 1u);
    }
    for (;;) {
        uint8_t byte;
        (void)mc_device_poll(&s_dev);
        while (s_rx_len < MAIN_RX_SIZE && mc_uart_cmsdk_read_byte(&s_uart, &byte) == MC_OK) {
            s_rx[s_rx_len++] = byte;
        }
        if (s_rx_len > 0u) {
            const size_t used = mc_device_rx_bytes(&s_dev, s_rx, s_rx_len);
            for (size_t i = used; i < s_rx_len; ++i) {
                s_rx[i - used] = s_rx[i];
            }
            s_rx_len -= used;
        }
        if (mc_synth_due(&s_synth)) {
            (void)mc_device_sample(&s_dev);
        }
    }
}
