/* SPDX-License-Identifier: Apache-2.0 */
/* File-backed NOR flash for the POSIX SIL device. See flash_file.h. */
#define _POSIX_C_SOURCE 200809L

#include "flash_file.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* Bytes per pwrite when erasing or creating: small enough for any stack. */
#define FLASH_FILE_BLOCK 256u

static uint64_t region_size(const mc_flash_file_t *ff)
{
    return (uint64_t)ff->page_size * ff->page_count;
}

/* pread/pwrite may transfer less than asked (signals, odd file systems): loop until done. */
static int read_all(int fd, uint8_t *buf, size_t len, off_t off)
{
    while (len > 0) {
        const ssize_t n = pread(fd, buf, len, off);
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n <= 0) {
            return -1;
        }
        buf += n;
        len -= (size_t)n;
        off += n;
    }
    return 0;
}

static int write_all(int fd, const uint8_t *buf, size_t len, off_t off)
{
    while (len > 0) {
        const ssize_t n = pwrite(fd, buf, len, off);
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n <= 0) {
            return -1;
        }
        buf += n;
        len -= (size_t)n;
        off += n;
    }
    return 0;
}

/* Writes 0xFF over [off, off + len). */
static int fill_erased(int fd, off_t off, uint64_t len)
{
    uint8_t block[FLASH_FILE_BLOCK];
    memset(block, 0xFF, sizeof block);
    while (len > 0) {
        const size_t n = len < sizeof block ? (size_t)len : sizeof block;
        if (write_all(fd, block, n, off) != 0) {
            return -1;
        }
        off += (off_t)n;
        len -= n;
    }
    return 0;
}

static mc_status_t file_erase_page(void *ctx, uint32_t page)
{
    mc_flash_file_t *ff = (mc_flash_file_t *)ctx;
    if (ff == NULL || ff->fd < 0) {
        return MC_E_ARG;
    }
    if (page >= ff->page_count) {
        return MC_E_RANGE;
    }
    return fill_erased(ff->fd, (off_t)page * (off_t)ff->page_size, ff->page_size) == 0
               ? MC_OK
               : MC_E_FLASH;
}

static mc_status_t file_program_word(void *ctx, uint32_t addr, uint32_t word)
{
    mc_flash_file_t *ff = (mc_flash_file_t *)ctx;
    if (ff == NULL || ff->fd < 0 || addr % MC_FLASH_WORD_SIZE != 0) {
        return MC_E_ARG;
    }
    if ((uint64_t)addr + MC_FLASH_WORD_SIZE > region_size(ff)) {
        return MC_E_RANGE;
    }
    uint8_t b[MC_FLASH_WORD_SIZE];
    if (read_all(ff->fd, b, sizeof b, (off_t)addr) != 0) {
        return MC_E_FLASH;
    }
    for (unsigned i = 0; i < MC_FLASH_WORD_SIZE; ++i) {
        if (b[i] != 0xFFu) {
            return MC_E_FLASH; /* programmed twice without an erase */
        }
        b[i] = (uint8_t)(b[i] & ((word >> (8u * i)) & 0xFFu));
    }
    return write_all(ff->fd, b, sizeof b, (off_t)addr) == 0 ? MC_OK : MC_E_FLASH;
}

static mc_status_t file_read(void *ctx, uint32_t addr, uint8_t *buf, size_t len)
{
    mc_flash_file_t *ff = (mc_flash_file_t *)ctx;
    if (ff == NULL || ff->fd < 0 || (buf == NULL && len > 0)) {
        return MC_E_ARG;
    }
    if ((uint64_t)addr + len > region_size(ff)) {
        return MC_E_RANGE;
    }
    return read_all(ff->fd, buf, len, (off_t)addr) == 0 ? MC_OK : MC_E_FLASH;
}

static const mc_flash_ops_t file_ops = {file_erase_page, file_program_word, file_read};

/* Creates path as an erased image: written under a temporary name, then link()ed into place
 * (which, unlike rename, fails if the name exists), so the real name only ever holds a
 * complete image. */
static mc_status_t create_erased(const char *path, uint64_t size)
{
    char tmp[4096];
    const int len = snprintf(tmp, sizeof tmp, "%s.tmp%ld", path, (long)getpid());
    if (len < 0 || (size_t)len >= sizeof tmp) {
        return MC_E_ARG;
    }
    const int fd = open(tmp, O_RDWR | O_CREAT | O_TRUNC, 0644);
    if (fd < 0) {
        return MC_E_FLASH;
    }
    int bad = fill_erased(fd, 0, size) != 0 || fsync(fd) != 0;
    bad |= close(fd) != 0;
    /* link() fails if path appeared meanwhile (another process created it): keep theirs. */
    if (!bad && link(tmp, path) != 0 && errno != EEXIST) {
        bad = 1;
    }
    (void)unlink(tmp);
    return bad ? MC_E_FLASH : MC_OK;
}

mc_status_t mc_flash_file_open(mc_flash_file_t *ff, const char *path, uint32_t page_size,
                               uint32_t page_count)
{
    if (ff == NULL) {
        return MC_E_ARG;
    }
    memset(ff, 0, sizeof *ff);
    ff->fd = -1;
    if (path == NULL || page_size == 0 || page_size % MC_FLASH_WORD_SIZE != 0 || page_count == 0
        || (uint64_t)page_size * page_count > 0x7FFFFFFFu) {
        return MC_E_ARG;
    }
    const uint64_t size = (uint64_t)page_size * page_count;
    int fd = open(path, O_RDWR);
    if (fd < 0 && errno == ENOENT) {
        const mc_status_t s = create_erased(path, size);
        if (s != MC_OK) {
            return s;
        }
        fd = open(path, O_RDWR);
    }
    if (fd < 0) {
        return MC_E_FLASH;
    }
    struct stat sb;
    if (fstat(fd, &sb) != 0) {
        (void)close(fd);
        return MC_E_FLASH;
    }
    if (!S_ISREG(sb.st_mode) || (uint64_t)sb.st_size != size) {
        (void)close(fd);
        return MC_E_RANGE;
    }
    ff->fd = fd;
    ff->page_size = page_size;
    ff->page_count = page_count;
    ff->flash.ops = &file_ops;
    ff->flash.ctx = ff;
    ff->flash.page_size = page_size;
    ff->flash.page_count = page_count;
    return MC_OK;
}

mc_status_t mc_flash_file_close(mc_flash_file_t *ff)
{
    if (ff == NULL || ff->fd < 0) {
        return MC_E_ARG;
    }
    const int rc = close(ff->fd);
    ff->fd = -1;
    ff->flash.ops = NULL;
    return rc == 0 ? MC_OK : MC_E_FLASH;
}
