/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The sample ring and the acquisition under ASan+UBSan: argument errors, wrap-around (of the
 * slots, of the free-running indices and of the 32-bit sequence number), drop-newest with
 * counting, sensor errors, timestamps, and two interleavings of an "interrupt" producer with
 * the main-loop consumer: a deterministic pseudo-random schedule, and a real asynchronous one
 * (a SIGALRM handler polling while the main loop pops) that can interrupt a pop anywhere.
 * Both check that nothing is lost uncounted: received + dropped == produced, and each gap in
 * the received sequence is exactly the samples dropped in it.
 */
#define _XOPEN_SOURCE 700 /* setitimer, sigaction */

#include "check.h"
#include "magcal/acquire.h"
#include "magcal/ring.h"
#include "sensor_sim.h"

#include <signal.h>
#include <stdlib.h>
#include <string.h>
#include <sys/time.h>

static mc_sample_t sample_with_seq(uint32_t seq)
{
    mc_sample_t s;
    memset(&s, 0, sizeof s);
    s.seq = seq;
    s.t_us = (uint64_t)seq * 3u + 7u;
    s.mag[0] = (int16_t)(seq & 0x7FFFu);
    s.gyr[2] = (int16_t)-(int16_t)(seq & 0x7FFFu);
    return s;
}

static int sample_equal(const mc_sample_t *a, const mc_sample_t *b)
{
    return a->seq == b->seq && a->t_us == b->t_us && memcmp(a->mag, b->mag, sizeof a->mag) == 0
        && memcmp(a->acc, b->acc, sizeof a->acc) == 0 && memcmp(a->gyr, b->gyr, sizeof a->gyr) == 0;
}

/* Does s carry the counts of the sim's k-th successful read? */
static int sample_is_read(const mc_sample_t *s, uint32_t k)
{
    mc_raw_sample_t e;
    sensor_sim_expected(k, &e);
    return memcmp(s->mag, e.mag, sizeof e.mag) == 0 && memcmp(s->acc, e.acc, sizeof e.acc) == 0
        && memcmp(s->gyr, e.gyr, sizeof e.gyr) == 0;
}

static uint32_t xorshift32(uint32_t *state)
{
    uint32_t x = *state;
    x ^= x << 13;
    x ^= x >> 17;
    x ^= x << 5;
    *state = x;
    return x;
}

/* ------------------------------------------------------------------------------- ring */

static void test_ring_init_arguments(void)
{
    mc_sample_t storage[8];
    mc_ring_t ring;
    memset(&ring, 0x5A, sizeof ring);
    const mc_ring_t before = ring;
    CHECK_EQ_INT(mc_ring_init(NULL, storage, 8u), MC_E_ARG);
    CHECK_EQ_INT(mc_ring_init(&ring, NULL, 8u), MC_E_ARG);
    CHECK_EQ_INT(mc_ring_init(&ring, storage, 0u), MC_E_ARG);
    const uint32_t not_pow2[] = {3u, 5u, 6u, 7u, 12u, 0x80000001u, 0xFFFFFFFFu};
    for (size_t i = 0; i < sizeof not_pow2 / sizeof not_pow2[0]; ++i) {
        CHECK_EQ_INT(mc_ring_init(&ring, storage, not_pow2[i]), MC_E_ARG);
    }
    CHECK(memcmp(&ring, &before, sizeof ring) == 0); /* untouched by the failures */
    for (uint32_t cap = 1u; cap <= 8u; cap *= 2u) {
        CHECK_EQ_INT(mc_ring_init(&ring, storage, cap), MC_OK);
        CHECK_EQ_INT(mc_ring_capacity(&ring), cap);
        CHECK_EQ_INT(mc_ring_count(&ring), 0);
        CHECK_EQ_INT(mc_ring_overflow(&ring), 0);
    }
    /* 2^31 is the largest capacity; init does not touch the storage, so a small array is
     * enough to check that it is accepted. */
    CHECK_EQ_INT(mc_ring_init(&ring, storage, 0x80000000u), MC_OK);
    CHECK_EQ_INT(mc_ring_capacity(&ring), 0x80000000u);
    CHECK_EQ_INT(mc_ring_capacity(NULL), 0);
    CHECK_EQ_INT(mc_ring_count(NULL), 0);
    CHECK_EQ_INT(mc_ring_overflow(NULL), 0);
    CHECK_EQ_INT(MC_RING_CAPACITY & (MC_RING_CAPACITY - 1u), 0); /* config.h default */
}

