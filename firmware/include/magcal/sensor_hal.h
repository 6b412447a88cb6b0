/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Sensor hardware-abstraction layer: how the acquisition (acquire.h) reads the magnetometer,
 * accelerometer and gyroscope, and how a port tells the host exactly what one raw count is.
 *
 * A HAL is a table of operations plus the port's context pointer:
 *
 *     static const mc_sensor_hal_ops_t my_ops = { my_read, my_now_us, my_describe };
 *     mc_sensor_hal_t hal = { &my_ops, &my_driver_state };
 *
 * Ports: firmware/port/posix/sensor_feed.h (the SIL device, fed by the simulator) and the
 * target's drivers; tests/native/sensor_sim.h (a scripted HAL for the native tests).
 *
 * Raw counts and frames
 *   Counts are the sensor's signed output registers as int16_t, not converted in any way
 *   (no floating point anywhere in acquisition). The accelerometer and gyroscope counts are in
 *   the body frame b of docs/contracts.md (the accelerometer triad's axes, right-handed): a
 *   port whose chip is mounted rotated permutes axes and flips signs on the integer counts,
 *   saturating -(-32768) to 32767. The magnetometer counts may stay in the chip's own axes:
 *   the calibration estimates the rotation between them and b.
 *
 * Time
 *   Timestamps are microseconds of one device clock as uint64_t (it would wrap after 584 000
 *   years, so nobody unwraps it). A port with a 32-bit hardware timer extends it to 64 bits
 *   (count the timer's wraps); timestamps never decrease. read() stamps each sample with the
 *   time the sensors sampled it (for example the data-ready interrupt), which is better than
 *   the time the bus transfer finished; now_us() gives the same clock's current time.
 *
 * Exact scale of a count (mc_scale_t)
 *   One count of a sensor is worth exactly  num / den * 10^exp10  of `unit` (mc_unit_t), with
 *   integers only, so that the host can convert to SI units with exact rational arithmetic
 *   (Python: fractions.Fraction) and round once at the end. Each unit has an exact SI factor:
 *
 *     unit                        SI unit   factor (exact)
 *     MC_UNIT_TESLA               T         1
 *     MC_UNIT_GAUSS               T         1/10000               (1 G = 1e-4 T)
 *     MC_UNIT_METRE_PER_S2        m/s^2     1
 *     MC_UNIT_STANDARD_GRAVITY    m/s^2     980665/100000         (g0 = 9.80665 m/s^2, CGPM 1901)
 *     MC_UNIT_RAD_PER_S           rad/s     1
 *     MC_UNIT_DEG_PER_S           rad/s     pi/180                (rational multiple of pi)
 *
 *   So value_SI = count * Fraction(num, den) * Fraction(10)**exp10 * factor(unit), exact for
 *   every unit but one: degrees per second, whose factor pi/180 is not rational. There the
 *   host keeps count * num/den * 10^exp10 / 180 as an exact Fraction and multiplies by pi
 *   only at the end (in float64, a few ulp); a port that knows its gyroscope's scale in rad/s
 *   reports MC_UNIT_RAD_PER_S instead. Decimal multiples (nT, uT, mg, mdps, urad/s) are
 *   written with exp10, so datasheet figures go in as printed. Examples:
 *
 *     part, setting        datasheet        count_scale                       full_scale
 *     LIS3MDL  +-4 G       6842 LSB/G       {1, 6842, 0, GAUSS}               {4, 1, 0, GAUSS}
 *     AK8963   16-bit      0.15 uT/LSB      {15, 100, -6, TESLA}              {4912, 1, -6, TESLA}
 *     MPU-6050 +-2 g       16384 LSB/g      {1, 16384, 0, STANDARD_GRAVITY}   {2, 1, 0, ...}
 *     MPU-6050 +-2000 dps  16.4 LSB/dps     {10, 164, 0, DEG_PER_S}           {2000, 1, 0, ...}
 *     LSM6DSO  +-2000 dps  70 mdps/LSB      {70, 1, -3, DEG_PER_S}            {2000, 1, 0, ...}
 *
 *   The scale is the sensor's nominal sensitivity, the same on all three axes; per-axis gain
 *   and offset errors are what the calibration estimates. The full-scale setting is a scale
 *   too (the range is +-full_scale); it is informative, the conversion uses count_scale only.
 *
 * Concurrency
 *   read() runs in the producer's context (an interrupt on the target) and must not block;
 *   describe() and now_us() may be called from the main loop. The port makes read() and
 *   now_us() safe to call from those two contexts.
 */
#ifndef MAGCAL_SENSOR_HAL_H
#define MAGCAL_SENSOR_HAL_H

#include <stdint.h>

#include "magcal/status.h"

#ifdef __cplusplus
extern "C" {
#endif

/* The three sensors, in the order of describe()'s output and of mc_sensor_info_t.kind. */
typedef enum {
    MC_SENSOR_MAG = 0, /* magnetometer */
    MC_SENSOR_ACC = 1, /* accelerometer (specific force) */
    MC_SENSOR_GYR = 2, /* gyroscope (body angular rate) */
    MC_SENSOR_COUNT = 3
} mc_sensor_kind_t;

/* The unit a mc_scale_t is expressed in; the table above gives each one's SI factor. The
 * values are part of the device protocol (the `info` message): never renumber. 0 is invalid,
 * so a zeroed (forgotten) scale is rejected. */
typedef enum {
    MC_UNIT_INVALID = 0,
    MC_UNIT_TESLA = 1,
    MC_UNIT_GAUSS = 2,
    MC_UNIT_METRE_PER_S2 = 3,
    MC_UNIT_STANDARD_GRAVITY = 4,
    MC_UNIT_RAD_PER_S = 5,
    MC_UNIT_DEG_PER_S = 6
} mc_unit_t;

/* A quantity, exactly num / den * 10^exp10 of unit. Valid (mc_sensor_info_check): num > 0,
 * den > 0, MC_SCALE_EXP10_MIN <= exp10 <= MC_SCALE_EXP10_MAX, unit one of the sensor's. */
typedef struct {
    int32_t num;
    uint32_t den;
    int8_t exp10;
    uint8_t unit; /* mc_unit_t */
} mc_scale_t;

#define MC_SCALE_EXP10_MIN (-18)
#define MC_SCALE_EXP10_MAX 18

/* Size of mc_sensor_info_t.name, including its terminating NUL. */
#define MC_SENSOR_NAME_SIZE 12

/* What the host needs to know about one sensor. */
typedef struct {
    uint8_t kind;                   /* mc_sensor_kind_t: its index in describe()'s output */
    uint8_t id;                     /* the port's id for the part, e.g. its WHO_AM_I value */
    char name[MC_SENSOR_NAME_SIZE]; /* short part name ("LIS3MDL"), NUL-terminated, may be "" */
    mc_scale_t full_scale;          /* configured range: the sensor measures +-full_scale */
    mc_scale_t count_scale;         /* exact value of one count */
} mc_sensor_info_t;

/* One reading of all three sensors. */
typedef struct {
    uint64_t t_us;    /* device time of the sample, microseconds, never decreasing */
    int16_t mag[3];   /* magnetometer counts, chip axes */
    int16_t acc[3];   /* accelerometer counts, body frame b */
    int16_t gyr[3];   /* gyroscope counts, body frame b */
} mc_raw_sample_t;

typedef struct mc_sensor_hal_ops {
    /* Read one sample of the three sensors into *out. Returns MC_OK, or MC_E_SENSOR when a bus
     * transfer fails or no new data is ready (then *out is unspecified and is not used). */
    mc_status_t (*read)(void *ctx, mc_raw_sample_t *out);
    /* The device clock now, microseconds (the clock of mc_raw_sample_t.t_us). */
    uint64_t (*now_us)(void *ctx);
    /* Fill out[MC_SENSOR_MAG], out[MC_SENSOR_ACC], out[MC_SENSOR_GYR]. Returns MC_OK or
     * MC_E_SENSOR. */
    mc_status_t (*describe)(void *ctx, mc_sensor_info_t out[MC_SENSOR_COUNT]);
} mc_sensor_hal_ops_t;

typedef struct {
    const mc_sensor_hal_ops_t *ops; /* every operation non-NULL */
    void *ctx;                      /* passed to every operation; may be NULL */
} mc_sensor_hal_t;

/* Check one sensor's description: kind == expected kind, a NUL within name, both scales valid
 * and in a unit of that sensor (magnetometer: TESLA or GAUSS; accelerometer: METRE_PER_S2 or
 * STANDARD_GRAVITY; gyroscope: RAD_PER_S or DEG_PER_S). Returns MC_OK, MC_E_ARG (info NULL
 * or kind not a sensor) or MC_E_RANGE. Defined in src/acquire.c. */
mc_status_t mc_sensor_info_check(const mc_sensor_info_t *info, mc_sensor_kind_t kind);

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_SENSOR_HAL_H */
