/* SPDX-License-Identifier: Apache-2.0 */
/*
 * A sensor HAL (sensor_hal.h) fed by the caller instead of hardware: the SIL device reads
 * samples that the Python world simulator writes to a pipe or socket, and hands each one to
 * the acquisition as if a data-ready interrupt had fired:
 *
 *     mc_sensor_feed_init(&feed, info);               // what describe() will report
 *     mc_sensor_hal_t hal = mc_sensor_feed_hal(&feed);
 *     mc_acquire_init(&acq, &hal, storage, MC_RING_CAPACITY, 0u);
 *     for each line from the simulator:
 *         st = mc_sensor_feed_apply_line(&feed, line);      // report st != MC_OK
 *         if (mc_sensor_feed_pending(&feed)) mc_acquire_poll(&acq);
 *
 * The feed holds ONE pending read (a mailbox, like a sensor's data registers): a sample or a
 * failed read. read() consumes it; a read with nothing pending fails (MC_E_SENSOR: no new
 * data, as from a sensor polled too early). Putting while one is pending refuses the new one
 * with MC_E_OVERFLOW and counts it in overruns (poll after every put).
 *
 * The clock: now_us() is the simulator's time, the latest time put (by a sample, a failed
 * read or a clock line), so a SIL run is deterministic. Times never decrease: an earlier time
 * is refused with MC_E_RANGE.
 *
 * Line format (ASCII, fields separated by spaces or tabs, optional "\r\n" or "\n" at the
 * end, nothing else; t_us a decimal integer in 0 .. 2^64-1):
 *     S <t_us> <mag_x> <mag_y> <mag_z> <acc_x> <acc_y> <acc_z> <gyr_x> <gyr_y> <gyr_z>
 *                         a sample in raw counts: decimal integers in -32768 .. 32767
 *     P <t_us> <b_x> <b_y> <b_z> <a_x> <a_y> <a_z> <w_x> <w_y> <w_z>
 *                         a sample in physical units, which the feed quantises to counts as
 *                         the sensors' ADCs would (mc_sensor_quantise, below): the magnetic
 *                         field in tesla in the magnetometer's own axes (the world has applied
 *                         its distortion: soft iron D, hard iron o, misalignment), the specific
 *                         force in m/s^2 and the angular rate in rad/s in the body frame.
 *                         Each is a decimal real: an optional '-', digits with an optional
 *                         '.' and fraction (or '.' and a fraction), an optional exponent
 *                         ('e' or 'E', optional sign, digits), e.g. 4.5e-05, -9.80665, 0, .5.
 *                         The world simulator writes Python's repr() of each float, which
 *                         strtod reads back to the same double (the SIL keeps the "C" locale).
 *     E <t_us>            a read at t_us that fails (sensor error injection)
 *     T <t_us>            the clock advances to t_us, no read
 *
 * Quantisation of a P line (mc_sensor_quantise), per value x and the sensor's count_scale
 * (the table describe() reports, so the host converts back with the same scales):
 *   lsb   = mc_sensor_count_si(count_scale): num / den, times (or divided by, for exp10 < 0)
 *           10^|exp10|, times the unit's SI factor (GAUSS 1e-4, STANDARD_GRAVITY 9.80665,
 *           DEG_PER_S pi / 180, others 1), each step one IEEE-754 double operation;
 *   q     = x / lsb (one double division);
 *   count = q rounded to the nearest integer, halves AWAY FROM ZERO (0.5 -> 1, -0.5 -> -1,
 *           2.5 -> 3), computed exactly (no q + 0.5 double rounding);
 *   saturation at the int16 register limits: q >= 32767 gives 32767, q <= -32768 gives
 *           -32768. Not at the nominal full scale: ST's full scale (LIS3MDL +-4 G, LSM6DSO
 *           +-4 g, +-500 dps) is the guaranteed range, and the 16-bit output goes on past it
 *           to the register limits (LIS3MDL 4.79 G, LSM6DSO 3.998 g, 573 dps), where it clips.
 *   A non-finite value (written nan, inf or infinity in any case, with an optional '-', or a
 *   decimal too large for a double, like 1e999) is refused with MC_E_RANGE; any other text
 *   that is not a decimal real (hexadecimal, '+' first, "1.2.3", "1e", ",") with MC_E_FRAME.
 *   The refused line is not applied (the SIL device reports and skips it).
 *   evaluation/src/magcal_evaluation/world.py (device_counts) mirrors this rule operation
 *   for operation, so the tests predict the counts exactly.
 *
 * Not interrupt-safe: the SIL device calls put/apply and mc_acquire_poll from one thread.
 */