static void test_ring_push_pop_arguments(void)
{
    mc_sample_t storage[4], out;
    mc_ring_t ring;
    CHECK_EQ_INT(mc_ring_init(&ring, storage, 4u), MC_OK);
    const mc_sample_t s = sample_with_seq(1u);
    CHECK_EQ_INT(mc_ring_push(NULL, &s), MC_E_ARG);
    CHECK_EQ_INT(mc_ring_push(&ring, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_ring_pop(NULL, &out), MC_E_ARG);
    CHECK_EQ_INT(mc_ring_pop(&ring, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_ring_count(&ring), 0);
    CHECK_EQ_INT(mc_ring_overflow(&ring), 0); /* argument errors are not drops */
    memset(&out, 0x33, sizeof out);
    const mc_sample_t untouched = out;
    CHECK_EQ_INT(mc_ring_pop(&ring, &out), MC_E_EMPTY);
    CHECK(memcmp(&out, &untouched, sizeof out) == 0);
}

static void test_ring_full_drops_newest(void)
{
    mc_sample_t storage[4], out;
    mc_ring_t ring;
    CHECK_EQ_INT(mc_ring_init(&ring, storage, 4u), MC_OK);
    for (uint32_t i = 0; i < 4u; ++i) {
        const mc_sample_t s = sample_with_seq(i);
        CHECK_EQ_INT(mc_ring_push(&ring, &s), MC_OK);
    }
    CHECK_EQ_INT(mc_ring_count(&ring), 4);
    for (uint32_t i = 4; i < 7u; ++i) {
        const mc_sample_t s = sample_with_seq(i);
        CHECK_EQ_INT(mc_ring_push(&ring, &s), MC_E_OVERFLOW);
        CHECK_EQ_INT(mc_ring_overflow(&ring), i - 3u);
    }
    CHECK_EQ_INT(mc_ring_count(&ring), 4);
    for (uint32_t i = 0; i < 4u; ++i) { /* the oldest were kept, in order */
        const mc_sample_t e = sample_with_seq(i);
        CHECK_EQ_INT(mc_ring_pop(&ring, &out), MC_OK);
        CHECK(sample_equal(&out, &e));
    }
    CHECK_EQ_INT(mc_ring_pop(&ring, &out), MC_E_EMPTY);
    const mc_sample_t s7 = sample_with_seq(7u);
    CHECK_EQ_INT(mc_ring_push(&ring, &s7), MC_OK); /* room again */
    CHECK_EQ_INT(mc_ring_pop(&ring, &out), MC_OK);
    CHECK(sample_equal(&out, &s7));
    CHECK_EQ_INT(mc_ring_overflow(&ring), 3);

    /* Capacity 1 works too (no slot is wasted to tell full from empty). */
    CHECK_EQ_INT(mc_ring_init(&ring, storage, 1u), MC_OK);
    CHECK_EQ_INT(mc_ring_push(&ring, &s7), MC_OK);
    CHECK_EQ_INT(mc_ring_push(&ring, &s7), MC_E_OVERFLOW);
    CHECK_EQ_INT(mc_ring_pop(&ring, &out), MC_OK);
    CHECK_EQ_INT(mc_ring_pop(&ring, &out), MC_E_EMPTY);
}

/* Many cycles of pushes and pops in batches of varying size: FIFO order, every slot reused,
 * count always right; then the same across the 2^32 wrap of the free-running indices (set
 * directly: the struct is public, and this is the state after 2^32 - 5 pushes). */
static void test_ring_wrap_around(void)
{
    mc_sample_t storage[8], out;
    mc_ring_t ring;
    const uint32_t starts[] = {0u, 0xFFFFFFFBu};
    for (size_t r = 0; r < 2u; ++r) {
        CHECK_EQ_INT(mc_ring_init(&ring, storage, 8u), MC_OK);
        ring.head = ring.tail = starts[r];
        uint32_t next_push = 0u, next_pop = 0u, state = 12345u;
        int fifo_ok = 1, count_ok = 1;
        for (int cycle = 0; cycle < 5000; ++cycle) {
            const uint32_t n_push = xorshift32(&state) % 9u; /* 0 .. capacity */
            for (uint32_t i = 0; i < n_push && next_push - next_pop < 8u; ++i) {
                const mc_sample_t s = sample_with_seq(next_push++);
                fifo_ok &= mc_ring_push(&ring, &s) == MC_OK;
            }
            count_ok &= mc_ring_count(&ring) == next_push - next_pop;
            const uint32_t n_pop = xorshift32(&state) % 9u;
            for (uint32_t i = 0; i < n_pop && next_pop < next_push; ++i) {
                const mc_sample_t e = sample_with_seq(next_pop++);
                fifo_ok &= mc_ring_pop(&ring, &out) == MC_OK && sample_equal(&out, &e);
            }
        }
        CHECK(fifo_ok);
        CHECK(count_ok);
        CHECK(next_pop > 10000u); /* many laps of the 8 slots */
        CHECK_EQ_INT(mc_ring_overflow(&ring), 0);
        if (r == 1u) {
            CHECK(ring.head < starts[r]); /* the indices did wrap */
        }
    }
}

/* ------------------------------------------------------------------------ acquisition */

static mc_status_t null_read(void *ctx, mc_raw_sample_t *out)
{
    (void)ctx;
    (void)out;
    return MC_E_SENSOR;
}

static void test_acquire_arguments(void)
{
    sensor_sim_t sim;
    sensor_sim_init(&sim);
    const mc_sensor_hal_t hal = sensor_sim_hal(&sim);
    mc_sample_t storage[4], out;
    mc_acquire_t acq;
    mc_acquire_stats_t st;
    mc_sensor_info_t info[MC_SENSOR_COUNT];

    CHECK_EQ_INT(mc_acquire_init(NULL, &hal, storage, 4u, 0u), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_init(&acq, NULL, storage, 4u, 0u), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, NULL, 4u, 0u), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 0u, 0u), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 3u, 0u), MC_E_ARG);
    const mc_sensor_hal_t no_ops = {NULL, &sim};
    CHECK_EQ_INT(mc_acquire_init(&acq, &no_ops, storage, 4u, 0u), MC_E_ARG);
    const mc_sensor_hal_ops_t partial[3] = {
        {NULL, sensor_sim_now_us, sensor_sim_describe},
        {null_read, NULL, sensor_sim_describe},
        {null_read, sensor_sim_now_us, NULL},
    };
    for (int i = 0; i < 3; ++i) {
        const mc_sensor_hal_t h = {&partial[i], &sim};
        CHECK_EQ_INT(mc_acquire_init(&acq, &h, storage, 4u, 0u), MC_E_ARG);
    }
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 4u, 0u), MC_OK);
    CHECK_EQ_INT(mc_acquire_poll(NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_pop(NULL, &out), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_pop(&acq, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_pop(&acq, &out), MC_E_EMPTY);
    CHECK_EQ_INT(mc_acquire_stats(NULL, &st), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_stats(&acq, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_describe(NULL, info), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_describe(&acq, NULL), MC_E_ARG);
    CHECK_EQ_INT(sim.calls, 0); /* no argument error reached the HAL */
    CHECK_EQ_INT(mc_acquire_stats(&acq, &st), MC_OK);
    CHECK_EQ_INT(st.produced + st.dropped + st.sensor_errors + st.queued + st.next_seq, 0);

    /* Not initialised (zeroed, as a static instance is before init, or after a refused init
     * of a formerly good one): MC_E_STATE, and the HAL's unset pointers are never called. */
    mc_acquire_t zero;
    memset(&zero, 0, sizeof zero);
    CHECK_EQ_INT(mc_acquire_poll(&zero), MC_E_STATE);
    CHECK_EQ_INT(mc_acquire_pop(&zero, &out), MC_E_STATE);
    CHECK_EQ_INT(mc_acquire_stats(&zero, &st), MC_E_STATE);
    CHECK_EQ_INT(mc_acquire_describe(&zero, info), MC_E_STATE);
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 3u, 0u), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_E_STATE);
    CHECK_EQ_INT(mc_acquire_describe(&acq, info), MC_E_STATE);
    CHECK_EQ_INT(mc_acquire_init(&acq, NULL, storage, 4u, 0u), MC_E_ARG);
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_E_STATE);
    CHECK_EQ_INT(sim.calls, 0);
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 4u, 0u), MC_OK);
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_OK);
}

