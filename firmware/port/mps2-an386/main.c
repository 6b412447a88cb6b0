/*
 * The magcal firmware on mps2-an386 (Cortex-M4 under QEMU): UART0 is the host link.
 *
 * Until the protocol endpoint exists this is a bring-up program: it prints a banner line,
 * runs a self-test of the library modules that exist (CRC check values) and of the time
 * source, then echoes every byte it receives. tests/target/test_qemu_target.py drives it.
 * The protocol loop (frames in, dispatcher, frames out) replaces run_echo().
 *
 * Lines it prints (CR LF ended, key=value fields):
 *   magcal-target fw=<version> lib=<git revision> board=mps2-an386 cpu=cortex-m4
 *   selftest crc16=29B1 crc32=CBF43926 time=ok|backwards|stuck boot_us=<n> result=PASS|FAIL
 *   echo
 *   FAULT exception=<n>       (only from the fault hook)
 */
#include <stddef.h>
#include <stdint.h>

#include "board.h"
#include "magcal/crc.h"
#include "mc_target_version.h"
#include "startup.h"
#include "systick_time.h"
#include "uart_cmsdk.h"

#ifndef MC_TARGET_FW_VERSION
#define MC_TARGET_FW_VERSION "0.1.0"
#endif

/* The catalogue check values of crc.h for "123456789". */
#define SELFTEST_CRC16_CHECK 0x29B1u
#define SELFTEST_CRC32_CHECK 0xCBF43926u
/* The time source must advance this far, never stepping back, while we read it at most
 * SELFTEST_SPIN_LIMIT times (20 millisecond interrupts: each is a chance for a race). */
#define SELFTEST_TIME_STEP_US 20000u
#define SELFTEST_SPIN_LIMIT 100000000u

static mc_uart_cmsdk_t s_uart;

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

static void run_echo(void)
{
    put_str("echo\r\n");
    for (;;) {
        uint8_t byte;
        if (mc_uart_cmsdk_read_byte(&s_uart, &byte) == MC_OK) {
            (void)mc_uart_cmsdk_write(&s_uart, &byte, 1u);
        }
    }
}

void mc_startup_on_fault(uint32_t exception)
{
    if (s_uart.regs != NULL) {
        put_str("FAULT exception=");
        put_dec(exception);
        put_str("\r\n");
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
    run_echo();
    return 0;
}
