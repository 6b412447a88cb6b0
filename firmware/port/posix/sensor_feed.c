/* SPDX-License-Identifier: Apache-2.0 */
/* A sensor HAL fed by the SIL device from the world simulator. See sensor_feed.h. */
#include "sensor_feed.h"

#include <math.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>

/* pi as a double (M_PI is not C99); pi / 180 folds to math.pi / 180.0 in Python. */
#define FEED_PI 3.14159265358979323846

static mc_status_t feed_read(void *ctx, mc_raw_sample_t *out)
{
    mc_sensor_feed_t *feed = (mc_sensor_feed_t *)ctx;
    if (feed == NULL || out == NULL) {
        return MC_E_SENSOR;
    }
    if (feed->has_sample) {
        *out = feed->pending;
        feed->has_sample = 0u;
        return MC_OK;
    }
    feed->has_error = 0u; /* a failed read, injected or for want of data */
    return MC_E_SENSOR;
}

static uint64_t feed_now_us(void *ctx)
{
    const mc_sensor_feed_t *feed = (const mc_sensor_feed_t *)ctx;
    return feed == NULL ? 0u : feed->now_us;
}

static mc_status_t feed_describe(void *ctx, mc_sensor_info_t out[MC_SENSOR_COUNT])
{
    const mc_sensor_feed_t *feed = (const mc_sensor_feed_t *)ctx;
    if (feed == NULL || out == NULL) {
        return MC_E_SENSOR;
    }
    memcpy(out, feed->info, sizeof feed->info);
    return MC_OK;
}

static const mc_sensor_hal_ops_t feed_ops = {feed_read, feed_now_us, feed_describe};

mc_status_t mc_sensor_feed_init(mc_sensor_feed_t *feed,
                                const mc_sensor_info_t info[MC_SENSOR_COUNT])
{
    if (feed == NULL || info == NULL) {
        return MC_E_ARG;
    }
    for (int k = 0; k < (int)MC_SENSOR_COUNT; ++k) {
        if (mc_sensor_info_check(&info[k], (mc_sensor_kind_t)k) != MC_OK) {
            return MC_E_RANGE;
        }
    }
    memset(feed, 0, sizeof *feed);
    memcpy(feed->info, info, sizeof feed->info);
    return MC_OK;
}

mc_sensor_hal_t mc_sensor_feed_hal(mc_sensor_feed_t *feed)
{
    mc_sensor_hal_t hal = {&feed_ops, feed};
    return hal;
}

int mc_sensor_feed_pending(const mc_sensor_feed_t *feed)
{
    return feed != NULL && (feed->has_sample || feed->has_error);
}

/* The checks put and put_error share: MC_OK when a read may be queued at t_us. */
static mc_status_t feed_can_put(mc_sensor_feed_t *feed, uint64_t t_us)
{
    if (t_us < feed->now_us) {
        return MC_E_RANGE;
    }
    if (mc_sensor_feed_pending(feed)) {
        feed->overruns = feed->overruns + 1u;
        return MC_E_OVERFLOW;
    }
    return MC_OK;
}

mc_status_t mc_sensor_feed_put(mc_sensor_feed_t *feed, const mc_raw_sample_t *sample)
{
    if (feed == NULL || sample == NULL) {
        return MC_E_ARG;
    }
    const mc_status_t st = feed_can_put(feed, sample->t_us);
    if (st != MC_OK) {
        return st;
    }
    feed->pending = *sample;
    feed->has_sample = 1u;
    feed->now_us = sample->t_us;
    return MC_OK;
}

mc_status_t mc_sensor_feed_put_error(mc_sensor_feed_t *feed, uint64_t t_us)
{
    if (feed == NULL) {
        return MC_E_ARG;
    }
    const mc_status_t st = feed_can_put(feed, t_us);
    if (st != MC_OK) {
        return st;
    }
    feed->has_error = 1u;
    feed->now_us = t_us;
    return MC_OK;
}

mc_status_t mc_sensor_feed_set_time(mc_sensor_feed_t *feed, uint64_t t_us)
{
    if (feed == NULL) {
        return MC_E_ARG;
    }
    if (t_us < feed->now_us) {
        return MC_E_RANGE;
    }
    feed->now_us = t_us;
    return MC_OK;
}

/* ---- quantisation (floating point: the port only, never firmware/src) ---- */

/* The SI factor of a unit as a double, 0.0 for an unknown unit. */
static double unit_si_factor(uint8_t unit)
{
    switch (unit) {
    case MC_UNIT_TESLA:
    case MC_UNIT_METRE_PER_S2:
    case MC_UNIT_RAD_PER_S:
        return 1.0;
    case MC_UNIT_GAUSS:
        return 1e-4;
    case MC_UNIT_STANDARD_GRAVITY:
        return 9.80665;
    case MC_UNIT_DEG_PER_S:
        return FEED_PI / 180.0;
    default:
        return 0.0;
    }
}

