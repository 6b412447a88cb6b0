/* SPDX-License-Identifier: Apache-2.0 */
/*
 * A minimal test harness for the native C tests (no framework to install): CHECK counts and
 * reports, CHECK_EQ_INT prints both sides, and check_summary() prints
 * "<passed> passed, <failed> failed" last and returns the exit status.
 * Include it from exactly one translation unit per test program.
 */
#ifndef MAGCAL_TEST_CHECK_H
#define MAGCAL_TEST_CHECK_H

#include <stdio.h>

static int check_passed, check_failed;

static void check_report(int ok, const char *what, const char *file, int line)
{
    if (ok) {
        ++check_passed;
    } else {
        ++check_failed;
        printf("FAIL %s:%d: %s\n", file, line, what);
    }
}

#define CHECK(cond) check_report((cond) ? 1 : 0, #cond, __FILE__, __LINE__)

#define CHECK_EQ_INT(a, b)                                                                \
    do {                                                                                  \
        const long long check_a_ = (long long)(a), check_b_ = (long long)(b);             \
        if (check_a_ != check_b_) {                                                       \
            printf("  %s = %lld, %s = %lld\n", #a, check_a_, #b, check_b_);               \
        }                                                                                 \
        check_report(check_a_ == check_b_, #a " == " #b, __FILE__, __LINE__);             \
    } while (0)

static int check_summary(const char *program)
{
    printf("%s: %d passed, %d failed\n", program, check_passed, check_failed);
    return check_failed == 0 && check_passed > 0 ? 0 : 1;
}

#endif /* MAGCAL_TEST_CHECK_H */
