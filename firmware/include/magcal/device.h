/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The protocol endpoint (protocol/SPEC.md): one mc_device_t ties the frame decoder (frame.h),
 * the message codec (messages.h), the idempotent-retry cache, acquisition (acquire.h), the
 * active and staged parameter sets (params.h, correction.h) and their storage (storage.h).
 * No malloc, no floating point. The caller owns the instance (its frame-sized buffers are
 * members, sized by the protocol's constants), the ring storage and the flash, and provides a
 * transmit function:
 *
 *     static mc_sample_t ring[MC_RING_CAPACITY];
 *     static mc_device_t dev;
 *     mc_device_config_t cfg = {0};
 *     cfg.tx = uart_tx; cfg.hal = &hal; cfg.ring = ring; cfg.ring_capacity = MC_RING_CAPACITY;
 *     cfg.flash = &flash; cfg.slot_a_page = 0; cfg.slot_b_page = 1; cfg.pages_per_slot = 1;
 *     ... firmware version, uid, sample rate, optional reset hook ...
 *     mc_device_init(&dev, &cfg);
 *     data-ready interrupt:  mc_device_sample(&dev);          (mc_acquire_poll)
 *     bytes received:        used = mc_device_rx_bytes(&dev, bytes, n);  keep bytes[used..n)
 *     main loop:             mc_device_poll(&dev);            (flush, stream samples)
 *
 * Contexts: mc_device_sample is the acquisition's producer (an interrupt); every other
 * function runs in one context (the main loop), never concurrently with each other, and tx
 * and the reset hook must not call back into the device. The library has no global state:
 * several instances may coexist.
 *
 * Transmit and drop policy
 *   tx(ctx, bytes, len) must not block: it takes a prefix of bytes (0 .. len) and returns how
 *   many it took (a negative return counts as 0, more than len as len). The device offers
 *   one whole encoded frame at a time. When tx takes only part of a frame, the device keeps
 *   the rest as its PENDING output and offers it again first, on every later call, so a frame
 *   is never torn on the wire. While output is pending:
 *     - responses are never dropped: mc_device_rx_bytes stops consuming input (it returns
 *       the count it used; the caller offers the rest later) until the pending output is
 *       gone, so no new request is acted on before its response can be transmitted. The
 *       link's back-pressure becomes back-pressure on the host, which retries (SPEC §3);
 *     - stream messages are dropped and counted: a sample that is due while output is
 *       pending, or that tx refuses entirely (returns 0), is not sent and adds 1 to the
 *       stream's dropped count (stream_stop_resp.dropped); its seq gap shows it to the host.
 *       A stream message that tx takes in part counts as sent (its rest is pending).
 *   Decimation and dropped. With decimation d the stream is due to send the samples whose
 *   acquisition seq is first + k*d (k = 0, 1, ...), first being the seq of the first sample
 *   the stream sees (so a host sees seq steps of d). stream_stop_resp.dropped counts, in
 *   messages, the due samples that were not sent: those the link refused (above) and those
 *   lost in the acquisition ring before the stream saw them (a seq gap between two samples
 *   it saw, or lost after the last one it saw and before the stop; a lost sample that was not
 *   due is no lost message, and one numbered before the stream started is not counted). So
 *   the seq gaps a host sees, each (gap / d - 1) messages, add up to dropped, except for
 *   messages dropped after the last one it received. Samples still queued when the stream
 *   stops are neither sent nor dropped. (The tail at a stop is read from the acquisition's
 *   counters while the producer may run: off by one at most if a sample lands meanwhile.)
 *   So a port with a byte FIFO (a UART) passes what fits, and a port with a frame queue may
 *   take all or nothing; either way a full link costs stream messages only.
 *
 * Requests (SPEC §3, §5), in the order a good frame is judged:
 *   1. an id that is not a request (0x01..0x08) gets nack(E_UNKNOWN_MESSAGE), a payload
 *      size wrong for the id nack(E_LENGTH); these are not acted on (not cached);
 *   2. hello is always acted on and clears the retry cache;
 *   3. any other request with the cached seq: same id and CRC-16 -> the cached response is
 *      sent again, nothing is acted on (mc_device_stats_t.retries); otherwise
 *      nack(E_SEQUENCE);
 *   4. the request is acted on, its response sent and remembered (seq, id, CRC, frame).
 *   Bad CRC or broken COBS: no answer (frame.h counts them).
 *
 * Parameter sets
 *   ACTIVE: the set loaded from storage at init and at each reset (if its format version is
 *   MC_PARAMS_FORMAT_VERSION and it decodes and validates); corrected streams use it. A
 *   commit does not change it: the committed set becomes active at the next reset (SPEC §5).
 *   STAGED: the set of the last successful param_set; a refused param_set clears it (so a
 *   commit never stores a set older than the last one sent). A commit stores it and keeps it
 *   staged; a reset clears it. param_commit's answer says what flash holds (mc_storage_commit's
 *   outcomes): OK stored; E_FLASH only when the previous set certainly still wins;
 *   E_OUTCOME_UNKNOWN when a flash error after the commit point could not be settled;
 *   E_RANGE when the stored sequence number is exhausted (nothing written).
 *
 * Reset (reset with MC_RESET_MAGIC): the device sends reset_resp(OK); once tx has taken all
 * of it, the device resets its own state as a reboot would: no stream, no staged set, an
 * empty retry cache, a fresh frame decoder, the queued samples discarded and the active set
 * reloaded from storage. The acquisition keeps running and keeps numbering (acquire.h: a
 * restart without a reboot continues the numbers, so the host never sees one twice; it is
 * also the one part the data-ready interrupt touches, so it is never re-initialised under
 * it). Then the device calls the optional reset hook, where a target that must really
 * reboot drains its UART and resets the MCU (NVIC_SystemReset); a SIL device needs none.
 */
