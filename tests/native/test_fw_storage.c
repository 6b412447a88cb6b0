/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Parameter storage (storage.h) on the RAM flash of flash_sim.h:
 *   - power loss: a commit is cut at EVERY byte step (program and erase), with the cut byte
 *     untouched or half done, for three erase orders, after 0 to 3 earlier commits; each time
 *     a fresh mc_storage_t "boots" over the same flash and must load exactly the old payload
 *     or exactly the new one (none only if nothing was ever written), and a later commit must
 *     succeed and win;
 *   - the on-flash layout against an independent encoder written here from storage.h's table;
 *   - corruption of any byte of the best record falls back to the other slot;
 *   - flash errors (erase failure, programs silently dropped), sequence limit, tie, argument
 *     errors, the payload size limits, and the format version passed through.
 */
#include "check.h"
#include "flash_sim.h"
#include "magcal/crc.h"
#include "magcal/storage.h"

#include <stdio.h>
#include <string.h>

#define PAGE_SIZE 128u
#define PAGE_COUNT 8u
#define SLOT_A_PAGE 1u
#define SLOT_B_PAGE 4u
#define PAGES_PER_SLOT 2u
#define SLOT_A_ADDR (SLOT_A_PAGE * PAGE_SIZE)
#define SLOT_B_ADDR (SLOT_B_PAGE * PAGE_SIZE)

/* Static: the sim holds 4 KB and the sweeps keep snapshots. */
static flash_sim_t sim;
static mc_flash_t flash;

/* ------------------------------------------------------------------ payloads */

#define N_PAYLOADS 6
/* Lengths chosen for coverage: the maximum, odd lengths (padding), a single byte, and a short
 * record over a slot that held a long one. */
static const size_t payload_len[N_PAYLOADS] = {MC_STORAGE_PAYLOAD_MAX, 37, 1, 100, 64, 3};
static uint8_t payloads[N_PAYLOADS][MC_STORAGE_PAYLOAD_MAX];

static uint16_t payload_format(int i)
{
    return (uint16_t)(0x0100 + i);
}

static void make_payloads(void)
{
    for (int i = 0; i < N_PAYLOADS; ++i) {
        for (size_t j = 0; j < MC_STORAGE_PAYLOAD_MAX; ++j) {
            /* Distinct per payload, and containing 0x00 and 0xFF bytes. */
            payloads[i][j] = (uint8_t)((i * 31 + (int)j * 7 + 1) * (j % 5 == 0 ? 0 : 1)
                                       + (j % 11 == 0 ? 0xFF : 0));
        }
    }
}

static mc_status_t commit_payload(mc_storage_t *st, int i)
{
    return mc_storage_commit(st, payloads[i], payload_len[i], payload_format(i));
}

/* ------------------------------------------------------------------ boot helpers */

typedef struct {
    mc_status_t status;
    size_t len;
    uint16_t format;
    uint32_t sequence;
    uint8_t data[MC_STORAGE_PAYLOAD_MAX];
} loaded_t;

/* What a device does after reset: a fresh instance over the flash as it is, then load. */
static loaded_t boot_and_load(void)
{
    loaded_t l;
    memset(&l, 0, sizeof l);
    mc_storage_t st;
    l.status = mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT);
    if (l.status == MC_OK) {
        l.status = mc_storage_load(&st, l.data, sizeof l.data, &l.len, &l.format, &l.sequence);
    }
    return l;
}

static int is_payload(const loaded_t *l, int i, uint32_t sequence)
{
    return l->status == MC_OK && l->len == payload_len[i] && l->format == payload_format(i)
           && l->sequence == sequence && memcmp(l->data, payloads[i], l->len) == 0;
}

/* Pages outside the slots hold a pattern the storage must never touch. */
static void fill_canaries(void)
{
    for (uint32_t p = 0; p < PAGE_COUNT; ++p) {
        const int in_a = p >= SLOT_A_PAGE && p < SLOT_A_PAGE + PAGES_PER_SLOT;
        const int in_b = p >= SLOT_B_PAGE && p < SLOT_B_PAGE + PAGES_PER_SLOT;
        if (!in_a && !in_b) {
            for (uint32_t i = 0; i < PAGE_SIZE; ++i) {
                sim.mem[p * PAGE_SIZE + i] = (uint8_t)(0xA5u ^ i ^ p);
            }
        }
    }
}

