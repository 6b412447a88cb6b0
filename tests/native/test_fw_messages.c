/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The generated message codec (messages.h): the unit table agrees with sensor_hal.h, every
 * message's pack/unpack checks its arguments, the room at out and the payload size, and the
 * golden vectors round-trip at every truncation.
 */
#include "check.h"
#include "magcal/messages.h"
#include "magcal/sensor_hal.h"

#include "../../protocol/vectors/vectors.h"

#include <string.h>

static void test_units_match_schema(void)
{
    for (size_t i = 0; i < MC_VEC_N_UNITS; ++i) {
        CHECK_EQ_INT(mc_vec_units[i][0], mc_vec_units[i][1]);
    }
}

static void test_sizes_and_names(void)
{
    size_t lo = 0, hi = 0;
    CHECK_EQ_INT(mc_msg_payload_size(MC_MSG_SAMPLE, &lo, &hi), MC_OK);
    CHECK(lo == MC_MSG_SAMPLE_SIZE && hi == MC_MSG_SAMPLE_SIZE && lo == 30u);
    CHECK_EQ_INT(mc_msg_payload_size(MC_MSG_PARAM_SET, &lo, NULL), MC_OK);
    CHECK_EQ_INT(lo, MC_MSG_PARAM_SET_MIN_SIZE);
    CHECK_EQ_INT(mc_msg_payload_size(MC_MSG_PARAM_SET, NULL, &hi), MC_OK);
    CHECK_EQ_INT(hi, MC_MSG_PARAM_SET_MAX_SIZE);
    CHECK(MC_MSG_PARAM_SET_BLOB_MAX >= 128u); /* a stored payload (MC_STORAGE_PAYLOAD_MAX) */
    CHECK_EQ_INT(mc_msg_payload_size(0x7E, &lo, &hi), MC_E_UNKNOWN_MESSAGE);
    CHECK(mc_msg_name(0x7E) == NULL);
    CHECK(strcmp(mc_msg_name(MC_MSG_CORRECTED), "corrected") == 0);
    /* Every message fits a frame. */
    for (unsigned id = 0; id < 256u; ++id) {
        if (mc_msg_payload_size((uint8_t)id, &lo, &hi) == MC_OK) {
            CHECK(lo <= hi && hi <= MC_FRAME_MAX_PAYLOAD);
        }
    }
}

