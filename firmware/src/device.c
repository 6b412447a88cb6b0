/* SPDX-License-Identifier: Apache-2.0 */
/* The protocol endpoint and command dispatcher. See device.h and protocol/SPEC.md. */
#include "magcal/device.h"

#include <string.h>

#include "magcal/crc.h"

/* ---------------------------------------------------------------- output */

/* Offers the pending output to tx until it is all taken or tx takes nothing. */
static void flush(mc_device_t *dev)
{
    while (dev->out_off < dev->out_len) {
        const size_t left = dev->out_len - dev->out_off;
        const int n = dev->cfg.tx(dev->cfg.tx_ctx, &dev->out[dev->out_off], left);
        if (n <= 0) {
            break;
        }
        dev->out_off += (size_t)n > left ? left : (size_t)n;
    }
    if (dev->out_off >= dev->out_len) {
        dev->out_len = 0u;
        dev->out_off = 0u;
    }
}

static int busy(const mc_device_t *dev)
{
    return dev->out_len != 0u;
}

/* Encodes a frame into the (empty) output buffer. */
static mc_status_t encode_out(mc_device_t *dev, uint8_t id, uint16_t seq, const uint8_t *payload,
                              size_t len)
{
    size_t n = 0u;
    const mc_status_t st = mc_frame_encode(id, seq, payload, len, dev->out, sizeof dev->out, &n);
    dev->out_len = st == MC_OK ? n : 0u;
    dev->out_off = 0u;
    return st;
}

/* ---------------------------------------------------------------- parameter sets */

static void load_active(mc_device_t *dev)
{
    size_t len = 0u;
    uint16_t format = 0u;
    uint32_t sequence = 0u;
    mc_params_t p;
    mc_status_t st;

    dev->active_ok = 0u;
    dev->active_format = 0u;
    dev->active_crc = 0u;
    dev->correction.ready = 0u;
    st = mc_storage_load(&dev->storage, dev->active_blob, sizeof dev->active_blob, &len, &format,
                         &sequence);
    if (st == MC_OK && format != MC_PARAMS_FORMAT_VERSION) {
        st = MC_E_VERSION;
    }
    if (st == MC_OK) {
        st = mc_params_decode(dev->active_blob, len, &p);
    }
    if (st == MC_OK) {
        st = mc_correction_init(&dev->correction, &p);
    }
    dev->load_status = (int8_t)st;
    if (st != MC_OK) {
        memset(dev->active_blob, 0, sizeof dev->active_blob);
        return;
    }
    dev->active_ok = 1u;
    dev->active_format = format;
    dev->active_crc = mc_crc32_iso_hdlc(dev->active_blob, len);
}

/* ---------------------------------------------------------------- stream */

/* The running stream ends (count reached, stop, replaced): its counts stay for stream_stop. */
static void stream_end(mc_device_t *dev)
{
    dev->stream_on = 0u;
}

static void stream_clear(mc_device_t *dev)
{
    dev->stream_on = 0u;
    dev->stream_kind = 0u;
    dev->stream_seen = 0u;
    dev->stream_seq = 0u;
    dev->stream_decimation = 1u;
    dev->stream_next_due = 0u;
    dev->stream_last_seq = 0u;
    dev->stream_start_next = 0u;
    dev->stream_overflow0 = 0u;
    dev->stream_count = 0u;
    dev->stream_sent = 0u;
    dev->stream_link_dropped = 0u;
    dev->stream_ring_dropped = 0u;
}

/*
 * How many due seqs (next_due + k * d, k >= 0) lie in [a, a + len), in uint32 arithmetic
 * modulo 2^32 (so across the seq wrap). next_due is either at most d - 1 ahead of a or
 * behind it (a - next_due < 2^31): the stream keeps it just past the last sample it saw.
 */
static uint32_t count_due(uint32_t next_due, uint32_t d, uint32_t a, uint32_t len)
{
    uint32_t first_off; /* offset of the first due seq >= a */
    if (a - next_due < 0x80000000u) {
        const uint32_t r = (a - next_due) % d;
        first_off = r == 0u ? 0u : d - r;
    } else {
        first_off = next_due - a;
    }
    return first_off < len ? (len - 1u - first_off) / d + 1u : 0u;
}

