/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The SIL device's sensor HAL (firmware/port/posix/sensor_feed.c) under ASan+UBSan: the
 * mailbox, the simulator's clock, the line format (valid, malformed and out-of-range lines,
 * nothing applied on error), the quantisation of physical values to counts (the value of a
 * count, rounding at +-half a count, saturation, non-finite values) and P lines, and a
 * scripted session through the acquisition as the SIL device runs it.
 */
#include "check.h"
#include "magcal/acquire.h"
#include "sensor_sim.h" /* for its example sensor descriptions */

#include "../../firmware/port/posix/sensor_feed.c"

#include <float.h>
#include <math.h>
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

/* The sensors of the SIL device (sil_main.c), to check the values of one count. */
static const mc_scale_t SIL_MAG = {1, 6842u, 0, MC_UNIT_GAUSS};
static const mc_scale_t SIL_ACC = {122, 1u, -6, MC_UNIT_STANDARD_GRAVITY};
static const mc_scale_t SIL_GYR = {175, 1u, -4, MC_UNIT_DEG_PER_S};

static int16_t quantised(double v, const mc_scale_t *scale)
{
    int16_t c = 12345;
    CHECK_EQ_INT(mc_sensor_quantise(v, scale, &c), MC_OK);
    return c;
}

static void test_count_si(void)
{
    /* The documented operations, in order, each a double operation. */
    CHECK(mc_sensor_count_si(&SIL_MAG) == 1.0 / 6842.0 * 1e-4);
    CHECK(mc_sensor_count_si(&SIL_ACC) == 122.0 / 1.0 / 1e6 * 9.80665);
    CHECK(mc_sensor_count_si(&SIL_GYR) == 175.0 / 1.0 / 1e4 * (FEED_PI / 180.0));
    /* Within an ulp or two of the exact values. */
    CHECK(fabs(mc_sensor_count_si(&SIL_MAG) / (1e-4 / 6842.0) - 1.0) < 4 * DBL_EPSILON);
    CHECK(fabs(mc_sensor_count_si(&SIL_ACC) / 1.19641130e-3 - 1.0) < 1e-9);
    CHECK(fabs(mc_sensor_count_si(&SIL_GYR) / 3.05432619099e-4 - 1.0) < 1e-10);
    const mc_scale_t big = {2000, 1u, 18, MC_UNIT_TESLA};
    const mc_scale_t tiny = {1, 4000000000u, -18, MC_UNIT_GAUSS};
    CHECK(mc_sensor_count_si(&big) == 2e21);
    CHECK(mc_sensor_count_si(&tiny) == 1.0 / 4e9 / 1e18 * 1e-4);
    /* Invalid scales have no value. */
    mc_scale_t bad = SIL_MAG;
    CHECK(mc_sensor_count_si(NULL) == 0.0);
    bad.num = 0;
    CHECK(mc_sensor_count_si(&bad) == 0.0);
    bad = SIL_MAG;
    bad.den = 0u;
    CHECK(mc_sensor_count_si(&bad) == 0.0);
    bad = SIL_MAG;
    bad.exp10 = 19;
    CHECK(mc_sensor_count_si(&bad) == 0.0);
    bad = SIL_MAG;
    bad.unit = 0u;
    CHECK(mc_sensor_count_si(&bad) == 0.0);
    bad.unit = 7u;
    CHECK(mc_sensor_count_si(&bad) == 0.0);
    int16_t c = 5;
    CHECK_EQ_INT(mc_sensor_quantise(1.0, &bad, &c), MC_E_ARG);
    CHECK_EQ_INT(mc_sensor_quantise(1.0, NULL, &c), MC_E_ARG);
    CHECK_EQ_INT(mc_sensor_quantise(1.0, &SIL_MAG, NULL), MC_E_ARG);
    CHECK_EQ_INT(c, 5);
}

