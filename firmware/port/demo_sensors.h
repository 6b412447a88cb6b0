/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The sensors both emulated devices report through info: the native SIL device
 * (port/posix/sil_main.c) and the QEMU target's synthetic sensors
 * (port/mps2-an386/synthetic_sensors.c). One table, so the host sees the same device on
 * either, and tests/target checks the target against it.
 *
 *   magnetometer   LIS3MDL (WHO_AM_I 0x3D), +-4 gauss, 1/6842 gauss per count
 *   accelerometer  LSM6DSO (0x6C), +-4 g, 0.122 mg per count
 *   gyroscope      LSM6DSO (0x6C), +-500 dps, 17.5 mdps per count
 */
#ifndef MAGCAL_PORT_DEMO_SENSORS_H
#define MAGCAL_PORT_DEMO_SENSORS_H

#include "magcal/sensor_hal.h"

#include <string.h>

static void mc_demo_sensor_info(mc_sensor_info_t *info, mc_sensor_kind_t kind, uint8_t id,
                                const char *name, mc_scale_t full_scale, mc_scale_t count_scale)
{
    size_t i = 0;
    memset(info, 0, sizeof *info);
    info->kind = (uint8_t)kind;
    info->id = id;
    for (; name[i] != '\0' && i + 1u < sizeof info->name; ++i) {
        info->name[i] = name[i];
    }
    info->full_scale = full_scale;
    info->count_scale = count_scale;
}

/* Fills out[] with the table above. */
static void mc_demo_sensors_describe(mc_sensor_info_t out[MC_SENSOR_COUNT])
{
    static const mc_scale_t mag_fs = {4, 1u, 0, MC_UNIT_GAUSS};
    static const mc_scale_t mag_count = {1, 6842u, 0, MC_UNIT_GAUSS};
    static const mc_scale_t acc_fs = {4, 1u, 0, MC_UNIT_STANDARD_GRAVITY};
    static const mc_scale_t acc_count = {122, 1u, -6, MC_UNIT_STANDARD_GRAVITY};
    static const mc_scale_t gyr_fs = {500, 1u, 0, MC_UNIT_DEG_PER_S};
    static const mc_scale_t gyr_count = {175, 1u, -4, MC_UNIT_DEG_PER_S};
    mc_demo_sensor_info(&out[MC_SENSOR_MAG], MC_SENSOR_MAG, 0x3Du, "LIS3MDL", mag_fs, mag_count);
    mc_demo_sensor_info(&out[MC_SENSOR_ACC], MC_SENSOR_ACC, 0x6Cu, "LSM6DSO", acc_fs, acc_count);
    mc_demo_sensor_info(&out[MC_SENSOR_GYR], MC_SENSOR_GYR, 0x6Cu, "LSM6DSO", gyr_fs, gyr_count);
}

#endif /* MAGCAL_PORT_DEMO_SENSORS_H */