/* Seqs in [a, a + len) from stream_start_next on: the part of a gap the stream answers for. */
static void clamp_to_stream(const mc_device_t *dev, uint32_t *a, uint32_t *len)
{
    const uint32_t before = dev->stream_start_next - *a; /* seqs of the range before the start */
    if (before != 0u && before < 0x80000000u) {
        *len = before >= *len ? 0u : *len - before;
        *a = dev->stream_start_next;
    }
}

/*
 * Whether sample seq is due (device.h: first + k * decimation), adding the due samples in the
 * gap since the last sample seen (lost in the ring) to stream_ring_dropped. Samples arrive in
 * seq order.
 */
static int stream_due(mc_device_t *dev, uint32_t seq)
{
    const uint32_t d = dev->stream_decimation;
    if (!dev->stream_seen) {
        dev->stream_seen = 1u;
        dev->stream_next_due = seq;
    } else {
        uint32_t a = dev->stream_last_seq + 1u, len = seq - a;
        clamp_to_stream(dev, &a, &len);
        dev->stream_ring_dropped =
            dev->stream_ring_dropped + count_due(dev->stream_next_due, d, a, len);
    }
    dev->stream_last_seq = seq;
    const uint32_t behind = dev->stream_next_due - seq;
    if (behind != 0u && behind < d) {
        return 0; /* between two due samples */
    }
    const uint32_t r = (seq - dev->stream_next_due) % d;
    dev->stream_next_due = seq + (r == 0u ? d : d - r);
    return r == 0u;
}

/* At a stop: the due samples lost in the ring after the last one seen. No pop happened since,
 * so the ring filled in seq order and then dropped every newer sample: the unseen seqs are
 * the queued ones followed by the dropped ones, up to the acquisition's next seq. */
static void stream_count_tail(mc_device_t *dev)
{
    mc_acquire_stats_t s;
    if (!dev->stream_on || mc_acquire_stats(&dev->acq, &s) != MC_OK) {
        return;
    }
    uint32_t a, len, next_due;
    if (dev->stream_seen) {
        const uint32_t unseen = s.next_seq - (dev->stream_last_seq + 1u);
        len = unseen > s.queued ? unseen - s.queued : 0u;
        next_due = dev->stream_next_due;
    } else { /* nothing seen: every drop since the start is of this stream's samples */
        len = s.dropped - dev->stream_overflow0;
        next_due = s.next_seq - len - s.queued; /* where the first sample seen would be */
    }
    a = s.next_seq - len;
    clamp_to_stream(dev, &a, &len);
    dev->stream_ring_dropped =
        dev->stream_ring_dropped + count_due(next_due, dev->stream_decimation, a, len);
}

static void stream_drop(mc_device_t *dev)
{
    dev->stream_link_dropped = dev->stream_link_dropped + 1u;
    dev->stats.stream_dropped = dev->stats.stream_dropped + 1u;
}

static void stream_sample(mc_device_t *dev, const mc_sample_t *s)
{
    uint8_t payload[MC_MSG_CORRECTED_SIZE];
    size_t len = 0u;
    uint8_t id;
    int n;
    int due;

    if (!dev->stream_on) {
        return;
    }
    due = stream_due(dev, s->seq);
    if (!due) {
        return;
    }
    flush(dev);
    if (busy(dev)) {
        stream_drop(dev);
        return;
    }
    if (dev->stream_kind == MC_DEVICE_STREAM_RAW) {
        mc_msg_sample_t m;
        m.seq = s->seq;
        m.t_us = s->t_us;
        memcpy(m.mag, s->mag, sizeof m.mag);
        memcpy(m.acc, s->acc, sizeof m.acc);
        memcpy(m.gyr, s->gyr, sizeof m.gyr);
        id = (uint8_t)MC_MSG_SAMPLE;
        (void)mc_msg_sample_pack(&m, payload, sizeof payload, &len);
    } else {
        mc_msg_corrected_t m;
        m.seq = s->seq;
        m.t_us = s->t_us;
        memcpy(m.mag, s->mag, sizeof m.mag);
        m.out_exp = dev->correction.params.out_exp;
        if (mc_correction_apply(&dev->correction, s->mag, m.m_b) != MC_OK) {
            stream_drop(dev); /* not reachable: the stream starts only with a ready set */
            return;
        }
        id = (uint8_t)MC_MSG_CORRECTED;
        (void)mc_msg_corrected_pack(&m, payload, sizeof payload, &len);
    }
    if (encode_out(dev, id, dev->stream_seq, payload, len) != MC_OK) {
        stream_drop(dev);
        return;
    }
    n = dev->cfg.tx(dev->cfg.tx_ctx, dev->out, dev->out_len);
    if (n <= 0) {
        dev->out_len = 0u; /* nothing of it reached the link: dropped whole */
        stream_drop(dev);
        return;
    }
    dev->out_off = (size_t)n > dev->out_len ? dev->out_len : (size_t)n;
    flush(dev);
    dev->stream_sent = dev->stream_sent + 1u;
    dev->stats.stream_sent = dev->stats.stream_sent + 1u;
    if (dev->stream_count != 0u && dev->stream_sent >= dev->stream_count) {
        stream_end(dev);
    }
}