double mc_sensor_count_si(const mc_scale_t *count_scale)
{
    if (count_scale == NULL || count_scale->num <= 0 || count_scale->den == 0u
        || count_scale->exp10 < MC_SCALE_EXP10_MIN || count_scale->exp10 > MC_SCALE_EXP10_MAX) {
        return 0.0;
    }
    const double factor = unit_si_factor(count_scale->unit);
    if (factor == 0.0) {
        return 0.0;
    }
    const int e = count_scale->exp10 < 0 ? -(int)count_scale->exp10 : (int)count_scale->exp10;
    double p10 = 1.0;
    for (int i = 0; i < e; ++i) {
        p10 *= 10.0; /* exact: 10^k = 2^k 5^k, and 5^18 < 2^53 */
    }
    double v = (double)count_scale->num / (double)count_scale->den;
    v = count_scale->exp10 < 0 ? v / p10 : v * p10;
    return v * factor;
}

mc_status_t mc_sensor_quantise(double value_si, const mc_scale_t *count_scale, int16_t *count)
{
    const double lsb = mc_sensor_count_si(count_scale);
    if (count == NULL || !(lsb > 0.0)) {
        return MC_E_ARG;
    }
    if (!isfinite(value_si)) {
        return MC_E_RANGE;
    }
    const double q = value_si / lsb; /* may overflow to +-inf: saturates below */
    if (q >= 32767.0) {
        *count = INT16_MAX;
        return MC_OK;
    }
    if (q <= -32768.0) {
        *count = INT16_MIN;
        return MC_OK;
    }
    const double a = q < 0.0 ? -q : q; /* 0 <= a < 32768 */
    int32_t n = (int32_t)a;            /* truncation */
    if (a - (double)n >= 0.5) {        /* exact: the fraction of a double has no rounding */
        ++n;                           /* halves away from zero */
    }
    *count = (int16_t)(q < 0.0 ? -n : n); /* -32768 .. 32767 */
    return MC_OK;
}

/* ---- the line format ---- */

static int is_blank(char c)
{
    return c == ' ' || c == '\t';
}

/* Skip blanks, then read a decimal integer (an optional '-' when negative_ok) followed by a
 * blank, the end of the line or of the string. *neg tells the sign; *mag is the magnitude.
 * Returns MC_OK, MC_E_FRAME (no number there) or MC_E_RANGE (more than 2^64 - 1). */
static mc_status_t parse_number(const char **p, int negative_ok, int *neg, uint64_t *mag)
{
    const char *s = *p;
    if (!is_blank(*s)) {
        return MC_E_FRAME; /* fields are separated */
    }
    while (is_blank(*s)) {
        ++s;
    }
    *neg = 0;
    if (*s == '-' && negative_ok) {
        *neg = 1;
        ++s;
    }
    if (*s < '0' || *s > '9') {
        return MC_E_FRAME;
    }
    uint64_t v = 0u;
    int too_big = 0;
    for (; *s >= '0' && *s <= '9'; ++s) {
        const unsigned d = (unsigned)(*s - '0');
        if (v > (UINT64_MAX - d) / 10u) {
            too_big = 1; /* keep scanning so a malformed tail still reads as malformed */
        } else {
            v = v * 10u + d;
        }
    }
    if (*s != '\0' && *s != '\r' && *s != '\n' && !is_blank(*s)) {
        return MC_E_FRAME;
    }
    *p = s;
    *mag = v;
    return too_big ? MC_E_RANGE : MC_OK;
}

static int is_digit(char c)
{
    return c >= '0' && c <= '9';
}

/* 1 when s starts with word (lower case) in any case, followed by the end of the field. */
static int is_word(const char *s, const char *word, const char **end)
{
    size_t i = 0u;
    for (; word[i] != '\0'; ++i) {
        const char c = s[i];
        if ((c >= 'A' && c <= 'Z' ? (char)(c - 'A' + 'a') : c) != word[i]) {
            return 0;
        }
    }
    *end = s + i;
    return 1;
}

static int at_field_end(char c)
{
    return c == '\0' || c == '\r' || c == '\n' || is_blank(c);
}

/* Skip blanks (at least one), then read a decimal real of the P line (see sensor_feed.h)
 * followed by a blank, the end of the line or of the string. Returns MC_OK, MC_E_FRAME (no
 * decimal real there) or MC_E_RANGE (nan, inf, infinity, or too large for a double). */
