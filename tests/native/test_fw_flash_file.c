/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The POSIX file-backed flash (firmware/port/posix/flash_file.c) and the storage over it.
 *
 * Ports are outside the library's sources (firmware/src), and `make test-native` compiles each
 * test_fw_*.c alone with those sources, so this test #includes the port's .c file: the port
 * is compiled exactly once, in this program, with the same flags and sanitizers. (The make
 * rule does not list the port as a prerequisite: touch this test after editing the port.)
 *
 * Checks: a new file is created erased at the right size; NOR rules (AND, once per erase,
 * alignment, range); contents survive close and reopen; a file of another geometry is
 * refused; parameters committed through mc_storage survive a "restart"; and a child process
 * killed (_exit) before each flash operation of a commit leaves a file from which the next
 * process loads exactly the old parameters (or the new ones once the commit completed).
 */
#define _POSIX_C_SOURCE 200809L
#include "../../firmware/port/posix/flash_file.c"

#include "check.h"
#include "magcal/storage.h"

#include <stdlib.h>
#include <sys/wait.h>

#define PAGE_SIZE 128u
#define PAGE_COUNT 4u

static char dir[64];
static char path[128];

static long file_size(const char *p)
{
    struct stat sb;
    return stat(p, &sb) == 0 ? (long)sb.st_size : -1;
}

static void test_file_flash(void)
{
    mc_flash_file_t ff;
    uint8_t buf[PAGE_SIZE * PAGE_COUNT];

    CHECK_EQ_INT(mc_flash_file_open(NULL, path, PAGE_SIZE, PAGE_COUNT), MC_E_ARG);
    CHECK_EQ_INT(mc_flash_file_open(&ff, NULL, PAGE_SIZE, PAGE_COUNT), MC_E_ARG);
    CHECK_EQ_INT(mc_flash_file_open(&ff, path, 0, PAGE_COUNT), MC_E_ARG);
    CHECK_EQ_INT(mc_flash_file_open(&ff, path, 6, PAGE_COUNT), MC_E_ARG);
    CHECK_EQ_INT(mc_flash_file_open(&ff, path, PAGE_SIZE, 0), MC_E_ARG);
    CHECK_EQ_INT(mc_flash_file_open(&ff, path, 0x10000u, 0x8000u), MC_E_ARG);
    CHECK_EQ_INT(file_size(path), -1); /* argument errors create nothing */
    CHECK_EQ_INT(mc_flash_file_close(NULL), MC_E_ARG);

    /* A new file: erased, the region's size, no temporary left behind. */
    CHECK_EQ_INT(mc_flash_file_open(&ff, path, PAGE_SIZE, PAGE_COUNT), MC_OK);
    CHECK_EQ_INT(file_size(path), PAGE_SIZE * PAGE_COUNT);
    const mc_flash_t *f = &ff.flash;
    CHECK(f->ops != NULL && f->ctx == &ff);
    CHECK_EQ_INT(f->page_size, PAGE_SIZE);
    CHECK_EQ_INT(f->page_count, PAGE_COUNT);
    CHECK_EQ_INT(f->ops->read(f->ctx, 0, buf, sizeof buf), MC_OK);
    int erased = 1;
    for (size_t i = 0; i < sizeof buf; ++i) {
        erased &= buf[i] == 0xFFu;
    }
    CHECK(erased);

    /* Program: little-endian, once per erase, aligned, in range. */
    CHECK_EQ_INT(f->ops->program_word(f->ctx, 132, 0x11223344u), MC_OK);
    CHECK_EQ_INT(f->ops->read(f->ctx, 132, buf, 4), MC_OK);
    CHECK(buf[0] == 0x44 && buf[1] == 0x33 && buf[2] == 0x22 && buf[3] == 0x11);
    CHECK_EQ_INT(f->ops->program_word(f->ctx, 132, 0x01020304u), MC_E_FLASH);
    CHECK_EQ_INT(f->ops->read(f->ctx, 132, buf, 4), MC_OK);
    CHECK(buf[0] == 0x44 && buf[3] == 0x11); /* the refused program changed nothing */
    CHECK_EQ_INT(f->ops->program_word(f->ctx, 2, 0), MC_E_ARG);
    CHECK_EQ_INT(f->ops->program_word(f->ctx, PAGE_SIZE * PAGE_COUNT, 0), MC_E_RANGE);
    CHECK_EQ_INT(f->ops->read(f->ctx, PAGE_SIZE * PAGE_COUNT - 2, buf, 4), MC_E_RANGE);
    CHECK_EQ_INT(f->ops->read(f->ctx, 0, NULL, 4), MC_E_ARG);
    CHECK_EQ_INT(f->ops->erase_page(f->ctx, PAGE_COUNT), MC_E_RANGE);
    /* Programming only clears bits: 0xFF bytes in the word leave the flash erased there. */
    CHECK_EQ_INT(f->ops->program_word(f->ctx, 0, 0xFF00FF5Au), MC_OK);
    CHECK_EQ_INT(f->ops->read(f->ctx, 0, buf, 4), MC_OK);
    CHECK(buf[0] == 0x5A && buf[1] == 0xFF && buf[2] == 0x00 && buf[3] == 0xFF);

    /* Survives close and reopen; erase touches only its page. */
    CHECK_EQ_INT(mc_flash_file_close(&ff), MC_OK);
    CHECK_EQ_INT(mc_flash_file_close(&ff), MC_E_ARG);
    CHECK_EQ_INT(mc_flash_file_open(&ff, path, PAGE_SIZE, PAGE_COUNT), MC_OK);
    CHECK_EQ_INT(f->ops->read(f->ctx, 132, buf, 4), MC_OK);
    CHECK(buf[0] == 0x44 && buf[3] == 0x11);
    CHECK_EQ_INT(f->ops->erase_page(f->ctx, 0), MC_OK);
    CHECK_EQ_INT(f->ops->read(f->ctx, 0, buf, 4), MC_OK);
    CHECK(buf[0] == 0xFF && buf[2] == 0xFF);
    CHECK_EQ_INT(f->ops->read(f->ctx, 132, buf, 4), MC_OK);
    CHECK(buf[0] == 0x44);
    CHECK_EQ_INT(f->ops->erase_page(f->ctx, 1), MC_OK);
    CHECK_EQ_INT(f->ops->program_word(f->ctx, 132, 0x01020304u), MC_OK); /* erased: allowed */
    CHECK_EQ_INT(mc_flash_file_close(&ff), MC_OK);

    /* Another geometry is refused, and the file is left as it was. */
    CHECK_EQ_INT(mc_flash_file_open(&ff, path, PAGE_SIZE, PAGE_COUNT + 1u), MC_E_RANGE);
    CHECK(ff.fd == -1 && ff.flash.ops == NULL);
    CHECK_EQ_INT(mc_flash_file_open(&ff, path, PAGE_SIZE * 2u, PAGE_COUNT), MC_E_RANGE);
    CHECK_EQ_INT(file_size(path), PAGE_SIZE * PAGE_COUNT);
    /* A path in a missing directory cannot be created. */
    char missing[160];
    snprintf(missing, sizeof missing, "%s/no/such/flash.bin", dir);
    CHECK_EQ_INT(mc_flash_file_open(&ff, missing, PAGE_SIZE, PAGE_COUNT), MC_E_FLASH);
    CHECK_EQ_INT(unlink(path), 0);
}

