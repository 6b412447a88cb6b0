/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Host driver for bench/firmware_figures.py: calls mc_correction_apply N times (argv[1],
 * default 100000) on pseudo-random int16 samples with a realistic parameter set, so that
 * valgrind --tool=callgrind --toggle-collect=mc_correction_apply counts the host
 * instructions of N corrections. Prints "calls=<N> checksum=<hex>" (the checksum keeps the
 * outputs live). Exit status 1 when the parameter set is refused or a call fails.
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

#include "magcal/correction.h"
#include "magcal/params.h"

#define DEFAULT_CALLS 100000UL

/* Q1.30 and Q16.15 mantissas of a real value (exact for the constants below). */
#define Q30(x) ((int32_t)((x) * 1073741824.0))
#define Q15(x) ((int32_t)((x) * 32768.0))

int main(int argc, char **argv)
{
    unsigned long calls = DEFAULT_CALLS;
    if (argc > 1) {
        calls = strtoul(argv[1], NULL, 10);
    }
    /* A unit-scale D^-1 (entries about 1, E_d = 0) with cross-axis terms, a hard-iron offset
     * of a few hundred counts, and output in counts with E_m = 17 (shift s = 31). */
    const mc_params_t p = {
        .version = MC_PARAMS_FORMAT_VERSION,
        .d_inv_exp = 0,
        .out_exp = 17,
        .d_inv = {Q30(0.96875), Q30(0.015625), Q30(-0.0078125),
                  Q30(0.015625), Q30(1.0), Q30(0.00390625),
                  Q30(-0.0078125), Q30(0.00390625), Q30(0.9375)},
        .offset = {Q15(312.5), Q15(-187.25), Q15(41.0)},
    };
    mc_correction_t c;
    mc_status_t st = mc_correction_init(&c, &p);
    if (st != MC_OK) {
        fprintf(stderr, "correction_driver: mc_correction_init refused the parameters (%d)\n",
                (int)st);
        return 1;
    }
    uint32_t lcg = 12345u;
    uint32_t checksum = 0u;
    for (unsigned long k = 0; k < calls; ++k) {
        int16_t raw[3];
        for (int i = 0; i < 3; ++i) {
            lcg = lcg * 1664525u + 1013904223u; /* Numerical Recipes LCG */
            raw[i] = (int16_t)((int32_t)(lcg >> 16) - 32768);
        }
        int32_t out[3];
        st = mc_correction_apply(&c, raw, out);
        if (st != MC_OK) {
            fprintf(stderr, "correction_driver: mc_correction_apply failed (%d)\n", (int)st);
            return 1;
        }
        checksum = checksum * 31u + (uint32_t)out[0] + (uint32_t)out[1] + (uint32_t)out[2];
    }
    printf("calls=%lu checksum=%08lx\n", calls, (unsigned long)checksum);
    return 0;
}