static void test_quantise(void)
{
    /* One count = 1 T, so the quotient is the value itself and halves are exact. */
    const mc_scale_t one = {1, 1u, 0, MC_UNIT_TESLA};
    static const struct {
        double v;
        int16_t c;
    } cases[] = {
        {0.0, 0},          {-0.0, 0},          {0.4, 0},           {-0.4, 0},
        {0.49999999999999994, 0},               /* the largest double below 1/2: not 1 */
        {-0.49999999999999994, 0},
        {0.5, 1},          {-0.5, -1},         /* halves away from zero */
        {1.5, 2},          {2.5, 3},           {-2.5, -3},         {-1.5, -2},
        {2.4999999999999996, 2},               {2.5000000000000004, 3},
        {1234.5, 1235},    {-1234.5, -1235},   {1234.49, 1234},
        {32766.4, 32766},  {32766.5, 32767},   {32767.0, 32767},   /* the top count */
        {32767.4, 32767},  {32767.5, 32767},   {32768.0, 32767},   /* saturated */
        {1e9, 32767},      {DBL_MAX, 32767},
        {-32767.4, -32767}, {-32767.5, -32768}, {-32768.0, -32768}, /* the bottom count */
        {-32768.5, -32768}, {-32769.0, -32768}, {-1e300, -32768},  {-DBL_MAX, -32768},
        {DBL_MIN, 0},      {-4.9e-324, 0},     /* tiny and subnormal */
    };
    for (size_t i = 0; i < sizeof cases / sizeof cases[0]; ++i) {
        const int16_t c = quantised(cases[i].v, &one);
        if (c != cases[i].c) {
            printf("  value %.17g\n", cases[i].v);
        }
        CHECK_EQ_INT(c, cases[i].c);
    }
    /* A binary count (2^-10 T): halves still exact; the quotient overflowing to inf saturates. */
    const mc_scale_t bin = {1, 1024u, 0, MC_UNIT_TESLA};
    CHECK_EQ_INT(quantised(3.5 / 1024.0, &bin), 4);
    CHECK_EQ_INT(quantised(-3.5 / 1024.0, &bin), -4);
    CHECK_EQ_INT(quantised(100.0 / 1024.0, &bin), 100);
    CHECK_EQ_INT(quantised(DBL_MAX, &bin), 32767);
    CHECK_EQ_INT(quantised(-DBL_MAX, &bin), -32768);
    /* Non-finite values are refused, the count untouched. */
    int16_t c = 77;
    CHECK_EQ_INT(mc_sensor_quantise(NAN, &one, &c), MC_E_RANGE);
    CHECK_EQ_INT(mc_sensor_quantise(INFINITY, &one, &c), MC_E_RANGE);
    CHECK_EQ_INT(mc_sensor_quantise(-INFINITY, &one, &c), MC_E_RANGE);
    CHECK_EQ_INT(c, 77);

    /* The SIL's sensors: every count's exact SI value (the host's conversion, here the count
     * times the value of a count) comes back as that count, also +-0.49 count away. */
    const mc_scale_t *sil[3] = {&SIL_MAG, &SIL_ACC, &SIL_GYR};
    int all_ok = 1;
    for (int k = 0; k < 3; ++k) {
        const double lsb = mc_sensor_count_si(sil[k]);
        for (int32_t n = -32768; n <= 32767; ++n) {
            const double v = (double)n * lsb;
            int16_t a = 0, b = 0, d = 0;
            all_ok &= mc_sensor_quantise(v, sil[k], &a) == MC_OK && a == n;
            if (n > -32768 && n < 32767) {
                all_ok &= mc_sensor_quantise(v + 0.49 * lsb, sil[k], &b) == MC_OK && b == n;
                all_ok &= mc_sensor_quantise(v - 0.49 * lsb, sil[k], &d) == MC_OK && d == n;
            }
        }
    }
    CHECK(all_ok);
    /* Physical values: 45 uT = 0.45 G = 3078.9 counts of 1/6842 G; 1 g = 8196.7 counts of
     * 122 ug0; 0.01 rad/s = 0.573 dps = 32.74 counts of 17.5 mdps; 4 G is inside the register
     * range (27368), 4 g just outside (32787 -> 32767). */
    CHECK_EQ_INT(quantised(45e-6, &SIL_MAG), 3079);
    CHECK_EQ_INT(quantised(-45e-6, &SIL_MAG), -3079);
    CHECK_EQ_INT(quantised(4e-4, &SIL_MAG), 27368);
    CHECK_EQ_INT(quantised(5e-4, &SIL_MAG), 32767);
    CHECK_EQ_INT(quantised(9.80665, &SIL_ACC), 8197);
    CHECK_EQ_INT(quantised(-4.0 * 9.80665, &SIL_ACC), -32768);
    CHECK_EQ_INT(quantised(4.0 * 9.80665, &SIL_ACC), 32767);
    CHECK_EQ_INT(quantised(0.01, &SIL_GYR), 33);
    CHECK_EQ_INT(quantised(-0.01, &SIL_GYR), -33);
    CHECK_EQ_INT(quantised(500.0 * FEED_PI / 180.0, &SIL_GYR), 28571);
    CHECK_EQ_INT(quantised(600.0 * FEED_PI / 180.0, &SIL_GYR), 32767);
}

