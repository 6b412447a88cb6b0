/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Protocol framing (protocol/SPEC.md): COBS-encoded frames delimited by 0x00, each checked by
 * a CRC-16/CCITT-FALSE.
 *
 *   wire  = COBS(body) 0x00
 *   body  = id (uint8) | seq (uint16 LE) | payload (0..MC_FRAME_MAX_PAYLOAD bytes) | crc
 *   crc   = CRC-16/CCITT-FALSE over id | seq | payload, little-endian (uint16)
 *
 * The decoder takes one byte at a time (from a UART interrupt's ring, for example) and decodes
 * COBS in place into a buffer the caller owns; it never reads or writes outside that buffer
 * whatever the input. A frame whose body does not fit is dropped up to the next delimiter and
 * counted. Empty frames (0x00 0x00) are ignored, so a sender may put a 0x00 before a frame
 * to flush line noise at the receiver.
 *
 * The encoder writes COBS(body) and the delimiter into a buffer the caller owns, checking
 * room as it goes (MC_FRAME_ENCODED_SIZE(n) bytes always suffice for an n-byte payload).
 *
 * Scaling and overflow: no arithmetic beyond byte counts, all bounded by the buffer sizes;
 * the counters wrap modulo 2^32.
 */
#ifndef MAGCAL_FRAME_H
#define MAGCAL_FRAME_H

#include <stddef.h>
#include <stdint.h>

#include "magcal/messages.h"
#include "magcal/status.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Worst-case wire size (COBS overhead and delimiter included) of a frame with an n-byte
 * payload: body + body / 254 + 1 COBS code bytes + 1 delimiter. */
#define MC_FRAME_ENCODED_SIZE(n) \
    ((n) + MC_FRAME_MIN_BODY + ((n) + MC_FRAME_MIN_BODY) / 254u + 2u)

/* A decoded frame. payload points into the decoder's buffer: valid until the next push. */
typedef struct {
    uint8_t id;             /* message id (mc_msg_id_t, or unknown: framing does not check) */
    uint16_t seq;           /* request sequence */
    const uint8_t *payload; /* NULL when payload_len is 0 */
    size_t payload_len;
} mc_frame_t;

/* A streaming decoder. The caller owns it and its buffer; fields are read-only outside
 * frame.c. The counters count delimiter-terminated non-empty frames by outcome. */
typedef struct {
    uint8_t *buf;          /* decoded body of the frame in progress */
    size_t cap;            /* size of buf: the largest body accepted */
    size_t len;            /* decoded bytes so far */
    uint8_t code;          /* COBS code of the current block, 0 before a frame's first byte */
    uint8_t left;          /* data bytes still to come in the current block */
    uint8_t discarding;    /* 1 after an overflow, until the delimiter */
    uint32_t n_ok;         /* good frames */
    uint32_t n_crc;        /* frames with a wrong CRC (MC_E_CRC) */
    uint32_t n_malformed;  /* truncated COBS block or body shorter than 5 bytes (MC_E_FRAME) */
    uint32_t n_overflow;   /* frames longer than cap, dropped (MC_E_OVERFLOW) */
} mc_frame_decoder_t;

/*
 * Initialises d to decode into buf[0..cap). cap must be at least MC_FRAME_MIN_BODY (5);
 * MC_FRAME_MAX_BODY holds every frame of the protocol, a smaller buffer drops the frames
 * that do not fit (MC_E_OVERFLOW). MC_E_ARG for a NULL pointer or a too small cap.
 */
mc_status_t mc_frame_decoder_init(mc_frame_decoder_t *d, uint8_t *buf, size_t cap);

/* Drops the frame in progress (counters are kept). MC_E_ARG when d is NULL. */
mc_status_t mc_frame_decoder_reset(mc_frame_decoder_t *d);

/*
 * Pushes one received byte. Returns
 *   MC_E_EMPTY     no frame ended with this byte (also for an empty frame),
 *   MC_OK          a good frame ended: *frame holds it,
 *   MC_E_CRC       a frame ended whose CRC does not match,
 *   MC_E_FRAME     a frame ended inside a COBS block, or its body is shorter than 5 bytes,
 *   MC_E_OVERFLOW  a frame ended that did not fit the buffer (dropped as it came),
 *   MC_E_ARG       d or frame is NULL, or d is not initialised.
 * *frame is zeroed unless MC_OK.
 */
mc_status_t mc_frame_decoder_push(mc_frame_decoder_t *d, uint8_t byte, mc_frame_t *frame);

/*
 * Pushes data[0..len) until a push returns something other than MC_E_EMPTY, and returns that
 * (MC_E_EMPTY when all bytes were used without an event). *consumed is the number of bytes
 * pushed: call again with the rest. data may be NULL when len is 0.
 */
mc_status_t mc_frame_decoder_feed(mc_frame_decoder_t *d, const uint8_t *data, size_t len,
                                  size_t *consumed, mc_frame_t *frame);

/*
 * Encodes a frame: COBS(id | seq | payload | crc) and the 0x00 delimiter, into out[0..cap).
 * *out_len is the bytes written (0 on error; out is then unspecified). MC_E_ARG for a NULL
 * out or out_len, or payload NULL with len > 0; MC_E_LENGTH when len > MC_FRAME_MAX_PAYLOAD;
 * MC_E_NO_SPACE when cap is too small.
 */
mc_status_t mc_frame_encode(uint8_t id, uint16_t seq, const uint8_t *payload, size_t len,
                            uint8_t *out, size_t cap, size_t *out_len);

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_FRAME_H */