static int canaries_intact(void)
{
    for (uint32_t p = 0; p < PAGE_COUNT; ++p) {
        const int in_a = p >= SLOT_A_PAGE && p < SLOT_A_PAGE + PAGES_PER_SLOT;
        const int in_b = p >= SLOT_B_PAGE && p < SLOT_B_PAGE + PAGES_PER_SLOT;
        for (uint32_t i = 0; !in_a && !in_b && i < PAGE_SIZE; ++i) {
            if (sim.mem[p * PAGE_SIZE + i] != (uint8_t)(0xA5u ^ i ^ p)) {
                return 0;
            }
        }
    }
    return 1;
}

/* A blank flash with canaries, then `history` successful commits of payloads 0 .. history-1. */
static void build_history(int history)
{
    flash_sim_init(&sim, &flash, PAGE_SIZE, PAGE_COUNT);
    fill_canaries();
    mc_storage_t st;
    CHECK_EQ_INT(mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT), MC_OK);
    for (int i = 0; i < history; ++i) {
        CHECK_EQ_INT(commit_payload(&st, i), MC_OK);
    }
}

/* ------------------------------------------------------------------ independent encoder */

static void put32(uint8_t *b, uint32_t w)
{
    for (int i = 0; i < 4; ++i) {
        b[i] = (uint8_t)(w >> (8 * i));
    }
}

/* The record of storage.h's table, built from the table alone. Returns its size. */
static size_t encode_record(uint8_t *out, uint32_t sequence, uint16_t format, const uint8_t *p,
                            size_t n, uint32_t marker)
{
    const size_t padded = (n + 3u) / 4u * 4u;
    put32(out, 0x5350434Du);
    out[4] = 1;
    out[5] = 0;
    out[6] = (uint8_t)(format & 0xFFu);
    out[7] = (uint8_t)(format >> 8);
    put32(out + 8, sequence);
    put32(out + 12, (uint32_t)n);
    memset(out + 16, 0xFF, padded);
    memcpy(out + 16, p, n);
    put32(out + 16 + padded, mc_crc32_iso_hdlc(out, 16 + padded));
    put32(out + 20 + padded, marker);
    return 24 + padded;
}

static void test_layout(void)
{
    uint8_t expect[MC_STORAGE_RECORD_SIZE(MC_STORAGE_PAYLOAD_MAX)];
    build_history(2);
    size_t n = encode_record(expect, 1, payload_format(0), payloads[0], payload_len[0],
                             0xC0DE600Du);
    CHECK_EQ_INT(n, MC_STORAGE_RECORD_SIZE(payload_len[0]));
    CHECK(memcmp(sim.mem + SLOT_A_ADDR, expect, n) == 0);
    n = encode_record(expect, 2, payload_format(1), payloads[1], payload_len[1], 0xC0DE600Du);
    CHECK_EQ_INT(n, MC_STORAGE_RECORD_SIZE(payload_len[1]));
    CHECK(memcmp(sim.mem + SLOT_B_ADDR, expect, n) == 0);
    /* The rest of each slot stays erased. */
    int erased = 1;
    for (size_t i = n; i < PAGES_PER_SLOT * PAGE_SIZE; ++i) {
        erased &= sim.mem[SLOT_B_ADDR + i] == 0xFFu;
    }
    CHECK(erased);
    CHECK_EQ_INT(MC_STORAGE_RECORD_SIZE(MC_STORAGE_PAYLOAD_MAX), 152);
    CHECK_EQ_INT(MC_STORAGE_RECORD_SIZE(1), 28);
    CHECK_EQ_INT(sim.violations, 0);
}

/* ------------------------------------------------------------------ power loss */

static long cut_points_total;

/*
 * With `history` commits done, commit payload `history` and cut it at every step. After each
 * cut: boot must load exactly the previous payload (or the new one: only possible once the
 * marker is complete, which is the last flash write, so never for a cut) or, with no history,
 * nothing; then a commit of the last payload must succeed and win.
 */
