/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The protocol endpoint (device.h) under ASan+UBSan: scripted request frames in, response
 * frames out, for every flow of protocol/SPEC.md §3 and §5: hello/version negotiation, info,
 * nacks (unknown id, bad length, E_SEQUENCE), no answer to a bad CRC or broken COBS, the
 * retry cache (answered without acting twice; hello clears it), parameter get/set/commit with
 * every refusal, reset (magic, state after it, hook), a reboot showing the committed set,
 * raw and corrected streams (decimation, count, values equal to mc_correction_apply), and a
 * full link: stream messages dropped and counted, responses held back and never torn.
 */
#include "check.h"
#include "flash_sim.h"
#include "sensor_sim.h"

#include <string.h>

#include "magcal/crc.h"
#include "magcal/device.h"

/* ---------------------------------------------------------------- the rig */

#define LINK_CAP 65536u
#define PAGE_SIZE 256u

typedef struct {
    uint8_t buf[LINK_CAP];
    size_t len;
    long room; /* bytes tx may still take; -1: unlimited */
    long calls;
} link_t;

typedef struct {
    mc_device_t dev;
    flash_sim_t fsim;
    mc_flash_t flash;
    sensor_sim_t ssim;
    mc_sensor_hal_t hal;
    mc_sample_t ring[MC_RING_CAPACITY];
    link_t link;
    int resets; /* reset hook calls */
    uint32_t reads; /* successful sensor reads so far: the next sample's data index */
} rig_t;

static rig_t R;

static int link_tx(void *ctx, const uint8_t *bytes, size_t len)
{
    link_t *l = (link_t *)ctx;
    size_t take = len;
    ++l->calls;
    if (l->room >= 0 && take > (size_t)l->room) {
        take = (size_t)l->room;
    }
    if (take > LINK_CAP - l->len) {
        take = LINK_CAP - l->len;
    }
    memcpy(l->buf + l->len, bytes, take);
    l->len += take;
    if (l->room >= 0) {
        l->room -= (long)take;
    }
    return (int)take;
}

static void on_reset(void *ctx)
{
    ++*(int *)ctx;
}

static mc_device_config_t rig_config(rig_t *r)
{
    mc_device_config_t cfg;
    memset(&cfg, 0, sizeof cfg);
    cfg.tx = link_tx;
    cfg.tx_ctx = &r->link;
    cfg.on_reset = on_reset;
    cfg.reset_ctx = &r->resets;
    cfg.hal = &r->hal;
    cfg.ring = r->ring;
    cfg.ring_capacity = MC_RING_CAPACITY;
    cfg.flash = &r->flash;
    cfg.slot_a_page = 0u;
    cfg.slot_b_page = 1u;
    cfg.pages_per_slot = 1u;
    cfg.fw_version[0] = 1u;
    cfg.fw_version[1] = 2u;
    cfg.fw_version[2] = 3u;
    cfg.fw_build = 0xDEADBEEFu;
    cfg.device_uid[0] = 0x11111111u;
    cfg.device_uid[1] = 0x22222222u;
    cfg.device_uid[2] = 0x33333333u;
    cfg.sample_rate_mhz = 100000u;
    return cfg;
}

/* A fresh device; blank flash unless keep_flash (a reboot). */
static void rig_boot(int keep_flash)
{
    if (!keep_flash) {
        flash_sim_init(&R.fsim, &R.flash, PAGE_SIZE, 2u);
    }
    sensor_sim_init(&R.ssim);
    R.hal = sensor_sim_hal(&R.ssim);
    memset(&R.link, 0, sizeof R.link);
    R.link.room = -1;
    R.resets = 0;
    R.reads = 0u;
    const mc_device_config_t cfg = rig_config(&R);
    CHECK_EQ_INT(mc_device_init(&R.dev, &cfg), MC_OK);
}

/* ---------------------------------------------------------------- host side */

typedef struct {
    uint8_t id;
    uint16_t seq;
    uint8_t payload[MC_FRAME_MAX_PAYLOAD];
    size_t len;
} rx_frame_t;

#define MAX_FRAMES 128

static rx_frame_t got[MAX_FRAMES];

/* Decodes and clears everything the device sent; every chunk must be a good frame. */
static size_t take_frames(void)
{
    uint8_t buf[MC_FRAME_MAX_BODY];
    mc_frame_decoder_t d;
    mc_frame_t f;
    size_t n = 0u, bad = 0u;
    CHECK_EQ_INT(mc_frame_decoder_init(&d, buf, sizeof buf), MC_OK);
    for (size_t i = 0; i < R.link.len; ++i) {
        const mc_status_t st = mc_frame_decoder_push(&d, R.link.buf[i], &f);
        if (st == MC_OK && n < MAX_FRAMES) {
            got[n].id = f.id;
            got[n].seq = f.seq;
            got[n].len = f.payload_len;
            if (f.payload_len > 0u) {
                memcpy(got[n].payload, f.payload, f.payload_len);
            }
            ++n;
        } else if (st != MC_E_EMPTY) {
            ++bad;
        }
    }
    CHECK_EQ_INT(bad, 0);
    CHECK_EQ_INT(d.len, 0); /* nothing left half-sent */
    R.link.len = 0u;
    return n;
}

static size_t wire_len;
static uint8_t wire[MC_FRAME_MAX_ENCODED];

static void send_raw(const uint8_t *bytes, size_t n)
{
    CHECK_EQ_INT(mc_device_rx_bytes(&R.dev, bytes, n), n);
}

static void send_frame(uint8_t id, uint16_t seq, const uint8_t *payload, size_t len)
{
    CHECK_EQ_INT(mc_frame_encode(id, seq, payload, len, wire, sizeof wire, &wire_len), MC_OK);
    send_raw(wire, wire_len);
}

/* Sends a request and returns its one answer (id 0 when there was not exactly one). */
static rx_frame_t request(uint8_t id, uint16_t seq, const uint8_t *payload, size_t len)
{
    rx_frame_t none;
    memset(&none, 0, sizeof none);
    send_frame(id, seq, payload, len);
    const size_t n = take_frames();
    CHECK_EQ_INT(n, 1);
    return n == 1u ? got[0] : none;
}

static void check_nack(const rx_frame_t *f, uint16_t seq, mc_status_t status, uint8_t req_id)
{
    mc_msg_nack_t m;
    CHECK_EQ_INT(f->id, MC_MSG_NACK);
    CHECK_EQ_INT(f->seq, seq);
    CHECK_EQ_INT(mc_msg_nack_unpack(f->payload, f->len, &m), MC_OK);
    CHECK_EQ_INT(m.status, status);
    CHECK_EQ_INT(m.request_id, req_id);
}

/* One-status responses (stream_start, param_commit, reset). */
static int status_of(const rx_frame_t *f, uint8_t resp_id, uint16_t seq)
{
    CHECK_EQ_INT(f->id, resp_id);
    CHECK_EQ_INT(f->seq, seq);
    CHECK(f->len >= 1u);
    return f->len >= 1u ? (int)(int8_t)f->payload[0] : 999;
}

