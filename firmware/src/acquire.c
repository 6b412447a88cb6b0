/* SPDX-License-Identifier: Apache-2.0 */
/* Acquisition through the sensor HAL into the sample ring. See acquire.h and sensor_hal.h. */
#include "magcal/acquire.h"

#include <stddef.h>
#include <string.h>

/* ---- sensor descriptions (sensor_hal.h) ---- */

static int unit_fits(uint8_t unit, mc_sensor_kind_t kind)
{
    if (kind == MC_SENSOR_MAG) {
        return unit == MC_UNIT_TESLA || unit == MC_UNIT_GAUSS;
    }
    if (kind == MC_SENSOR_ACC) {
        return unit == MC_UNIT_METRE_PER_S2 || unit == MC_UNIT_STANDARD_GRAVITY;
    }
    return unit == MC_UNIT_RAD_PER_S || unit == MC_UNIT_DEG_PER_S; /* MC_SENSOR_GYR */
}

static int scale_valid(const mc_scale_t *s, mc_sensor_kind_t kind)
{
    return s->num > 0 && s->den > 0u && s->exp10 >= MC_SCALE_EXP10_MIN
        && s->exp10 <= MC_SCALE_EXP10_MAX && unit_fits(s->unit, kind);
}

mc_status_t mc_sensor_info_check(const mc_sensor_info_t *info, mc_sensor_kind_t kind)
{
    /* Unsigned compare: enums may be unsigned (arm-none-eabi's short enums). */
    if (info == NULL || (unsigned)kind >= (unsigned)MC_SENSOR_COUNT) {
        return MC_E_ARG;
    }
    if (info->kind != (uint8_t)kind || memchr(info->name, '\0', sizeof info->name) == NULL
        || !scale_valid(&info->full_scale, kind) || !scale_valid(&info->count_scale, kind)) {
        return MC_E_RANGE;
    }
    return MC_OK;
}

/* ---- acquisition ---- */

mc_status_t mc_acquire_init(mc_acquire_t *acq, const mc_sensor_hal_t *hal, mc_sample_t *storage,
                            uint32_t capacity, uint32_t first_seq)
{
    if (acq == NULL) {
        return MC_E_ARG;
    }
    acq->ready = 0u;
    if (hal == NULL || hal->ops == NULL || hal->ops->read == NULL || hal->ops->now_us == NULL
        || hal->ops->describe == NULL) {
        return MC_E_ARG;
    }
    const mc_status_t st = mc_ring_init(&acq->ring, storage, capacity);
    if (st != MC_OK) {
        return st;
    }
    acq->hal = *hal;
    acq->next_seq = first_seq;
    acq->produced = 0u;
    acq->sensor_errors = 0u;
    acq->ready = MC_ACQUIRE_READY; /* last: everything above is in place */
    return MC_OK;
}

static int ready(const mc_acquire_t *acq)
{
    return acq->ready == MC_ACQUIRE_READY;
}

mc_status_t mc_acquire_poll(mc_acquire_t *acq)
{
    if (acq == NULL) {
        return MC_E_ARG;
    }
    if (!ready(acq)) {
        return MC_E_STATE;
    }
    mc_raw_sample_t raw;
    if (acq->hal.ops->read(acq->hal.ctx, &raw) != MC_OK) {
        acq->sensor_errors = acq->sensor_errors + 1u;
        return MC_E_SENSOR;
    }
    mc_sample_t s;
    s.t_us = raw.t_us;
    s.seq = acq->next_seq;
    for (int i = 0; i < 3; ++i) {
        s.mag[i] = raw.mag[i];
        s.acc[i] = raw.acc[i];
        s.gyr[i] = raw.gyr[i];
    }
    /* The number is taken before the push, so a dropped sample leaves its gap. */
    acq->next_seq = s.seq + 1u;
    acq->produced = acq->produced + 1u;
    return mc_ring_push(&acq->ring, &s); /* MC_OK or MC_E_OVERFLOW (counted by the ring) */
}

mc_status_t mc_acquire_pop(mc_acquire_t *acq, mc_sample_t *out)
{
    if (acq == NULL || out == NULL) {
        return MC_E_ARG;
    }
    if (!ready(acq)) {
        return MC_E_STATE;
    }
    return mc_ring_pop(&acq->ring, out);
}

mc_status_t mc_acquire_stats(const mc_acquire_t *acq, mc_acquire_stats_t *out)
{
    if (acq == NULL || out == NULL) {
        return MC_E_ARG;
    }
    if (!ready(acq)) {
        return MC_E_STATE;
    }
    out->produced = acq->produced;
    out->dropped = mc_ring_overflow(&acq->ring);
    out->sensor_errors = acq->sensor_errors;
    out->queued = mc_ring_count(&acq->ring);
    out->next_seq = acq->next_seq;
    return MC_OK;
}

mc_status_t mc_acquire_describe(const mc_acquire_t *acq, mc_sensor_info_t out[MC_SENSOR_COUNT])
{
    if (acq == NULL || out == NULL) {
        return MC_E_ARG;
    }
    if (!ready(acq)) {
        return MC_E_STATE;
    }
    if (acq->hal.ops->describe(acq->hal.ctx, out) != MC_OK) {
        return MC_E_SENSOR;
    }
    for (int k = 0; k < (int)MC_SENSOR_COUNT; ++k) {
        if (mc_sensor_info_check(&out[k], (mc_sensor_kind_t)k) != MC_OK) {
            return MC_E_RANGE;
        }
    }
    return MC_OK;
}
