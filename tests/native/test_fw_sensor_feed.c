/*
 * The SIL device's sensor HAL (firmware/port/posix/sensor_feed.c) under ASan+UBSan: the
 * mailbox, the simulator's clock, the line format (valid, malformed and out-of-range lines,
 * nothing applied on error), and a scripted session through the acquisition as the SIL device
 * runs it.
 */
#include "check.h"
#include "magcal/acquire.h"
#include "sensor_sim.h" /* for its example sensor descriptions */

#include "../../firmware/port/posix/sensor_feed.c"

#include <string.h>

static void example_info(mc_sensor_info_t info[MC_SENSOR_COUNT])
{
    sensor_sim_t sim;
    sensor_sim_init(&sim);
    memcpy(info, sim.info, sizeof sim.info);
}

static void test_init_and_describe(void)
{
    mc_sensor_info_t info[MC_SENSOR_COUNT], got[MC_SENSOR_COUNT];
    example_info(info);
    mc_sensor_feed_t feed;
    CHECK_EQ_INT(mc_sensor_feed_init(NULL, info), MC_E_ARG);
    CHECK_EQ_INT(mc_sensor_feed_init(&feed, NULL), MC_E_ARG);
    memset(&feed, 0x77, sizeof feed);
    const mc_sensor_feed_t before = feed;
    info[MC_SENSOR_ACC].count_scale.den = 0u;
    CHECK_EQ_INT(mc_sensor_feed_init(&feed, info), MC_E_RANGE);
    CHECK(memcmp(&feed, &before, sizeof feed) == 0);
    example_info(info);
    CHECK_EQ_INT(mc_sensor_feed_init(&feed, info), MC_OK);
    CHECK(!mc_sensor_feed_pending(&feed));
    CHECK(!mc_sensor_feed_pending(NULL));

    const mc_sensor_hal_t hal = mc_sensor_feed_hal(&feed);
    CHECK(hal.ctx == &feed);
    CHECK_EQ_INT(hal.ops->now_us(hal.ctx), 0);
    static mc_sample_t storage[4];
    mc_acquire_t acq;
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 4u, 0u), MC_OK);
    CHECK_EQ_INT(mc_acquire_describe(&acq, got), MC_OK);
    CHECK(memcmp(got, info, sizeof got) == 0);
    /* The ops refuse a NULL context or output instead of crashing. */
    mc_raw_sample_t raw;
    CHECK_EQ_INT(hal.ops->read(NULL, &raw), MC_E_SENSOR);
    CHECK_EQ_INT(hal.ops->read(&feed, NULL), MC_E_SENSOR);
    CHECK_EQ_INT(hal.ops->describe(NULL, got), MC_E_SENSOR);
    CHECK_EQ_INT(hal.ops->now_us(NULL), 0);
}

static void test_mailbox_and_clock(void)
{
    mc_sensor_info_t info[MC_SENSOR_COUNT];
    example_info(info);
    mc_sensor_feed_t feed;
    CHECK_EQ_INT(mc_sensor_feed_init(&feed, info), MC_OK);
    const mc_sensor_hal_t hal = mc_sensor_feed_hal(&feed);
    static mc_sample_t storage[4];
    mc_acquire_t acq;
    mc_acquire_stats_t st;
    mc_sample_t out;
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 4u, 0u), MC_OK);

    /* Nothing pending: the read fails and is counted. */
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_E_SENSOR);

    mc_raw_sample_t a = {5000u, {1, -2, 3}, {-32768, 0, 32767}, {7, 8, 9}};
    CHECK_EQ_INT(mc_sensor_feed_put(NULL, &a), MC_E_ARG);
    CHECK_EQ_INT(mc_sensor_feed_put(&feed, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_sensor_feed_put(&feed, &a), MC_OK);
    CHECK(mc_sensor_feed_pending(&feed));
    CHECK_EQ_INT(hal.ops->now_us(hal.ctx), 5000);
    /* A second put before the read is refused and counted; the first stays. */
    mc_raw_sample_t b = a;
    b.t_us = 6000u;
    b.mag[0] = 99;
    CHECK_EQ_INT(mc_sensor_feed_put(&feed, &b), MC_E_OVERFLOW);
    CHECK_EQ_INT(mc_sensor_feed_put_error(&feed, 6000u), MC_E_OVERFLOW);
    CHECK_EQ_INT(feed.overruns, 2);
    CHECK_EQ_INT(hal.ops->now_us(hal.ctx), 5000);
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_OK);
    CHECK(!mc_sensor_feed_pending(&feed));
    CHECK_EQ_INT(mc_acquire_pop(&acq, &out), MC_OK);
    CHECK_EQ_INT(out.seq, 0);
    CHECK_EQ_INT(out.t_us, 5000);
    CHECK(memcmp(out.mag, a.mag, sizeof a.mag) == 0 && memcmp(out.acc, a.acc, sizeof a.acc) == 0
          && memcmp(out.gyr, a.gyr, sizeof a.gyr) == 0);

    /* Time never goes back. */
    b.t_us = 4999u;
    CHECK_EQ_INT(mc_sensor_feed_put(&feed, &b), MC_E_RANGE);
    CHECK_EQ_INT(mc_sensor_feed_put_error(&feed, 4999u), MC_E_RANGE);
    CHECK_EQ_INT(mc_sensor_feed_set_time(&feed, 4999u), MC_E_RANGE);
    CHECK_EQ_INT(mc_sensor_feed_set_time(NULL, 6000u), MC_E_ARG);
    CHECK_EQ_INT(mc_sensor_feed_put_error(NULL, 6000u), MC_E_ARG);
    CHECK(!mc_sensor_feed_pending(&feed));
    CHECK_EQ_INT(mc_sensor_feed_set_time(&feed, 5000u), MC_OK); /* equal is fine */
    CHECK_EQ_INT(mc_sensor_feed_set_time(&feed, 7000u), MC_OK);
    CHECK_EQ_INT(hal.ops->now_us(hal.ctx), 7000);
    CHECK(!mc_sensor_feed_pending(&feed));

    /* An injected failure: counted, takes no number. */
    CHECK_EQ_INT(mc_sensor_feed_put_error(&feed, 8000u), MC_OK);
    CHECK(mc_sensor_feed_pending(&feed));
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_E_SENSOR);
    CHECK(!mc_sensor_feed_pending(&feed));
    b.t_us = 9000u;
    CHECK_EQ_INT(mc_sensor_feed_put(&feed, &b), MC_OK);
    CHECK_EQ_INT(mc_acquire_poll(&acq), MC_OK);
    CHECK_EQ_INT(mc_acquire_pop(&acq, &out), MC_OK);
    CHECK_EQ_INT(out.seq, 1);
    CHECK_EQ_INT(out.mag[0], 99);
    CHECK_EQ_INT(mc_acquire_stats(&acq, &st), MC_OK);
    CHECK_EQ_INT(st.produced, 2);
    CHECK_EQ_INT(st.sensor_errors, 2);
}

