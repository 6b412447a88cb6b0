/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The frame decoder and encoder (frame.h) against the golden vectors (protocol/vectors, as C
 * arrays generated into protocol/vectors/vectors.h), their argument checks and the encoder's
 * room checks, and a deterministic pseudo-random replay: a few hundred thousand byte strings
 * (noise, valid frames, mutated frames) through decoders with several buffer sizes, checked
 * against a simple whole-buffer reference decoder and the decoder's invariants. Runs under
 * ASan+UBSan (make test-native), so any out-of-bounds access fails the test even where clang's
 * libFuzzer (make fuzz-smoke) is not installed.
 */
#include "check.h"
#include "magcal/crc.h"
#include "magcal/frame.h"
#include "magcal/messages.h"

#include "../../protocol/vectors/vectors.h"

#include <stdlib.h>
#include <string.h>

#define RANDOM_STRINGS 300000u

/* ---------------------------------------------------------------- golden vectors */
static void test_stream_vectors(void)
{
    for (size_t v = 0; v < MC_VEC_N_STREAMS; ++v) {
        const mc_vec_stream_t *s = &mc_vec_streams[v];
        uint8_t buf[MC_FRAME_MAX_BODY];
        mc_frame_decoder_t d;
        CHECK_EQ_INT(mc_frame_decoder_init(&d, buf, sizeof buf), MC_OK);
        size_t n_events = 0;
        int all_match = 1;
        for (size_t i = 0; i < s->wire_len; ++i) {
            mc_frame_t f;
            const mc_status_t st = mc_frame_decoder_push(&d, s->wire[i], &f);
            if (st == MC_E_EMPTY) {
                continue;
            }
            if (n_events >= s->n_events) {
                ++n_events;
                all_match = 0;
                continue;
            }
            const mc_vec_event_t *e = &s->events[n_events++];
            if (st != e->status) {
                printf("  %s event %zu: status %d, expected %d\n", s->name, n_events - 1, st,
                       e->status);
                all_match = 0;
                continue;
            }
            if (st != MC_OK) {
                continue;
            }
            mc_msg_t msg;
            const int same = f.id == e->id && f.seq == e->seq &&
                             f.payload_len == e->payload_len &&
                             (e->payload_len == 0 ||
                              memcmp(f.payload, e->payload, e->payload_len) == 0) &&
                             mc_msg_unpack(f.id, f.payload, f.payload_len, &msg) ==
                                 e->message_status;
            if (!same) {
                printf("  %s event %zu: frame or message status differs\n", s->name,
                       n_events - 1);
                all_match = 0;
            }
        }
        CHECK(all_match);
        CHECK_EQ_INT(n_events, s->n_events);
        CHECK_EQ_INT(d.n_ok + d.n_crc + d.n_malformed + d.n_overflow, s->n_events);

        /* The same stream through feed() in uneven chunks gives the same events. */
        CHECK_EQ_INT(mc_frame_decoder_init(&d, buf, sizeof buf), MC_OK);
        size_t at = 0, k = 0, chunk = 1;
        while (at < s->wire_len) {
            const size_t n = chunk < s->wire_len - at ? chunk : s->wire_len - at;
            size_t used = 0;
            mc_frame_t f;
            const mc_status_t st = mc_frame_decoder_feed(&d, s->wire + at, n, &used, &f);
            CHECK(used >= 1 && used <= n);
            at += used;
            if (st != MC_E_EMPTY) {
                CHECK(k < s->n_events && st == s->events[k].status);
                ++k;
            }
            chunk = chunk * 3 % 17 + 1;
        }
        CHECK_EQ_INT(k, s->n_events);
    }
}