#ifndef MAGCAL_PORT_POSIX_SENSOR_FEED_H
#define MAGCAL_PORT_POSIX_SENSOR_FEED_H

#include <stdint.h>

#include "magcal/sensor_hal.h"
#include "magcal/status.h"

typedef struct {
    mc_sensor_info_t info[MC_SENSOR_COUNT]; /* what describe() reports */
    mc_raw_sample_t pending;                /* the sample the next read returns */
    uint8_t has_sample;                     /* pending holds a sample */
    uint8_t has_error;                      /* the next read fails */
    uint64_t now_us;                        /* the simulator's clock */
    uint32_t overruns;                      /* puts refused because a read was pending */
} mc_sensor_feed_t;

/* Start with nothing pending, the clock at 0, and a copy of info[] (each checked with
 * mc_sensor_info_check). Returns MC_OK, MC_E_ARG (NULL) or MC_E_RANGE (invalid info; the feed
 * is then left untouched). */
mc_status_t mc_sensor_feed_init(mc_sensor_feed_t *feed,
                                const mc_sensor_info_t info[MC_SENSOR_COUNT]);

/* The HAL over this feed (its ctx is feed). */
mc_sensor_hal_t mc_sensor_feed_hal(mc_sensor_feed_t *feed);

/* The next read returns *sample, and the clock moves to sample->t_us. Returns MC_OK; MC_E_ARG;
 * MC_E_RANGE when sample->t_us is before the clock; MC_E_OVERFLOW when a read is pending
 * (counted in overruns; the sample is not stored). */
mc_status_t mc_sensor_feed_put(mc_sensor_feed_t *feed, const mc_raw_sample_t *sample);

/* The next read fails with MC_E_SENSOR, and the clock moves to t_us. Same returns as put. */
mc_status_t mc_sensor_feed_put_error(mc_sensor_feed_t *feed, uint64_t t_us);

/* The clock moves to t_us. Returns MC_OK, MC_E_ARG or MC_E_RANGE (t_us before the clock). */
mc_status_t mc_sensor_feed_set_time(mc_sensor_feed_t *feed, uint64_t t_us);

/* 1 when a sample or a failed read awaits a read, 0 otherwise (and for NULL). */
int mc_sensor_feed_pending(const mc_sensor_feed_t *feed);

/* Parse one line of the format above and apply it (put, put_error or set_time; a P line's
 * values quantised with the feed's count scales). Returns what that returns, MC_E_FRAME for a
 * malformed line (unknown letter, missing, extra or non-decimal fields), MC_E_RANGE for a
 * number out of range or a non-finite P value; a malformed field wins over an out-of-range
 * one. Nothing is applied unless MC_OK. */
mc_status_t mc_sensor_feed_apply_line(mc_sensor_feed_t *feed, const char *line);

/* Why apply_line refused a line, for a log message ("malformed line", ...); "ok" for MC_OK. */
const char *mc_sensor_feed_refusal(mc_status_t st);

/* The value of one count in SI units (T, m/s^2, rad/s) as the quantiser computes it (see
 * above), or 0.0 for NULL or an invalid scale (num <= 0, den == 0, exp10 out of range or an
 * unknown unit). */
double mc_sensor_count_si(const mc_scale_t *count_scale);

/* One physical value (SI units of count_scale's unit) to the int16 count a sensor with that
 * count scale outputs, by the rule above, into *count. Returns MC_OK (also when saturated),
 * MC_E_ARG (count NULL, or mc_sensor_count_si gives 0) or MC_E_RANGE (value not finite; *count
 * untouched). */
mc_status_t mc_sensor_quantise(double value_si, const mc_scale_t *count_scale, int16_t *count);

#endif /* MAGCAL_PORT_POSIX_SENSOR_FEED_H */
