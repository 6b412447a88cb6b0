/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Synthetic sensors for the mps2-an386 target: the board has no magnetometer or IMU, so this
 * HAL (sensor_hal.h) produces deterministic counts of a physically consistent motion, in
 * integer arithmetic only, on the SysTick clock at 100 Hz.
 *
 * The description (describe) is the SIL's (firmware/port/posix/sil_main.c), datasheet scales:
 *   magnetometer   LIS3MDL (id 0x3D) +-4 G,     count {1, 6842, 0, GAUSS}
 *   accelerometer  LSM6DSO (id 0x6C) +-4 g,     count {122, 1, -6, STANDARD_GRAVITY}
 *   gyroscope      LSM6DSO (id 0x6C) +-500 dps, count {175, 1, -4, DEG_PER_S}
 *
 * The motion: the board lies level (body z up) and yaws about z at a constant rate, one turn
 * in 256 samples (2.56 s, 140.625 deg/s), in an Earth field of 0.20 G horizontal and 0.45 G
 * down, seen through a magnetometer with soft iron (y gain 0.9) and hard iron. Sample k (k =
 * 0, 1, ... counted from boot; on this port it is also the sample's acquisition seq, since
 * both start at 0 at boot and every read succeeds) is EXACTLY, in counts:
 *
 *   S(i)  = round(32767 * sin(2 pi i / 256)) for i = 0..64 (the table in the .c), extended to
 *           i = 0..255 by symmetry: S(i) for i < 64, S(128 - i) for 64 <= i < 128, and
 *           -S(i - 128) for 128 <= i < 256; sin_k = S(k mod 256), cos_k = S((k + 64) mod 256)
 *   q(a, x) = floor((a * x + 16384) / 2^15)               (a * x / 32768, rounded)
 *   mag = (412 + q(1368, cos_k), -237 - q(1231, sin_k), 158 - 3079)
 *         (H = 0.20 G = 1368 counts, 0.9 H = 1231, V = 0.45 G = 3079, hard iron (412, -237, 158))
 *   acc = (0, 0, 8197)                                    (+1 g specific force on z)
 *   gyr = (0, 0, 8036)                                    (140.625 deg/s about z)
 *   t_us = 10000 * (k + k0): the sample instants are the multiples of 10 ms on the device
 *          clock, from the first one after mc_synth_init (k0).
 *
 * So D_inv = R diag(1/F, 1/(0.9 F), 1/F) with F = sqrt(1368^2 + 3079^2) counts (any rotation
 * R) and o = (412, -237, 158) make the corrected field unit norm, up to rounding.
 *
 * Timing: the synthetic sensor has "data ready" at each multiple of 10 ms; read() refuses
 * (MC_E_SENSOR, "no new data") before the next one is due and stamps a sample with its due
 * instant, not with the time the main loop got round to it. The main loop calls
 * mc_device_sample when mc_synth_due says one is due (main.c); a late loop catches up one
 * sample per pass, each with its own instant. The 64-bit clock adds up the forward steps of
 * mc_systick_time_us (32 bits, wraps every 71.6 min; unsigned differences are right across
 * the wrap), so it needs a reading at least every 35 minutes (every pass makes one); a
 * reading below the last one is ignored and counted (backsteps), so the clock never goes
 * back even if the time source glitched.
 *
 * Contexts: everything runs in the main loop on this port (no interrupt reads the sensors).
 */
#ifndef MAGCAL_PORT_SYNTHETIC_SENSORS_H
#define MAGCAL_PORT_SYNTHETIC_SENSORS_H

#include <stdint.h>

#include "magcal/sensor_hal.h"

#define MC_SYNTH_PERIOD_US 10000u          /* 100 Hz */
#define MC_SYNTH_SAMPLE_RATE_MHZ 100000u   /* the same, millihertz (info_resp) */
#define MC_SYNTH_STEPS_PER_TURN 256u

typedef struct {
    uint32_t k;           /* the next sample's index */
    uint64_t next_due_us; /* its instant */
    uint64_t now_us;      /* the 64-bit clock at ... */
    uint32_t last32;      /* ... the last mc_systick_time_us reading */
    uint32_t backsteps;   /* readings below the one before, ignored (never seen so far) */
} mc_synth_sensors_t;

/* Start: the first sample is due at the next multiple of MC_SYNTH_PERIOD_US. SysTick
 * (mc_systick_time_init) must be running. */
void mc_synth_init(mc_synth_sensors_t *s);

/* The HAL over *s (read, now_us, describe). */
mc_sensor_hal_t mc_synth_hal(mc_synth_sensors_t *s);

/* 1 when a sample is due (read() would succeed), else 0. */
int mc_synth_due(mc_synth_sensors_t *s);

/* The device clock, microseconds since mc_systick_time_init (64 bits). */
uint64_t mc_synth_now_us(mc_synth_sensors_t *s);

/* The counts of sample k (t_us left 0): the formulas above. */
void mc_synth_counts(uint32_t k, mc_raw_sample_t *out);

#endif /* MAGCAL_PORT_SYNTHETIC_SENSORS_H */