/* Overflow: the newest are dropped and counted, each takes a number, and the gap the consumer
 * sees is exactly the number dropped. */
static void test_acquire_overflow_gap(void)
{
    sensor_sim_t sim;
    sensor_sim_init(&sim);
    const mc_sensor_hal_t hal = sensor_sim_hal(&sim);
    mc_sample_t storage[4], out;
    mc_acquire_t acq;
    mc_acquire_stats_t st;
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 4u, 100u), MC_OK);
    for (int i = 0; i < 10; ++i) {
        CHECK_EQ_INT(mc_acquire_poll(&acq), i < 4 ? MC_OK : MC_E_OVERFLOW);
    }
    CHECK_EQ_INT(mc_acquire_stats(&acq, &st), MC_OK);
    CHECK_EQ_INT(st.produced, 10);
    CHECK_EQ_INT(st.dropped, 6);
    CHECK_EQ_INT(st.queued, 4);
    CHECK_EQ_INT(st.sensor_errors, 0);
    CHECK_EQ_INT(st.next_seq, 110);
    for (uint32_t i = 0; i < 4u; ++i) {
        CHECK_EQ_INT(mc_acquire_pop(&acq, &out), MC_OK);
        CHECK_EQ_INT(out.seq, 100u + i);
        CHECK(sample_is_read(&out, i));
    }
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_OK);
    CHECK_EQ_INT(mc_acquire_pop(&acq, &out), MC_OK);
    CHECK_EQ_INT(out.seq - 103u - 1u, 6); /* the gap after 103 is the 6 dropped */
    CHECK(sample_is_read(&out, 10u));     /* and the data is read 10's */
}

