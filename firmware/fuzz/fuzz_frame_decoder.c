/* SPDX-License-Identifier: Apache-2.0 */
/*
 * libFuzzer target for the frame decoder (frame.h) and the message codec (messages.h), built
 * with -fsanitize=fuzzer,address,undefined by `make fuzz-smoke`.
 *
 * The first input byte picks the receive buffer size (MC_FRAME_MIN_BODY .. MC_FRAME_MAX_BODY,
 * allocated exactly so that ASan sees any overrun); the rest is pushed one byte at a time.
 * Invariants checked (abort on violation):
 *   - push returns only MC_E_EMPTY, MC_OK, MC_E_CRC, MC_E_FRAME, MC_E_OVERFLOW;
 *   - a non-delimiter byte never ends a frame; the decoded length never exceeds the buffer;
 *   - a good frame's payload lies inside the buffer, and encoding it again and decoding that
 *     gives the same id, seq and payload;
 *   - a payload the message layer accepts packs back to the same bytes;
 *   - the counters count every non-empty frame once.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "magcal/frame.h"
#include "magcal/messages.h"

#define REQUIRE(cond)     \
    do {                  \
        if (!(cond)) {    \
            abort();      \
        }                 \
    } while (0)

static void check_reencode(const mc_frame_t *f)
{
    uint8_t wire[MC_FRAME_MAX_ENCODED];
    uint8_t body[MC_FRAME_MAX_BODY];
    size_t n = 0;
    REQUIRE(mc_frame_encode(f->id, f->seq, f->payload, f->payload_len, wire, sizeof wire, &n) ==
            MC_OK);
    REQUIRE(n <= MC_FRAME_ENCODED_SIZE(f->payload_len) && wire[n - 1] == 0);
    mc_frame_decoder_t d;
    mc_frame_t g;
    size_t used = 0;
    REQUIRE(mc_frame_decoder_init(&d, body, sizeof body) == MC_OK);
    REQUIRE(mc_frame_decoder_feed(&d, wire, n, &used, &g) == MC_OK && used == n);
    REQUIRE(g.id == f->id && g.seq == f->seq && g.payload_len == f->payload_len);
    REQUIRE(f->payload_len == 0 || memcmp(g.payload, f->payload, f->payload_len) == 0);
}

static void check_message(const mc_frame_t *f)
{
    static mc_msg_t msg;
    uint8_t again[MC_FRAME_MAX_PAYLOAD];
    size_t n = 0;
    const mc_status_t st = mc_msg_unpack(f->id, f->payload, f->payload_len, &msg);
    REQUIRE(st == MC_OK || st == MC_E_UNKNOWN_MESSAGE || st == MC_E_LENGTH);
    if (st == MC_OK) {
        REQUIRE(mc_msg_pack(&msg, again, sizeof again, &n) == MC_OK);
        REQUIRE(n == f->payload_len && (n == 0 || memcmp(again, f->payload, n) == 0));
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (size == 0) {
        return 0;
    }
    const size_t span = MC_FRAME_MAX_BODY - MC_FRAME_MIN_BODY + 1u;
    const size_t cap = data[0] >= 0x80u ? MC_FRAME_MAX_BODY : MC_FRAME_MIN_BODY + data[0] % span;
    uint8_t *buf = malloc(cap);
    REQUIRE(buf != NULL);
    mc_frame_decoder_t d;
    REQUIRE(mc_frame_decoder_init(&d, buf, cap) == MC_OK);
    uint32_t events = 0;
    for (size_t i = 1; i < size; ++i) {
        mc_frame_t f;
        const mc_status_t st = mc_frame_decoder_push(&d, data[i], &f);
        REQUIRE(d.len <= d.cap);
        if (data[i] != 0) {
            REQUIRE(st == MC_E_EMPTY);
            continue;
        }
        REQUIRE(st == MC_E_EMPTY || st == MC_OK || st == MC_E_CRC || st == MC_E_FRAME ||
                st == MC_E_OVERFLOW);
        events += st != MC_E_EMPTY;
        if (st != MC_OK) {
            REQUIRE(f.payload == NULL && f.payload_len == 0);
            continue;
        }
        REQUIRE(f.payload_len + MC_FRAME_MIN_BODY <= cap);
        REQUIRE(f.payload_len == 0 || f.payload == buf + MC_FRAME_HEADER_SIZE);
        check_reencode(&f);
        check_message(&f);
    }
    REQUIRE(d.n_ok + d.n_crc + d.n_malformed + d.n_overflow == events);
    free(buf);
    return 0;
}
