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
 * Line format (ASCII decimal integers, fields separated by spaces or tabs, optional "\r\n"
 * or "\n" at the end, nothing else):
 *     S <t_us> <mag_x> <mag_y> <mag_z> <acc_x> <acc_y> <acc_z> <gyr_x> <gyr_y> <gyr_z>
 *                         a sample: t_us in 0 .. 2^64-1, counts in -32768 .. 32767
 *     E <t_us>            a read at t_us that fails (sensor error injection)
 *     T <t_us>            the clock advances to t_us, no read
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

/* Parse one line of the format above and apply it (put, put_error or set_time). Returns what
 * that returns, MC_E_FRAME for a malformed line (unknown letter, missing, extra or non-decimal
 * fields) or MC_E_RANGE for a number out of range; nothing is applied unless MC_OK. */
mc_status_t mc_sensor_feed_apply_line(mc_sensor_feed_t *feed, const char *line);

#endif /* MAGCAL_PORT_POSIX_SENSOR_FEED_H */