/* A failed read is counted, takes no number (no gap) and leaves a gap in time. */
static void test_acquire_sensor_error(void)
{
    sensor_sim_t sim;
    sensor_sim_init(&sim);
    const mc_sensor_hal_t hal = sensor_sim_hal(&sim);
    mc_sample_t storage[8], out;
    mc_acquire_t acq;
    mc_acquire_stats_t st;
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 8u, 0u), MC_OK);
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_OK);
    sim.fail_next = 2u;
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_E_SENSOR);
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_E_SENSOR);
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_OK);
    CHECK_EQ_INT(mc_acquire_stats(&acq, &st), MC_OK);
    CHECK_EQ_INT(st.produced, 2);
    CHECK_EQ_INT(st.sensor_errors, 2);
    CHECK_EQ_INT(st.dropped, 0);
    CHECK_EQ_INT(st.queued, 2);
    CHECK_EQ_INT(mc_acquire_pop(&acq, &out), MC_OK);
    const uint64_t t0 = out.t_us;
    CHECK_EQ_INT(out.seq, 0);
    CHECK_EQ_INT(mc_acquire_pop(&acq, &out), MC_OK);
    CHECK_EQ_INT(out.seq, 1);                          /* no sequence gap */
    CHECK(sample_is_read(&out, 1u));                   /* not the failed read's garbage */
    CHECK_EQ_INT(out.t_us - t0, 3u * sim.period_us);  /* but a time gap of 2 periods */
    CHECK_EQ_INT(mc_acquire_pop(&acq, &out), MC_E_EMPTY);

    /* Ring full and read failing at once: only the sensor error is counted. */
    for (int i = 0; i < 8; ++i) {
        CHECK_EQ_INT(mc_acquire_poll(&acq), MC_OK);
    }
    sim.fail_next = 1u;
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_E_SENSOR);
    CHECK_EQ_INT(mc_acquire_stats(&acq, &st), MC_OK);
    CHECK_EQ_INT(st.dropped, 0);
    CHECK_EQ_INT(st.sensor_errors, 3);
    CHECK_EQ_INT(st.next_seq, 10);
}

