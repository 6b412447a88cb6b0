/* SPDX-License-Identifier: Apache-2.0 */
/* Synthetic sensors: see synthetic_sensors.h for the exact counts. */
#include "synthetic_sensors.h"

#include <stddef.h>

#include "../demo_sensors.h"
#include "magcal/fixed.h"
#include "systick_time.h"

/* round(32767 * sin(2 pi i / 256)), i = 0..64 (a quarter turn), made with
 * python3 -c "import math; print([round(32767*math.sin(2*math.pi*i/256)) for i in range(65)])" */
static const int16_t k_sin_q15[65] = {
    0,     804,   1608,  2410,  3212,  4011,  4808,  5602,  6393,  7179,  7962,  8739,  9512,
    10278, 11039, 11793, 12539, 13279, 14010, 14732, 15446, 16151, 16846, 17530, 18204, 18868,
    19519, 20159, 20787, 21403, 22005, 22594, 23170, 23731, 24279, 24811, 25329, 25832, 26319,
    26790, 27245, 27683, 28105, 28510, 28898, 29268, 29621, 29956, 30273, 30571, 30852, 31113,
    31356, 31580, 31785, 31971, 32137, 32285, 32412, 32521, 32609, 32678, 32728, 32757, 32767,
};

#define SYNTH_MAG_H_X 1368    /* 0.20 G horizontal field, counts (0.20 * 6842 = 1368.4) */
#define SYNTH_MAG_H_Y 1231    /* the same through the y axis' soft iron, gain 0.9 */
#define SYNTH_MAG_V 3079      /* 0.45 G down (0.45 * 6842 = 3078.9) */
#define SYNTH_MAG_O_X 412     /* hard iron, counts */
#define SYNTH_MAG_O_Y (-237)
#define SYNTH_MAG_O_Z 158
#define SYNTH_ACC_Z 8197      /* 1 g / 0.122 mg = 8196.7 */
#define SYNTH_GYR_Z 8036      /* 140.625 dps / 17.5 mdps = 8035.7 */

/* S(i mod 256). */
static int32_t sin_q15(uint32_t i)
{
    i &= MC_SYNTH_STEPS_PER_TURN - 1u;
    if (i < 64u) {
        return k_sin_q15[i];
    }
    if (i < 128u) {
        return k_sin_q15[128u - i];
    }
    return -(int32_t)sin_q15(i - 128u);
}

/* floor((a * x + 2^14) / 2^15), the round-half-up of a * x / 2^15 that the header documents,
 * by fixed.h's rounding shift (well defined for negative products, unlike >> on a negative
 * int32). |a| <= 1368 and |x| <= 32767, so |a * x| < 2^26 and the result fits int16_t. */
static int16_t q15_mul(int32_t a, int32_t x)
{
    return (int16_t)mc_fx_rshift_round_i64((int64_t)a * x, 15u);
}

void mc_synth_counts(uint32_t k, mc_raw_sample_t *out)
{
    const int32_t s = sin_q15(k);
    const int32_t c = sin_q15(k + 64u);
    out->t_us = 0u;
    out->mag[0] = (int16_t)(SYNTH_MAG_O_X + q15_mul(SYNTH_MAG_H_X, c));
    out->mag[1] = (int16_t)(SYNTH_MAG_O_Y - q15_mul(SYNTH_MAG_H_Y, s));
    out->mag[2] = (int16_t)(SYNTH_MAG_O_Z - SYNTH_MAG_V);
    out->acc[0] = 0;
    out->acc[1] = 0;
    out->acc[2] = SYNTH_ACC_Z;
    out->gyr[0] = 0;
    out->gyr[1] = 0;
    out->gyr[2] = SYNTH_GYR_Z;
}

uint64_t mc_synth_now_us(mc_synth_sensors_t *s)
{
    const uint32_t now = mc_systick_time_us();
    const uint32_t step = now - s->last32; /* modulo 2^32: right across the wrap */
    if (step > UINT32_MAX / 2u) {
        ++s->backsteps; /* a reading before the last one: the clock never goes back */
    } else {
        s->now_us += step;
        s->last32 = now;
    }
    return s->now_us;
}

void mc_synth_init(mc_synth_sensors_t *s)
{
    uint64_t now;
    s->k = 0u;
    s->last32 = 0u;
    s->now_us = 0u;
    s->backsteps = 0u;
    now = mc_synth_now_us(s);
    /* The clock has just started (it is below 2^32 us): a 32-bit division does, and keeps
     * libgcc's 64-bit division out of the image. */
    s->next_due_us = ((uint64_t)((uint32_t)now / MC_SYNTH_PERIOD_US) + 1u) * MC_SYNTH_PERIOD_US;
}

int mc_synth_due(mc_synth_sensors_t *s)
{
    return mc_synth_now_us(s) >= s->next_due_us;
}

static mc_status_t synth_read(void *ctx, mc_raw_sample_t *out)
{
    mc_synth_sensors_t *s = (mc_synth_sensors_t *)ctx;
    if (!mc_synth_due(s)) {
        return MC_E_SENSOR; /* no new data yet */
    }
    mc_synth_counts(s->k, out);
    out->t_us = s->next_due_us;
    ++s->k;
    s->next_due_us += MC_SYNTH_PERIOD_US;
    return MC_OK;
}

static uint64_t synth_now_us(void *ctx)
{
    return mc_synth_now_us((mc_synth_sensors_t *)ctx);
}

/* The SIL's table (port/demo_sensors.h). */
static mc_status_t synth_describe(void *ctx, mc_sensor_info_t out[MC_SENSOR_COUNT])
{
    (void)ctx;
    mc_demo_sensors_describe(out);
    return MC_OK;
}

static const mc_sensor_hal_ops_t k_synth_ops = {synth_read, synth_now_us, synth_describe};

mc_sensor_hal_t mc_synth_hal(mc_synth_sensors_t *s)
{
    mc_sensor_hal_t hal = {&k_synth_ops, s};
    return hal;
}
