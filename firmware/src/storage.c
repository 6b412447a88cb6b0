/* SPDX-License-Identifier: Apache-2.0 */
/* Two-slot power-loss-safe parameter storage. The layout and the protocol are in storage.h. */
#include "magcal/storage.h"

#include <string.h>

#include "magcal/crc.h"

/* Header word offsets within a record. */
enum { OFF_MAGIC = 0, OFF_VERSIONS = 4, OFF_SEQUENCE = 8, OFF_LENGTH = 12 };

/* What a scan learned about one slot. */
typedef struct {
    int valid;
    uint16_t format_version;
    uint32_t sequence;
    uint32_t length;
} slot_info_t;

static uint32_t get_le32(const uint8_t *b)
{
    return (uint32_t)b[0] | ((uint32_t)b[1] << 8) | ((uint32_t)b[2] << 16) | ((uint32_t)b[3] << 24);
}

static void put_le32(uint8_t *b, uint32_t w)
{
    b[0] = (uint8_t)(w & 0xFFu);
    b[1] = (uint8_t)((w >> 8) & 0xFFu);
    b[2] = (uint8_t)((w >> 16) & 0xFFu);
    b[3] = (uint8_t)((w >> 24) & 0xFFu);
}

static uint32_t padded(uint32_t n)
{
    return (n + 3u) & ~3u;
}

/* Largest payload a slot can hold: its size minus header, CRC and marker, word-aligned down. */
static uint32_t slot_capacity(const mc_storage_t *st)
{
    return (st->slot_size - MC_STORAGE_HEADER_SIZE - 8u) & ~3u;
}

static mc_status_t flash_read(const mc_storage_t *st, uint32_t addr, uint8_t *buf, size_t len)
{
    /* Any driver error is a flash error to our caller, whatever code the driver chose. */
    return st->flash->ops->read(st->flash->ctx, addr, buf, len) == MC_OK ? MC_OK : MC_E_FLASH;
}

/* Reads one little-endian word. */
static mc_status_t read_word(const mc_storage_t *st, uint32_t addr, uint32_t *word)
{
    uint8_t b[4];
    const mc_status_t s = flash_read(st, addr, b, sizeof b);
    if (s == MC_OK) {
        *word = get_le32(b);
    }
    return s;
}

/* Programs one word and reads it back: a word that does not read back is a flash error at
 * the point it happened, not later as a CRC mismatch with no location. */
static mc_status_t program_verified(const mc_storage_t *st, uint32_t addr, uint32_t word)
{
    if (st->flash->ops->program_word(st->flash->ctx, addr, word) != MC_OK) {
        return MC_E_FLASH;
    }
    uint32_t back = 0;
    const mc_status_t s = read_word(st, addr, &back);
    if (s != MC_OK) {
        return s;
    }
    return back == word ? MC_OK : MC_E_FLASH;
}

/* CRC-32 state over len bytes of flash at addr, read in chunks (no payload-sized buffer). */
static mc_status_t crc_flash(const mc_storage_t *st, uint32_t addr, uint32_t len, uint32_t *state)
{
    uint8_t chunk[MC_STORAGE_READ_CHUNK];
    while (len > 0) {
        const uint32_t n = len < MC_STORAGE_READ_CHUNK ? len : MC_STORAGE_READ_CHUNK;
        const mc_status_t s = flash_read(st, addr, chunk, n);
        if (s != MC_OK) {
            return s;
        }
        *state = mc_crc32_iso_hdlc_update(*state, chunk, n);
        addr += n;
        len -= n;
    }
    return MC_OK;
}

/*
 * Checks one slot as boot does. Cheap tests first (magic, layout, length, marker), the CRC
 * last. Returns MC_OK with info->valid 0 or 1, or MC_E_FLASH if a read failed. The length is
 * bounded by the slot before it is used to locate anything, so a torn or corrupted length
 * field cannot send reads outside the slot.
 */