/* The sequence number wraps from 0xFFFFFFFF to 0 with no gap; the first number comes from
 * mc_acquire_init, here just below the wrap. Timestamps pass through, increasing. */
static void test_acquire_seq_wrap_and_time(void)
{
    sensor_sim_t sim;
    sensor_sim_init(&sim);
    sim.t0_us = 0xFFFFFFF0ull; /* past a 32-bit microsecond counter's wrap: 64-bit time */
    const mc_sensor_hal_t hal = sensor_sim_hal(&sim);
    mc_sample_t storage[4], out;
    mc_acquire_t acq;
    mc_acquire_stats_t st;
    const uint32_t first = 0xFFFFFFF0u;
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 4u, first), MC_OK);
    uint32_t expect = first, k = 0u;
    uint64_t prev_t = 0u;
    int seq_ok = 1, data_ok = 1, time_ok = 1;
    for (int i = 0; i < 40; ++i) {
        CHECK_EQ_INT(mc_acquire_poll(&acq), MC_OK);
        CHECK_EQ_INT(mc_acquire_pop(&acq, &out), MC_OK);
        seq_ok &= out.seq == expect;
        data_ok &= sample_is_read(&out, k);
        time_ok &= out.t_us == sim.t0_us + (uint64_t)k * sim.period_us && out.t_us > prev_t;
        prev_t = out.t_us;
        expect += 1u;
        k += 1u;
    }
    CHECK(seq_ok);
    CHECK(data_ok);
    CHECK(time_ok);
    CHECK_EQ_INT(out.seq, 23); /* 0xFFFFFFF0 + 39 - 2^32 */
    CHECK(out.t_us > 0xFFFFFFFFull);
    CHECK_EQ_INT(mc_acquire_stats(&acq, &st), MC_OK);
    CHECK_EQ_INT(st.next_seq, 24);
    CHECK_EQ_INT(st.produced, 40);
    CHECK_EQ_INT(sensor_sim_now_us(&sim), sim.t0_us + 40u * sim.period_us);
}