static void test_power_loss(int history)
{
    static uint8_t snapshot[FLASH_SIM_MAX_BYTES];
    const int next = history, follow = N_PAYLOADS - 1;
    build_history(history);
    memcpy(snapshot, sim.mem, sizeof snapshot);

    /* Count the steps of the uninterrupted commit. */
    mc_storage_t st;
    CHECK_EQ_INT(mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT), MC_OK);
    const long before = sim.steps;
    CHECK_EQ_INT(commit_payload(&st, next), MC_OK);
    const long total = sim.steps - before;
    const long expected_total = (long)(PAGES_PER_SLOT * PAGE_SIZE)
                                + (long)MC_STORAGE_RECORD_SIZE(payload_len[next]);
    CHECK_EQ_INT(total, expected_total);
    loaded_t l = boot_and_load();
    CHECK(is_payload(&l, next, (uint32_t)history + 1u));

    long failures = 0, old_seen = 0, none_seen = 0;
    for (int order = 0; order < 3; ++order) {
        for (int tear = 0; tear < 2; ++tear) {
            for (long k = 0; k < total; ++k) {
                memcpy(sim.mem, snapshot, sizeof snapshot);
                flash_sim_power_on(&sim);
                sim.violations = 0;
                int ok = mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT)
                         == MC_OK;
                flash_sim_arm_cut(&sim, k, tear, order);
                /* A cut in the marker's program (its last 4 steps) is after the commit
                 * point: the rescan cannot read a dead flash, so the outcome is unknown. */
                const mc_status_t want = k >= total - (long)MC_FLASH_WORD_SIZE
                                             ? MC_E_OUTCOME_UNKNOWN : MC_E_FLASH;
                ok &= commit_payload(&st, next) == want && sim.dead;
                flash_sim_power_on(&sim);

                l = boot_and_load();
                uint32_t seq_after_cut = 0;
                if (history == 0 && l.status == MC_E_NO_PARAMS) {
                    ++none_seen;
                } else if (history > 0 && is_payload(&l, history - 1, (uint32_t)history)) {
                    ++old_seen;
                    seq_after_cut = (uint32_t)history;
                } else {
                    ok = 0; /* a mix, the new one before its marker, or none after a commit */
                }

                /* Recovery: the next commit succeeds and is what boot loads. */
                ok &= mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT)
                      == MC_OK;
                ok &= commit_payload(&st, follow) == MC_OK;
                l = boot_and_load();
                ok &= is_payload(&l, follow, seq_after_cut + 1u);
                ok &= sim.violations == 0 && canaries_intact();
                if (!ok) {
                    if (failures < 5) {
                        printf("  power loss: history %d, erase order %d, tear %d, cut at step "
                               "%ld of %ld failed (load status %d)\n",
                               history, order, tear, k, total, (int)l.status);
                    }
                    ++failures;
                }
                ++cut_points_total;
            }
        }
    }
    printf("  history %d: %ld steps per commit, %ld cuts -> old %ld, none %ld, failures %ld\n",
           history, total, 6 * total, old_seen, none_seen, failures);
    CHECK_EQ_INT(failures, 0);
    CHECK_EQ_INT(old_seen + none_seen, 6 * total);
}

/* ------------------------------------------------------------------ corruption, faults */

/* Flip one bit in every byte of the best record in turn: boot falls back to the other slot
 * (or to none); bytes after the record do not matter. Then a commit repairs. */
static void test_corruption(void)
{
    static uint8_t snapshot[FLASH_SIM_MAX_BYTES];
    build_history(2); /* A: payload 0, seq 1; B: payload 1, seq 2 */
    memcpy(snapshot, sim.mem, sizeof snapshot);
    const size_t record = MC_STORAGE_RECORD_SIZE(payload_len[1]);
    long wrong = 0;
    for (size_t i = 0; i < PAGES_PER_SLOT * PAGE_SIZE; ++i) {
        for (int bit = 0; bit < 8; bit += 3) {
            memcpy(sim.mem, snapshot, sizeof snapshot);
            sim.mem[SLOT_B_ADDR + i] ^= (uint8_t)(1u << bit);
            const loaded_t l = boot_and_load();
            const int expect_fallback = i < record;
            wrong += expect_fallback ? !is_payload(&l, 0, 1) : !is_payload(&l, 1, 2);
        }
    }
    CHECK_EQ_INT(wrong, 0);

    /* With B corrupted, the next commit goes to B (A is the best) and wins with seq 2. */
    memcpy(sim.mem, snapshot, sizeof snapshot);
    sim.mem[SLOT_B_ADDR + 20] ^= 0x01u;
    mc_storage_t st;
    mc_storage_slot_t slot;
    uint32_t seq;
    CHECK_EQ_INT(mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT), MC_OK);
    CHECK_EQ_INT(mc_storage_active(&st, &slot, &seq), MC_OK);
    CHECK_EQ_INT(slot, MC_STORAGE_SLOT_A);
    CHECK_EQ_INT(seq, 1);
    CHECK_EQ_INT(commit_payload(&st, 3), MC_OK);
    CHECK_EQ_INT(mc_storage_active(&st, &slot, &seq), MC_OK);
    CHECK_EQ_INT(slot, MC_STORAGE_SLOT_B);
    CHECK_EQ_INT(seq, 2);
    loaded_t l = boot_and_load();
    CHECK(is_payload(&l, 3, 2));

    /* Only one record, corrupted: none. */
    build_history(1);
    sim.mem[SLOT_A_ADDR + 16] ^= 0x80u;
    l = boot_and_load();
    CHECK_EQ_INT(l.status, MC_E_NO_PARAMS);
    CHECK_EQ_INT(l.len, 0);
    CHECK_EQ_INT(sim.violations, 0);
}