static mc_msg_hello_resp_t hello(uint16_t seq, uint16_t lo, uint16_t hi)
{
    uint8_t p[MC_MSG_HELLO_SIZE];
    size_t n;
    mc_msg_hello_t m = {lo, hi};
    mc_msg_hello_resp_t r;
    CHECK_EQ_INT(mc_msg_hello_pack(&m, p, sizeof p, &n), MC_OK);
    const rx_frame_t f = request(MC_MSG_HELLO, seq, p, n);
    CHECK_EQ_INT(f.id, MC_MSG_HELLO_RESP);
    CHECK_EQ_INT(f.seq, seq);
    CHECK_EQ_INT(mc_msg_hello_resp_unpack(f.payload, f.len, &r), MC_OK);
    return r;
}

static mc_msg_param_get_resp_t param_get(uint16_t seq, uint8_t which)
{
    const uint8_t p[1] = {which};
    mc_msg_param_get_resp_t r;
    const rx_frame_t f = request(MC_MSG_PARAM_GET, seq, p, 1u);
    CHECK_EQ_INT(f.id, MC_MSG_PARAM_GET_RESP);
    CHECK_EQ_INT(f.seq, seq);
    CHECK_EQ_INT(mc_msg_param_get_resp_unpack(f.payload, f.len, &r), MC_OK);
    CHECK_EQ_INT(r.which, which);
    return r;
}

static size_t param_set_payload(uint16_t format, const uint8_t *blob, size_t blob_len,
                                uint8_t *out)
{
    mc_msg_param_set_t m;
    size_t n = 0u;
    m.format_version = format;
    memcpy(m.blob, blob, blob_len);
    m.blob_len = blob_len;
    CHECK_EQ_INT(mc_msg_param_set_pack(&m, out, MC_FRAME_MAX_PAYLOAD, &n), MC_OK);
    return n;
}

static mc_msg_param_set_resp_t param_set(uint16_t seq, uint16_t format, const uint8_t *blob,
                                         size_t blob_len)
{
    uint8_t p[MC_FRAME_MAX_PAYLOAD];
    mc_msg_param_set_resp_t r;
    const size_t n = param_set_payload(format, blob, blob_len, p);
    const rx_frame_t f = request(MC_MSG_PARAM_SET, seq, p, n);
    CHECK_EQ_INT(f.id, MC_MSG_PARAM_SET_RESP);
    CHECK_EQ_INT(mc_msg_param_set_resp_unpack(f.payload, f.len, &r), MC_OK);
    return r;
}

static int param_commit(uint16_t seq, uint32_t crc)
{
    uint8_t p[4];
    size_t n;
    mc_msg_param_commit_t m = {crc};
    CHECK_EQ_INT(mc_msg_param_commit_pack(&m, p, sizeof p, &n), MC_OK);
    const rx_frame_t f = request(MC_MSG_PARAM_COMMIT, seq, p, n);
    return status_of(&f, MC_MSG_PARAM_COMMIT_RESP, seq);
}

static int reset_req(uint16_t seq, uint32_t magic)
{
    uint8_t p[4];
    size_t n;
    mc_msg_reset_t m = {magic};
    CHECK_EQ_INT(mc_msg_reset_pack(&m, p, sizeof p, &n), MC_OK);
    const rx_frame_t f = request(MC_MSG_RESET, seq, p, n);
    return status_of(&f, MC_MSG_RESET_RESP, seq);
}

static size_t stream_start_payload(uint8_t kind, uint16_t dec, uint32_t count, uint8_t *out)
{
    mc_msg_stream_start_t m = {kind, dec, count};
    size_t n = 0u;
    CHECK_EQ_INT(mc_msg_stream_start_pack(&m, out, MC_MSG_STREAM_START_SIZE, &n), MC_OK);
    return n;
}

static int stream_start(uint16_t seq, uint8_t kind, uint16_t dec, uint32_t count)
{
    uint8_t p[MC_MSG_STREAM_START_SIZE];
    const size_t n = stream_start_payload(kind, dec, count, p);
    const rx_frame_t f = request(MC_MSG_STREAM_START, seq, p, n);
    return status_of(&f, MC_MSG_STREAM_START_RESP, seq);
}

static mc_msg_stream_stop_resp_t stream_stop(uint16_t seq)
{
    mc_msg_stream_stop_resp_t r;
    const rx_frame_t f = request(MC_MSG_STREAM_STOP, seq, NULL, 0u);
    CHECK_EQ_INT(f.id, MC_MSG_STREAM_STOP_RESP);
    CHECK_EQ_INT(mc_msg_stream_stop_resp_unpack(f.payload, f.len, &r), MC_OK);
    CHECK_EQ_INT(r.status, MC_OK);
    return r;
}

/* n sensor reads, each followed by a main-loop poll. */
static void samples(uint32_t n)
{
    for (uint32_t i = 0; i < n; ++i) {
        CHECK_EQ_INT(mc_device_sample(&R.dev), MC_OK);
        CHECK_EQ_INT(mc_device_poll(&R.dev), MC_OK);
        ++R.reads;
    }
}

/* A valid set: D^-1 = diag(1, 1.5, 0.75) (E_d = 1), offset (100, -50, 12.5) counts,
 * output in counts with E_m = 16. */
static mc_params_t good_params(void)
{
    mc_params_t p;
    memset(&p, 0, sizeof p);
    p.version = MC_PARAMS_FORMAT_VERSION;
    p.d_inv_exp = 1;
    p.out_exp = 16;
    p.d_inv[0] = INT32_C(1) << 29;
    p.d_inv[4] = 3 * (INT32_C(1) << 28);
    p.d_inv[8] = 3 * (INT32_C(1) << 27);
    p.d_inv[1] = 12345;
    p.offset[0] = 100 * 32768;
    p.offset[1] = -50 * 32768;
    p.offset[2] = 25 * 16384;
    return p;
}

static void encode(const mc_params_t *p, uint8_t blob[MC_PARAMS_ENCODED_SIZE])
{
    size_t n = 0u;
    CHECK_EQ_INT(mc_params_encode(p, blob, MC_PARAMS_ENCODED_SIZE, &n), MC_OK);
}

/* ---------------------------------------------------------------- tests */