/* ---------------------------------------------------------------- reset */

static void clear_cache(mc_device_t *dev)
{
    dev->cache_valid = 0u;
    dev->cache_len = 0u;
    dev->cache_seq = 0u;
    dev->cache_crc = 0u;
    dev->cache_id = 0u;
}

/* The state a boot starts from; the output buffer is left alone (it may hold reset_resp). */
static void soft_reset(mc_device_t *dev)
{
    mc_sample_t s;
    stream_clear(dev);
    clear_cache(dev);
    dev->reset_due = 0u;
    dev->staged_ok = 0u;
    dev->staged_format = 0u;
    dev->staged_crc = 0u;
    memset(dev->staged_blob, 0, sizeof dev->staged_blob);
    (void)mc_frame_decoder_reset(&dev->decoder);
    while (mc_acquire_pop(&dev->acq, &s) == MC_OK) {
    }
    load_active(dev);
}

/* Flushes; does a due reset once its response is out. Returns 1 while output is pending. */
static int drain(mc_device_t *dev)
{
    flush(dev);
    if (busy(dev)) {
        return 1;
    }
    if (dev->reset_due) {
        soft_reset(dev);
        dev->stats.resets = dev->stats.resets + 1u;
        if (dev->cfg.on_reset != NULL) {
            dev->cfg.on_reset(dev->cfg.reset_ctx);
        }
    }
    return 0;
}

/* ---------------------------------------------------------------- requests */

/* Sends a response frame and, unless it answers hello, remembers it for retries. */
static void respond(mc_device_t *dev, const mc_frame_t *req, uint16_t req_crc,
                    const uint8_t *payload, size_t len)
{
    if (encode_out(dev, (uint8_t)(req->id | 0x80u), req->seq, payload, len) != MC_OK) {
        return; /* not reachable: every response fits the buffer */
    }
    dev->stats.requests = dev->stats.requests + 1u;
    if (req->id != (uint8_t)MC_MSG_HELLO) {
        memcpy(dev->cache, dev->out, dev->out_len);
        dev->cache_len = dev->out_len;
        dev->cache_seq = req->seq;
        dev->cache_id = req->id;
        dev->cache_crc = req_crc;
        dev->cache_valid = 1u;
    }
    flush(dev);
}

static void nack(mc_device_t *dev, const mc_frame_t *req, mc_status_t status)
{
    uint8_t payload[MC_MSG_NACK_SIZE];
    size_t len = 0u;
    mc_msg_nack_t m;
    m.status = (int8_t)status;
    m.request_id = req->id;
    (void)mc_msg_nack_pack(&m, payload, sizeof payload, &len);
    if (encode_out(dev, (uint8_t)MC_MSG_NACK, req->seq, payload, len) == MC_OK) {
        dev->stats.nacks = dev->stats.nacks + 1u;
        flush(dev);
    }
}

