/* SPDX-License-Identifier: Apache-2.0 */
/* Protocol framing: streaming COBS decoder and encoder with CRC-16/CCITT-FALSE. See frame.h. */
#include "magcal/frame.h"

#include <string.h>

#include "magcal/crc.h"

/* The largest COBS code: a block of 254 data bytes not followed by an implied zero. */
#define COBS_MAX_CODE 0xFFu

static int decoder_ok(const mc_frame_decoder_t *d)
{
    return d->buf != NULL && d->cap >= MC_FRAME_MIN_BODY && d->len <= d->cap;
}

static void decoder_restart(mc_frame_decoder_t *d)
{
    d->len = 0;
    d->code = 0;
    d->left = 0;
    d->discarding = 0;
}

mc_status_t mc_frame_decoder_init(mc_frame_decoder_t *d, uint8_t *buf, size_t cap)
{
    if (d == NULL || buf == NULL || cap < MC_FRAME_MIN_BODY) {
        return MC_E_ARG;
    }
    memset(d, 0, sizeof *d);
    d->buf = buf;
    d->cap = cap;
    return MC_OK;
}

mc_status_t mc_frame_decoder_reset(mc_frame_decoder_t *d)
{
    if (d == NULL) {
        return MC_E_ARG;
    }
    decoder_restart(d);
    return MC_OK;
}

/* Appends one decoded byte; on a full buffer switches to discarding the rest of the frame. */
static void decoder_append(mc_frame_decoder_t *d, uint8_t byte)
{
    if (d->len >= d->cap) {
        d->discarding = 1;
        return;
    }
    d->buf[d->len++] = byte;
}

/* The delimiter: judge the frame in progress and start the next one. */
static mc_status_t decoder_end(mc_frame_decoder_t *d, mc_frame_t *frame)
{
    mc_status_t st;
    if (d->discarding) {
        st = MC_E_OVERFLOW;
        ++d->n_overflow;
    } else if (d->code == 0) {
        st = MC_E_EMPTY; /* 0x00 0x00: nothing between delimiters */
    } else if (d->left != 0 || d->len < MC_FRAME_MIN_BODY) {
        st = MC_E_FRAME;
        ++d->n_malformed;
    } else {
        const size_t body = d->len - MC_FRAME_CRC_SIZE;
        const uint16_t got = (uint16_t)((uint16_t)d->buf[body] | (uint16_t)(d->buf[body + 1] << 8));
        if (mc_crc16_ccitt_false(d->buf, body) != got) {
            st = MC_E_CRC;
            ++d->n_crc;
        } else {
            st = MC_OK;
            ++d->n_ok;
            frame->id = d->buf[0];
            frame->seq = (uint16_t)((uint16_t)d->buf[1] | (uint16_t)(d->buf[2] << 8));
            frame->payload_len = body - MC_FRAME_HEADER_SIZE;
            frame->payload = frame->payload_len > 0 ? d->buf + MC_FRAME_HEADER_SIZE : NULL;
        }
    }
    decoder_restart(d);
    return st;
}

mc_status_t mc_frame_decoder_push(mc_frame_decoder_t *d, uint8_t byte, mc_frame_t *frame)
{
    if (d == NULL || frame == NULL || !decoder_ok(d)) {
        return MC_E_ARG;
    }
    frame->id = 0;
    frame->seq = 0;
    frame->payload = NULL;
    frame->payload_len = 0;
    if (byte == MC_FRAME_DELIMITER) {
        return decoder_end(d, frame);
    }
    if (d->discarding) {
        return MC_E_EMPTY;
    }
    if (d->left == 0) {
        /* A code byte. The block before it implies a zero unless it was a full 0xFF block;
         * the last block's implied zero is never written (it is the delimiter). */
        if (d->code != 0 && d->code != COBS_MAX_CODE) {
            decoder_append(d, 0);
        }
        d->code = byte;
        d->left = (uint8_t)(byte - 1u);
    } else {
        decoder_append(d, byte);
        --d->left;
    }
    return MC_E_EMPTY;
}

mc_status_t mc_frame_decoder_feed(mc_frame_decoder_t *d, const uint8_t *data, size_t len,
                                  size_t *consumed, mc_frame_t *frame)
{
    if (consumed != NULL) {
        *consumed = 0;
    }
    if (d == NULL || frame == NULL || consumed == NULL || (data == NULL && len > 0)) {
        return MC_E_ARG;
    }
    for (size_t i = 0; i < len; ++i) {
        const mc_status_t st = mc_frame_decoder_push(d, data[i], frame);
        if (st != MC_E_EMPTY) {
            *consumed = i + 1;
            return st;
        }
    }
    *consumed = len;
    return MC_E_EMPTY;
}

/* COBS encoder state over out[0..cap): code_at is where the current block's code goes. */
typedef struct {
    uint8_t *out;
    size_t cap;
    size_t pos;
    size_t code_at;
    uint8_t code;
} cobs_writer_t;

static int cobs_put(cobs_writer_t *w, uint8_t byte)
{
    if (byte == 0) {
        w->out[w->code_at] = w->code;
        if (w->pos >= w->cap) {
            return 0;
        }
        w->code_at = w->pos++;
        w->code = 1;
        return 1;
    }
    if (w->pos >= w->cap) {
        return 0;
    }
    w->out[w->pos++] = byte;
    if (++w->code == COBS_MAX_CODE) {
        w->out[w->code_at] = w->code;
        if (w->pos >= w->cap) {
            return 0;
        }
        w->code_at = w->pos++;
        w->code = 1;
    }
    return 1;
}

mc_status_t mc_frame_encode(uint8_t id, uint16_t seq, const uint8_t *payload, size_t len,
                            uint8_t *out, size_t cap, size_t *out_len)
{
    if (out_len != NULL) {
        *out_len = 0;
    }
    if (out == NULL || out_len == NULL || (payload == NULL && len > 0)) {
        return MC_E_ARG;
    }
    if (len > MC_FRAME_MAX_PAYLOAD) {
        return MC_E_LENGTH;
    }
    if (cap < 2u) {
        return MC_E_NO_SPACE;
    }
    const uint8_t header[MC_FRAME_HEADER_SIZE] = {id, (uint8_t)(seq & 0xFFu), (uint8_t)(seq >> 8)};
    uint16_t crc = mc_crc16_ccitt_false(header, sizeof header);
    crc = mc_crc16_ccitt_false_update(crc, payload, len);
    const uint8_t trailer[MC_FRAME_CRC_SIZE] = {(uint8_t)(crc & 0xFFu), (uint8_t)(crc >> 8)};

    cobs_writer_t w = {out, cap, 1, 0, 1};
    int ok = 1;
    for (size_t i = 0; ok && i < sizeof header; ++i) {
        ok = cobs_put(&w, header[i]);
    }
    for (size_t i = 0; ok && i < len; ++i) {
        ok = cobs_put(&w, payload[i]);
    }
    for (size_t i = 0; ok && i < sizeof trailer; ++i) {
        ok = cobs_put(&w, trailer[i]);
    }
    if (!ok || w.pos >= w.cap) {
        return MC_E_NO_SPACE;
    }
    out[w.code_at] = w.code;
    out[w.pos++] = MC_FRAME_DELIMITER;
    *out_len = w.pos;
    return MC_OK;
}