static void test_acquire_describe(void)
{
    sensor_sim_t sim;
    sensor_sim_init(&sim);
    const mc_sensor_hal_t hal = sensor_sim_hal(&sim);
    mc_sample_t storage[4];
    mc_acquire_t acq;
    mc_sensor_info_t info[MC_SENSOR_COUNT];
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 4u, 0u), MC_OK);
    CHECK_EQ_INT(mc_acquire_describe(&acq, info), MC_OK);
    CHECK(memcmp(info, sim.info, sizeof info) == 0);
    CHECK(strcmp(info[MC_SENSOR_MAG].name, "LIS3MDL") == 0);
    CHECK_EQ_INT(info[MC_SENSOR_GYR].count_scale.den, 164);
    sim.describe_fails = 1;
    CHECK_EQ_INT(mc_acquire_describe(&acq, info), MC_E_SENSOR);
    sim.describe_fails = 0;

    /* Each invalid field of each sensor is refused. */
    for (int k = 0; k < (int)MC_SENSOR_COUNT; ++k) {
        const mc_sensor_info_t good = sim.info[k];
        CHECK_EQ_INT(mc_sensor_info_check(&good, (mc_sensor_kind_t)k), MC_OK);
        mc_sensor_info_t bad[9];
        for (int b = 0; b < 9; ++b) {
            bad[b] = good;
        }
        bad[0].kind = (uint8_t)((k + 1) % 3);
        memset(bad[1].name, 'x', sizeof bad[1].name); /* no NUL */
        bad[2].count_scale.num = 0;
        bad[3].count_scale.num = -1;
        bad[4].count_scale.den = 0u;
        bad[5].count_scale.exp10 = MC_SCALE_EXP10_MAX + 1;
        bad[6].full_scale.exp10 = MC_SCALE_EXP10_MIN - 1;
        bad[7].count_scale.unit = MC_UNIT_INVALID;
        bad[8].full_scale.unit = (uint8_t)(k == MC_SENSOR_MAG ? MC_UNIT_RAD_PER_S : MC_UNIT_TESLA);
        for (int b = 0; b < 9; ++b) {
            CHECK_EQ_INT(mc_sensor_info_check(&bad[b], (mc_sensor_kind_t)k), MC_E_RANGE);
            sim.info[k] = bad[b];
            CHECK_EQ_INT(mc_acquire_describe(&acq, info), MC_E_RANGE);
        }
        sim.info[k] = good;
    }
    CHECK_EQ_INT(mc_acquire_describe(&acq, info), MC_OK);
    CHECK_EQ_INT(mc_sensor_info_check(NULL, MC_SENSOR_MAG), MC_E_ARG);
    CHECK_EQ_INT(mc_sensor_info_check(&info[0], MC_SENSOR_COUNT), MC_E_ARG);
    /* Every unit of each sensor, and the extreme exponents, are accepted. */
    const uint8_t units[3][2] = {{MC_UNIT_TESLA, MC_UNIT_GAUSS},
                                 {MC_UNIT_METRE_PER_S2, MC_UNIT_STANDARD_GRAVITY},
                                 {MC_UNIT_RAD_PER_S, MC_UNIT_DEG_PER_S}};
    for (int k = 0; k < 3; ++k) {
        for (int u = 0; u < 2; ++u) {
            mc_sensor_info_t i = sim.info[k];
            i.full_scale.unit = i.count_scale.unit = units[k][u];
            i.full_scale.exp10 = MC_SCALE_EXP10_MIN;
            i.count_scale.exp10 = MC_SCALE_EXP10_MAX;
            CHECK_EQ_INT(mc_sensor_info_check(&i, (mc_sensor_kind_t)k), MC_OK);
        }
    }
}

/* ----------------------------------------------------------------------- interleavings */

/* Bookkeeping shared by both interleaving tests, indexed by k = seq - first_seq (the sim's
 * k-th successful read). */
#define MAX_PRODUCED 400000u
static unsigned char dropped_k[MAX_PRODUCED];

typedef struct {
    uint32_t first_seq;
    uint32_t received;
    uint32_t prev_k;   /* k of the last received sample */
    int have_prev;
    int order_ok;      /* k strictly increasing, data intact */
    int gap_ok;        /* each gap = the samples dropped in it */
} receiver_t;