static void test_physical_lines(void)
{
    mc_sensor_info_t info[MC_SENSOR_COUNT];
    example_info(info); /* LIS3MDL 1/6842 G, MPU-6050 1/16384 g and 10/164 dps */
    info[MC_SENSOR_ACC].count_scale = SIL_ACC;
    info[MC_SENSOR_GYR].count_scale = SIL_GYR;
    mc_sensor_feed_t feed;
    CHECK_EQ_INT(mc_sensor_feed_init(&feed, info), MC_OK);
    mc_raw_sample_t raw;

    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "P 10 4.5e-05 -1E-5 0 .5 -0 9.80665 0.01 "
                                                  "-0.01 \t 1e+0\r\n"),
                 MC_OK);
    CHECK(feed.has_sample);
    CHECK_EQ_INT(feed.now_us, 10);
    CHECK_EQ_INT(feed_read(&feed, &raw), MC_OK);
    {
        const mc_raw_sample_t e = {10u, {3079, -684, 0}, {418, 0, 8197}, {33, -33, 3274}};
        CHECK(raw.t_us == e.t_us && memcmp(raw.mag, e.mag, sizeof e.mag) == 0
              && memcmp(raw.acc, e.acc, sizeof e.acc) == 0
              && memcmp(raw.gyr, e.gyr, sizeof e.gyr) == 0);
    }
    /* Extreme values saturate at the int16 limits, like the registers. */
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "P 20 1 -1 1e-3 1e3 -1e3 40 1e9 -1e308 11"),
                 MC_OK);
    CHECK_EQ_INT(feed_read(&feed, &raw), MC_OK);
    {
        const mc_raw_sample_t e = {20u, {32767, -32768, 32767}, {32767, -32768, 32767},
                                   {32767, -32768, 32767}};
        CHECK(raw.t_us == e.t_us && memcmp(raw.mag, e.mag, sizeof e.mag) == 0
              && memcmp(raw.acc, e.acc, sizeof e.acc) == 0
              && memcmp(raw.gyr, e.gyr, sizeof e.gyr) == 0);
    }
    /* Every decimal form. */
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "P 30 5. 00.0001 -.0e5 0 0 0 0 0 1E-2"),
                 MC_OK);
    CHECK_EQ_INT(feed_read(&feed, &raw), MC_OK);
    CHECK_EQ_INT(raw.mag[0], 32767);
    CHECK_EQ_INT(raw.mag[1], 6842);
    CHECK_EQ_INT(raw.mag[2], 0);
    CHECK_EQ_INT(raw.gyr[2], 33);

    /* Refused lines change nothing: non-finite values MC_E_RANGE, other text MC_E_FRAME. */
    CHECK_EQ_INT(mc_sensor_feed_set_time(&feed, 100u), MC_OK);
    const mc_sensor_feed_t before = feed;
    static const struct {
        const char *line;
        mc_status_t st;
    } bad[] = {
        {"P 200 nan 0 0 0 0 0 0 0 0", MC_E_RANGE},
        {"P 200 0 NaN 0 0 0 0 0 0 0", MC_E_RANGE},
        {"P 200 0 0 -nan 0 0 0 0 0 0", MC_E_RANGE},
        {"P 200 0 0 0 inf 0 0 0 0 0", MC_E_RANGE},
        {"P 200 0 0 0 0 -inf 0 0 0 0", MC_E_RANGE},
        {"P 200 0 0 0 0 0 Infinity 0 0 0", MC_E_RANGE},
        {"P 200 0 0 0 0 0 0 -INF 0 0", MC_E_RANGE},
        {"P 200 0 0 0 0 0 0 0 1e999 0", MC_E_RANGE},      /* too large for a double */
        {"P 200 0 0 0 0 0 0 0 0 -1e400\n", MC_E_RANGE},
        {"P 99 0 0 0 0 0 0 0 0 0", MC_E_RANGE},           /* before the clock (100) */
        {"P 18446744073709551616 0 0 0 0 0 0 0 0 0", MC_E_RANGE},
        {"P 200 nan 0 0 0 0 0 0 0 x", MC_E_FRAME},        /* malformed wins over range */
        {"P 200 nanx 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 infin 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 0x1p3 0 0 0 0 0 0 0 0", MC_E_FRAME},      /* no hexadecimal */
        {"P 200 +1 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 --1 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 1.2.3 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 1e 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 1e+ 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 . 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 - 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 e5 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 1,5 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 1e5x 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200 0 0 0 0 0 0 0 0", MC_E_FRAME},            /* a field missing */
        {"P 200 0 0 0 0 0 0 0 0 0 0", MC_E_FRAME},        /* one too many */
        {"P 200 0 0 0 0 0 0 0 0 0\r", MC_E_FRAME},
        {"P200 0 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"p 200 0 0 0 0 0 0 0 0 0", MC_E_FRAME},
        {"P 200.5 0 0 0 0 0 0 0 0 0", MC_E_FRAME},        /* time is an integer */
        {"P", MC_E_FRAME},
    };
    for (size_t i = 0; i < sizeof bad / sizeof bad[0]; ++i) {
        const mc_status_t st = mc_sensor_feed_apply_line(&feed, bad[i].line);
        if (st != bad[i].st) {
            printf("  line \"%s\"\n", bad[i].line);
        }
        CHECK_EQ_INT(st, bad[i].st);
        CHECK(memcmp(&feed, &before, sizeof feed) == 0);
    }
    /* A P line while a read is pending: an overrun, like an S line. */
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "P 200 0 0 0 0 0 0 0 0 0"), MC_OK);
    CHECK_EQ_INT(mc_sensor_feed_apply_line(&feed, "P 300 1 0 0 0 0 0 0 0 0"), MC_E_OVERFLOW);
    CHECK_EQ_INT(feed.overruns, 1);
    CHECK_EQ_INT(feed.pending.t_us, 200);

    /* The reasons the SIL device prints. */
    CHECK(strcmp(mc_sensor_feed_refusal(MC_OK), "ok") == 0);
    CHECK(strcmp(mc_sensor_feed_refusal(MC_E_FRAME), "malformed line") == 0);
    CHECK(strstr(mc_sensor_feed_refusal(MC_E_RANGE), "not finite") != NULL);
    CHECK(strstr(mc_sensor_feed_refusal(MC_E_OVERFLOW), "overrun") != NULL);
    CHECK(strcmp(mc_sensor_feed_refusal(MC_E_ARG), "no feed or no line") == 0);
    CHECK(strcmp(mc_sensor_feed_refusal(MC_E_CRC), "refused") == 0);
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
    test_count_si();
    test_quantise();
    test_physical_lines();
    test_scripted_session();
    return check_summary("test_fw_sensor_feed");
}