static void test_message_vectors(void)
{
    for (size_t v = 0; v < MC_VEC_N_MESSAGES; ++v) {
        const mc_vec_message_t *m = &mc_vec_messages[v];
        uint8_t payload[MC_FRAME_MAX_PAYLOAD];
        uint8_t wire[MC_FRAME_MAX_ENCODED];
        size_t n = 0;
        /* pack(values) = payload, and the frame of it = wire. */
        CHECK_EQ_INT(mc_msg_pack(&m->msg, payload, sizeof payload, &n), MC_OK);
        CHECK(n == m->payload_len && memcmp(payload, m->payload, n) == 0);
        CHECK_EQ_INT(mc_frame_encode(m->id, m->seq, payload, n, wire, sizeof wire, &n), MC_OK);
        CHECK(n == m->wire_len && memcmp(wire, m->wire, n) == 0);
        CHECK(n <= MC_FRAME_ENCODED_SIZE(m->payload_len));
        /* decode(wire) gives id, seq and payload back; unpack and pack again are exact. */
        uint8_t buf[MC_FRAME_MAX_BODY];
        mc_frame_decoder_t d;
        mc_frame_t f;
        size_t used = 0;
        CHECK_EQ_INT(mc_frame_decoder_init(&d, buf, sizeof buf), MC_OK);
        CHECK_EQ_INT(mc_frame_decoder_feed(&d, m->wire, m->wire_len, &used, &f), MC_OK);
        CHECK_EQ_INT(used, m->wire_len);
        CHECK(f.id == m->id && f.seq == m->seq && f.payload_len == m->payload_len);
        mc_msg_t got;
        CHECK_EQ_INT(mc_msg_unpack(f.id, f.payload, f.payload_len, &got), MC_OK);
        CHECK_EQ_INT(mc_msg_pack(&got, payload, sizeof payload, &n), MC_OK);
        CHECK(n == m->payload_len && memcmp(payload, m->payload, n) == 0);
        CHECK(mc_msg_name(m->id) != NULL);
    }
}