static mc_status_t parse_real(const char **p, double *out)
{
    const char *s = *p;
    if (!is_blank(*s)) {
        return MC_E_FRAME;
    }
    while (is_blank(*s)) {
        ++s;
    }
    const char *start = s;
    const char *e = s;
    if (*e == '-') {
        ++e;
    }
    const char *word_end = NULL;
    if ((is_word(e, "infinity", &word_end) || is_word(e, "inf", &word_end)
         || is_word(e, "nan", &word_end))
        && at_field_end(*word_end)) {
        *p = word_end;
        return MC_E_RANGE; /* not finite: no sensor outputs that */
    }
    size_t digits = 0u;
    for (; is_digit(*e); ++e) {
        ++digits;
    }
    if (*e == '.') {
        ++e;
        for (; is_digit(*e); ++e) {
            ++digits;
        }
    }
    if (digits == 0u) {
        return MC_E_FRAME;
    }
    if (*e == 'e' || *e == 'E') {
        ++e;
        if (*e == '-' || *e == '+') {
            ++e;
        }
        if (!is_digit(*e)) {
            return MC_E_FRAME;
        }
        for (; is_digit(*e); ++e) {
        }
    }
    if (!at_field_end(*e)) {
        return MC_E_FRAME;
    }
    /* The text is a decimal real: strtod (correctly rounded in glibc, "C" locale) reads it
     * exactly up to e. */
    char *end = NULL;
    const double v = strtod(start, &end);
    if (end != e) {
        return MC_E_FRAME; /* cannot happen for the grammar above; refuse rather than guess */
    }
    *p = e;
    if (!isfinite(v)) {
        return MC_E_RANGE;
    }
    *out = v;
    return MC_OK;
}

/* After the last field: blanks, then "", "\n" or "\r\n". */
static int at_line_end(const char *s)
{
    while (is_blank(*s)) {
        ++s;
    }
    return s[0] == '\0' || (s[0] == '\n' && s[1] == '\0')
        || (s[0] == '\r' && s[1] == '\n' && s[2] == '\0');
}

mc_status_t mc_sensor_feed_apply_line(mc_sensor_feed_t *feed, const char *line)
{
    if (feed == NULL || line == NULL) {
        return MC_E_ARG;
    }
    const char kind = line[0];
    if (kind != 'S' && kind != 'P' && kind != 'E' && kind != 'T') {
        return MC_E_FRAME;
    }
    const char *p = line + 1;
    int neg = 0;
    uint64_t t_us = 0u;
    mc_status_t range = MC_OK; /* a range error is reported only for a well-formed line */
    mc_status_t st = parse_number(&p, 0, &neg, &t_us);
    if (st == MC_E_FRAME) {
        return st;
    }
    if (st == MC_E_RANGE) {
        range = st;
    }
    mc_raw_sample_t raw;
    raw.t_us = t_us;
    int16_t *const fields[9] = {&raw.mag[0], &raw.mag[1], &raw.mag[2], &raw.acc[0], &raw.acc[1],
                                &raw.acc[2], &raw.gyr[0], &raw.gyr[1], &raw.gyr[2]};
    if (kind == 'S') {
        for (int i = 0; i < 9; ++i) {
            uint64_t mag = 0u;
            st = parse_number(&p, 1, &neg, &mag);
            if (st == MC_E_FRAME) {
                return st;
            }
            if (st == MC_E_RANGE || mag > (neg ? 32768u : 32767u)) {
                range = MC_E_RANGE;
                *fields[i] = 0;
            } else {
                /* -32768 is formed without negating 32768 in int16_t. */
                *fields[i] = neg ? (int16_t)(-(int32_t)mag) : (int16_t)mag;
            }
        }
    } else if (kind == 'P') {
        for (int i = 0; i < 9; ++i) {
            double v = 0.0;
            st = parse_real(&p, &v);
            if (st == MC_E_FRAME) {
                return st;
            }
            if (st == MC_E_RANGE) {
                range = MC_E_RANGE;
                *fields[i] = 0;
                continue;
            }
            /* fields 0-2 magnetometer, 3-5 accelerometer, 6-8 gyroscope: the sensor's own
             * count scale, the one describe() reports */
            st = mc_sensor_quantise(v, &feed->info[i / 3].count_scale, fields[i]);
            if (st != MC_OK) {
                return st; /* MC_E_ARG: cannot happen, init checked the scales */
            }
        }
    }
    if (!at_line_end(p)) {
        return MC_E_FRAME;
    }
    if (range != MC_OK) {
        return range;
    }
    if (kind == 'S' || kind == 'P') {
        return mc_sensor_feed_put(feed, &raw);
    }
    if (kind == 'E') {
        return mc_sensor_feed_put_error(feed, t_us);
    }
    return mc_sensor_feed_set_time(feed, t_us);
}

const char *mc_sensor_feed_refusal(mc_status_t st)
{
    switch (st) {
    case MC_OK:
        return "ok";
    case MC_E_ARG:
        return "no feed or no line";
    case MC_E_FRAME:
        return "malformed line";
    case MC_E_RANGE:
        return "a value out of range, not finite, or a time before the clock";
    case MC_E_OVERFLOW:
        return "a read was still pending (overrun)";
    default:
        return "refused";
    }
}
