/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Power-loss-safe storage of one opaque payload (the encoded parameter set) in two flash
 * slots, A and B, over the flash abstraction of flash.h. No malloc; the caller owns the
 * mc_storage_t, the mc_flash_t and the payload buffers.
 *
 * On-flash record (at the start of a slot; all words little-endian, see flash.h):
 *
 *   offset        size  field
 *   0             4     magic MC_STORAGE_MAGIC (the bytes "MCPS")
 *   4             2     layout version MC_STORAGE_LAYOUT_VERSION (this table)
 *   6             2     payload format version (the caller's; opaque to storage)
 *   8             4     sequence number, 1 for the first commit ever, +1 per commit
 *   12            4     payload length n in bytes, 1 .. slot capacity
 *   16            n     payload, then 0xFF padding up to a multiple of 4 (p = padded n)
 *   16 + p        4     CRC-32/ISO-HDLC of bytes [0, 16 + p): header, payload, padding
 *   20 + p        4     commit marker MC_STORAGE_COMMIT_MARKER
 *
 * The rest of the slot is unused (left erased). MC_STORAGE_RECORD_SIZE(n) = 24 + p.
 *
 * A slot is VALID when its magic and layout version match, its length fits the slot, its
 * CRC matches and its commit marker reads exactly MC_STORAGE_COMMIT_MARKER. Of the valid
 * slots the one with the higher sequence number is the current ("best") record; if both
 * are valid with the same sequence (a commit never writes that; only a foreign writer
 * could) slot A wins, so the choice is still deterministic.
 *
 * Commit protocol (mc_storage_commit), writing only the slot that does NOT hold the best:
 *   1. scan both slots afresh (the target never depends on stale RAM state);
 *   2. erase every page of the target slot and read it back: all 0xFF;
 *   3. program header, payload, padding and CRC word by word, reading back each word;
 *   4. read the whole body back and check its CRC again (catches a later program disturbing
 *      an earlier word);
 *   5. program the commit marker last, then scan the slot as boot would.
 * Why this is atomic: the best record is never erased or programmed, so until the marker
 * word is complete it stays valid and wins. A cut during erase or body programming leaves
 * the target without a valid marker + CRC; a cut while programming the marker leaves some
 * of its bits still 1 (programming only clears bits), so it does not read as the marker.
 * Once the marker is complete the new record is valid with sequence best + 1 and wins.
 * Boot therefore finds exactly the old or exactly the new payload, never a mix, and none
 * only if no commit ever completed. The old record stays on flash as the fallback if the new
 * one is later corrupted (a bit flip): its CRC fails and the older slot wins.
 * Residual risks, not covered by any two-slot scheme: a CRC-32 collision on a torn slot
 * (2^-32), and a marginally programmed marker bit that reads differently on later boots.
 *
 * Sequence numbers are uint32_t and compared with plain ">". They cannot wrap in practice:
 * each commit erases a slot, so 2^32 commits would need two billion erase cycles per page
 * against NOR endurance of about 10^5. Should the best record ever hold 0xFFFFFFFF, commit
 * refuses with MC_E_RANGE rather than wrap.
 *
 * Format versions: storage does not interpret the payload format version. mc_storage_load
 * returns it with the payload and the caller decides (decode, migrate or refuse with
 * MC_E_VERSION). A record of another LAYOUT version is not valid to this code.
 */
#ifndef MAGCAL_STORAGE_H
#define MAGCAL_STORAGE_H

#include <stddef.h>
#include <stdint.h>

#include "magcal/config.h"
#include "magcal/flash.h"
#include "magcal/status.h"

#ifdef __cplusplus
extern "C" {
#endif

#define MC_STORAGE_MAGIC 0x5350434Du /* "MCPS" as stored (little-endian) */
#define MC_STORAGE_LAYOUT_VERSION 1u
/* Not 0xFFFFFFFF (erased) and not 0: no partially programmed or partially erased word equals
 * it unless its own bits all completed, and a zeroed word is not mistaken for it. */
#define MC_STORAGE_COMMIT_MARKER 0xC0DE600Du
#define MC_STORAGE_HEADER_SIZE 16u
/* Bytes a record with an n-byte payload occupies in a slot. */
#define MC_STORAGE_RECORD_SIZE(n) (MC_STORAGE_HEADER_SIZE + (((n) + 3u) & ~3u) + 8u)

typedef enum {
    MC_STORAGE_SLOT_NONE = -1, /* no valid record */
    MC_STORAGE_SLOT_A = 0,
    MC_STORAGE_SLOT_B = 1
} mc_storage_slot_t;

/* Instance state; read it through mc_storage_active, not directly. */
typedef struct mc_storage {
    const mc_flash_t *flash;
    uint32_t slot_addr[2];  /* byte address of slot A and slot B */
    uint32_t slot_page[2];  /* first page of each slot */
    uint32_t pages_per_slot;
    uint32_t slot_size;     /* bytes */
    int8_t active;             /* best slot at the last scan (an mc_storage_slot_t value;
                                * stored as int8_t so the layout does not depend on the
                                * enum's size, see firmware/README.md) */
    uint32_t active_sequence;  /* its sequence, 0 when active is NONE */
} mc_storage_t;

/*
 * Sets up st over flash with slot A at pages [slot_a_page, slot_a_page + pages_per_slot) and
 * slot B likewise, then scans both slots to find the best record (mc_storage_active).
 * The flash descriptor must outlive st. init first clears *st, so after an MC_E_ARG or
 * MC_E_RANGE load and commit refuse st with MC_E_ARG (they check st->flash; an instance
 * that init never saw cannot be detected: call init first). Returns:
 *   MC_OK;
 *   MC_E_ARG: st, flash, flash->ops or one of its functions NULL, page_size 0 or not a
 *     multiple of MC_FLASH_WORD_SIZE, page_count or pages_per_slot 0;
 *   MC_E_RANGE: a slot leaves the region, the slots overlap, the region's byte size does not
 *     fit uint32_t, or a slot is smaller than MC_STORAGE_RECORD_SIZE(MC_STORAGE_PAYLOAD_MAX);
 *   MC_E_FLASH: a read failed (st is then set up, with no active slot).
 * Finding no valid record is not an error: mc_storage_active then says MC_E_NO_PARAMS.
 */
mc_status_t mc_storage_init(mc_storage_t *st, const mc_flash_t *flash, uint32_t slot_a_page,
                            uint32_t slot_b_page, uint32_t pages_per_slot);

/*
 * Scans both slots afresh (what boot does), then copies the best record's payload into
 * payload[0 .. *len) and returns its payload format version and sequence. Outputs are all
 * required. Returns:
 *   MC_OK;
 *   MC_E_NO_PARAMS: no slot holds a valid record (*len = 0, *format_version = 0,
 *     *sequence = 0);
 *   MC_E_NO_SPACE: cap is smaller than the stored payload; *len is set to the size needed
 *     and *format_version, *sequence to the record's, nothing is copied;
 *   MC_E_CRC: the payload read into the buffer no longer matched the CRC (a flaky read);
 *   MC_E_FLASH: a read failed;
 *   MC_E_ARG: a NULL pointer (payload may be NULL only if cap is 0), or st not initialised.
 */
mc_status_t mc_storage_load(mc_storage_t *st, uint8_t *payload, size_t cap, size_t *len,
                            uint16_t *format_version, uint32_t *sequence);

/*
 * Atomically replaces the stored payload with payload[0 .. len) tagged format_version, by
 * the protocol above. The previous best record is never erased or programmed.
 * Cost: pages_per_slot page erases and MC_STORAGE_RECORD_SIZE(len) / 4 word programs, all
 * read back; slots alternate, so each slot page is erased once per two commits.
 *
 * Outcome. Before the commit marker's program is issued an error leaves the previous best
 * certainly the best. From that program on, flash alone decides which record a boot loads
 * (the marker may be complete even though its program or read-back reported an error), so
 * on any error after that point commit scans both slots again, sets st from what it finds
 * and returns what flash says rather than the error. So every return but
 * MC_E_OUTCOME_UNKNOWN tells which record a boot would load now:
 *   MC_OK: the new record is the best, with sequence previous best + 1 (1 if there was
 *     none), also when an error occurred after the commit point but the rescan found the
 *     new record complete;
 *   MC_E_ARG: st or payload NULL, st not initialised, len 0 or len > MC_STORAGE_PAYLOAD_MAX
 *     (nothing read or written, st unchanged);
 *   MC_E_RANGE: the best sequence is already 0xFFFFFFFF (see above); nothing written;
 *   MC_E_FLASH: an erase, program or read failed, or flash did not read back as written,
 *     and the previous best (or none) is certainly still the best; st says which. A read
 *     failing in the first scan, before anything is written, also gives MC_E_FLASH and
 *     leaves st as the last init, load or commit set it;
 *   MC_E_OUTCOME_UNKNOWN: an error after the commit point and the rescan failed too (or
 *     found neither record as expected): a boot finds the old or the new record, which one
 *     is unknown. st then says "none" (MC_E_NO_PARAMS from mc_storage_active) until a later
 *     init, load or commit scans successfully; mc_storage_load tells which record won.
 */
mc_status_t mc_storage_commit(mc_storage_t *st, const uint8_t *payload, size_t len,
                              uint16_t format_version);

/*
 * The best slot and its sequence as of the last init, load or commit (no flash access; the
 * host's `flash` command reports it): commit updates it on every return after its first
 * scan, to what flash holds (see mc_storage_commit's outcomes). Returns MC_OK, MC_E_NO_PARAMS when no
 * valid record was found (*slot = MC_STORAGE_SLOT_NONE, *sequence = 0), or MC_E_ARG.
 */
mc_status_t mc_storage_active(const mc_storage_t *st, mc_storage_slot_t *slot,
                              uint32_t *sequence);

#ifdef __cplusplus
}
#endif

#endif /* MAGCAL_STORAGE_H */