static void test_flash_faults(void)
{
    static uint8_t snapshot[FLASH_SIM_MAX_BYTES];
    mc_storage_t st;
    build_history(2);
    memcpy(snapshot, sim.mem, sizeof snapshot);

    /* The driver reports an erase failure: commit fails, old record still loads. */
    CHECK_EQ_INT(mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT), MC_OK);
    sim.fail_erase = 1;
    CHECK_EQ_INT(commit_payload(&st, 2), MC_E_FLASH);
    sim.fail_erase = 0;
    mc_storage_slot_t slot;
    uint32_t seq;
    CHECK_EQ_INT(mc_storage_active(&st, &slot, &seq), MC_OK);
    CHECK_EQ_INT(slot, MC_STORAGE_SLOT_B);
    CHECK_EQ_INT(seq, 2);
    loaded_t l = boot_and_load();
    CHECK(is_payload(&l, 1, 2));

    /* Programs silently dropped from every possible step on: read-back catches each. */
    const long erase_steps = (long)(PAGES_PER_SLOT * PAGE_SIZE);
    const long record = (long)MC_STORAGE_RECORD_SIZE(payload_len[2]);
    long wrong = 0;
    for (long k = 0; k < record; ++k) {
        memcpy(sim.mem, snapshot, sizeof snapshot);
        flash_sim_power_on(&sim);
        CHECK_EQ_INT(mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT),
                     MC_OK);
        sim.lie_after = sim.steps + erase_steps + k;
        wrong += commit_payload(&st, 2) != MC_E_FLASH;
        sim.lie_after = -1;
        l = boot_and_load();
        wrong += !is_payload(&l, 1, 2);
    }
    CHECK_EQ_INT(wrong, 0);
    CHECK_EQ_INT(sim.violations, 0);

    /* A read that goes bad between the scan and the copy: load checks the CRC over the bytes
     * it hands out, so it reports MC_E_CRC instead of returning them. */
    memcpy(sim.mem, snapshot, sizeof snapshot);
    flash_sim_power_on(&sim);
    const long reads_before_init = sim.reads;
    CHECK_EQ_INT(mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT), MC_OK);
    const long scan_reads = sim.reads - reads_before_init; /* load scans the same way first */
    sim.flip_reads_from = sim.reads + scan_reads;
    size_t len = 0;
    uint16_t fmt = 0;
    uint8_t out[MC_STORAGE_PAYLOAD_MAX];
    CHECK_EQ_INT(mc_storage_load(&st, out, sizeof out, &len, &fmt, &seq), MC_E_CRC);
    sim.flip_reads_from = -1;
    CHECK_EQ_INT(mc_storage_load(&st, out, sizeof out, &len, &fmt, &seq), MC_OK);
    CHECK(len == payload_len[1] && memcmp(out, payloads[1], len) == 0 && seq == 2);
}

/* ------------------------------------------------------------------ failing reads */

/* flash_sim's ops with reads that FAIL (MC_E_FLASH, nothing read) in a window of read numbers
 * [fail_from, fail_to) counted by this wrapper: a driver error, not a flipped bit. */
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