static size_t do_hello(const mc_msg_hello_t *rq, uint8_t *out, size_t cap)
{
    mc_msg_hello_resp_t r;
    size_t len = 0u;
    const uint16_t lo = rq->host_min_version > MC_PROTOCOL_MIN_VERSION
                            ? rq->host_min_version
                            : (uint16_t)MC_PROTOCOL_MIN_VERSION;
    const uint16_t hi =
        rq->host_max_version < MC_PROTOCOL_VERSION ? rq->host_max_version
                                                   : (uint16_t)MC_PROTOCOL_VERSION;
    r.status = (int8_t)(lo <= hi ? MC_OK : MC_E_VERSION);
    r.version = lo <= hi ? hi : 0u;
    r.device_min_version = (uint16_t)MC_PROTOCOL_MIN_VERSION;
    r.device_max_version = (uint16_t)MC_PROTOCOL_VERSION;
    r.max_payload = (uint16_t)MC_FRAME_MAX_PAYLOAD;
    (void)mc_msg_hello_resp_pack(&r, out, cap, &len);
    return len;
}

/* Copies a NUL-terminated part name into a NUL-padded char[MC_SENSOR_NAME_SIZE]. */
static void copy_name(char dst[MC_SENSOR_NAME_SIZE], const char src[MC_SENSOR_NAME_SIZE])
{
    size_t i = 0u;
    memset(dst, 0, MC_SENSOR_NAME_SIZE);
    while (i < (size_t)MC_SENSOR_NAME_SIZE && src[i] != '\0') {
        dst[i] = src[i];
        ++i;
    }
}

static size_t do_info(mc_device_t *dev, uint8_t *out, size_t cap)
{
    mc_msg_info_resp_t *r = &dev->resp.info;
    mc_sensor_info_t info[MC_SENSOR_COUNT];
    size_t len = 0u;
    mc_status_t st;

    memset(r, 0, sizeof *r);
    memcpy(r->fw_version, dev->cfg.fw_version, sizeof r->fw_version);
    r->fw_build = dev->cfg.fw_build;
    r->protocol_version = (uint16_t)MC_PROTOCOL_VERSION;
    r->params_format_version = (uint16_t)MC_PARAMS_FORMAT_VERSION;
    r->params_size = (uint16_t)MC_PARAMS_ENCODED_SIZE;
    memcpy(r->device_uid, dev->cfg.device_uid, sizeof r->device_uid);
    r->sample_rate_mhz = dev->cfg.sample_rate_mhz;
    st = mc_acquire_describe(&dev->acq, info);
    if (st == MC_OK) {
        for (int k = 0; k < (int)MC_SENSOR_COUNT; ++k) {
            r->sensor_id[k] = info[k].id;
            r->fs_num[k] = info[k].full_scale.num;
            r->fs_den[k] = info[k].full_scale.den;
            r->fs_exp10[k] = info[k].full_scale.exp10;
            r->fs_unit[k] = info[k].full_scale.unit;
            r->scale_num[k] = info[k].count_scale.num;
            r->scale_den[k] = info[k].count_scale.den;
            r->scale_exp10[k] = info[k].count_scale.exp10;
            r->scale_unit[k] = info[k].count_scale.unit;
        }
        copy_name(r->mag_name, info[MC_SENSOR_MAG].name);
        copy_name(r->acc_name, info[MC_SENSOR_ACC].name);
        copy_name(r->gyr_name, info[MC_SENSOR_GYR].name);
    } else {
        st = MC_E_SENSOR; /* the versions are still told; the sensor fields stay 0 */
    }
    r->status = (int8_t)st;
    (void)mc_msg_info_resp_pack(r, out, cap, &len);
    return len;
}