static void receiver_take(receiver_t *r, const mc_sample_t *s)
{
    const uint32_t k = s->seq - r->first_seq;
    if (k >= MAX_PRODUCED || !sample_is_read(s, k) || dropped_k[k]
        || (r->have_prev && k <= r->prev_k)) {
        r->order_ok = 0;
        return;
    }
    const uint32_t from = r->have_prev ? r->prev_k + 1u : 0u;
    for (uint32_t j = from; j < k; ++j) { /* everything skipped was dropped */
        if (!dropped_k[j]) {
            r->gap_ok = 0;
        }
    }
    r->prev_k = k;
    r->have_prev = 1;
    ++r->received;
}

/* After the producer stopped and the ring was drained: the tail after the last received
 * sample was all dropped, and received + dropped == produced by every count. */
static void receiver_finish(const receiver_t *r, const mc_acquire_t *acq, uint32_t drops_seen)
{
    mc_acquire_stats_t st;
    CHECK_EQ_INT(mc_acquire_stats(acq, &st), MC_OK);
    CHECK(r->order_ok);
    CHECK(r->gap_ok);
    CHECK_EQ_INT(st.queued, 0);
    CHECK_EQ_INT(r->received + st.dropped, st.produced);
    CHECK_EQ_INT(st.dropped, drops_seen);
    CHECK_EQ_INT(st.next_seq - r->first_seq, st.produced);
    uint32_t marked = 0u;
    for (uint32_t j = 0; j < st.produced && j < MAX_PRODUCED; ++j) {
        marked += dropped_k[j];
    }
    CHECK_EQ_INT(marked, st.dropped);
    for (uint32_t j = r->have_prev ? r->prev_k + 1u : 0u; j < st.produced; ++j) {
        if (!dropped_k[j]) {
            CHECK(!"a sample after the last received one was neither received nor dropped");
            break;
        }
    }
    CHECK(st.dropped > 0u);       /* the schedules do overflow ... */
    CHECK(r->received > 1000u);   /* ... and do deliver */
    CHECK(st.sensor_errors > 0u); /* ... with failed reads mixed in */
}

/* The producer's side: one poll, noting which k it dropped. */
static uint32_t producer_drops;
static void producer_poll(mc_acquire_t *acq, const sensor_sim_t *sim)
{
    if (mc_acquire_poll(acq) == MC_E_OVERFLOW) {
        const uint32_t k = sim->reads - 1u;
        if (k < MAX_PRODUCED) {
            dropped_k[k] = 1u;
        }
        ++producer_drops;
    }
}

/* Deterministic: between consumer steps (pop 0 .. 3), the "interrupt" polls 0 .. 2 times, or
 * in a burst of up to 3 ring capacities; the rates swap every 2000 steps so the ring fills and
 * drains. The sequence number wraps early on. */
static void test_interleaving_deterministic(void)
{
    static sensor_sim_t sim;
    static mc_sample_t storage[16];
    static mc_acquire_t acq;
    sensor_sim_init(&sim);
    sim.fail_every = 37u;
    const mc_sensor_hal_t hal = sensor_sim_hal(&sim);
    memset(dropped_k, 0, sizeof dropped_k);
    producer_drops = 0u;
    receiver_t r = {0xFFFFFC00u, 0u, 0u, 0, 1, 1};
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 16u, r.first_seq), MC_OK);
    uint32_t state = 0x9E3779B9u;
    mc_sample_t out;
    for (uint32_t step = 0; step < 60000u && sim.reads < MAX_PRODUCED - 100u; ++step) {
        const int producer_fast = (step / 2000u) % 2u == 0u;
        const uint32_t x = xorshift32(&state);
        uint32_t n_irq = x % 3u;
        if (x % 64u == 0u) {
            n_irq = (x >> 8) % 48u; /* a burst */
        }
        n_irq += producer_fast ? 1u : 0u;
        for (uint32_t i = 0; i < n_irq; ++i) {
            producer_poll(&acq, &sim);
        }
        const uint32_t n_pop = (x >> 16) % 4u;
        for (uint32_t i = 0; i < n_pop; ++i) {
            if (mc_acquire_pop(&acq, &out) == MC_OK) {
                receiver_take(&r, &out);
            }
        }
    }
    while (mc_acquire_pop(&acq, &out) == MC_OK) {
        receiver_take(&r, &out);
    }
    receiver_finish(&r, &acq, producer_drops);
}