/*
 * A read fails at every point of a commit, once (a glitch) or from there on (the flash
 * stops answering). Whatever commit returns must agree with what a boot then loads and with
 * mc_storage_active: MC_OK = the new record wins, MC_E_FLASH = the old one (or none) certainly
 * still wins, MC_E_OUTCOME_UNKNOWN (only when reads keep failing, so the rescan fails too) =
 * either, and st then says "none". A single failed read after the marker is programmed must
 * be settled by the rescan as MC_OK, and one in the first scan must leave st as it was.
 */
static void test_failing_reads(void)
{
    static uint8_t snapshot[FLASH_SIM_MAX_BYTES];
    mc_flash_t flaky;
    mc_storage_t st;
    long wrong = 0, ok_after_fault = 0, unknown = 0, definite = 0;
    for (int history = 0; history <= 2; ++history) {
        build_history(history);
        memcpy(snapshot, sim.mem, sizeof snapshot);
        flaky = flash;
        flaky.ops = &failing_ops;
        /* Reads of a clean commit. */
        CHECK_EQ_INT(mc_storage_init(&st, &flaky, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT), MC_OK);
        wrapped_reads = 0;
        CHECK_EQ_INT(commit_payload(&st, history), MC_OK);
        const long commit_reads = wrapped_reads;
        CHECK(commit_reads > 10);
        for (int persistent = 0; persistent <= 1; ++persistent) {
            for (long k = 0; k < commit_reads; ++k) {
                memcpy(sim.mem, snapshot, sizeof snapshot);
                flash_sim_power_on(&sim);
                fail_from = -1;
                CHECK_EQ_INT(mc_storage_init(&st, &flaky, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT),
                             MC_OK);
                wrapped_reads = 0;
                fail_from = k;
                fail_to = persistent ? -1 : k + 1;
                const mc_status_t s = commit_payload(&st, history);
                fail_from = -1;
                mc_storage_slot_t slot;
                uint32_t seq = 0;
                const mc_status_t a = mc_storage_active(&st, &slot, &seq);
                const loaded_t l = boot_and_load();
                const int is_old = history == 0 ? l.status == MC_E_NO_PARAMS
                                                : is_payload(&l, history - 1, (uint32_t)history);
                const int is_new = is_payload(&l, history, (uint32_t)history + 1u);
                int good = 0;
                if (s == MC_OK) {
                    good = is_new && a == MC_OK && seq == (uint32_t)history + 1u;
                    ++ok_after_fault;
                } else if (s == MC_E_FLASH) {
                    good = is_old && (history == 0 ? a == MC_E_NO_PARAMS
                                                   : a == MC_OK && seq == (uint32_t)history);
                    ++definite;
                } else if (s == MC_E_OUTCOME_UNKNOWN) {
                    good = persistent && (is_old || is_new) && a == MC_E_NO_PARAMS
                           && slot == MC_STORAGE_SLOT_NONE;
                    ++unknown;
                }
                if (!good) {
                    printf("  history %d, read %ld fails%s: commit %d, active %d seq %u, boot "
                           "loads %s\n", history, k, persistent ? " on" : " once", (int)s,
                           (int)a, (unsigned)seq, is_new ? "new" : is_old ? "old" : "neither");
                    ++wrong;
                }
            }
        }
    }
    CHECK_EQ_INT(wrong, 0);
    CHECK(ok_after_fault > 0); /* a fault after the commit point, settled as committed */
    CHECK(definite > 0);
    CHECK(unknown > 0);
    CHECK_EQ_INT(sim.violations, 0);
}

/* Two valid records with the same sequence (only a foreign writer makes this): A wins. */
static void test_tie(void)
{
    uint8_t rec[MC_STORAGE_RECORD_SIZE(MC_STORAGE_PAYLOAD_MAX)];
    flash_sim_init(&sim, &flash, PAGE_SIZE, PAGE_COUNT);
    size_t n = encode_record(rec, 7, payload_format(0), payloads[0], payload_len[0],
                             MC_STORAGE_COMMIT_MARKER);
    memcpy(sim.mem + SLOT_A_ADDR, rec, n);
    n = encode_record(rec, 7, payload_format(1), payloads[1], payload_len[1],
                      MC_STORAGE_COMMIT_MARKER);
    memcpy(sim.mem + SLOT_B_ADDR, rec, n);
    loaded_t l = boot_and_load();
    CHECK(is_payload(&l, 0, 7));
    /* ... and the next commit overwrites B with sequence 8. */
    mc_storage_t st;
    CHECK_EQ_INT(mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT), MC_OK);
    CHECK_EQ_INT(commit_payload(&st, 2), MC_OK);
    l = boot_and_load();
    CHECK(is_payload(&l, 2, 8));
    CHECK(is_payload(&l, 2, 8) && memcmp(sim.mem + SLOT_A_ADDR + 16, payloads[0], 16) == 0);
}