static void test_init_args(void)
{
    mc_device_config_t cfg;
    rig_boot(0);
    cfg = rig_config(&R);
    CHECK_EQ_INT(mc_device_init(NULL, &cfg), MC_E_ARG);
    CHECK_EQ_INT(mc_device_init(&R.dev, NULL), MC_E_ARG);
    cfg.tx = NULL;
    CHECK_EQ_INT(mc_device_init(&R.dev, &cfg), MC_E_ARG);
    cfg = rig_config(&R);
    cfg.ring_capacity = 3u; /* not a power of two */
    CHECK_EQ_INT(mc_device_init(&R.dev, &cfg), MC_E_ARG);
    CHECK_EQ_INT(mc_device_poll(&R.dev), MC_E_ARG); /* left uninitialised */
    cfg = rig_config(&R);
    cfg.slot_b_page = 0u; /* overlapping slots */
    CHECK_EQ_INT(mc_device_init(&R.dev, &cfg), MC_E_RANGE);
    CHECK_EQ_INT(mc_device_rx_bytes(NULL, wire, 1u), 0);
    CHECK_EQ_INT(mc_device_sample(NULL), MC_E_ARG);
    /* The producer on a device init never set up (zeroed, or cleared by a refused init):
     * MC_E_STATE, no call through the acquisition's unset HAL pointers. */
    memset(&R.dev, 0, sizeof R.dev);
    CHECK_EQ_INT(mc_device_sample(&R.dev), MC_E_STATE);
    cfg = rig_config(&R);
    cfg.ring_capacity = 3u;
    CHECK_EQ_INT(mc_device_init(&R.dev, &cfg), MC_E_ARG);
    CHECK_EQ_INT(mc_device_sample(&R.dev), MC_E_STATE);
    CHECK_EQ_INT(R.ssim.calls, 0);
    CHECK_EQ_INT(mc_device_link_reset(NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_device_stats(NULL, NULL), MC_E_ARG);
    CHECK(!mc_device_tx_pending(NULL));
    rig_boot(0);
    CHECK_EQ_INT(mc_device_rx_bytes(&R.dev, NULL, 3u), 0);
    CHECK_EQ_INT(R.dev.load_status, MC_E_NO_PARAMS);
    /* No enum-typed field in mc_device_t: its layout must not depend on -fshort-enums. */
    CHECK_EQ_INT(sizeof R.dev.load_status, sizeof(int8_t));
}

static void test_hello_and_info(void)
{
    rig_boot(0);
    mc_msg_hello_resp_t h = hello(1u, 1u, 1u);
    CHECK_EQ_INT(h.status, MC_OK);
    CHECK_EQ_INT(h.version, 1);
    CHECK_EQ_INT(h.device_min_version, MC_PROTOCOL_MIN_VERSION);
    CHECK_EQ_INT(h.device_max_version, MC_PROTOCOL_VERSION);
    CHECK_EQ_INT(h.max_payload, MC_FRAME_MAX_PAYLOAD);
    h = hello(2u, 0u, 9u); /* a wider host: the highest common version */
    CHECK_EQ_INT(h.status, MC_OK);
    CHECK_EQ_INT(h.version, MC_PROTOCOL_VERSION);
    h = hello(3u, 2u, 5u); /* no overlap */
    CHECK_EQ_INT(h.status, MC_E_VERSION);
    CHECK_EQ_INT(h.version, 0);
    CHECK_EQ_INT(h.device_max_version, MC_PROTOCOL_VERSION);
    h = hello(4u, 1u, 0u); /* an empty host range */
    CHECK_EQ_INT(h.status, MC_E_VERSION);

    rx_frame_t f = request(MC_MSG_INFO, 5u, NULL, 0u);
    mc_msg_info_resp_t r;
    CHECK_EQ_INT(f.id, MC_MSG_INFO_RESP);
    CHECK_EQ_INT(f.seq, 5);
    CHECK_EQ_INT(f.len, MC_MSG_INFO_RESP_SIZE);
    CHECK_EQ_INT(mc_msg_info_resp_unpack(f.payload, f.len, &r), MC_OK);
    CHECK_EQ_INT(r.status, MC_OK);
    CHECK(r.fw_version[0] == 1u && r.fw_version[1] == 2u && r.fw_version[2] == 3u);
    CHECK_EQ_INT(r.fw_build, 0xDEADBEEFu);
    CHECK_EQ_INT(r.protocol_version, MC_PROTOCOL_VERSION);
    CHECK_EQ_INT(r.params_format_version, MC_PARAMS_FORMAT_VERSION);
    CHECK_EQ_INT(r.params_size, MC_PARAMS_ENCODED_SIZE);
    CHECK(r.device_uid[0] == 0x11111111u && r.device_uid[2] == 0x33333333u);
    CHECK_EQ_INT(r.sample_rate_mhz, 100000);
    CHECK(memcmp(r.mag_name, "LIS3MDL\0\0\0\0\0", 12) == 0);
    CHECK(memcmp(r.acc_name, "MPU-6050\0\0\0\0", 12) == 0);
    CHECK_EQ_INT(r.sensor_id[MC_SENSOR_MAG], 0x3D);
    CHECK_EQ_INT(r.scale_den[MC_SENSOR_MAG], 6842);
    CHECK_EQ_INT(r.scale_unit[MC_SENSOR_MAG], MC_UNIT_GAUSS);
    CHECK_EQ_INT(r.fs_num[MC_SENSOR_GYR], 2000);
    CHECK_EQ_INT(r.scale_num[MC_SENSOR_GYR], 10);
    CHECK_EQ_INT(r.scale_den[MC_SENSOR_GYR], 164);
    CHECK_EQ_INT(r.scale_unit[MC_SENSOR_ACC], MC_UNIT_STANDARD_GRAVITY);

    R.ssim.describe_fails = 1;
    f = request(MC_MSG_INFO, 6u, NULL, 0u);
    CHECK_EQ_INT(mc_msg_info_resp_unpack(f.payload, f.len, &r), MC_OK);
    CHECK_EQ_INT(r.status, MC_E_SENSOR);
    CHECK_EQ_INT(r.params_size, MC_PARAMS_ENCODED_SIZE); /* the versions are still told */
    CHECK_EQ_INT(r.scale_den[MC_SENSOR_MAG], 0);
}

static void test_nacks_and_bad_frames(void)
{
    rig_boot(0);
    const uint8_t one[1] = {0u};
    rx_frame_t f = request(0x09u, 7u, NULL, 0u);
    check_nack(&f, 7u, MC_E_UNKNOWN_MESSAGE, 0x09u);
    f = request(0x00u, 8u, NULL, 0u);
    check_nack(&f, 8u, MC_E_UNKNOWN_MESSAGE, 0x00u);
    f = request(MC_MSG_HELLO_RESP, 9u, NULL, 0u); /* a device message sent to the device */
    check_nack(&f, 9u, MC_E_UNKNOWN_MESSAGE, MC_MSG_HELLO_RESP);
    f = request(MC_MSG_SAMPLE, 10u, NULL, 0u);
    check_nack(&f, 10u, MC_E_UNKNOWN_MESSAGE, MC_MSG_SAMPLE);
    f = request(MC_MSG_INFO, 11u, one, 1u);
    check_nack(&f, 11u, MC_E_LENGTH, MC_MSG_INFO);
    f = request(MC_MSG_HELLO, 12u, one, 1u);
    check_nack(&f, 12u, MC_E_LENGTH, MC_MSG_HELLO);
    f = request(MC_MSG_PARAM_SET, 13u, one, 1u); /* below its 2-byte minimum */
    check_nack(&f, 13u, MC_E_LENGTH, MC_MSG_PARAM_SET);
    f = request(MC_MSG_PARAM_GET, 14u, NULL, 0u);
    check_nack(&f, 14u, MC_E_LENGTH, MC_MSG_PARAM_GET);

    /* A nacked frame is not acted on, so its seq is not cached: the same seq is free. */
    f = request(MC_MSG_INFO, 11u, NULL, 0u);
    CHECK_EQ_INT(f.id, MC_MSG_INFO_RESP);

    /* Bad CRC, broken COBS, a runt: no answer; the next good frame is answered. */
    CHECK_EQ_INT(mc_frame_encode(MC_MSG_INFO, 20u, NULL, 0u, wire, sizeof wire, &wire_len),
                 MC_OK);
    wire[1] ^= 0x01u;
    send_raw(wire, wire_len);
    CHECK_EQ_INT(take_frames(), 0);
    const uint8_t broken[] = {0x07u, 0x02u, 0x00u}; /* the block promises 6 bytes */
    send_raw(broken, sizeof broken);
    const uint8_t runt[] = {0x03u, 0x02u, 0x01u, 0x00u};
    send_raw(runt, sizeof runt);
    CHECK_EQ_INT(take_frames(), 0);
    f = request(MC_MSG_INFO, 21u, NULL, 0u);
    CHECK_EQ_INT(f.id, MC_MSG_INFO_RESP);
    mc_device_stats_t st;
    CHECK_EQ_INT(mc_device_stats(&R.dev, &st), MC_OK);
    CHECK_EQ_INT(st.rx_crc, 1);
    CHECK_EQ_INT(st.rx_malformed, 2);
    CHECK_EQ_INT(st.nacks, 8);
}

static void test_retry_cache(void)
{
    uint8_t blob[MC_PARAMS_ENCODED_SIZE];
    uint8_t p[MC_FRAME_MAX_PAYLOAD], first[MC_FRAME_MAX_ENCODED];
    const mc_params_t good = good_params();
    rig_boot(0);
    encode(&good, blob);
    (void)hello(100u, 1u, 1u);

    /* param_set, then its retry: the same response bytes, and the staged set unchanged. */
    const size_t n = param_set_payload(MC_PARAMS_FORMAT_VERSION, blob, sizeof blob, p);
    send_frame(MC_MSG_PARAM_SET, 101u, p, n);
    const size_t first_len = R.link.len;
    memcpy(first, R.link.buf, first_len);
    R.link.len = 0u;
    send_frame(MC_MSG_PARAM_SET, 101u, p, n);
    CHECK_EQ_INT(R.link.len, first_len);
    CHECK(memcmp(R.link.buf, first, first_len) == 0);
    R.link.len = 0u;

    /* commit, lost response, retry: stored once (same flash programs, same sequence). */
    const uint32_t crc = mc_crc32_iso_hdlc(blob, sizeof blob);
    CHECK_EQ_INT(param_commit(102u, crc), MC_OK);
    const long programs = R.fsim.programs, erases = R.fsim.erases;
    CHECK_EQ_INT(param_commit(102u, crc), MC_OK);
    CHECK_EQ_INT(R.fsim.programs, programs);
    CHECK_EQ_INT(R.fsim.erases, erases);
    mc_storage_slot_t slot;
    uint32_t sequence;
    CHECK_EQ_INT(mc_storage_active(&R.dev.storage, &slot, &sequence), MC_OK);
    CHECK_EQ_INT(sequence, 1);

    /* The same seq with another id, or the same id and another body: E_SEQUENCE. */
    rx_frame_t f = request(MC_MSG_INFO, 102u, NULL, 0u);
    check_nack(&f, 102u, MC_E_SEQUENCE, MC_MSG_INFO);
    const uint8_t other[4] = {1u, 2u, 3u, 4u};
    f = request(MC_MSG_PARAM_COMMIT, 102u, other, 4u);
    check_nack(&f, 102u, MC_E_SEQUENCE, MC_MSG_PARAM_COMMIT);
    /* The cache still holds the commit: its retry is still answered. */
    CHECK_EQ_INT(param_commit(102u, crc), MC_OK);
    CHECK_EQ_INT(R.fsim.programs, programs);

    /* A stream_stop retry repeats its counts; the stream is not stopped twice. */
    CHECK_EQ_INT(stream_start(103u, MC_DEVICE_STREAM_RAW, 1u, 0u), MC_OK);
    samples(3u);
    CHECK_EQ_INT(take_frames(), 3);
    mc_msg_stream_stop_resp_t s = stream_stop(104u);
    CHECK_EQ_INT(s.sent, 3);
    s = stream_stop(104u);
    CHECK_EQ_INT(s.sent, 3);
    s = stream_stop(105u); /* a new request: nothing runs */
    CHECK_EQ_INT(s.sent, 0);

    /* hello is never cached and clears the cache: the old seq is acted on afresh. */
    (void)hello(105u, 1u, 1u);
    (void)hello(105u, 1u, 1u);
    CHECK_EQ_INT(param_commit(102u, crc), MC_OK);
    CHECK_EQ_INT(mc_storage_active(&R.dev.storage, &slot, &sequence), MC_OK);
    CHECK_EQ_INT(sequence, 2); /* stored again: acted on, not replayed */
    mc_device_stats_t st;
    CHECK_EQ_INT(mc_device_stats(&R.dev, &st), MC_OK);
    CHECK_EQ_INT(st.retries, 4);
}

static void test_param_flows(void)
{
    uint8_t blob[MC_PARAMS_ENCODED_SIZE], bad_blob[MC_PARAMS_ENCODED_SIZE];
    const mc_params_t good = good_params();
    mc_params_t bad;
    uint16_t seq = 200u;
    rig_boot(0);
    encode(&good, blob);
    const uint32_t crc = mc_crc32_iso_hdlc(blob, sizeof blob);

    mc_msg_param_get_resp_t g = param_get(seq++, MC_DEVICE_SET_ACTIVE);
    CHECK_EQ_INT(g.status, MC_E_NO_PARAMS);
    CHECK_EQ_INT(g.blob_len, 0);
    CHECK_EQ_INT(g.crc32, 0);
    g = param_get(seq++, MC_DEVICE_SET_STAGED);
    CHECK_EQ_INT(g.status, MC_E_NO_PARAMS);
    g = param_get(seq++, 2u);
    CHECK_EQ_INT(g.status, MC_E_RANGE);
    CHECK_EQ_INT(param_commit(seq++, crc), MC_E_STATE);

    /* Each refusal of param_set has its own code. */
    mc_msg_param_set_resp_t s = param_set(seq++, 2u, blob, sizeof blob);
    CHECK_EQ_INT(s.status, MC_E_VERSION);
    CHECK_EQ_INT(s.crc32, 0);
    s = param_set(seq++, MC_PARAMS_FORMAT_VERSION, blob, sizeof blob - 1u);
    CHECK_EQ_INT(s.status, MC_E_LENGTH);
    s = param_set(seq++, MC_PARAMS_FORMAT_VERSION, blob, 0u);
    CHECK_EQ_INT(s.status, MC_E_LENGTH);
    bad = good;
    bad.version = 2u;
    encode(&bad, bad_blob);
    s = param_set(seq++, MC_PARAMS_FORMAT_VERSION, bad_blob, sizeof bad_blob);
    CHECK_EQ_INT(s.status, MC_E_VERSION);
    bad = good;
    bad.d_inv_exp = 40;
    encode(&bad, bad_blob);
    s = param_set(seq++, MC_PARAMS_FORMAT_VERSION, bad_blob, sizeof bad_blob);
    CHECK_EQ_INT(s.status, MC_E_EXPONENT);
    bad = good;
    bad.offset[2] = MC_PARAMS_OFFSET_MAX_ABS + 1;
    encode(&bad, bad_blob);
    s = param_set(seq++, MC_PARAMS_FORMAT_VERSION, bad_blob, sizeof bad_blob);
    CHECK_EQ_INT(s.status, MC_E_RANGE);
    bad = good;
    memset(bad.d_inv, 0, sizeof bad.d_inv);
    encode(&bad, bad_blob);
    s = param_set(seq++, MC_PARAMS_FORMAT_VERSION, bad_blob, sizeof bad_blob);
    CHECK_EQ_INT(s.status, MC_E_SINGULAR);
    bad = good;
    memset(bad.d_inv, 0, sizeof bad.d_inv);
    bad.d_inv[0] = MC_PARAMS_D_INV_MAX_ABS;
    bad.d_inv[4] = MC_PARAMS_D_INV_MAX_ABS;
    bad.d_inv[8] = 1;
    encode(&bad, bad_blob);
    s = param_set(seq++, MC_PARAMS_FORMAT_VERSION, bad_blob, sizeof bad_blob);
    CHECK_EQ_INT(s.status, MC_E_CONDITION);

    /* Stage, read back bit for bit, a refusal clears it, stage again. */
    s = param_set(seq++, MC_PARAMS_FORMAT_VERSION, blob, sizeof blob);
    CHECK_EQ_INT(s.status, MC_OK);
    CHECK_EQ_INT(s.crc32, crc);
    g = param_get(seq++, MC_DEVICE_SET_STAGED);
    CHECK_EQ_INT(g.status, MC_OK);
    CHECK_EQ_INT(g.format_version, MC_PARAMS_FORMAT_VERSION);
    CHECK_EQ_INT(g.crc32, crc);
    CHECK_EQ_INT(g.blob_len, sizeof blob);
    CHECK(memcmp(g.blob, blob, sizeof blob) == 0);
    s = param_set(seq++, 2u, blob, sizeof blob);
    CHECK_EQ_INT(s.status, MC_E_VERSION);
    CHECK_EQ_INT(param_get(seq++, MC_DEVICE_SET_STAGED).status, MC_E_NO_PARAMS);
    CHECK_EQ_INT(param_commit(seq++, crc), MC_E_STATE);
    CHECK_EQ_INT(param_set(seq++, MC_PARAMS_FORMAT_VERSION, blob, sizeof blob).status, MC_OK);

    /* Commit: wrong CRC, flash failure (old record untouched), then stored. */
    CHECK_EQ_INT(param_commit(seq++, crc ^ 1u), MC_E_CRC);
    R.fsim.fail_erase = 1;
    CHECK_EQ_INT(param_commit(seq++, crc), MC_E_FLASH);
    R.fsim.fail_erase = 0;
    flash_sim_arm_cut(&R.fsim, 300, FLASH_SIM_TEAR_PARTIAL, FLASH_SIM_ERASE_FORWARD);
    CHECK_EQ_INT(param_commit(seq++, crc), MC_E_FLASH); /* power cut in the middle */
    flash_sim_power_on(&R.fsim);
    CHECK_EQ_INT(param_commit(seq++, crc), MC_OK);
    CHECK_EQ_INT(R.fsim.violations, 0);
    /* Not active before a reset; corrected streams still refused. */
    CHECK_EQ_INT(param_get(seq++, MC_DEVICE_SET_ACTIVE).status, MC_E_NO_PARAMS);
    CHECK_EQ_INT(stream_start(seq++, MC_DEVICE_STREAM_CORRECTED, 1u, 0u), MC_E_NO_PARAMS);
    CHECK_EQ_INT(param_get(seq++, MC_DEVICE_SET_STAGED).status, MC_OK);

    /* Reset: a wrong magic changes nothing; the right one resets after its response. */
    CHECK_EQ_INT(reset_req(seq++, 0x12345678u), MC_E_ARG);
    CHECK_EQ_INT(R.resets, 0);
    CHECK_EQ_INT(param_get(seq++, MC_DEVICE_SET_STAGED).status, MC_OK);
    CHECK_EQ_INT(stream_start(seq++, MC_DEVICE_STREAM_RAW, 1u, 0u), MC_OK);
    const uint16_t reset_seq = seq++;
    CHECK_EQ_INT(reset_req(reset_seq, MC_RESET_MAGIC), MC_OK);
    CHECK_EQ_INT(R.resets, 1);
    samples(2u);
    CHECK_EQ_INT(take_frames(), 0); /* no stream after a reset */
    CHECK_EQ_INT(param_get(seq++, MC_DEVICE_SET_STAGED).status, MC_E_NO_PARAMS);
    g = param_get(seq++, MC_DEVICE_SET_ACTIVE);
    CHECK_EQ_INT(g.status, MC_OK);
    CHECK_EQ_INT(g.crc32, crc);
    CHECK(memcmp(g.blob, blob, sizeof blob) == 0);
    /* Empty cache: a reset request with the same seq again is acted on again. */
    CHECK_EQ_INT(reset_req(reset_seq, MC_RESET_MAGIC), MC_OK);
    CHECK_EQ_INT(R.resets, 2);
    CHECK_EQ_INT(stream_stop(seq++).sent, 0);

    /* A reboot (power cycle) finds the committed set active too. */
    rig_boot(1);
    CHECK_EQ_INT(R.dev.load_status, MC_OK);
    g = param_get(1u, MC_DEVICE_SET_ACTIVE);
    CHECK_EQ_INT(g.status, MC_OK);
    CHECK(memcmp(g.blob, blob, sizeof blob) == 0);
    CHECK_EQ_INT(stream_start(2u, MC_DEVICE_STREAM_CORRECTED, 1u, 0u), MC_OK);
}

/* flash_sim's ops with reads that fail (MC_E_FLASH) from read number fail_from to fail_to
 * (exclusive, -1: on and on), counted by this wrapper; swapped into R.flash after boot. */
static long wrapped_reads, fail_from = -1, fail_to = -1;

static mc_status_t failing_read(void *ctx, uint32_t addr, uint8_t *buf, size_t len)
{
    const long n = wrapped_reads++;
    if (fail_from >= 0 && n >= fail_from && (fail_to < 0 || n < fail_to)) {
        return MC_E_FLASH;
    }
    return flash_sim_read(ctx, addr, buf, len);
}

static const mc_flash_ops_t failing_ops = {flash_sim_erase_page, flash_sim_program_word,
                                           failing_read};

/* Commits blob with its last read failing (once, or on and on) and returns the answer. The
 * read count comes from a clean commit of the same blob over the same flash contents. */
static int commit_with_late_read_failure(uint16_t seq, uint32_t crc, int persistent)
{
    static uint8_t snapshot[FLASH_SIM_MAX_BYTES];
    memcpy(snapshot, R.fsim.mem, sizeof snapshot);
    wrapped_reads = 0;
    fail_from = -1;
    CHECK_EQ_INT(param_commit(seq, crc), MC_OK);
    const long reads = wrapped_reads;
    memcpy(R.fsim.mem, snapshot, sizeof snapshot);
    wrapped_reads = 0;
    fail_from = reads - 1; /* the final scan of the new slot: after the commit point */
    fail_to = persistent ? -1 : reads;
    const int st = param_commit((uint16_t)(seq + 1u), crc);
    fail_from = -1;
    return st;
}

/*
 * param_commit answers what flash holds: a read failing after the commit point (the marker
 * is complete) is settled by the storage's rescan as committed (OK), and when the flash
 * cannot be read back at all the answer is E_OUTCOME_UNKNOWN, never a definite E_FLASH;
 * E_FLASH only when the old set certainly still wins.
 */
static void test_commit_outcome(void)
{
    uint8_t blob[MC_PARAMS_ENCODED_SIZE], blob2[MC_PARAMS_ENCODED_SIZE];
    mc_params_t p = good_params();
    uint16_t seq = 900u;
    rig_boot(0);
    R.flash.ops = &failing_ops; /* the device's storage holds &R.flash */
    encode(&p, blob);
    const uint32_t crc = mc_crc32_iso_hdlc(blob, sizeof blob);
    CHECK_EQ_INT(param_set(seq++, MC_PARAMS_FORMAT_VERSION, blob, sizeof blob).status, MC_OK);
    CHECK_EQ_INT(param_commit(seq++, crc), MC_OK); /* set 1 stored */

    /* Set 2 with one failing read in the commit's final scan: committed, and said so. */
    p.offset[0] = 7 * 32768;
    encode(&p, blob2);
    const uint32_t crc2 = mc_crc32_iso_hdlc(blob2, sizeof blob2);
    CHECK_EQ_INT(param_set(seq++, MC_PARAMS_FORMAT_VERSION, blob2, sizeof blob2).status, MC_OK);
    CHECK_EQ_INT(commit_with_late_read_failure(seq, crc2, 0), MC_OK);
    seq = (uint16_t)(seq + 2u);
    CHECK_EQ_INT(reset_req(seq++, MC_RESET_MAGIC), MC_OK);
    mc_msg_param_get_resp_t g = param_get(seq++, MC_DEVICE_SET_ACTIVE);
    CHECK_EQ_INT(g.status, MC_OK);
    CHECK_EQ_INT(g.crc32, crc2);

    /* Set 1 again, the flash unreadable from the final scan on: the outcome is unknown. */
    CHECK_EQ_INT(param_set(seq++, MC_PARAMS_FORMAT_VERSION, blob, sizeof blob).status, MC_OK);
    CHECK_EQ_INT(commit_with_late_read_failure(seq, crc, 1), MC_E_OUTCOME_UNKNOWN);
    seq = (uint16_t)(seq + 2u);
    CHECK_EQ_INT(reset_req(seq++, MC_RESET_MAGIC), MC_OK);
    g = param_get(seq++, MC_DEVICE_SET_ACTIVE);
    CHECK_EQ_INT(g.status, MC_OK);
    CHECK_EQ_INT(g.crc32, crc); /* here the new one had won */

    /* A failure before the commit point is definite, the old set still active. */
    CHECK_EQ_INT(param_set(seq++, MC_PARAMS_FORMAT_VERSION, blob2, sizeof blob2).status, MC_OK);
    R.fsim.fail_erase = 1;
    CHECK_EQ_INT(param_commit(seq++, crc2), MC_E_FLASH);
    R.fsim.fail_erase = 0;
    CHECK_EQ_INT(reset_req(seq++, MC_RESET_MAGIC), MC_OK);
    CHECK_EQ_INT(param_get(seq++, MC_DEVICE_SET_ACTIVE).crc32, crc);
    CHECK_EQ_INT(R.fsim.violations, 0);
    R.flash.ops = &flash_sim_ops;
}

/* A stored sequence of 0xFFFFFFFF: param_commit says E_RANGE (not E_FLASH), nothing written. */
static void test_commit_sequence_exhausted(void)
{
    uint8_t blob[MC_PARAMS_ENCODED_SIZE];
    const mc_params_t p = good_params();
    uint16_t seq = 950u;
    rig_boot(0);
    encode(&p, blob);
    const uint32_t crc = mc_crc32_iso_hdlc(blob, sizeof blob);
    CHECK_EQ_INT(param_set(seq++, MC_PARAMS_FORMAT_VERSION, blob, sizeof blob).status, MC_OK);
    CHECK_EQ_INT(param_commit(seq++, crc), MC_OK); /* slot A, page 0, sequence 1 */
    /* Rewrite its sequence field to 0xFFFFFFFF and its CRC to match (storage.h's layout). */
    const uint32_t body = MC_STORAGE_HEADER_SIZE + ((MC_PARAMS_ENCODED_SIZE + 3u) & ~3u);
    memset(R.fsim.mem + 8, 0xFF, 4);
    const uint32_t rec_crc = mc_crc32_iso_hdlc(R.fsim.mem, body);
    for (unsigned i = 0; i < 4u; ++i) {
        R.fsim.mem[body + i] = (uint8_t)(rec_crc >> (8u * i));
    }
    static uint8_t snapshot[FLASH_SIM_MAX_BYTES];
    memcpy(snapshot, R.fsim.mem, sizeof snapshot);
    const long programs = R.fsim.programs, erases = R.fsim.erases;
    CHECK_EQ_INT(param_commit(seq++, crc), MC_E_RANGE);
    CHECK_EQ_INT(R.fsim.programs, programs);
    CHECK_EQ_INT(R.fsim.erases, erases);
    CHECK(memcmp(snapshot, R.fsim.mem, sizeof snapshot) == 0);
    rig_boot(1); /* the record is still valid and loads */
    CHECK_EQ_INT(R.dev.load_status, MC_OK);
}

static void test_streams(void)
{
    mc_raw_sample_t want;
    mc_msg_sample_t m;
    rig_boot(0);
    CHECK_EQ_INT(stream_start(300u, 2u, 1u, 0u), MC_E_RANGE);
    CHECK_EQ_INT(stream_start(301u, MC_DEVICE_STREAM_RAW, 0u, 0u), MC_E_RANGE);
    CHECK_EQ_INT(stream_start(302u, MC_DEVICE_STREAM_CORRECTED, 1u, 0u), MC_E_NO_PARAMS);
    samples(2u); /* no stream: discarded */
    CHECK_EQ_INT(take_frames(), 0);

    CHECK_EQ_INT(stream_start(303u, MC_DEVICE_STREAM_RAW, 1u, 0u), MC_OK);
    const uint32_t first = R.reads;
    samples(5u);
    CHECK_EQ_INT(take_frames(), 5);
    for (uint32_t k = 0; k < 5u; ++k) {
        CHECK_EQ_INT(got[k].id, MC_MSG_SAMPLE);
        CHECK_EQ_INT(got[k].seq, 303);
        CHECK_EQ_INT(mc_msg_sample_unpack(got[k].payload, got[k].len, &m), MC_OK);
        CHECK_EQ_INT(m.seq, first + k);
        CHECK_EQ_INT(m.t_us, R.ssim.t0_us + (uint64_t)(first + k) * R.ssim.period_us);
        sensor_sim_expected(first + k, &want);
        CHECK(memcmp(m.mag, want.mag, sizeof m.mag) == 0);
        CHECK(memcmp(m.acc, want.acc, sizeof m.acc) == 0);
        CHECK(memcmp(m.gyr, want.gyr, sizeof m.gyr) == 0);
    }
    /* A refused start leaves the stream running. */
    CHECK_EQ_INT(stream_start(304u, MC_DEVICE_STREAM_RAW, 0u, 0u), MC_E_RANGE);
    samples(1u);
    CHECK_EQ_INT(take_frames(), 1);
    CHECK_EQ_INT(got[0].seq, 303);

    /* A new start replaces it: decimation 3, count 4, its own seq. */
    CHECK_EQ_INT(stream_start(305u, MC_DEVICE_STREAM_RAW, 3u, 4u), MC_OK);
    const uint32_t base = R.reads;
    samples(20u);
    CHECK_EQ_INT(take_frames(), 4);
    for (uint32_t k = 0; k < 4u; ++k) {
        CHECK_EQ_INT(got[k].seq, 305);
        CHECK_EQ_INT(mc_msg_sample_unpack(got[k].payload, got[k].len, &m), MC_OK);
        CHECK_EQ_INT(m.seq, base + 3u * k);
    }
    mc_msg_stream_stop_resp_t s = stream_stop(306u);
    CHECK_EQ_INT(s.sent, 4);
    CHECK_EQ_INT(s.dropped, 0);
    CHECK_EQ_INT(stream_stop(307u).sent, 0);

    /* Samples lost in the ring (the main loop too slow) count as dropped. */
    CHECK_EQ_INT(stream_start(308u, MC_DEVICE_STREAM_RAW, 1u, 0u), MC_OK);
    for (uint32_t i = 0; i < MC_RING_CAPACITY + 6u; ++i) {
        (void)mc_device_sample(&R.dev);
    }
    CHECK_EQ_INT(mc_device_poll(&R.dev), MC_OK);
    CHECK_EQ_INT(take_frames(), MC_RING_CAPACITY);
    s = stream_stop(309u);
    CHECK_EQ_INT(s.sent, MC_RING_CAPACITY);
    CHECK_EQ_INT(s.dropped, 6);
    R.reads += MC_RING_CAPACITY + 6u;

    /* With decimation, dropped counts MESSAGES: due samples (seq first + 3k) that were lost,
     * not every sample the ring lost; and it equals what the host's seq gaps show. */
    const uint32_t dec = 3u, lost = 10u, after = 9u;
    CHECK_EQ_INT(stream_start(310u, MC_DEVICE_STREAM_RAW, (uint16_t)dec, 0u), MC_OK);
    const uint32_t d0 = R.reads;
    for (uint32_t i = 0; i < MC_RING_CAPACITY + lost; ++i) {
        (void)mc_device_sample(&R.dev);
    }
    R.reads += MC_RING_CAPACITY + lost;
    CHECK_EQ_INT(mc_device_poll(&R.dev), MC_OK);
    samples(after);
    uint32_t want_sent = 0u, want_dropped = 0u;
    for (uint32_t k = 0; k < MC_RING_CAPACITY + lost + after; ++k) {
        if (k % dec == 0u) {
            const int in_ring_loss = k >= MC_RING_CAPACITY && k < MC_RING_CAPACITY + lost;
            want_sent += in_ring_loss ? 0u : 1u;
            want_dropped += in_ring_loss ? 1u : 0u;
        }
    }
    const size_t n = take_frames();
    CHECK_EQ_INT(n, want_sent);
    uint32_t gap_messages = 0u, prev = d0;
    for (size_t k = 0; k < n; ++k) {
        CHECK_EQ_INT(mc_msg_sample_unpack(got[k].payload, got[k].len, &m), MC_OK);
        CHECK_EQ_INT((m.seq - d0) % dec, 0);
        if (k > 0u) {
            gap_messages += (m.seq - prev) / dec - 1u;
        }
        prev = m.seq;
    }
    CHECK_EQ_INT(gap_messages, want_dropped);
    CHECK(want_dropped > 0u && want_dropped < lost);
    /* Then the main loop stalls until the stop: a ring full of unseen samples (neither sent
     * nor dropped) and `lost` more lost after them, of which the due ones are dropped. */
    const uint32_t k0 = MC_RING_CAPACITY + lost + after;
    for (uint32_t i = 0; i < MC_RING_CAPACITY + lost; ++i) {
        (void)mc_device_sample(&R.dev);
        const uint32_t k = k0 + i;
        want_dropped += i >= MC_RING_CAPACITY && k % dec == 0u ? 1u : 0u;
    }
    R.reads += MC_RING_CAPACITY + lost;
    s = stream_stop(311u);
    CHECK_EQ_INT(s.sent, want_sent);
    CHECK_EQ_INT(s.dropped, want_dropped);
    CHECK(want_dropped > gap_messages);
    CHECK_EQ_INT(mc_device_poll(&R.dev), MC_OK); /* the queued ones: no stream, discarded */
    CHECK_EQ_INT(take_frames(), 0);

    /* A stream that saw nothing: every sample lost after its start is its own. */
    CHECK_EQ_INT(stream_start(312u, MC_DEVICE_STREAM_RAW, (uint16_t)dec, 0u), MC_OK);
    for (uint32_t i = 0; i < MC_RING_CAPACITY + lost; ++i) {
        (void)mc_device_sample(&R.dev);
    }
    R.reads += MC_RING_CAPACITY + lost;
    want_dropped = 0u;
    for (uint32_t i = MC_RING_CAPACITY; i < MC_RING_CAPACITY + lost; ++i) {
        want_dropped += i % dec == 0u ? 1u : 0u;
    }
    s = stream_stop(313u);
    CHECK_EQ_INT(s.sent, 0);
    CHECK_EQ_INT(s.dropped, want_dropped);
    CHECK_EQ_INT(mc_device_poll(&R.dev), MC_OK);
    CHECK_EQ_INT(take_frames(), 0);
}

static void test_corrected_stream(void)
{
    uint8_t blob[MC_PARAMS_ENCODED_SIZE];
    const mc_params_t good = good_params();
    mc_correction_t c;
    mc_msg_corrected_t m;
    mc_raw_sample_t want;
    int32_t out[3];
    rig_boot(0);
    encode(&good, blob);
    CHECK_EQ_INT(param_set(1u, MC_PARAMS_FORMAT_VERSION, blob, sizeof blob).status, MC_OK);
    CHECK_EQ_INT(param_commit(2u, mc_crc32_iso_hdlc(blob, sizeof blob)), MC_OK);
    CHECK_EQ_INT(reset_req(3u, MC_RESET_MAGIC), MC_OK);
    CHECK_EQ_INT(mc_correction_init(&c, &good), MC_OK);
    CHECK_EQ_INT(stream_start(4u, MC_DEVICE_STREAM_CORRECTED, 2u, 10u), MC_OK);
    const uint32_t base = R.reads;
    samples(40u);
    CHECK_EQ_INT(take_frames(), 10);
    for (uint32_t k = 0; k < 10u; ++k) {
        CHECK_EQ_INT(got[k].id, MC_MSG_CORRECTED);
        CHECK_EQ_INT(got[k].seq, 4);
        CHECK_EQ_INT(mc_msg_corrected_unpack(got[k].payload, got[k].len, &m), MC_OK);
        CHECK_EQ_INT(m.seq, base + 2u * k);
        sensor_sim_expected(base + 2u * k, &want);
        CHECK(memcmp(m.mag, want.mag, sizeof m.mag) == 0);
        CHECK_EQ_INT(m.out_exp, good.out_exp);
        CHECK_EQ_INT(mc_correction_apply(&c, want.mag, out), MC_OK);
        CHECK(m.m_b[0] == out[0] && m.m_b[1] == out[1] && m.m_b[2] == out[2]);
    }
    const mc_msg_stream_stop_resp_t s = stream_stop(5u);
    CHECK_EQ_INT(s.sent, 10);
    CHECK_EQ_INT(s.dropped, 0);
}

static void test_full_link(void)
{
    mc_msg_sample_t m;
    rig_boot(0);
    CHECK_EQ_INT(stream_start(400u, MC_DEVICE_STREAM_RAW, 1u, 0u), MC_OK);

    /* A link that takes nothing: every message dropped whole, counted. */
    R.link.room = 0;
    samples(5u);
    CHECK_EQ_INT(R.link.len, 0);
    CHECK(!mc_device_tx_pending(&R.dev));
    R.link.room = -1;
    samples(2u);
    CHECK_EQ_INT(take_frames(), 2);
    CHECK_EQ_INT(mc_msg_sample_unpack(got[0].payload, got[0].len, &m), MC_OK);
    CHECK_EQ_INT(m.seq, 5); /* the gap shows the 5 drops */

    /* A link that takes part of a frame: the rest is pending and sent first, never torn;
     * samples due meanwhile are dropped. */
    R.link.room = 10;
    samples(4u);
    CHECK(mc_device_tx_pending(&R.dev));
    CHECK_EQ_INT(R.link.len, 10);
    R.link.room = -1;
    CHECK_EQ_INT(mc_device_poll(&R.dev), MC_OK);
    CHECK(!mc_device_tx_pending(&R.dev));
    CHECK_EQ_INT(take_frames(), 1);
    CHECK_EQ_INT(mc_msg_sample_unpack(got[0].payload, got[0].len, &m), MC_OK);
    CHECK_EQ_INT(m.seq, 7);

    /* Responses are never dropped: two requests in one buffer, a link taking 3 bytes. The
     * device stops using input while the first response is pending. */
    uint8_t two[2 * MC_FRAME_MAX_ENCODED];
    size_t a = 0u, b = 0u;
    CHECK_EQ_INT(mc_frame_encode(MC_MSG_INFO, 401u, NULL, 0u, two, sizeof two, &a), MC_OK);
    const uint8_t which[1] = {0u};
    CHECK_EQ_INT(mc_frame_encode(MC_MSG_PARAM_GET, 402u, which, 1u, two + a, sizeof two - a, &b),
                 MC_OK);
    R.link.room = 3;
    const size_t used = mc_device_rx_bytes(&R.dev, two, a + b);
    CHECK_EQ_INT(used, a);
    CHECK(mc_device_tx_pending(&R.dev));
    samples(1u); /* a stream sample due now is dropped */
    R.link.room = -1;
    CHECK_EQ_INT(mc_device_poll(&R.dev), MC_OK);
    CHECK_EQ_INT(mc_device_rx_bytes(&R.dev, two + used, a + b - used), a + b - used);
    CHECK_EQ_INT(take_frames(), 2);
    CHECK_EQ_INT(got[0].id, MC_MSG_INFO_RESP);
    CHECK_EQ_INT(got[0].len, MC_MSG_INFO_RESP_SIZE);
    CHECK_EQ_INT(got[1].id, MC_MSG_PARAM_GET_RESP);

    const mc_msg_stream_stop_resp_t s = stream_stop(403u);
    CHECK_EQ_INT(s.sent, 3);
    CHECK_EQ_INT(s.dropped, 5 + 3 + 1);
    mc_device_stats_t st;
    CHECK_EQ_INT(mc_device_stats(&R.dev, &st), MC_OK);
    CHECK_EQ_INT(st.stream_dropped, 9);
    CHECK_EQ_INT(st.stream_sent, 3);

    /* A reset whose response is held back happens once the response is out. */
    uint8_t p[4];
    size_t n;
    mc_msg_reset_t r = {MC_RESET_MAGIC};
    CHECK_EQ_INT(mc_msg_reset_pack(&r, p, sizeof p, &n), MC_OK);
    R.link.room = 2;
    send_frame(MC_MSG_RESET, 404u, p, n);
    CHECK_EQ_INT(R.resets, 0);
    R.link.room = -1;
    CHECK_EQ_INT(mc_device_poll(&R.dev), MC_OK);
    CHECK_EQ_INT(R.resets, 1);
    CHECK_EQ_INT(take_frames(), 1);
    CHECK_EQ_INT(status_of(&got[0], MC_MSG_RESET_RESP, 404u), MC_OK);

    /* A new link never sees the tail of a frame meant for the old one. */
    CHECK_EQ_INT(stream_start(405u, MC_DEVICE_STREAM_RAW, 1u, 0u), MC_OK);
    R.link.room = 7;
    samples(1u);
    CHECK(mc_device_tx_pending(&R.dev));
    R.link.len = 0u;
    R.link.room = -1;
    CHECK_EQ_INT(mc_device_link_reset(&R.dev), MC_OK);
    CHECK(!mc_device_tx_pending(&R.dev));
    samples(1u);
    CHECK_EQ_INT(take_frames(), 1);
}

int main(void)
{
    test_init_args();
    test_hello_and_info();
    test_nacks_and_bad_frames();
    test_retry_cache();
    test_param_flows();
    test_commit_outcome();
    test_commit_sequence_exhausted();
    test_streams();
    test_corrected_stream();
    test_full_link();
    return check_summary("test_fw_device");
}