/* ------------------------------------------------------------------ storage over the file */

static const uint8_t old_params[] = "old parameter set, 36 bytes long...";
static const uint8_t new_params[] = "the new parameter set: longer, 50 bytes of it....";

/* One "process": open the file, boot the storage, load. */
static mc_status_t restart_and_load(uint8_t *out, size_t *len, uint32_t *seq)
{
    mc_flash_file_t ff;
    mc_storage_t st;
    uint16_t fmt = 0;
    mc_status_t s = mc_flash_file_open(&ff, path, PAGE_SIZE, PAGE_COUNT);
    if (s != MC_OK) {
        return s;
    }
    s = mc_storage_init(&st, &ff.flash, 0, 2, 2);
    if (s == MC_OK) {
        s = mc_storage_load(&st, out, MC_STORAGE_PAYLOAD_MAX, len, &fmt, seq);
    }
    (void)mc_flash_file_close(&ff);
    return s;
}

static mc_status_t commit_once(const uint8_t *p, size_t n)
{
    mc_flash_file_t ff;
    mc_storage_t st;
    mc_status_t s = mc_flash_file_open(&ff, path, PAGE_SIZE, PAGE_COUNT);
    if (s != MC_OK) {
        return s;
    }
    s = mc_storage_init(&st, &ff.flash, 0, 2, 2);
    if (s == MC_OK) {
        s = mc_storage_commit(&st, p, n, 3);
    }
    (void)mc_flash_file_close(&ff);
    return s;
}

/* The child's flash: the file flash, but the process dies before its `kill_before`-th
 * erase or program (as a SIL device killed mid-commit would). */
static const mc_flash_t *kill_inner;
static long kill_before;