/* The sequence never wraps: at 0xFFFFFFFF commit refuses and the record stays. A higher
 * sequence wins whatever the slot. Unknown layout versions, a wrong marker, or a length
 * beyond the slot make a record invalid. */
static void test_sequence_and_validity(void)
{
    uint8_t rec[MC_STORAGE_RECORD_SIZE(MC_STORAGE_PAYLOAD_MAX)];
    mc_storage_t st;
    flash_sim_init(&sim, &flash, PAGE_SIZE, PAGE_COUNT);
    size_t n = encode_record(rec, 0xFFFFFFFFu, payload_format(0), payloads[0], payload_len[0],
                             MC_STORAGE_COMMIT_MARKER);
    memcpy(sim.mem + SLOT_B_ADDR, rec, n);
    n = encode_record(rec, 5, payload_format(1), payloads[1], payload_len[1],
                      MC_STORAGE_COMMIT_MARKER);
    memcpy(sim.mem + SLOT_A_ADDR, rec, n);
    CHECK_EQ_INT(mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT), MC_OK);
    CHECK_EQ_INT(commit_payload(&st, 2), MC_E_RANGE);
    loaded_t l = boot_and_load();
    CHECK(is_payload(&l, 0, 0xFFFFFFFFu));

    /* Layout version 2: not ours. */
    flash_sim_init(&sim, &flash, PAGE_SIZE, PAGE_COUNT);
    n = encode_record(rec, 1, payload_format(0), payloads[0], payload_len[0],
                      MC_STORAGE_COMMIT_MARKER);
    rec[4] = 2;
    put32(rec + n - 8, mc_crc32_iso_hdlc(rec, n - 8)); /* a correct CRC: only the version is off */
    memcpy(sim.mem + SLOT_A_ADDR, rec, n);
    l = boot_and_load();
    CHECK_EQ_INT(l.status, MC_E_NO_PARAMS);

    /* Every marker value but the right one, for each single cleared or set bit. */
    long wrong = 0;
    for (int bit = 0; bit < 32; ++bit) {
        flash_sim_init(&sim, &flash, PAGE_SIZE, PAGE_COUNT);
        n = encode_record(rec, 1, payload_format(0), payloads[0], payload_len[0],
                          MC_STORAGE_COMMIT_MARKER ^ (1u << bit));
        memcpy(sim.mem + SLOT_A_ADDR, rec, n);
        l = boot_and_load();
        wrong += l.status != MC_E_NO_PARAMS;
    }
    CHECK_EQ_INT(wrong, 0);

    /* A length beyond the slot (with a consistent CRC where it would be) is not followed. */
    flash_sim_init(&sim, &flash, PAGE_SIZE, PAGE_COUNT);
    n = encode_record(rec, 1, payload_format(0), payloads[0], payload_len[0],
                      MC_STORAGE_COMMIT_MARKER);
    put32(rec + 12, 0xFFFFFFF0u);
    memcpy(sim.mem + SLOT_A_ADDR, rec, n);
    l = boot_and_load();
    CHECK_EQ_INT(l.status, MC_E_NO_PARAMS);
    CHECK_EQ_INT(sim.violations, 0);
}

/* ------------------------------------------------------------------ API */

static mc_status_t null_erase(void *ctx, uint32_t page)
{
    (void)ctx;
    (void)page;
    return MC_OK;
}

