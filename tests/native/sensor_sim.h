/* SPDX-License-Identifier: Apache-2.0 */
/*
 * A simulated sensor HAL for the native tests (static inline functions, so that a test
 * program may include it and use only some of them).
 *
 * Read call number c (from 0) happens at time t0_us + c * period_us, so failed reads show as
 * gaps in the timestamps. The k-th successful read (from 0) returns sensor_sim_expected(k):
 * counts that are a known function of k, so a test can check that the sample numbered
 * first_seq + k carries exactly the data of read k (nothing torn, reordered or duplicated).
 * Reads fail on demand: the next fail_next calls, and every call c with
 * c % fail_every == fail_every - 1 when fail_every is not 0. Everything is plain memory, so
 * read() may run in a signal handler standing in for an interrupt.
 */
#ifndef MAGCAL_TEST_SENSOR_SIM_H
#define MAGCAL_TEST_SENSOR_SIM_H

#include <stdint.h>
#include <string.h>

#include "magcal/sensor_hal.h"

typedef struct {
    uint64_t t0_us;      /* time of read call 0 */
    uint32_t period_us;  /* time between read calls */
    uint32_t calls;      /* read calls so far */
    uint32_t reads;      /* successful reads so far */
    uint32_t fail_next;  /* this many next calls fail */
    uint32_t fail_every; /* 0, or every fail_every-th call fails */
    int describe_fails;  /* describe returns MC_E_SENSOR */
    mc_sensor_info_t info[MC_SENSOR_COUNT];
} sensor_sim_t;

/* A count from k and a salt, wrapped into int16_t's range without overflow. */
static inline int16_t sensor_sim_count(uint32_t k, uint32_t salt)
{
    const uint32_t u = (k * 2654435761u + salt * 40503u) & 0xFFFFu;
    return (int16_t)((int32_t)u - 32768);
}

/* The counts of the k-th successful read (t_us is left 0: it depends on failures). */
static inline void sensor_sim_expected(uint32_t k, mc_raw_sample_t *out)
{
    out->t_us = 0u;
    for (uint32_t i = 0; i < 3u; ++i) {
        out->mag[i] = sensor_sim_count(k, i);
        out->acc[i] = sensor_sim_count(k, 3u + i);
        out->gyr[i] = sensor_sim_count(k, 6u + i);
    }
}

static inline mc_status_t sensor_sim_read(void *ctx, mc_raw_sample_t *out)
{
    sensor_sim_t *sim = (sensor_sim_t *)ctx;
    const uint32_t c = sim->calls++;
    int fail = 0;
    if (sim->fail_next > 0u) {
        --sim->fail_next;
        fail = 1;
    }
    if (sim->fail_every != 0u && c % sim->fail_every == sim->fail_every - 1u) {
        fail = 1;
    }
    if (fail) {
        memset(out, 0xA5, sizeof *out); /* garbage the acquisition must not use */
        return MC_E_SENSOR;
    }
    sensor_sim_expected(sim->reads++, out);
    out->t_us = sim->t0_us + (uint64_t)c * sim->period_us;
    return MC_OK;
}

static inline uint64_t sensor_sim_now_us(void *ctx)
{
    const sensor_sim_t *sim = (const sensor_sim_t *)ctx;
    return sim->t0_us + (uint64_t)sim->calls * sim->period_us;
}

static inline mc_status_t sensor_sim_describe(void *ctx, mc_sensor_info_t out[MC_SENSOR_COUNT])
{
    const sensor_sim_t *sim = (const sensor_sim_t *)ctx;
    if (sim->describe_fails) {
        return MC_E_SENSOR;
    }
    memcpy(out, sim->info, sizeof sim->info);
    return MC_OK;
}

static const mc_sensor_hal_ops_t sensor_sim_ops = {
    sensor_sim_read, sensor_sim_now_us, sensor_sim_describe
};

static inline void sensor_sim_set_info(mc_sensor_info_t *info, mc_sensor_kind_t kind, uint8_t id,
                                const char *name, mc_scale_t full_scale, mc_scale_t count_scale)
{
    memset(info, 0, sizeof *info);
    info->kind = (uint8_t)kind;
    info->id = id;
    strncpy(info->name, name, sizeof info->name - 1u);
    info->full_scale = full_scale;
    info->count_scale = count_scale;
}

/* A simulator at 100 Hz from t0_us = 1000000, never failing, describing an LIS3MDL at +-4 G,
 * an MPU-6050 accelerometer at +-2 g and its gyroscope at +-2000 deg/s (sensor_hal.h). */
static inline void sensor_sim_init(sensor_sim_t *sim)
{
    memset(sim, 0, sizeof *sim);
    sim->t0_us = 1000000u;
    sim->period_us = 10000u;
    const mc_scale_t mag_fs = {4, 1u, 0, MC_UNIT_GAUSS}, mag_count = {1, 6842u, 0, MC_UNIT_GAUSS};
    const mc_scale_t acc_fs = {2, 1u, 0, MC_UNIT_STANDARD_GRAVITY};
    const mc_scale_t acc_count = {1, 16384u, 0, MC_UNIT_STANDARD_GRAVITY};
    const mc_scale_t gyr_fs = {2000, 1u, 0, MC_UNIT_DEG_PER_S};
    const mc_scale_t gyr_count = {10, 164u, 0, MC_UNIT_DEG_PER_S};
    sensor_sim_set_info(&sim->info[MC_SENSOR_MAG], MC_SENSOR_MAG, 0x3Du, "LIS3MDL", mag_fs,
                        mag_count);
    sensor_sim_set_info(&sim->info[MC_SENSOR_ACC], MC_SENSOR_ACC, 0x68u, "MPU-6050", acc_fs,
                        acc_count);
    sensor_sim_set_info(&sim->info[MC_SENSOR_GYR], MC_SENSOR_GYR, 0x68u, "MPU-6050", gyr_fs,
                        gyr_count);
}

static inline mc_sensor_hal_t sensor_sim_hal(sensor_sim_t *sim)
{
    mc_sensor_hal_t hal = {&sensor_sim_ops, sim};
    return hal;
}

#endif /* MAGCAL_TEST_SENSOR_SIM_H */