static size_t do_stream_start(mc_device_t *dev, const mc_frame_t *req,
                              const mc_msg_stream_start_t *rq, uint8_t *out, size_t cap)
{
    mc_msg_stream_start_resp_t r;
    size_t len = 0u;
    mc_status_t st = MC_OK;
    if (rq->kind > MC_DEVICE_STREAM_CORRECTED || rq->decimation == 0u) {
        st = MC_E_RANGE;
    } else if (rq->kind == MC_DEVICE_STREAM_CORRECTED && !dev->active_ok) {
        st = MC_E_NO_PARAMS;
    }
    if (st == MC_OK) { /* replaces a running stream; a refused start leaves it running */
        stream_clear(dev);
        dev->stream_on = 1u;
        dev->stream_kind = rq->kind;
        dev->stream_seq = req->seq;
        dev->stream_decimation = rq->decimation;
        dev->stream_count = rq->count;
        {
            mc_acquire_stats_t as;
            if (mc_acquire_stats(&dev->acq, &as) == MC_OK) {
                dev->stream_start_next = as.next_seq; /* losses before it are not ours */
                dev->stream_overflow0 = as.dropped;
            }
        }
    }
    r.status = (int8_t)st;
    (void)mc_msg_stream_start_resp_pack(&r, out, cap, &len);
    return len;
}

static size_t do_stream_stop(mc_device_t *dev, uint8_t *out, size_t cap)
{
    mc_msg_stream_stop_resp_t r;
    size_t len = 0u;
    stream_count_tail(dev);
    stream_end(dev);
    r.status = (int8_t)MC_OK;
    r.sent = dev->stream_sent;
    r.dropped = dev->stream_link_dropped + dev->stream_ring_dropped;
    stream_clear(dev);
    (void)mc_msg_stream_stop_resp_pack(&r, out, cap, &len);
    return len;
}

static size_t do_param_get(mc_device_t *dev, const mc_msg_param_get_t *rq, uint8_t *out,
                           size_t cap)
{
    mc_msg_param_get_resp_t *r = &dev->resp.param_get;
    size_t len = 0u;
    memset(r, 0, sizeof *r);
    r->which = rq->which;
    if (rq->which == MC_DEVICE_SET_ACTIVE && dev->active_ok) {
        r->status = (int8_t)MC_OK;
        r->format_version = dev->active_format;
        r->crc32 = dev->active_crc;
        memcpy(r->blob, dev->active_blob, sizeof dev->active_blob);
        r->blob_len = sizeof dev->active_blob;
    } else if (rq->which == MC_DEVICE_SET_STAGED && dev->staged_ok) {
        r->status = (int8_t)MC_OK;
        r->format_version = dev->staged_format;
        r->crc32 = dev->staged_crc;
        memcpy(r->blob, dev->staged_blob, sizeof dev->staged_blob);
        r->blob_len = sizeof dev->staged_blob;
    } else {
        r->status = (int8_t)(rq->which > MC_DEVICE_SET_STAGED ? MC_E_RANGE : MC_E_NO_PARAMS);
    }
    (void)mc_msg_param_get_resp_pack(r, out, cap, &len);
    return len;
}

static size_t do_param_set(mc_device_t *dev, const mc_msg_param_set_t *rq, uint8_t *out,
                           size_t cap)
{
    mc_msg_param_set_resp_t r;
    mc_params_t p;
    size_t len = 0u;
    mc_status_t st = MC_OK;
    if (rq->format_version != MC_PARAMS_FORMAT_VERSION) {
        st = MC_E_VERSION;
    }
    if (st == MC_OK) {
        st = mc_params_decode(rq->blob, rq->blob_len, &p); /* E_VERSION, E_LENGTH */
    }
    if (st == MC_OK) {
        st = mc_params_validate(&p); /* E_EXPONENT, E_RANGE, E_SINGULAR, E_CONDITION */
    }
    dev->staged_ok = 0u;
    dev->staged_format = 0u;
    dev->staged_crc = 0u;
    memset(dev->staged_blob, 0, sizeof dev->staged_blob);
    if (st == MC_OK) {
        memcpy(dev->staged_blob, rq->blob, sizeof dev->staged_blob);
        dev->staged_format = rq->format_version;
        dev->staged_crc = mc_crc32_iso_hdlc(dev->staged_blob, sizeof dev->staged_blob);
        dev->staged_ok = 1u;
    }
    r.status = (int8_t)st;
    r.crc32 = dev->staged_crc;
    (void)mc_msg_param_set_resp_pack(&r, out, cap, &len);
    return len;
}

