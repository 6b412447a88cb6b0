/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Single-producer / single-consumer ring of acquisition samples in a caller-owned array.
 *
 * The producer (mc_ring_push) may be an interrupt handler and the consumer (mc_ring_pop) the
 * main loop, with no locks and no interrupt masking. There is exactly one producer context and
 * one consumer context: two producers (or two consumers) need a lock of the caller's.
 *
 * Full ring: the NEW sample is dropped and counted (mc_ring_overflow), the oldest are kept.
 * Keeping the oldest lets the producer never touch the consumer's index (overwriting the
 * oldest would race with a pop in progress on the same slot) and keeps what the host receives
 * a contiguous run up to the moment of overflow: the loss is one gap of exactly the dropped
 * count in the sequence numbers (acquire.h), never a silent hole.
 *
 * Indices and capacity
 *   head and tail are free-running uint32_t counts of pushes and pops (they wrap modulo 2^32);
 *   the slot is index & (capacity - 1), and head - tail (modulo 2^32) is the number stored, from
 *   0 to capacity. So capacity is a power of two from 1 to 2^31 (checked by mc_ring_init), and
 *   all slots are usable (no empty slot wasted to tell full from empty).
 *
 * Memory ordering (why this is safe without C11 atomics)
 *   - Each index has one writer: the producer writes head and the overflow counter, the
 *     consumer writes tail. A reader of another side's index sees
 *     either its old or its new value: aligned 32-bit loads and stores are single-copy atomic
 *     on Cortex-M4 (and on every 32/64-bit host we build for). The indices are volatile, so
 *     the compiler reads them afresh each time and does not invent or merge accesses.
 *   - The producer writes the slot, then MC_RING_BARRIER(), then head = head + 1. The
 *     consumer reads head, MC_RING_BARRIER(), reads the slot, MC_RING_BARRIER(), then
 *     tail = tail + 1. Volatile accesses stay in program order among themselves, but the slot
 *     copy is an ordinary access the compiler could move across them; the barrier (a compiler
 *     barrier by default, config.h) forbids that. So a slot is complete before its index is
 *     published, and a slot is released only after it has been copied out.
 *   - The hardware: Cortex-M4 is a single in-order core, and an interrupt handler observes the
 *     interrupted code's memory accesses in program order (it runs on the same core, behind
 *     the same write buffer), so no hardware barrier is needed. A multi-core or DMA producer
 *     needs MC_RING_BARRIER defined as a hardware barrier (DMB).
 *   - The consumer may see a stale head (a push in progress): the ring then looks emptier than
 *     it is, never fuller. The producer may see a stale tail: the ring looks fuller, so at
 *     worst a sample is dropped (and counted) one pop early; never is a slot overwritten while
 *     the consumer reads it.
 *
 * Scaling and overflow
 *   The overflow counter wraps modulo 2^32 (after 2^32 drops); readers compare differences of
 *   it, which stay correct across the wrap.
 */
#ifndef MAGCAL_RING_H
#define MAGCAL_RING_H

#include <stdint.h>

#include "magcal/config.h"
#include "magcal/status.h"

#ifdef __cplusplus
extern "C" {
#endif

/* One acquired sample, as the ring stores it and the protocol streams it (32 bytes: 30 of
 * fields, no inner padding, 2 of tail padding on every ABI we build for). */
typedef struct {
    uint64_t t_us;   /* device time, microseconds (sensor_hal.h) */
    uint32_t seq;    /* sequence number, consecutive modulo 2^32 (acquire.h) */
    int16_t mag[3];  /* raw counts (sensor_hal.h gives their frames and exact scale) */
    int16_t acc[3];
    int16_t gyr[3];
} mc_sample_t;

typedef struct {
    mc_sample_t *buf;           /* caller-owned, capacity elements */
    uint32_t mask;              /* capacity - 1 */
    volatile uint32_t head;     /* pushes so far (producer writes) */
    volatile uint32_t tail;     /* pops so far (consumer writes) */
    volatile uint32_t overflow; /* samples dropped because the ring was full (producer writes) */
} mc_ring_t;

/* Start an empty ring over storage[0 .. capacity-1] with a zero overflow count. Returns MC_OK,
 * or MC_E_ARG when ring or storage is NULL, or capacity is 0, above 2^31 or not a power of
 * two (the ring is then left untouched). Not concurrent with push or pop. */
mc_status_t mc_ring_init(mc_ring_t *ring, mc_sample_t *storage, uint32_t capacity);

/* Producer: copy *sample into the ring. Returns MC_OK; MC_E_OVERFLOW when the ring is full
 * (the sample is dropped and the overflow counter incremented); MC_E_ARG when an argument is
 * NULL (nothing counted). */
mc_status_t mc_ring_push(mc_ring_t *ring, const mc_sample_t *sample);

/* Consumer: move the oldest sample to *out. Returns MC_OK, MC_E_EMPTY (nothing stored; *out
 * untouched) or MC_E_ARG when an argument is NULL. */
mc_status_t mc_ring_pop(mc_ring_t *ring, mc_sample_t *out);

/* Any context: samples stored now (a snapshot the other side may change at once, clamped to
 * 0 .. capacity), the capacity, and the overflow count; each gives 0 for a NULL ring. */
uint32_t mc_ring_count(const mc_ring_t *ring);
uint32_t mc_ring_capacity(const mc_ring_t *ring);
uint32_t mc_ring_overflow(const mc_ring_t *ring);

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_RING_H */