/* Asynchronous: a SIGALRM handler polls (the "interrupt") every 20 us or so while the main
 * loop pops as fast as it can, so a poll can land anywhere inside a pop. Not reproducible step
 * by step, but the checks are the same and must hold for every interleaving. (Checked by
 * mutation: a pop that stores tail before copying its slot fails here in every run.) */
static sensor_sim_t async_sim;
static mc_acquire_t async_acq;
static volatile sig_atomic_t async_stop;
static volatile uint32_t async_polls;

static void on_alarm(int sig)
{
    (void)sig;
    if (async_stop || async_sim.reads >= MAX_PRODUCED - 100u) {
        return;
    }
    /* Mostly fill the ring up to its first drop: then if this interrupt landed inside a pop,
     * the slot being copied out is the one the producer writes next, and a pop that released
     * its slot before copying it would hand out a torn sample. */
    if (async_polls % 5u == 0u) {
        producer_poll(&async_acq, &async_sim);
    } else {
        const uint32_t drops_before = producer_drops;
        for (int i = 0; i < 64 && producer_drops == drops_before; ++i) {
            producer_poll(&async_acq, &async_sim);
        }
    }
    async_polls = async_polls + 1u;
}

static void test_interleaving_signal(void)
{
    static mc_sample_t storage[16];
    sensor_sim_init(&async_sim);
    async_sim.fail_every = 53u;
    const mc_sensor_hal_t hal = sensor_sim_hal(&async_sim);
    memset(dropped_k, 0, sizeof dropped_k);
    producer_drops = 0u;
    async_stop = 0;
    async_polls = 0u;
    receiver_t r = {0xFFFFFF00u, 0u, 0u, 0, 1, 1};
    CHECK_EQ_INT(mc_acquire_init(&async_acq, &hal, storage, 16u, r.first_seq), MC_OK);

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_alarm;
    sigemptyset(&sa.sa_mask);
    sa.sa_flags = SA_RESTART;
    CHECK_EQ_INT(sigaction(SIGALRM, &sa, NULL), 0);
    struct itimerval it;
    memset(&it, 0, sizeof it);
    it.it_interval.tv_usec = 20;
    it.it_value.tv_usec = 20;
    CHECK_EQ_INT(setitimer(ITIMER_REAL, &it, NULL), 0);

    mc_sample_t out;
    uint32_t spins = 0u;
    /* Run until enough polls happened (or a generous spin bound on a very slow machine). */
    while (async_polls < 12000u && spins < 200000000u) {
        if (mc_acquire_pop(&async_acq, &out) == MC_OK) {
            receiver_take(&r, &out);
        }
        ++spins;
    }
    async_stop = 1;
    memset(&it, 0, sizeof it);
    CHECK_EQ_INT(setitimer(ITIMER_REAL, &it, NULL), 0);
    signal(SIGALRM, SIG_IGN);
    while (mc_acquire_pop(&async_acq, &out) == MC_OK) {
        receiver_take(&r, &out);
    }
    printf("  signal interleaving: %u polls, %u received, %u dropped\n", (unsigned)async_polls,
           (unsigned)r.received, (unsigned)producer_drops);
    receiver_finish(&r, &async_acq, producer_drops);
}

int main(void)
{
    test_ring_init_arguments();
    test_ring_push_pop_arguments();
    test_ring_full_drops_newest();
    test_ring_wrap_around();
    test_acquire_arguments();
    test_acquire_overflow_gap();
    test_acquire_sensor_error();
    test_acquire_seq_wrap_and_time();
    test_acquire_describe();
    test_interleaving_deterministic();
    test_interleaving_signal();
    return check_summary("test_fw_acquire");
}
