/* SPDX-License-Identifier: Apache-2.0 */
/*
 * A NOR flash (flash.h) kept in a file, for the POSIX software-in-the-loop device: what the
 * device stores survives a restart of the process, and a process killed in the middle of a
 * commit leaves the file as torn as real flash would be at word granularity.
 *
 * The file is exactly page_size * page_count bytes, byte for byte the flash region. A
 * missing file is created filled with 0xFF (erased); creation writes and fsyncs a temporary
 * file next to it, hard-links it to the real name with link() and removes the temporary name,
 * so a crash while creating never leaves a short file under the real name. link() rather than
 * rename(): it fails instead of replacing when the name already exists, so if another process
 * created the file meanwhile, theirs is kept (EEXIST is not an error). An existing
 * file of another size is refused (MC_E_RANGE) rather than resized: a different geometry
 * would silently move the slots.
 *
 * NOR rules are enforced, not just imitated, so the SIL catches what real flash would punish:
 * erase sets a page to 0xFF; program_word stores the word little-endian and ANDs it into the
 * flash (programming only clears bits), and refuses with MC_E_FLASH a word that is not fully
 * erased (flash.h: a word is programmed at most once per erase). Misaligned addresses are
 * MC_E_ARG, anything outside the region MC_E_RANGE, I/O errors MC_E_FLASH.
 *
 * Durability: every operation is a pread/pwrite straight to the kernel (no stdio buffer), so
 * it survives the process being killed; it is not fsync'ed, so a host OS crash may lose the
 * last writes. One process per file (there is no locking).
 *
 * Use: mc_flash_file_open(&ff, path, page_size, page_count), then pass &ff.flash to
 * mc_storage_init; mc_flash_file_close(&ff) at exit.
 */
#ifndef MAGCAL_PORT_POSIX_FLASH_FILE_H
#define MAGCAL_PORT_POSIX_FLASH_FILE_H

#include <stdint.h>

#include "magcal/flash.h"
#include "magcal/status.h"

typedef struct mc_flash_file {
    mc_flash_t flash; /* the descriptor to hand to the library; ctx points to this struct */
    int fd;           /* -1 when closed */
    uint32_t page_size;
    uint32_t page_count;
} mc_flash_file_t;

/*
 * Opens (or creates, erased) the flash file at path. page_size must be a non-zero multiple of
 * MC_FLASH_WORD_SIZE and page_size * page_count at most 2^31 - 1 bytes (a file offset on any
 * POSIX system). Returns MC_OK; MC_E_ARG for NULL pointers or bad geometry; MC_E_RANGE for an
 * existing file of another size; MC_E_FLASH when the file cannot be opened, created or read.
 * On error ff is left closed (fd -1, flash.ops NULL).
 */
mc_status_t mc_flash_file_open(mc_flash_file_t *ff, const char *path, uint32_t page_size,
                               uint32_t page_count);

/* Closes the file. Returns MC_OK, MC_E_ARG (NULL or not open) or MC_E_FLASH (close failed). */
mc_status_t mc_flash_file_close(mc_flash_file_t *ff);

#endif /* MAGCAL_PORT_POSIX_FLASH_FILE_H */