static void test_lines(void)
{
    mc_sensor_info_t info[MC_SENSOR_COUNT];
    example_info(info);
    mc_sensor_feed_t feed;
    CHECK_EQ_INT(mc_sensor_feed_init(&feed, info), MC_OK);
    mc_raw_sample_t raw;

    CHECK_EQ_INT(mc_sensor_feed_apply_line(NULL, "T 1"), MC_E_ARG);
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, NULL), MC_E_ARG);

    const char *line = "S 10 1 -2 3 -32768 32767 0 -0 \t 8 9\r\n";
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, line), MC_OK);
    CHECK(feed.has_sample);
    CHECK_EQ_INT(feed.now_us, 10);
    CHECK_EQ_INT(feed_read(&feed, &raw), MC_OK);
    const mc_raw_sample_t e = {10u, {1, -2, 3}, {-32768, 32767, 0}, {0, 8, 9}};
    CHECK(raw.t_us == e.t_us && memcmp(raw.mag, e.mag, sizeof e.mag) == 0
          && memcmp(raw.acc, e.acc, sizeof e.acc) == 0
          && memcmp(raw.gyr, e.gyr, sizeof e.gyr) == 0);

    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "E 20\n"), MC_OK);
    CHECK(feed.has_error);
    CHECK_EQ_INT(feed_read(&feed, &raw), MC_E_SENSOR);
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "T 30"), MC_OK);
    CHECK_EQ_INT(feed.now_us, 30);
    CHECK(!mc_sensor_feed_pending(&feed));
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "T 18446744073709551615 "), MC_OK);
    CHECK(feed.now_us == UINT64_MAX);

    /* Refused lines change nothing. */
    CHECK_EQ_INT(mc_sensor_feed_init(&feed, info), MC_OK);
    CHECK_EQ_INT(mc_sensor_feed_set_time(&feed, 100u), MC_OK);
    const mc_sensor_feed_t before = feed;
    static const struct {
        const char *line;
        mc_status_t st;
    } bad[] = {
        {"", MC_E_FRAME},
        {"\n", MC_E_FRAME},
        {"X 200", MC_E_FRAME},
        {"s 200 1 2 3 4 5 6 7 8 9", MC_E_FRAME},
        {" S 200 1 2 3 4 5 6 7 8 9", MC_E_FRAME},
        {"S", MC_E_FRAME},
        {"S200 1 2 3 4 5 6 7 8 9", MC_E_FRAME},
        {"S 200 1 2 3 4 5 6 7 8", MC_E_FRAME},        /* a field missing */
        {"S 200 1 2 3 4 5 6 7 8 9 10", MC_E_FRAME},   /* one too many */
        {"S 200 1 2 3 4 5 6 7 8 x", MC_E_FRAME},
        {"S 200 1 2 3 4 5 6 7 8 9x", MC_E_FRAME},
        {"S 200 1 2 3 4 5 6 7 8 +9", MC_E_FRAME},
        {"S 200 1 2 3 4 5 6 7 8 -", MC_E_FRAME},
        {"S 200 1 2 3 4 5 6 7 8 0x10", MC_E_FRAME},
        {"S 200 1 2 3 4 5 6 7 8 9\n\n", MC_E_FRAME},
        {"S 200 1 2 3 4 5 6 7 8 9\r", MC_E_FRAME},
        {"S -200 1 2 3 4 5 6 7 8 9", MC_E_FRAME},     /* time is unsigned */
        {"S 200,1,2,3,4,5,6,7,8,9", MC_E_FRAME},
        {"E", MC_E_FRAME},
        {"E 200 1", MC_E_FRAME},
        {"T 200 x", MC_E_FRAME},
        {"S 200 32768 2 3 4 5 6 7 8 9", MC_E_RANGE},
        {"S 200 1 2 3 4 5 6 7 8 -32769", MC_E_RANGE},
        {"S 200 1 2 3 4 5 6 7 8 99999999999999999999999", MC_E_RANGE},
        {"T 18446744073709551616", MC_E_RANGE},       /* 2^64 */
        {"E 99999999999999999999", MC_E_RANGE},
        {"T 18446744073709551616 x", MC_E_FRAME},     /* malformed wins over range */
        {"S 99 1 2 3 4 5 6 7 8 9", MC_E_RANGE},       /* before the clock (100) */
        {"E 99", MC_E_RANGE},
        {"T 99", MC_E_RANGE},
    };
    for (size_t i = 0; i < sizeof bad / sizeof bad[0]; ++i) {
        const mc_status_t st = mc_sensor_feed_apply_line(&feed, bad[i].line);
        if (st != bad[i].st) {
            printf("  line \"%s\"\n", bad[i].line);
        }
        CHECK_EQ_INT(st, bad[i].st);
        CHECK(memcmp(&feed, &before, sizeof feed) == 0);
    }
    /* A line while a read is pending: refused and counted, the pending one kept. */
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "S 200 1 2 3 4 5 6 7 8 9"), MC_OK);
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "S 300 1 2 3 4 5 6 7 8 9"), MC_E_OVERFLOW);
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "E 300"), MC_E_OVERFLOW);
    CHECK_EQ_INT(feed.overruns, 2);
    CHECK_EQ_INT(feed.pending.t_us, 200);
}

