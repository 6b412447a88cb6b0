/* A sensor HAL fed by the SIL device from the world simulator. See sensor_feed.h. */
#include "sensor_feed.h"

#include <stddef.h>
#include <string.h>

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
    if (kind != 'S' && kind != 'E' && kind != 'T') {
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
    if (kind == 'S') {
        int16_t *const fields[9] = {&raw.mag[0], &raw.mag[1], &raw.mag[2], &raw.acc[0], &raw.acc[1],
                                    &raw.acc[2], &raw.gyr[0], &raw.gyr[1], &raw.gyr[2]};
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
    }
    if (!at_line_end(p)) {
        return MC_E_FRAME;
    }
    if (range != MC_OK) {
        return range;
    }
    if (kind == 'S') {
        return mc_sensor_feed_put(feed, &raw);
    }
    if (kind == 'E') {
        return mc_sensor_feed_put_error(feed, t_us);
    }
    return mc_sensor_feed_set_time(feed, t_us);
}