static void test_arguments(void)
{
    mc_msg_sample_t s;
    uint8_t out[MC_FRAME_MAX_PAYLOAD];
    size_t n = 99;
    memset(&s, 0, sizeof s);
    CHECK_EQ_INT(mc_msg_sample_pack(NULL, out, sizeof out, &n), MC_E_ARG);
    CHECK_EQ_INT(n, 0);
    CHECK_EQ_INT(mc_msg_sample_pack(&s, NULL, sizeof out, &n), MC_E_ARG);
    CHECK_EQ_INT(mc_msg_sample_pack(&s, out, sizeof out, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_msg_sample_pack(&s, out, MC_MSG_SAMPLE_SIZE - 1, &n), MC_E_NO_SPACE);
    CHECK_EQ_INT(mc_msg_sample_pack(&s, out, MC_MSG_SAMPLE_SIZE, &n), MC_OK);
    CHECK_EQ_INT(n, MC_MSG_SAMPLE_SIZE);
    CHECK_EQ_INT(mc_msg_sample_unpack(NULL, 3, &s), MC_E_ARG);
    CHECK_EQ_INT(mc_msg_sample_unpack(out, MC_MSG_SAMPLE_SIZE, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_msg_sample_unpack(out, MC_MSG_SAMPLE_SIZE + 1, &s), MC_E_LENGTH);
    CHECK_EQ_INT(mc_msg_sample_unpack(NULL, 0, &s), MC_E_LENGTH);

    /* Messages without fields: payload NULL with length 0 is fine. */
    mc_msg_info_t info;
    CHECK_EQ_INT(mc_msg_info_unpack(NULL, 0, &info), MC_OK);
    CHECK_EQ_INT(mc_msg_info_pack(&info, out, 0, &n), MC_OK);
    CHECK_EQ_INT(n, 0);
    CHECK_EQ_INT(mc_msg_info_unpack(out, 1, &info), MC_E_LENGTH);

    /* A bytes field longer than its maximum is refused; the maximum is packed. */
    static mc_msg_param_set_t ps;
    memset(&ps, 0, sizeof ps);
    ps.blob_len = MC_MSG_PARAM_SET_BLOB_MAX + 1;
    CHECK_EQ_INT(mc_msg_param_set_pack(&ps, out, sizeof out, &n), MC_E_RANGE);
    ps.blob_len = MC_MSG_PARAM_SET_BLOB_MAX;
    CHECK_EQ_INT(mc_msg_param_set_pack(&ps, out, MC_MSG_PARAM_SET_MAX_SIZE - 1, &n), MC_E_NO_SPACE);
    CHECK_EQ_INT(mc_msg_param_set_pack(&ps, out, sizeof out, &n), MC_OK);
    CHECK_EQ_INT(n, MC_MSG_PARAM_SET_MAX_SIZE);
    CHECK_EQ_INT(mc_msg_param_set_unpack(out, MC_MSG_PARAM_SET_MIN_SIZE - 1, &ps), MC_E_LENGTH);
    CHECK_EQ_INT(mc_msg_param_set_unpack(out, MC_MSG_PARAM_SET_MAX_SIZE + 1, &ps), MC_E_LENGTH);
    CHECK_EQ_INT(mc_msg_param_set_unpack(out, MC_MSG_PARAM_SET_MIN_SIZE, &ps), MC_OK);
    CHECK_EQ_INT(ps.blob_len, 0);

    /* Generic forms. */
    mc_msg_t m;
    memset(&m, 0, sizeof m);
    CHECK_EQ_INT(mc_msg_pack(NULL, out, sizeof out, &n), MC_E_ARG);
    m.id = 0x7E;
    CHECK_EQ_INT(mc_msg_pack(&m, out, sizeof out, &n), MC_E_UNKNOWN_MESSAGE);
    CHECK_EQ_INT(mc_msg_unpack(0x7E, out, 0, &m), MC_E_UNKNOWN_MESSAGE);
    CHECK_EQ_INT(mc_msg_unpack(MC_MSG_HELLO, out, 4, NULL), MC_E_ARG);
}

/* Each vector: unpack at every shorter (and one longer) length fails with MC_E_LENGTH unless
 * the message has a bytes field and the length is within its bounds; pack with every smaller
 * cap fails with MC_E_NO_SPACE. */
static void test_vectors_truncated(void)
{
    for (size_t v = 0; v < MC_VEC_N_MESSAGES; ++v) {
        const mc_vec_message_t *vec = &mc_vec_messages[v];
        size_t lo = 0, hi = 0;
        CHECK_EQ_INT(mc_msg_payload_size(vec->id, &lo, &hi), MC_OK);
        uint8_t buf[MC_FRAME_MAX_PAYLOAD + 1];
        memset(buf, 0x5A, sizeof buf);
        memcpy(buf, vec->payload, vec->payload_len);
        int ok = 1;
        for (size_t len = 0; len <= vec->payload_len + 1; ++len) {
            mc_msg_t m;
            const mc_status_t want = (len >= lo && len <= hi) ? MC_OK : MC_E_LENGTH;
            ok &= mc_msg_unpack(vec->id, buf, len, &m) == want;
        }
        for (size_t cap = 0; cap < vec->payload_len; ++cap) {
            size_t n = 99;
            ok &= mc_msg_pack(&vec->msg, buf, cap, &n) == MC_E_NO_SPACE && n == 0;
        }
        CHECK(ok);
    }
}

/* Signed extremes and 64-bit timestamps survive a round trip bit-exactly. */
static void test_extremes(void)
{
    mc_msg_corrected_t c, back;
    uint8_t out[MC_MSG_CORRECTED_SIZE];
    size_t n = 0;
    memset(&c, 0, sizeof c);
    c.seq = 0xFFFFFFFFu;
    c.t_us = UINT64_C(0xFEDCBA9876543210);
    c.mag[0] = INT16_MIN;
    c.mag[1] = INT16_MAX;
    c.mag[2] = -1;
    c.out_exp = INT8_MIN;
    c.m_b[0] = INT32_MIN;
    c.m_b[1] = INT32_MAX;
    c.m_b[2] = -1;
    CHECK_EQ_INT(mc_msg_corrected_pack(&c, out, sizeof out, &n), MC_OK);
    CHECK_EQ_INT(out[4], 0x10); /* t_us little-endian after seq */
    CHECK_EQ_INT(out[11], 0xFE);
    CHECK_EQ_INT(mc_msg_corrected_unpack(out, n, &back), MC_OK);
    CHECK(back.seq == c.seq && back.t_us == c.t_us);
    CHECK(back.mag[0] == INT16_MIN && back.mag[1] == INT16_MAX && back.mag[2] == -1);
    CHECK(back.out_exp == INT8_MIN);
    CHECK(back.m_b[0] == INT32_MIN && back.m_b[1] == INT32_MAX && back.m_b[2] == -1);
}

int main(void)
{
    test_units_match_schema();
    test_sizes_and_names();
    test_arguments();
    test_vectors_truncated();
    test_extremes();
    return check_summary("test_fw_messages");
}