/* A session as the SIL device runs it: one poll per line that left a read pending, a ring of
 * 4 and a consumer that drains only at the end of each block, so some samples overflow. */
static void test_scripted_session(void)
{
    mc_sensor_info_t info[MC_SENSOR_COUNT];
    example_info(info);
    mc_sensor_feed_t feed;
    CHECK_EQ_INT(mc_sensor_feed_init(&feed, info), MC_OK);
    const mc_sensor_hal_t hal = mc_sensor_feed_hal(&feed);
    static mc_sample_t storage[4];
    mc_acquire_t acq;
    CHECK_EQ_INT(mc_acquire_init(&acq, &hal, storage, 4u, 0u), MC_OK);
    char line[128];
    uint32_t received = 0u, gaps = 0u, prev_seq = 0u, errors_put = 0u;
    int have_prev = 0, order_ok = 1;
    uint64_t t = 1000000u;
    for (uint32_t block = 0; block < 50u; ++block) {
        const uint32_t n = 1u + block % 7u; /* 1 .. 7 lines per block: above 4 overflows */
        for (uint32_t i = 0; i < n; ++i) {
            t += 10000u;
            if ((block * 7u + i) % 11u == 5u) {
                snprintf(line, sizeof line, "E %llu\n", (unsigned long long)t);
                ++errors_put;
            } else {
                snprintf(line, sizeof line, "S %llu %d %d %d 0 0 1000 -5 5 0\n",
                         (unsigned long long)t, (int)(block % 100u), -(int)i, 3);
            }
            CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, line), MC_OK);
            if (mc_sensor_feed_pending(&feed)) {
                (void)mc_acquire_poll(&acq); /* outcomes are in the counters, checked below */
            }
        }
        CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "T 0"), MC_E_RANGE);
        mc_sample_t out;
        while (mc_acquire_pop(&acq, &out) == MC_OK) {
            if (have_prev) {
                order_ok &= out.seq > prev_seq && out.t_us > 0u;
                gaps += out.seq - prev_seq - 1u;
            }
            prev_seq = out.seq;
            have_prev = 1;
            ++received;
        }
    }
    mc_acquire_stats_t st;
    CHECK_EQ_INT(mc_acquire_stats(&acq, &st), MC_OK);
    CHECK(order_ok);
    CHECK(st.dropped > 0u);
    CHECK_EQ_INT(received + st.dropped, st.produced);
    CHECK_EQ_INT(st.sensor_errors, errors_put);
    CHECK_EQ_INT(gaps + (st.next_seq - 1u - prev_seq), st.dropped);
    CHECK_EQ_INT(feed.overruns, 0);
    CHECK_EQ_INT(hal.ops->now_us(hal.ctx), t);
}

int main(void)
{
    test_init_and_describe();
    test_mailbox_and_clock();
    test_lines();
    test_scripted_session();
    return check_summary("test_fw_sensor_feed");
}