static void maybe_die(void)
{
    if (kill_before-- == 0) {
        _exit(0); /* no atexit, no flush: as abrupt as a kill */
    }
}

static mc_status_t kill_erase(void *ctx, uint32_t page)
{
    (void)ctx;
    maybe_die();
    return kill_inner->ops->erase_page(kill_inner->ctx, page);
}

static mc_status_t kill_program(void *ctx, uint32_t addr, uint32_t word)
{
    (void)ctx;
    maybe_die();
    return kill_inner->ops->program_word(kill_inner->ctx, addr, word);
}

static mc_status_t kill_read(void *ctx, uint32_t addr, uint8_t *buf, size_t len)
{
    (void)ctx;
    return kill_inner->ops->read(kill_inner->ctx, addr, buf, len);
}

static const mc_flash_ops_t kill_ops = {kill_erase, kill_program, kill_read};

static void test_storage_over_file(void)
{
    uint8_t out[MC_STORAGE_PAYLOAD_MAX];
    size_t len = 0;
    uint32_t seq = 0;

    CHECK_EQ_INT(restart_and_load(out, &len, &seq), MC_E_NO_PARAMS);
    CHECK_EQ_INT(commit_once(old_params, sizeof old_params), MC_OK);
    CHECK_EQ_INT(restart_and_load(out, &len, &seq), MC_OK);
    CHECK(len == sizeof old_params && memcmp(out, old_params, len) == 0 && seq == 1);

    /* Operations in an uninterrupted commit of new_params: 2 page erases + its words. */
    const long ops = 2 + (long)MC_STORAGE_RECORD_SIZE(sizeof new_params) / 4;
    long wrong = 0;
    uint8_t image[PAGE_SIZE * PAGE_COUNT];
    FILE *fp = fopen(path, "rb");
    CHECK(fp != NULL && fread(image, 1, sizeof image, fp) == sizeof image);
    if (fp != NULL) {
        fclose(fp);
    }
    for (long k = 0; k <= ops; ++k) {
        /* Restore the "old only" image, then let a child commit and die before op k. */
        fp = fopen(path, "wb");
        if (fp == NULL || fwrite(image, 1, sizeof image, fp) != sizeof image) {
            ++wrong;
        }
        if (fp != NULL) {
            fclose(fp);
        }
        fflush(stdout);
        const pid_t pid = fork();
        if (pid == 0) {
            mc_flash_file_t ff;
            mc_storage_t st;
            if (mc_flash_file_open(&ff, path, PAGE_SIZE, PAGE_COUNT) != MC_OK) {
                _exit(2);
            }
            const mc_flash_t killing = {&kill_ops, NULL, PAGE_SIZE, PAGE_COUNT};
            kill_inner = &ff.flash;
            kill_before = k;
            if (mc_storage_init(&st, &killing, 0, 2, 2) != MC_OK
                || mc_storage_commit(&st, new_params, sizeof new_params, 3) != MC_OK) {
                _exit(3);
            }
            _exit(k == ops ? 0 : 4); /* only the last k lets the commit finish */
        }
        int status = 0;
        wrong += pid < 0 || waitpid(pid, &status, 0) != pid || !WIFEXITED(status)
                 || WEXITSTATUS(status) != 0;
        const mc_status_t s = restart_and_load(out, &len, &seq);
        const int is_old = s == MC_OK && seq == 1 && len == sizeof old_params
                           && memcmp(out, old_params, len) == 0;
        const int is_new = s == MC_OK && seq == 2 && len == sizeof new_params
                           && memcmp(out, new_params, len) == 0;
        wrong += k < ops ? !is_old : !is_new;
        /* And the next process can commit over whatever the dead one left. */
        wrong += commit_once(new_params, sizeof new_params) != MC_OK;
        wrong += restart_and_load(out, &len, &seq) != MC_OK || seq != (k < ops ? 2u : 3u)
                 || memcmp(out, new_params, sizeof new_params) != 0;
    }
    printf("  %ld kills of a committing process: old before the last operation, new after\n",
           ops + 1);
    CHECK_EQ_INT(wrong, 0);
}

int main(void)
{
    snprintf(dir, sizeof dir, "/tmp/magcal_flash_file_XXXXXX");
    if (mkdtemp(dir) == NULL) {
        perror("mkdtemp");
        return 1;
    }
    snprintf(path, sizeof path, "%s/flash.bin", dir);
    test_file_flash();
    test_storage_over_file();
    (void)unlink(path);
    (void)rmdir(dir);
    return check_summary("test_fw_flash_file");
}