static mc_status_t scan_slot(const mc_storage_t *st, int slot, slot_info_t *info)
{
    const uint32_t base = st->slot_addr[slot];
    uint8_t hdr[MC_STORAGE_HEADER_SIZE];
    memset(info, 0, sizeof *info);
    mc_status_t s = flash_read(st, base, hdr, sizeof hdr);
    if (s != MC_OK) {
        return s;
    }
    const uint32_t versions = get_le32(hdr + OFF_VERSIONS);
    const uint32_t length = get_le32(hdr + OFF_LENGTH);
    if (get_le32(hdr + OFF_MAGIC) != MC_STORAGE_MAGIC
        || (versions & 0xFFFFu) != MC_STORAGE_LAYOUT_VERSION || length == 0
        || length > slot_capacity(st)) {
        return MC_OK;
    }
    const uint32_t body = MC_STORAGE_HEADER_SIZE + padded(length);
    uint32_t marker = 0;
    s = read_word(st, base + body + 4u, &marker);
    if (s != MC_OK || marker != MC_STORAGE_COMMIT_MARKER) {
        return s;
    }
    uint32_t state = mc_crc32_iso_hdlc_update(MC_CRC32_ISO_HDLC_INIT, hdr, sizeof hdr);
    s = crc_flash(st, base + MC_STORAGE_HEADER_SIZE, body - MC_STORAGE_HEADER_SIZE, &state);
    uint32_t stored_crc = 0;
    if (s == MC_OK) {
        s = read_word(st, base + body, &stored_crc);
    }
    if (s != MC_OK || mc_crc32_iso_hdlc_final(state) != stored_crc) {
        return s;
    }
    info->valid = 1;
    info->format_version = (uint16_t)(versions >> 16);
    info->sequence = get_le32(hdr + OFF_SEQUENCE);
    info->length = length;
    return MC_OK;
}

/* Scans both slots and records the best in st. On a read error st says "none": better to
 * report no parameters than a slot we could not check. */
static mc_status_t scan(mc_storage_t *st, slot_info_t info[2])
{
    st->active = (int8_t)MC_STORAGE_SLOT_NONE;
    st->active_sequence = 0;
    for (int i = 0; i < 2; ++i) {
        const mc_status_t s = scan_slot(st, i, &info[i]);
        if (s != MC_OK) {
            return s;
        }
    }
    /* Higher sequence wins; on a tie (never written by commit) A wins, deterministically. */
    if (info[0].valid && (!info[1].valid || info[0].sequence >= info[1].sequence)) {
        st->active = (int8_t)MC_STORAGE_SLOT_A;
        st->active_sequence = info[0].sequence;
    } else if (info[1].valid) {
        st->active = (int8_t)MC_STORAGE_SLOT_B;
        st->active_sequence = info[1].sequence;
    }
    return MC_OK;
}

mc_status_t mc_storage_init(mc_storage_t *st, const mc_flash_t *flash, uint32_t slot_a_page,
                            uint32_t slot_b_page, uint32_t pages_per_slot)
{
    if (st == NULL) {
        return MC_E_ARG;
    }
    memset(st, 0, sizeof *st);
    st->active = (int8_t)MC_STORAGE_SLOT_NONE;
    if (flash == NULL || flash->ops == NULL || flash->ops->erase_page == NULL
        || flash->ops->program_word == NULL || flash->ops->read == NULL || flash->page_size == 0
        || flash->page_size % MC_FLASH_WORD_SIZE != 0 || flash->page_count == 0
        || pages_per_slot == 0) {
        return MC_E_ARG;
    }
    /* Bounds in 64 bits so no product or sum below can wrap. */
    const uint64_t region = (uint64_t)flash->page_size * flash->page_count;
    const uint64_t slot_size = (uint64_t)flash->page_size * pages_per_slot;
    if (region > UINT32_MAX || (uint64_t)slot_a_page + pages_per_slot > flash->page_count
        || (uint64_t)slot_b_page + pages_per_slot > flash->page_count
        || ((uint64_t)slot_a_page < (uint64_t)slot_b_page + pages_per_slot
            && (uint64_t)slot_b_page < (uint64_t)slot_a_page + pages_per_slot)
        || slot_size < MC_STORAGE_RECORD_SIZE(MC_STORAGE_PAYLOAD_MAX)) {
        return MC_E_RANGE;
    }
    st->slot_page[0] = slot_a_page;
    st->slot_page[1] = slot_b_page;
    st->slot_addr[0] = slot_a_page * flash->page_size;
    st->slot_addr[1] = slot_b_page * flash->page_size;
    st->pages_per_slot = pages_per_slot;
    st->slot_size = (uint32_t)slot_size;
    st->flash = flash;
    slot_info_t info[2];
    return scan(st, info);
}

