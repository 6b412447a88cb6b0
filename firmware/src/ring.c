/* SPDX-License-Identifier: Apache-2.0 */
/* Single-producer / single-consumer sample ring. See ring.h for the memory-ordering argument. */
#include "magcal/ring.h"

#include <stddef.h>

/* Largest capacity: head - tail must tell 0 from capacity within uint32_t. */
#define MC_RING_CAPACITY_MAX 0x80000000u

mc_status_t mc_ring_init(mc_ring_t *ring, mc_sample_t *storage, uint32_t capacity)
{
    if (ring == NULL || storage == NULL || capacity == 0u || capacity > MC_RING_CAPACITY_MAX
        || (capacity & (capacity - 1u)) != 0u) {
        return MC_E_ARG;
    }
    ring->buf = storage;
    ring->mask = capacity - 1u;
    ring->head = 0u;
    ring->tail = 0u;
    ring->overflow = 0u;
    return MC_OK;
}

mc_status_t mc_ring_push(mc_ring_t *ring, const mc_sample_t *sample)
{
    if (ring == NULL || sample == NULL) {
        return MC_E_ARG;
    }
    const uint32_t head = ring->head; /* our own index */
    const uint32_t tail = ring->tail; /* the consumer's; possibly stale (looks fuller) */
    if ((uint32_t)(head - tail) > ring->mask) {
        ring->overflow = ring->overflow + 1u;
        return MC_E_OVERFLOW;
    }
    ring->buf[head & ring->mask] = *sample;
    MC_RING_BARRIER(); /* the slot is written before head publishes it */
    ring->head = head + 1u;
    return MC_OK;
}

mc_status_t mc_ring_pop(mc_ring_t *ring, mc_sample_t *out)
{
    if (ring == NULL || out == NULL) {
        return MC_E_ARG;
    }
    const uint32_t tail = ring->tail; /* our own index */
    const uint32_t head = ring->head; /* the producer's; possibly stale (looks emptier) */
    if (head == tail) {
        return MC_E_EMPTY;
    }
    MC_RING_BARRIER(); /* the slot is read after head said it is complete */
    *out = ring->buf[tail & ring->mask];
    MC_RING_BARRIER(); /* and copied out before tail releases it to the producer */
    ring->tail = tail + 1u;
    return MC_OK;
}

uint32_t mc_ring_count(const mc_ring_t *ring)
{
    if (ring == NULL) {
        return 0u;
    }
    const uint32_t tail = ring->tail;
    const uint32_t head = ring->head;
    const uint32_t count = (uint32_t)(head - tail);
    /* From a third context both may move between the two reads: clamp to what is possible. */
    return count > ring->mask ? ring->mask + 1u : count;
}

uint32_t mc_ring_capacity(const mc_ring_t *ring)
{
    return ring == NULL ? 0u : ring->mask + 1u;
}

uint32_t mc_ring_overflow(const mc_ring_t *ring)
{
    return ring == NULL ? 0u : ring->overflow;
}