static size_t do_param_commit(mc_device_t *dev, const mc_msg_param_commit_t *rq, uint8_t *out,
                              size_t cap)
{
    mc_msg_param_commit_resp_t r;
    size_t len = 0u;
    mc_status_t st = MC_OK;
    if (!dev->staged_ok) {
        st = MC_E_STATE;
    } else if (rq->crc32 != dev->staged_crc) {
        st = MC_E_CRC;
    } else {
        /* storage.h's outcomes, passed on as they are: OK = the staged set is stored (also
         * after an error past the commit point that the rescan settled), E_FLASH = the
         * previous set certainly still wins, E_OUTCOME_UNKNOWN = either, E_RANGE = the
         * sequence numbers are exhausted (nothing written). E_ARG cannot occur: the storage
         * was set up by init and the staged blob has its fixed non-zero size. */
        st = mc_storage_commit(&dev->storage, dev->staged_blob, sizeof dev->staged_blob,
                               dev->staged_format);
    }
    r.status = (int8_t)st;
    (void)mc_msg_param_commit_resp_pack(&r, out, cap, &len);
    return len;
}

static size_t do_reset(mc_device_t *dev, const mc_msg_reset_t *rq, uint8_t *out, size_t cap)
{
    mc_msg_reset_resp_t r;
    size_t len = 0u;
    r.status = (int8_t)(rq->magic == MC_RESET_MAGIC ? MC_OK : MC_E_ARG);
    if (r.status == (int8_t)MC_OK) {
        dev->reset_due = 1u; /* done by drain() once reset_resp is out */
    }
    (void)mc_msg_reset_resp_pack(&r, out, cap, &len);
    return len;
}

static int is_request(uint8_t id)
{
    return id >= (uint8_t)MC_MSG_HELLO && id <= (uint8_t)MC_MSG_RESET;
}

/* Acts on one good frame; the output buffer is empty on entry. */
static void handle_frame(mc_device_t *dev, const mc_frame_t *fr)
{
    mc_msg_t *rq = &dev->rq;
    uint8_t *payload = dev->payload; /* the response's */
    size_t min_len = 0u, max_len = 0u, len = 0u;
    uint16_t crc;

    if (!is_request(fr->id) || mc_msg_payload_size(fr->id, &min_len, &max_len) != MC_OK) {
        nack(dev, fr, MC_E_UNKNOWN_MESSAGE);
        return;
    }
    if (fr->payload_len < min_len || fr->payload_len > max_len ||
        mc_msg_unpack(fr->id, fr->payload, fr->payload_len, rq) != MC_OK) {
        nack(dev, fr, MC_E_LENGTH);
        return;
    }
    /* The frame's CRC-16 (checked by the decoder) follows the payload in rx_buf. */
    crc = (uint16_t)(dev->rx_buf[MC_FRAME_HEADER_SIZE + fr->payload_len] |
                     (dev->rx_buf[MC_FRAME_HEADER_SIZE + fr->payload_len + 1u] << 8));
    if (fr->id == (uint8_t)MC_MSG_HELLO) {
        clear_cache(dev);
    } else if (dev->cache_valid && fr->seq == dev->cache_seq) {
        if (fr->id == dev->cache_id && crc == dev->cache_crc) {
            memcpy(dev->out, dev->cache, dev->cache_len);
            dev->out_len = dev->cache_len;
            dev->out_off = 0u;
            dev->stats.retries = dev->stats.retries + 1u;
            flush(dev);
        } else {
            nack(dev, fr, MC_E_SEQUENCE);
        }
        return;
    }
    switch (fr->id) {
    case MC_MSG_HELLO:
        len = do_hello(&rq->u.hello, payload, MC_FRAME_MAX_PAYLOAD);
        break;
    case MC_MSG_INFO:
        len = do_info(dev, payload, MC_FRAME_MAX_PAYLOAD);
        break;
    case MC_MSG_STREAM_START:
        len = do_stream_start(dev, fr, &rq->u.stream_start, payload, MC_FRAME_MAX_PAYLOAD);
        break;
    case MC_MSG_STREAM_STOP:
        len = do_stream_stop(dev, payload, MC_FRAME_MAX_PAYLOAD);
        break;
    case MC_MSG_PARAM_GET:
        len = do_param_get(dev, &rq->u.param_get, payload, MC_FRAME_MAX_PAYLOAD);
        break;
    case MC_MSG_PARAM_SET:
        len = do_param_set(dev, &rq->u.param_set, payload, MC_FRAME_MAX_PAYLOAD);
        break;
    case MC_MSG_PARAM_COMMIT:
        len = do_param_commit(dev, &rq->u.param_commit, payload, MC_FRAME_MAX_PAYLOAD);
        break;
    case MC_MSG_RESET:
        len = do_reset(dev, &rq->u.reset, payload, MC_FRAME_MAX_PAYLOAD);
        break;
    default:
        nack(dev, fr, MC_E_UNKNOWN_MESSAGE); /* not reachable: is_request */
        return;
    }
    respond(dev, fr, crc, payload, len);
}