#ifndef MAGCAL_DEVICE_H
#define MAGCAL_DEVICE_H

#include <stddef.h>
#include <stdint.h>

#include "magcal/acquire.h"
#include "magcal/correction.h"
#include "magcal/flash.h"
#include "magcal/frame.h"
#include "magcal/messages.h"
#include "magcal/params.h"
#include "magcal/ring.h"
#include "magcal/sensor_hal.h"
#include "magcal/status.h"
#include "magcal/storage.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Stream kinds (stream_start.kind). */
#define MC_DEVICE_STREAM_RAW 0u
#define MC_DEVICE_STREAM_CORRECTED 1u
/* param_get.which. */
#define MC_DEVICE_SET_ACTIVE 0u
#define MC_DEVICE_SET_STAGED 1u

/* Transmit: takes a prefix of bytes[0 .. len), returns its length; must not block. */
typedef int (*mc_device_tx_fn)(void *ctx, const uint8_t *bytes, size_t len);
/* Called after the device reset its state on a reset request (see above). */
typedef void (*mc_device_reset_fn)(void *ctx);

typedef struct {
    mc_device_tx_fn tx;        /* required */
    void *tx_ctx;
    mc_device_reset_fn on_reset; /* optional (NULL) */
    void *reset_ctx;
    const mc_sensor_hal_t *hal; /* copied by the acquisition */
    mc_sample_t *ring;          /* acquisition ring storage, ring_capacity samples (ring.h) */
    uint32_t ring_capacity;
    const mc_flash_t *flash;    /* parameter storage; must outlive the device */
    uint32_t slot_a_page, slot_b_page, pages_per_slot; /* mc_storage_init */
    uint8_t fw_version[3];      /* major, minor, patch (info_resp) */
    uint32_t fw_build;          /* first 32 bits of the commit id, 0 if unknown */
    uint32_t device_uid[3];     /* 96-bit unique id, word 0 least significant; 0 if none */
    uint32_t sample_rate_mhz;   /* nominal sample rate, millihertz */
} mc_device_config_t;

/* Counters since init (a reset keeps them), all wrapping modulo 2^32. */
typedef struct {
    uint32_t rx_ok, rx_crc, rx_malformed, rx_overflow; /* frames, as frame.h counts them */
    uint32_t requests;       /* requests acted on (responses built) */
    uint32_t retries;        /* requests answered from the retry cache */
    uint32_t nacks;          /* nacks sent */
    uint32_t stream_sent;    /* stream messages sent, all streams */
    uint32_t stream_dropped; /* stream messages dropped because the link was full, all streams */
    uint32_t resets;         /* resets done on request */
} mc_device_stats_t;

