/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Acquisition: read the three sensors through the HAL (sensor_hal.h), number each sample and
 * queue it in a ring (ring.h) for the main loop, counting every sample that is lost.
 *
 *     static mc_sample_t storage[MC_RING_CAPACITY];
 *     static mc_acquire_t acq;
 *     mc_acquire_init(&acq, &hal, storage, MC_RING_CAPACITY, 0u);
 *     data-ready interrupt:  mc_acquire_poll(&acq);
 *     main loop:             while (mc_acquire_pop(&acq, &s) == MC_OK) { stream s }
 *
 * Contexts: mc_acquire_poll is the ring's single producer (one interrupt, or the main loop
 * itself), mc_acquire_pop its single consumer; see ring.h for why that needs no lock.
 * mc_acquire_stats and mc_acquire_describe may run in the consumer's context.
 *
 * Sequence numbers
 *   Each successful sensor read takes the next sequence number (uint32_t, +1 modulo 2^32: after
 *   0xFFFFFFFF comes 0), whether the sample is then queued or dropped because the ring is full.
 *   So the samples the host receives have consecutive numbers except where samples were
 *   dropped, and each gap (s_next - s_prev - 1, modulo 2^32) is exactly the number dropped
 *   there. A failed sensor read (MC_E_SENSOR) takes NO number: no sample exists to number, and
 *   keeping the numbers for samples means a sequence gap always means an overflow drop. Failed
 *   reads are counted in sensor_errors and show as a gap in the timestamps.
 *   The first number is an argument of mc_acquire_init (normally 0). A port that restarts
 *   acquisition without a reboot passes the next number so the host never sees one twice; the
 *   tests pass 0xFFFFFFF0 to check the wrap.
 *
 * Counters (mc_acquire_stats_t), all uint32_t wrapping modulo 2^32 (compare differences):
 *   produced       successful reads = samples numbered = queued + dropped
 *   dropped        samples numbered but dropped because the ring was full (the ring's count)
 *   sensor_errors  failed reads (no sample, no number)
 *   So at any moment when the producer is idle: produced == popped + queued + dropped, and
 *   next_seq - first_seq == produced (modulo 2^32).
 *
 * Timestamps are passed through from the HAL unchanged (not checked, not converted).
 */
#ifndef MAGCAL_ACQUIRE_H
#define MAGCAL_ACQUIRE_H

#include <stdint.h>

#include "magcal/config.h"
#include "magcal/ring.h"
#include "magcal/sensor_hal.h"
#include "magcal/status.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef struct {
    mc_sensor_hal_t hal;
    mc_ring_t ring;
    volatile uint32_t next_seq;      /* number of the next sample (producer writes) */
    volatile uint32_t produced;      /* producer writes */
    volatile uint32_t sensor_errors; /* producer writes */
    volatile uint32_t ready;         /* MC_ACQUIRE_READY once init succeeded, else not */
} mc_acquire_t;

#define MC_ACQUIRE_READY 0x4D434151u

/* Initialisation and the interrupt. Every function but init refuses an instance that init
 * has not set up with MC_E_STATE (never calling the HAL through an unset pointer): init
 * writes MC_ACQUIRE_READY last, after the HAL and the ring, and clears it first. A zeroed
 * (static) instance is therefore always detected; an instance in uninitialised stack or heap
 * memory is detected unless its garbage happens to equal the magic, so do not rely on that.
 * Enable the data-ready interrupt that calls mc_acquire_poll only after init returned MC_OK,
 * and disable it before calling init again on the same instance. */

typedef struct {
    uint32_t produced;      /* successful reads, each numbered */
    uint32_t dropped;       /* numbered, then dropped: ring full */
    uint32_t sensor_errors; /* failed reads, not numbered */
    uint32_t queued;        /* in the ring now */
    uint32_t next_seq;      /* the number the next sample will get */
} mc_acquire_stats_t;

/* Start acquisition over the caller's storage[capacity] (a power of two, see mc_ring_init),
 * copying *hal; the first sample gets number first_seq and every counter starts at 0. Returns
 * MC_OK, or MC_E_ARG when a pointer is NULL, hal->ops or one of its operations is NULL, or the
 * capacity is invalid (acq, if not NULL, is then not ready: the others say MC_E_STATE). */
mc_status_t mc_acquire_init(mc_acquire_t *acq, const mc_sensor_hal_t *hal, mc_sample_t *storage,
                            uint32_t capacity, uint32_t first_seq);

/* Producer: read one sample and queue it. Returns
 *   MC_OK           read, numbered and queued;
 *   MC_E_OVERFLOW   read and numbered, dropped because the ring is full (counted in dropped);
 *   MC_E_SENSOR     the HAL's read failed (any non-MC_OK status from it): counted in
 *                   sensor_errors, no number taken, nothing queued;
 *   MC_E_ARG        acq is NULL;
 *   MC_E_STATE      acq is not initialised (the HAL is not called). */
mc_status_t mc_acquire_poll(mc_acquire_t *acq);

/* Consumer: the oldest queued sample into *out. Returns MC_OK, MC_E_EMPTY, MC_E_ARG, or
 * MC_E_STATE when acq is not initialised. */
mc_status_t mc_acquire_pop(mc_acquire_t *acq, mc_sample_t *out);

/* The counters now. Each is read once; while the producer runs they may come from different
 * instants (each value itself is whole). Returns MC_OK, MC_E_ARG, or MC_E_STATE when acq is
 * not initialised. */
mc_status_t mc_acquire_stats(const mc_acquire_t *acq, mc_acquire_stats_t *out);

/* The HAL's description of the three sensors, checked with mc_sensor_info_check. Returns
 * MC_OK; MC_E_SENSOR when the HAL's describe fails; MC_E_RANGE when a description is invalid;
 * MC_E_ARG for a NULL argument; MC_E_STATE when acq is not initialised (the HAL is not
 * called). *out is unspecified unless MC_OK. */
mc_status_t mc_acquire_describe(const mc_acquire_t *acq, mc_sensor_info_t out[MC_SENSOR_COUNT]);

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_ACQUIRE_H */