/* ---------------------------------------------------------------- public */

static int ready(const mc_device_t *dev)
{
    return dev != NULL && dev->ready == MC_DEVICE_READY;
}

mc_status_t mc_device_init(mc_device_t *dev, const mc_device_config_t *cfg)
{
    mc_status_t st;
    if (dev == NULL || cfg == NULL || cfg->tx == NULL || cfg->hal == NULL ||
        cfg->flash == NULL) {
        return MC_E_ARG;
    }
    memset(dev, 0, sizeof *dev);
    dev->cfg = *cfg;
    st = mc_frame_decoder_init(&dev->decoder, dev->rx_buf, sizeof dev->rx_buf);
    if (st == MC_OK) {
        st = mc_acquire_init(&dev->acq, cfg->hal, cfg->ring, cfg->ring_capacity, 0u);
    }
    if (st == MC_OK) {
        st = mc_storage_init(&dev->storage, cfg->flash, cfg->slot_a_page, cfg->slot_b_page,
                             cfg->pages_per_slot);
        if (st == MC_E_FLASH) {
            st = MC_OK; /* set up without an active slot: load_active says so */
        }
    }
    if (st != MC_OK) {
        memset(dev, 0, sizeof *dev);
        return st;
    }
    soft_reset(dev);
    dev->ready = MC_DEVICE_READY;
    return MC_OK;
}

size_t mc_device_rx_bytes(mc_device_t *dev, const uint8_t *data, size_t len)
{
    mc_frame_t fr;
    if (!ready(dev) || data == NULL) {
        return 0u;
    }
    for (size_t i = 0; i < len; ++i) {
        if (drain(dev)) {
            return i;
        }
        if (mc_frame_decoder_push(&dev->decoder, data[i], &fr) == MC_OK) {
            handle_frame(dev, &fr);
        }
    }
    (void)drain(dev);
    return len;
}

mc_status_t mc_device_sample(mc_device_t *dev)
{
    if (dev == NULL) {
        return MC_E_ARG;
    }
    if (!ready(dev)) {
        return MC_E_STATE; /* init has not (successfully) run: nothing to read through */
    }
    return mc_acquire_poll(&dev->acq);
}

mc_status_t mc_device_poll(mc_device_t *dev)
{
    mc_sample_t s;
    if (!ready(dev)) {
        return MC_E_ARG;
    }
    (void)drain(dev);
    while (mc_acquire_pop(&dev->acq, &s) == MC_OK) {
        stream_sample(dev, &s);
    }
    return MC_OK;
}

int mc_device_tx_pending(const mc_device_t *dev)
{
    return ready(dev) && busy(dev);
}

mc_status_t mc_device_link_reset(mc_device_t *dev)
{
    if (!ready(dev)) {
        return MC_E_ARG;
    }
    dev->out_len = 0u;
    dev->out_off = 0u;
    (void)mc_frame_decoder_reset(&dev->decoder);
    (void)drain(dev); /* a reset whose response went to the old link still happens */
    return MC_OK;
}

mc_status_t mc_device_stats(const mc_device_t *dev, mc_device_stats_t *out)
{
    if (!ready(dev) || out == NULL) {
        return MC_E_ARG;
    }
    *out = dev->stats;
    out->rx_ok = dev->decoder.n_ok;
    out->rx_crc = dev->decoder.n_crc;
    out->rx_malformed = dev->decoder.n_malformed;
    out->rx_overflow = dev->decoder.n_overflow;
    return MC_OK;
}