/* ---------------------------------------------------------------- arguments and room */
static void test_arguments(void)
{
    uint8_t buf[MC_FRAME_MAX_BODY];
    mc_frame_decoder_t d;
    mc_frame_t f;
    size_t n = 99;
    CHECK_EQ_INT(mc_frame_decoder_init(NULL, buf, sizeof buf), MC_E_ARG);
    CHECK_EQ_INT(mc_frame_decoder_init(&d, NULL, sizeof buf), MC_E_ARG);
    CHECK_EQ_INT(mc_frame_decoder_init(&d, buf, MC_FRAME_MIN_BODY - 1), MC_E_ARG);
    CHECK_EQ_INT(mc_frame_decoder_init(&d, buf, MC_FRAME_MIN_BODY), MC_OK);
    CHECK_EQ_INT(mc_frame_decoder_push(NULL, 1, &f), MC_E_ARG);
    CHECK_EQ_INT(mc_frame_decoder_push(&d, 1, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_frame_decoder_feed(&d, NULL, 1, &n, &f), MC_E_ARG);
    CHECK_EQ_INT(n, 0);
    CHECK_EQ_INT(mc_frame_decoder_feed(&d, buf, 1, NULL, &f), MC_E_ARG);
    CHECK_EQ_INT(mc_frame_decoder_feed(&d, NULL, 0, &n, &f), MC_E_EMPTY);
    CHECK_EQ_INT(mc_frame_decoder_reset(NULL), MC_E_ARG);
    mc_frame_decoder_t zeroed;
    memset(&zeroed, 0, sizeof zeroed);
    CHECK_EQ_INT(mc_frame_decoder_push(&zeroed, 1, &f), MC_E_ARG); /* not initialised */

    /* reset drops a frame in progress: its tail then decodes as garbage, not as a frame. */
    const mc_vec_message_t *m = &mc_vec_messages[0];
    CHECK_EQ_INT(mc_frame_decoder_init(&d, buf, sizeof buf), MC_OK);
    CHECK_EQ_INT(mc_frame_decoder_feed(&d, m->wire, 3, &n, &f), MC_E_EMPTY);
    CHECK_EQ_INT(mc_frame_decoder_reset(&d), MC_OK);
    CHECK_EQ_INT(mc_frame_decoder_feed(&d, m->wire, m->wire_len, &n, &f), MC_OK);

    uint8_t out[MC_FRAME_MAX_ENCODED + 8];
    const uint8_t payload[MC_FRAME_MAX_PAYLOAD + 1] = {0};
    CHECK_EQ_INT(mc_frame_encode(1, 2, NULL, 1, out, sizeof out, &n), MC_E_ARG);
    CHECK_EQ_INT(mc_frame_encode(1, 2, payload, 1, NULL, sizeof out, &n), MC_E_ARG);
    CHECK_EQ_INT(mc_frame_encode(1, 2, payload, 1, out, sizeof out, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_frame_encode(1, 2, payload, MC_FRAME_MAX_PAYLOAD + 1, out, sizeof out, &n),
                 MC_E_LENGTH);
    CHECK_EQ_INT(mc_frame_encode(1, 2, NULL, 0, out, sizeof out, &n), MC_OK);
    CHECK_EQ_INT(n, 7); /* 5-byte body, 1 COBS code (no zero in it here), delimiter */
    CHECK_EQ_INT(mc_frame_encode(1, 2, payload, MC_FRAME_MAX_PAYLOAD, out, sizeof out, &n),
                 MC_OK);
    CHECK(n <= MC_FRAME_MAX_ENCODED && n <= MC_FRAME_ENCODED_SIZE(MC_FRAME_MAX_PAYLOAD));
}

/* Every cap below the frame's size gives MC_E_NO_SPACE without writing past cap. */
static void test_encoder_room(void)
{
    for (size_t v = 0; v < MC_VEC_N_MESSAGES; ++v) {
        const mc_vec_message_t *m = &mc_vec_messages[v];
        int all_ok = 1;
        for (size_t cap = 0; cap <= m->wire_len; ++cap) {
            uint8_t out[MC_FRAME_MAX_ENCODED + 16];
            memset(out, 0xA5, sizeof out);
            size_t n = 99;
            const mc_status_t st =
                mc_frame_encode(m->id, m->seq, m->payload, m->payload_len, out, cap, &n);
            const mc_status_t want = cap < m->wire_len ? MC_E_NO_SPACE : MC_OK;
            all_ok &= st == want && n == (st == MC_OK ? m->wire_len : 0);
            for (size_t i = cap; i < sizeof out; ++i) {
                all_ok &= out[i] == 0xA5;
            }
        }
        CHECK(all_ok);
    }
}

/* ---------------------------------------------------------------- pseudo-random replay */
static uint32_t rng_state = 0x12345678u;
static uint32_t rng(void)
{
    /* xorshift32 */
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 17;
    rng_state ^= rng_state << 5;
    return rng_state;
}

typedef struct {
    mc_status_t status;
    uint8_t id;
    uint16_t seq;
    size_t payload_len;
    uint8_t payload[MC_FRAME_MAX_BODY];
} ref_event_t;

/* The spec's receive rules on a whole chunk (the bytes between two delimiters). */
static mc_status_t ref_decode(const uint8_t *chunk, size_t n, size_t cap, ref_event_t *e)
{
    uint8_t out[1024];
    size_t len = 0, i = 0;
    int truncated = 0;
    while (i < n) {
        const size_t code = chunk[i];
        for (size_t k = 1; k < code; ++k) {
            if (i + k >= n) {
                truncated = 1;
                break;
            }
            if (len < sizeof out) {
                out[len] = chunk[i + k];
            }
            ++len;
        }
        i += code;
        if (i < n && code != 0xFFu) {
            if (len < sizeof out) {
                out[len] = 0;
            }
            ++len;
        }
    }
    if (len > cap) {
        return MC_E_OVERFLOW;
    }
    if (truncated || len < MC_FRAME_MIN_BODY) {
        return MC_E_FRAME;
    }
    const uint16_t crc = (uint16_t)(out[len - 2] | (out[len - 1] << 8));
    if (mc_crc16_ccitt_false(out, len - 2) != crc) {
        return MC_E_CRC;
    }
    e->id = out[0];
    e->seq = (uint16_t)(out[1] | (out[2] << 8));
    e->payload_len = len - MC_FRAME_MIN_BODY;
    memcpy(e->payload, out + 3, e->payload_len);
    return MC_OK;
}

/* Builds a random input: noise, zeros, valid frames and mutated valid frames. */
static size_t random_input(uint8_t *s, size_t max)
{
    const size_t target = rng() % (rng() % 8u == 0 ? max : 96u);
    size_t n = 0;
    while (n < target) {
        const uint32_t what = rng() % 8u;
        if (what < 3u) { /* a valid frame of random content, maybe mutated */
            uint8_t payload[MC_FRAME_MAX_PAYLOAD];
            const size_t plen = rng() % (rng() % 4u == 0 ? MC_FRAME_MAX_PAYLOAD + 1 : 32u);
            for (size_t i = 0; i < plen; ++i) {
                payload[i] = (uint8_t)(rng() % 3u == 0 ? 0 : rng());
            }
            uint8_t frame[MC_FRAME_MAX_ENCODED];
            size_t flen = 0;
            if (mc_frame_encode((uint8_t)rng(), (uint16_t)rng(), payload, plen, frame,
                                sizeof frame, &flen) != MC_OK) {
                continue;
            }
            if (what == 0u && flen > 0) {
                frame[rng() % flen] ^= (uint8_t)(1u << (rng() % 8u)); /* one bit flip */
            }
            if (what == 1u && flen > 1) {
                flen = rng() % flen; /* truncated */
            }
            for (size_t i = 0; i < flen && n < max; ++i) {
                s[n++] = frame[i];
            }
        } else if (what < 5u) {
            s[n++] = 0;
        } else {
            const size_t run = rng() % 300u;
            for (size_t i = 0; i < run && n < max; ++i) {
                s[n++] = (uint8_t)(rng() % 5u == 0 ? 0xFFu : rng());
            }
        }
    }
    return n < max ? n : max;
}

static void test_random_replay(void)
{
    static const size_t caps[] = {MC_FRAME_MIN_BODY, 16u, 64u, MC_FRAME_MAX_BODY};
    static uint8_t input[1200];
    unsigned long events = 0, ok_frames = 0, mismatches = 0;
    for (uint32_t t = 0; t < RANDOM_STRINGS; ++t) {
        const size_t n = random_input(input, sizeof input);
        const size_t cap = caps[t % (sizeof caps / sizeof caps[0])];
        uint8_t *buf = malloc(cap); /* exactly cap bytes, so ASan sees any overrun */
        if (buf == NULL) {
            CHECK(buf != NULL);
            return;
        }
        mc_frame_decoder_t d;
        if (mc_frame_decoder_init(&d, buf, cap) != MC_OK) {
            ++mismatches;
        }
        size_t chunk_start = 0;
        const unsigned long events_before = events;
        for (size_t i = 0; i < n; ++i) {
            mc_frame_t f;
            const mc_status_t st = mc_frame_decoder_push(&d, input[i], &f);
            if (d.len > d.cap || (input[i] != 0 && st != MC_E_EMPTY)) {
                ++mismatches;
            }
            if (input[i] != 0) {
                continue;
            }
            /* A delimiter: compare with the reference on the chunk it ends. */
            ref_event_t e;
            const size_t clen = i - chunk_start;
            const mc_status_t want =
                clen == 0 ? MC_E_EMPTY : ref_decode(input + chunk_start, clen, cap, &e);
            chunk_start = i + 1;
            if (st != want) {
                ++mismatches;
                continue;
            }
            if (st != MC_E_EMPTY) {
                ++events;
            }
            if (st != MC_OK) {
                if (f.payload != NULL || f.payload_len != 0) {
                    ++mismatches;
                }
                continue;
            }
            ++ok_frames;
            /* The payload lies inside the buffer and equals the reference's; the message
             * layer either refuses it or packs it back to the same bytes. */
            if (f.payload_len + MC_FRAME_MIN_BODY > cap || f.id != e.id || f.seq != e.seq ||
                f.payload_len != e.payload_len ||
                (f.payload_len > 0 && (f.payload != buf + MC_FRAME_HEADER_SIZE ||
                                       memcmp(f.payload, e.payload, f.payload_len) != 0))) {
                ++mismatches;
                continue;
            }
            mc_msg_t msg;
            if (mc_msg_unpack(f.id, f.payload, f.payload_len, &msg) == MC_OK) {
                uint8_t again[MC_FRAME_MAX_PAYLOAD];
                size_t alen = 0;
                if (mc_msg_pack(&msg, again, sizeof again, &alen) != MC_OK ||
                    alen != f.payload_len ||
                    (alen > 0 && memcmp(again, f.payload, alen) != 0)) {
                    ++mismatches;
                }
            }
        }
        if (d.n_ok + d.n_crc + d.n_malformed + d.n_overflow != events - events_before) {
            ++mismatches; /* every non-empty frame is counted once, by outcome */
        }
        free(buf);
    }
    printf("  random replay: %u strings, %lu frame events, %lu good frames\n",
           (unsigned)RANDOM_STRINGS, events, ok_frames);
    CHECK_EQ_INT(mismatches, 0);
    CHECK(ok_frames > 10000u); /* the generator does produce valid frames */
}

int main(void)
{
    test_stream_vectors();
    test_message_vectors();
    test_arguments();
    test_encoder_room();
    test_random_replay();
    return check_summary("test_fw_frame");
}