/* The instance. The caller owns it; fields are read-only outside device.c. */
typedef struct {
    mc_device_config_t cfg;
    mc_frame_decoder_t decoder;
    uint8_t rx_buf[MC_FRAME_MAX_BODY];
    /* pending output: out[out_off .. out_len) still to hand to tx */
    uint8_t out[MC_FRAME_MAX_ENCODED];
    size_t out_len, out_off;
    /* retry cache: the last request acted on and its response frame */
    uint8_t cache[MC_FRAME_MAX_ENCODED];
    size_t cache_len;
    uint16_t cache_seq, cache_crc;
    uint8_t cache_id, cache_valid;
    uint8_t reset_due;   /* a reset_resp is pending: reset once it is out */
    /* stream */
    uint8_t stream_on, stream_kind;
    uint8_t stream_seen;   /* the stream has seen a sample: next_due and last_seq are set */
    uint16_t stream_seq, stream_decimation;
    uint32_t stream_next_due;  /* acquisition seq of the next sample the stream must send */
    uint32_t stream_last_seq;  /* acquisition seq of the last sample the stream saw */
    uint32_t stream_start_next; /* acquisition's next seq when the stream started */
    uint32_t stream_overflow0;  /* acquisition's drop count when the stream started */
    uint32_t stream_count, stream_sent, stream_link_dropped;
    uint32_t stream_ring_dropped; /* due samples lost in the ring, in messages */
    /* parameter sets */
    uint8_t active_ok, staged_ok;
    uint16_t active_format, staged_format;
    uint32_t active_crc, staged_crc;
    uint8_t active_blob[MC_PARAMS_ENCODED_SIZE];
    uint8_t staged_blob[MC_PARAMS_ENCODED_SIZE];
    int8_t load_status; /* mc_storage_load's verdict at the last init or reset: an
                         * mc_status_t value, stored as int8_t (as on the wire) so the layout
                         * does not depend on the enum's size, see firmware/README.md */
    mc_correction_t correction; /* of the active set, ready when active_ok */
    mc_storage_t storage;
    mc_acquire_t acq;
    mc_device_stats_t stats;
    /* scratch of one request (about 700 bytes, kept off the stack) */
    mc_msg_t rq;
    union {
        mc_msg_info_resp_t info;
        mc_msg_param_get_resp_t param_get;
    } resp;
    uint8_t payload[MC_FRAME_MAX_PAYLOAD];
    uint32_t ready; /* MC_DEVICE_READY after a successful init */
} mc_device_t;

#define MC_DEVICE_READY 0x4D434456u

/*
 * Sets up dev from *cfg (copied): acquisition over cfg->ring, storage over cfg->flash, and
 * loads the active set. Returns MC_OK; MC_E_ARG for a NULL pointer, a missing tx, hal or
 * flash, or what mc_acquire_init / mc_storage_init refuse as MC_E_ARG; MC_E_RANGE for a
 * storage geometry mc_storage_init refuses. A flash that fails to read, or holds no valid
 * set, is not an error: the device then has no active set (load_status says why) and
 * answers corrected streams with E_NO_PARAMS.
 */
mc_status_t mc_device_init(mc_device_t *dev, const mc_device_config_t *cfg);

/*
 * Feeds received bytes to the frame decoder and acts on each complete frame (responses go
 * out through tx). Returns the number of bytes used, from 0 to len: fewer than len only when
 * output is pending (see the transmit policy above); offer the rest again later, after
 * mc_device_poll. 0 for a NULL or uninitialised dev, or data NULL.
 */
size_t mc_device_rx_bytes(mc_device_t *dev, const uint8_t *data, size_t len);

/* Producer (the data-ready interrupt, or the SIL's feed): one acquisition read
 * (mc_acquire_poll's returns). MC_E_ARG for a NULL dev; MC_E_STATE, without touching the HAL,
 * for a dev that mc_device_init has not set up (or that a failed init left cleared). Enable
 * the interrupt only after mc_device_init returned MC_OK (init clears dev, so an interrupt
 * during init could see a half-built instance), and disable it before calling init again. */
mc_status_t mc_device_sample(mc_device_t *dev);

/*
 * Main loop: offers pending output to tx, does a due reset once its response is out, then
 * pops every queued sample and streams it as the running stream says (decimation, count,
 * drops as above; with no stream the samples are discarded). Returns MC_OK, or MC_E_ARG.
 */
mc_status_t mc_device_poll(mc_device_t *dev);

/* 1 while output is pending (the port may wait for its link to drain, e.g. poll POLLOUT). */
int mc_device_tx_pending(const mc_device_t *dev);

/*
 * The link was replaced (a TCP client reconnected): drops the pending output and the frame
 * being received, so the new peer never sees the tail of a frame meant for the old one.
 * Stream, sets and retry cache are kept (the host starts with hello). MC_OK or MC_E_ARG.
 */
mc_status_t mc_device_link_reset(mc_device_t *dev);

/* The counters (frame counters taken from the decoder now). MC_OK or MC_E_ARG. */
mc_status_t mc_device_stats(const mc_device_t *dev, mc_device_stats_t *out);

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_DEVICE_H */