static void test_arguments(void)
{
    mc_storage_t st;
    uint8_t buf[MC_STORAGE_PAYLOAD_MAX + 1];
    size_t len = 99;
    uint16_t fmt = 99;
    uint32_t seq = 99;
    mc_storage_slot_t slot = MC_STORAGE_SLOT_A;
    memset(buf, 0x5A, sizeof buf);
    flash_sim_init(&sim, &flash, PAGE_SIZE, PAGE_COUNT);

    CHECK_EQ_INT(mc_storage_init(NULL, &flash, 1, 4, 2), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_init(&st, NULL, 1, 4, 2), MC_E_ARG);
    mc_flash_t bad = flash;
    bad.ops = NULL;
    CHECK_EQ_INT(mc_storage_init(&st, &bad, 1, 4, 2), MC_E_ARG);
    mc_flash_ops_t ops = flash_sim_ops;
    ops.read = NULL;
    bad = flash;
    bad.ops = &ops;
    CHECK_EQ_INT(mc_storage_init(&st, &bad, 1, 4, 2), MC_E_ARG);
    ops = flash_sim_ops;
    ops.program_word = NULL;
    CHECK_EQ_INT(mc_storage_init(&st, &bad, 1, 4, 2), MC_E_ARG);
    ops = flash_sim_ops;
    ops.erase_page = NULL;
    CHECK_EQ_INT(mc_storage_init(&st, &bad, 1, 4, 2), MC_E_ARG);
    ops.erase_page = null_erase;
    CHECK_EQ_INT(mc_storage_init(&st, &bad, 1, 4, 2), MC_OK);
    bad = flash;
    bad.page_size = 0;
    CHECK_EQ_INT(mc_storage_init(&st, &bad, 1, 4, 2), MC_E_ARG);
    bad.page_size = 130; /* not a multiple of the word */
    CHECK_EQ_INT(mc_storage_init(&st, &bad, 1, 4, 2), MC_E_ARG);
    bad = flash;
    bad.page_count = 0;
    CHECK_EQ_INT(mc_storage_init(&st, &bad, 0, 0, 1), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_init(&st, &flash, 1, 4, 0), MC_E_ARG);
    /* Range: out of the region, overlapping, too small, region beyond 32 bits. */
    CHECK_EQ_INT(mc_storage_init(&st, &flash, 1, 7, 2), MC_E_RANGE);
    CHECK_EQ_INT(mc_storage_init(&st, &flash, 0xFFFFFFFFu, 4, 2), MC_E_RANGE);
    CHECK_EQ_INT(mc_storage_init(&st, &flash, 1, 2, 2), MC_E_RANGE);
    CHECK_EQ_INT(mc_storage_init(&st, &flash, 2, 1, 2), MC_E_RANGE);
    CHECK_EQ_INT(mc_storage_init(&st, &flash, 3, 3, 2), MC_E_RANGE);
    CHECK_EQ_INT(mc_storage_init(&st, &flash, 1, 4, 1), MC_E_RANGE); /* 128 B < 152 B */
    bad = flash;
    bad.page_size = 0x10000u;
    bad.page_count = 0x10000u;
    CHECK_EQ_INT(mc_storage_init(&st, &bad, 1, 4, 2), MC_E_RANGE);
    CHECK_EQ_INT(mc_storage_init(&st, &flash, 1, 3, 2), MC_OK); /* adjacent slots are fine */

    /* A failed init leaves st unusable, not half set up. */
    CHECK_EQ_INT(mc_storage_init(&st, &flash, 1, 2, 2), MC_E_RANGE);
    CHECK_EQ_INT(mc_storage_load(&st, buf, sizeof buf, &len, &fmt, &seq), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_commit(&st, buf, 4, 1), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_active(&st, &slot, &seq), MC_E_NO_PARAMS);
    CHECK_EQ_INT(slot, MC_STORAGE_SLOT_NONE);

    CHECK_EQ_INT(mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT), MC_OK);
    CHECK_EQ_INT(mc_storage_active(NULL, &slot, &seq), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_active(&st, NULL, &seq), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_active(&st, &slot, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_active(&st, &slot, &seq), MC_E_NO_PARAMS);
    CHECK_EQ_INT(slot, MC_STORAGE_SLOT_NONE);
    CHECK_EQ_INT(seq, 0);

    CHECK_EQ_INT(mc_storage_load(NULL, buf, sizeof buf, &len, &fmt, &seq), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_load(&st, NULL, sizeof buf, &len, &fmt, &seq), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_load(&st, buf, sizeof buf, NULL, &fmt, &seq), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_load(&st, buf, sizeof buf, &len, NULL, &seq), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_load(&st, buf, sizeof buf, &len, &fmt, NULL), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_load(&st, buf, sizeof buf, &len, &fmt, &seq), MC_E_NO_PARAMS);
    CHECK_EQ_INT(len, 0);
    CHECK_EQ_INT(fmt, 0);
    CHECK_EQ_INT(seq, 0);

    /* Payload size: 0 and MAX + 1 are argument errors, MAX works. */
    CHECK_EQ_INT(mc_storage_commit(NULL, buf, 4, 1), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_commit(&st, NULL, 4, 1), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_commit(&st, buf, 0, 1), MC_E_ARG);
    CHECK_EQ_INT(mc_storage_commit(&st, buf, MC_STORAGE_PAYLOAD_MAX + 1u, 1), MC_E_ARG);
    CHECK_EQ_INT(sim.erases + sim.programs, 0); /* refused before touching flash */
    CHECK_EQ_INT(mc_storage_commit(&st, buf, MC_STORAGE_PAYLOAD_MAX, 0xBEEF), MC_OK);
    CHECK_EQ_INT(mc_storage_active(&st, &slot, &seq), MC_OK);
    CHECK_EQ_INT(slot, MC_STORAGE_SLOT_A);
    CHECK_EQ_INT(seq, 1);

    /* The format version comes back as given; storage does not judge it. */
    uint8_t out[MC_STORAGE_PAYLOAD_MAX];
    CHECK_EQ_INT(mc_storage_load(&st, out, sizeof out, &len, &fmt, &seq), MC_OK);
    CHECK_EQ_INT(len, MC_STORAGE_PAYLOAD_MAX);
    CHECK_EQ_INT(fmt, 0xBEEF);
    CHECK_EQ_INT(seq, 1);
    CHECK(memcmp(out, buf, MC_STORAGE_PAYLOAD_MAX) == 0);

    /* A buffer too small: MC_E_NO_SPACE with the needed size, nothing copied. */
    memset(out, 0, sizeof out);
    CHECK_EQ_INT(mc_storage_load(&st, out, MC_STORAGE_PAYLOAD_MAX - 1u, &len, &fmt, &seq),
                 MC_E_NO_SPACE);
    CHECK_EQ_INT(len, MC_STORAGE_PAYLOAD_MAX);
    CHECK_EQ_INT(out[0], 0);
    CHECK_EQ_INT(mc_storage_load(&st, NULL, 0, &len, &fmt, &seq), MC_E_NO_SPACE);
    CHECK_EQ_INT(len, MC_STORAGE_PAYLOAD_MAX);

    /* Alternation: A, B, A ... with sequences 1, 2, 3 ... */
    for (uint32_t i = 2; i <= 5; ++i) {
        CHECK_EQ_INT(mc_storage_commit(&st, buf, i, (uint16_t)i), MC_OK);
        CHECK_EQ_INT(mc_storage_active(&st, &slot, &seq), MC_OK);
        CHECK_EQ_INT(slot, i % 2 == 0 ? MC_STORAGE_SLOT_B : MC_STORAGE_SLOT_A);
        CHECK_EQ_INT(seq, i);
    }
    CHECK_EQ_INT(sim.violations, 0);

    /* A read error during boot is reported, not taken for "no parameters". */
    sim.dead = 1;
    CHECK_EQ_INT(mc_storage_init(&st, &flash, SLOT_A_PAGE, SLOT_B_PAGE, PAGES_PER_SLOT),
                 MC_E_FLASH);
    CHECK_EQ_INT(mc_storage_load(&st, out, sizeof out, &len, &fmt, &seq), MC_E_FLASH);
    sim.dead = 0;
}

/* No enum-typed field in the public struct: its layout must not depend on -fshort-enums
 * (arm-none-eabi-gcc's default) versus the application's choice. */
static void test_struct_layout_independent_of_enum_size(void)
{
    mc_storage_t st;
    CHECK_EQ_INT(sizeof st.active, sizeof(int8_t));
    CHECK_EQ_INT((int8_t)MC_STORAGE_SLOT_NONE, -1);
}

int main(void)
{
    make_payloads();
    test_struct_layout_independent_of_enum_size();
    test_arguments();
    test_layout();
    test_sequence_and_validity();
    test_tie();
    test_corruption();
    test_flash_faults();
    test_failing_reads();
    for (int history = 0; history <= 3; ++history) {
        test_power_loss(history);
    }
    printf("  %ld power cuts exercised\n", cut_points_total);
    return check_summary("test_fw_storage");
}