mc_status_t mc_storage_load(mc_storage_t *st, uint8_t *payload, size_t cap, size_t *len,
                            uint16_t *format_version, uint32_t *sequence)
{
    if (st == NULL || st->flash == NULL || (payload == NULL && cap > 0) || len == NULL
        || format_version == NULL || sequence == NULL) {
        return MC_E_ARG;
    }
    *len = 0;
    *format_version = 0;
    *sequence = 0;
    slot_info_t info[2];
    mc_status_t s = scan(st, info);
    if (s != MC_OK) {
        return s;
    }
    if (st->active == (int8_t)MC_STORAGE_SLOT_NONE) {
        return MC_E_NO_PARAMS;
    }
    const slot_info_t *best = &info[st->active];
    const uint32_t base = st->slot_addr[st->active];
    *len = best->length;
    *format_version = best->format_version;
    *sequence = best->sequence;
    if (cap < best->length) {
        return MC_E_NO_SPACE;
    }
    /* Copy, then check the CRC over exactly the bytes handed to the caller, so a read that
     * differs from the scan's cannot slip through. */
    uint8_t hdr[MC_STORAGE_HEADER_SIZE];
    s = flash_read(st, base, hdr, sizeof hdr);
    if (s == MC_OK) {
        s = flash_read(st, base + MC_STORAGE_HEADER_SIZE, payload, best->length);
    }
    uint32_t state = mc_crc32_iso_hdlc_update(MC_CRC32_ISO_HDLC_INIT, hdr, sizeof hdr);
    state = mc_crc32_iso_hdlc_update(state, payload, best->length);
    const uint32_t pad_start = MC_STORAGE_HEADER_SIZE + best->length;
    const uint32_t body = MC_STORAGE_HEADER_SIZE + padded(best->length);
    if (s == MC_OK) {
        s = crc_flash(st, base + pad_start, body - pad_start, &state);
    }
    uint32_t stored_crc = 0;
    if (s == MC_OK) {
        s = read_word(st, base + body, &stored_crc);
    }
    if (s != MC_OK) {
        return s;
    }
    if (mc_crc32_iso_hdlc_final(state) != stored_crc) {
        return MC_E_CRC;
    }
    return MC_OK;
}

/* Erases every page of a slot, then checks it reads all 0xFF: a program on a word that is not
 * erased would not give what we asked for, and "erase said OK" is not proof. */
static mc_status_t erase_slot(const mc_storage_t *st, int slot)
{
    for (uint32_t p = 0; p < st->pages_per_slot; ++p) {
        if (st->flash->ops->erase_page(st->flash->ctx, st->slot_page[slot] + p) != MC_OK) {
            return MC_E_FLASH;
        }
    }
    uint8_t chunk[MC_STORAGE_READ_CHUNK];
    for (uint32_t off = 0; off < st->slot_size; off += MC_STORAGE_READ_CHUNK) {
        const uint32_t rest = st->slot_size - off;
        const uint32_t n = rest < MC_STORAGE_READ_CHUNK ? rest : MC_STORAGE_READ_CHUNK;
        const mc_status_t s = flash_read(st, st->slot_addr[slot] + off, chunk, n);
        if (s != MC_OK) {
            return s;
        }
        for (uint32_t i = 0; i < n; ++i) {
            if (chunk[i] != 0xFFu) {
                return MC_E_FLASH;
            }
        }
    }
    return MC_OK;
}

mc_status_t mc_storage_commit(mc_storage_t *st, const uint8_t *payload, size_t len,
                              uint16_t format_version)
{
    if (st == NULL || st->flash == NULL || payload == NULL || len == 0
        || len > MC_STORAGE_PAYLOAD_MAX) {
        return MC_E_ARG;
    }
    slot_info_t info[2];
    const int8_t known = st->active;
    const uint32_t known_sequence = st->active_sequence;
    mc_status_t s = scan(st, info);
    if (s != MC_OK) {
        /* Nothing was written: st keeps what the last init, load or commit found. */
        st->active = known;
        st->active_sequence = known_sequence;
        return s;
    }
    const int8_t previous = st->active;
    const uint32_t previous_sequence = st->active_sequence;
    if (previous != (int8_t)MC_STORAGE_SLOT_NONE && previous_sequence == UINT32_MAX) {
        return MC_E_RANGE;
    }
    /* The target is never the best slot: that is what keeps the old record intact. */
    const int target = previous == (int8_t)MC_STORAGE_SLOT_A ? 1 : 0;
    const uint32_t base = st->slot_addr[target];
    const uint32_t length = (uint32_t)len;
    const uint32_t sequence = previous == (int8_t)MC_STORAGE_SLOT_NONE ? 1u : previous_sequence + 1u;

    uint8_t hdr[MC_STORAGE_HEADER_SIZE];
    put_le32(hdr + OFF_MAGIC, MC_STORAGE_MAGIC);
    put_le32(hdr + OFF_VERSIONS, MC_STORAGE_LAYOUT_VERSION | ((uint32_t)format_version << 16));
    put_le32(hdr + OFF_SEQUENCE, sequence);
    put_le32(hdr + OFF_LENGTH, length);
    const uint8_t pad[3] = {0xFFu, 0xFFu, 0xFFu};
    const uint32_t body = MC_STORAGE_HEADER_SIZE + padded(length);
    uint32_t crc = mc_crc32_iso_hdlc_update(MC_CRC32_ISO_HDLC_INIT, hdr, sizeof hdr);
    crc = mc_crc32_iso_hdlc_update(crc, payload, length);
    crc = mc_crc32_iso_hdlc_final(mc_crc32_iso_hdlc_update(crc, pad, padded(length) - length));

    s = erase_slot(st, target);
    for (uint32_t off = 0; s == MC_OK && off < MC_STORAGE_HEADER_SIZE; off += 4u) {
        s = program_verified(st, base + off, get_le32(hdr + off));
    }
    for (uint32_t off = 0; s == MC_OK && off < length; off += 4u) {
        uint8_t w[4] = {0xFFu, 0xFFu, 0xFFu, 0xFFu};
        memcpy(w, payload + off, length - off < 4u ? length - off : 4u);
        s = program_verified(st, base + MC_STORAGE_HEADER_SIZE + off, get_le32(w));
    }
    if (s == MC_OK) {
        s = program_verified(st, base + body, crc);
    }
    /* Re-read the whole body before the marker: the marker must only ever follow a body
     * that is on flash as a whole, not just word by word at the time each was written. */
    uint32_t state = MC_CRC32_ISO_HDLC_INIT;
    if (s == MC_OK) {
        s = crc_flash(st, base, body, &state);
    }
    if (s == MC_OK && mc_crc32_iso_hdlc_final(state) != crc) {
        s = MC_E_FLASH;
    }
    if (s != MC_OK) {
        /* Before the commit point: the previous best was never touched and still wins. */
        st->active = previous;
        st->active_sequence = previous_sequence;
        return s;
    }
    /* The commit point: until this word is fully programmed the previous best wins; once its
     * program has been issued, flash alone decides, so every error from here on is settled
     * by scanning both slots as boot would. */
    s = program_verified(st, base + body + 4u, MC_STORAGE_COMMIT_MARKER);
    slot_info_t check;
    if (s == MC_OK) {
        s = scan_slot(st, target, &check);
    }
    if (s == MC_OK && check.valid && check.sequence == sequence && check.length == length
        && check.format_version == format_version) {
        st->active = (int8_t)target;
        st->active_sequence = sequence;
        return MC_OK;
    }
    if (scan(st, info) != MC_OK) {
        return MC_E_OUTCOME_UNKNOWN; /* st says "none": nothing we could check */
    }
    const slot_info_t *won = st->active == (int8_t)MC_STORAGE_SLOT_NONE ? NULL : &info[st->active];
    if (st->active == target && won->sequence == sequence && won->length == length
        && won->format_version == format_version) {
        return MC_OK; /* the new record is complete and wins: committed */
    }
    if (st->active == previous && st->active_sequence == previous_sequence) {
        return MC_E_FLASH; /* the previous best still wins: a definite failure */
    }
    return MC_E_OUTCOME_UNKNOWN; /* neither record as expected (flash changing under us) */
}

mc_status_t mc_storage_active(const mc_storage_t *st, mc_storage_slot_t *slot,
                              uint32_t *sequence)
{
    if (st == NULL || slot == NULL || sequence == NULL) {
        return MC_E_ARG;
    }
    *slot = (mc_storage_slot_t)st->active;
    *sequence = st->active_sequence;
    return st->active == (int8_t)MC_STORAGE_SLOT_NONE ? MC_E_NO_PARAMS : MC_OK;
}
