/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The EKF likelihood kernel (host/csrc/mekf_likelihood.c, mekf_fisher.c) on its own, no Python: built and
 * run by `make test-native` under AddressSanitizer and UndefinedBehaviorSanitizer with
 * -std=c99 -Wall -Wextra -Wpedantic -Werror.
 *
 * A synthetic, smoothly rotating session (N samples at 100 Hz, some with accelerometer
 * inflation c_t > 0 and most with c_t = 0) is evaluated away from its true parameters:
 * - mc_mekf_cost and mc_mekf_cost_grad return the same cost, with and without
 *   magnetometer, and the forward outputs are finite;
 * - gradient components match fourth-order central differences of mc_mekf_cost to 1e-6
 *   relative;
 * - every argument error (NULL pointers, n = 0, short tape) and a covariance that is not
 *   positive definite give NaN, and mc_mekf_cost_grad then leaves a zero gradient;
 * - measurement masks: all-present masks give bit-identical results to none; with some
 *   samples lacking the accelerometer, the magnetometer or both (their values NaN, which
 *   must not be read) the two entry points agree, the outputs are NaN exactly for the
 *   absent measurements and the gradient matches central differences; with no
 *   measurement anywhere the cost and the gradient are zero;
 * - the Fisher pass (mekf_fisher.c): its cost and its derivatives along the model's unit
 *   directions equal mc_mekf_cost_grad's, unmasked and masked, with and without a delay.
 * Prints "<passed> passed, <failed> failed" last and exits non-zero on any failure.
 */
#include "mekf_likelihood.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#define N 300
#define RATE_HZ 100.0
#define GRAVITY 9.81
#define PI 3.14159265358979323846

static int n_passed, n_failed;

static void check(int ok, const char *what, int line)
{
    if (ok) {
        ++n_passed;
    } else {
        ++n_failed;
        printf("FAIL (line %d): %s\n", line, what);
    }
}

#define CHECK(cond) check((cond) ? 1 : 0, #cond, __LINE__)

/* ------------------------------------------------------------ synthetic session */

static double dt[N], gyr[3 * N], acc[3 * N], mag[3 * N], extra[N], turn[N], zeros[N];
static double tape[MC_MEKF_TAPE_DOUBLES * N];
static double q_filt[4 * N], innov[6 * N], normalised[6 * N];
static unsigned char ones[N], nothing[N], has_acc[N], has_mag[N];
static double acc_gaps[3 * N], mag_gaps[3 * N], extra_gaps[N];

/* xorshift64*: deterministic noise, uniform in [−√3, √3) (unit variance). */
static uint64_t rng_state = 0x9E3779B97F4A7C15u;

static double noise(void)
{
    rng_state ^= rng_state >> 12;
    rng_state ^= rng_state << 25;
    rng_state ^= rng_state >> 27;
    const uint64_t r = rng_state * 0x2545F4914F6CDD1Du;
    return sqrt(3.0) * (2.0 * (double)(r >> 11) / 9007199254740992.0 - 1.0);
}

static void quat_mul(const double *p, const double *q, double *r)
{
    r[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3];
    r[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2];
    r[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1];
    r[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0];
}

/* exp_q(v) = (cos|v|, sin|v| v/|v|), |v| > 0 */
static void quat_exp(const double *v, double *q)
{
    const double a = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    q[0] = cos(a);
    for (int i = 0; i < 3; ++i) q[i + 1] = sin(a) / a * v[i];
}

/* R(q_nb), row-major: body to navigation frame. */
static void quat_to_mat(const double *q, double *R)
{
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    R[0] = 1 - 2 * (y * y + z * z);
    R[1] = 2 * (x * y - w * z);
    R[2] = 2 * (x * z + w * y);
    R[3] = 2 * (x * y + w * z);
    R[4] = 1 - 2 * (x * x + z * z);
    R[5] = 2 * (y * z - w * x);
    R[6] = 2 * (x * z - w * y);
    R[7] = 2 * (y * z + w * x);
    R[8] = 1 - 2 * (x * x + y * y);
}

static void set_diag(double *S, double a, double b, double c, double off)
{
    for (int i = 0; i < 9; ++i) S[i] = off;
    S[0] = a;
    S[4] = b;
    S[8] = c;
}

/* The true model, the session drawn from it, and a model away from the truth at which the
 * gradient is checked (so its components are far from zero). */
static void make_problem(mc_mekf_model_t *truth, mc_mekf_model_t *model, mc_mekf_data_t *data)
{
    const double T = 1.0 / RATE_HZ, dip = 70.0 * PI / 180.0;
    const double D[9] = {1.05, 0.08, -0.03, 0.02, 0.95, 0.06, -0.04, 0.05, 1.10};
    memset(truth, 0, sizeof *truth);
    memcpy(truth->D, D, sizeof D);
    truth->o[0] = 0.15;
    truth->o[1] = -0.2;
    truth->o[2] = 0.1;
    truth->m[0] = cos(dip);
    truth->m[2] = -sin(dip);
    truth->bias[0] = 0.01;
    truth->bias[1] = -0.02;
    truth->bias[2] = 0.005;
    set_diag(truth->Sw, 2.6e-5, 3.1e-5, 2.1e-5, 1e-6);
    set_diag(truth->Sa, 2.5e-3, 3.0e-3, 2.0e-3, 0.0);
    set_diag(truth->Sm, 1.0e-4, 1.2e-4, 0.9e-4, 0.0);

    double q[4] = {0.9, 0.1, -0.3, 0.2}, R[9];
    const double qn = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    for (int i = 0; i < 4; ++i) q[i] /= qn;
    const double q_true0[4] = {q[0], q[1], q[2], q[3]};
    for (int k = 0; k < N; ++k) {
        const double t = k * T;
        const double w[3] = {0.5 + 0.4 * sin(0.9 * t), cos(0.5 * t), -0.7 + 0.3 * sin(1.3 * t + 0.4)};
        quat_to_mat(q, R);
        double mb[3];
        for (int i = 0; i < 3; ++i) {
            mb[i] = R[i] * truth->m[0] + R[3 + i] * truth->m[1] + R[6 + i] * truth->m[2];
            acc[3 * k + i] = GRAVITY * R[6 + i] + 0.05 * noise(); /* −Rᵀ g_n, g_n = (0, 0, −g) */
            gyr[3 * k + i] = w[i] + truth->bias[i] + 0.005 * noise();
        }
        for (int i = 0; i < 3; ++i)
            mag[3 * k + i] = D[3 * i] * mb[0] + D[3 * i + 1] * mb[1] + D[3 * i + 2] * mb[2] +
                             truth->o[i] + 0.01 * noise();
        dt[k] = k == 0 ? 0.0 : T;
        extra[k] = k % 7 == 3 ? 0.01 * (1.0 + (double)(k % 5)) : 0.0; /* one in seven inflated */
        /* one in five: the size of T² Σω, as a rate change of ~0.05 rad/s within a step gives */
        turn[k] = k % 5 == 2 ? 2e-9 * (1.0 + (double)(k % 3)) : 0.0;
        zeros[k] = 0.0;
        double half[3], dq[4], qn1[4];
        for (int i = 0; i < 3; ++i) half[i] = 0.5 * T * w[i];
        quat_exp(half, dq);
        quat_mul(q, dq, qn1);
        memcpy(q, qn1, sizeof q);
    }

    memset(data, 0, sizeof *data);
    data->n = N;
    data->dt = dt;
    data->gyr = gyr;
    data->acc = acc;
    data->mag = mag;
    data->acc_extra_var = extra;
    data->turn_var = turn;
    data->g = GRAVITY;
    const double err[3] = {0.05, -0.03, 0.1}; /* prior a few degrees off */
    double e[4];
    quat_exp(err, e);
    quat_mul(e, q_true0, data->q0);
    const double s2 = (10.0 * PI / 180.0) * (10.0 * PI / 180.0);
    set_diag(data->P0, s2, s2, s2, 0.0);
    data->use_mag = 1;

    *model = *truth;
    model->D[0] *= 1.03;
    model->D[5] += 0.02;
    model->o[1] += 0.03;
    model->m[0] *= 0.98;
    model->m[2] *= 1.02;
    model->bias[0] += 0.004;
    model->bias[2] -= 0.003;
    set_diag(model->Sw, 4.0e-5, 2.0e-5, 3.5e-5, 3e-6);
    set_diag(model->Sa, 4.0e-3, 2.0e-3, 3.0e-3, 4e-4);
    set_diag(model->Sm, 2.0e-4, 0.8e-4, 1.5e-4, 1e-5);
}

/* ------------------------------------------------------------ checks */

static void flat(const mc_mekf_model_t *m, double *v) { memcpy(v, m, sizeof *m); }

static int all_zero(const mc_mekf_model_t *m)
{
    double v[MC_MEKF_MODEL_DOUBLES];
    flat(m, v);
    for (int i = 0; i < MC_MEKF_MODEL_DOUBLES; ++i)
        if (v[i] != 0.0) return 0;
    return 1;
}

static void fill_garbage(mc_mekf_model_t *m)
{
    double v[MC_MEKF_MODEL_DOUBLES];
    for (int i = 0; i < MC_MEKF_MODEL_DOUBLES; ++i) v[i] = 1.0 + i;
    memcpy(m, v, sizeof *m);
}

/* V with flat entry i of the model moved by h. */
static double cost_at(const mc_mekf_model_t *model, const mc_mekf_data_t *data, int i, double h)
{
    double v[MC_MEKF_MODEL_DOUBLES];
    mc_mekf_model_t m;
    flat(model, v);
    v[i] += h;
    memcpy(&m, v, sizeof m);
    return mc_mekf_cost(&m, data, NULL);
}

/* ∂V/∂(flat entry i) by fourth-order central differences (truncation O(h⁴)). */
static double central_difference(const mc_mekf_model_t *model, const mc_mekf_data_t *data, int i,
                                 double h)
{
    const double f1 = cost_at(model, data, i, h) - cost_at(model, data, i, -h);
    const double f2 = cost_at(model, data, i, 2 * h) - cost_at(model, data, i, -2 * h);
    return (8.0 * f1 - f2) / (12.0 * h);
}

typedef struct {
    const char *name;
    int index; /* into the flat model */
    double h;  /* finite-difference step */
} component_t;

#define IDX(field, k) ((int)(offsetof(mc_mekf_model_t, field) / sizeof(double)) + (k))

static void check_gradient(const mc_mekf_model_t *model, const mc_mekf_data_t *data,
                           const component_t *comps, int n_comps)
{
    mc_mekf_model_t grad;
    const double c = mc_mekf_cost_grad(model, data, tape, sizeof tape / sizeof tape[0], &grad);
    CHECK(isfinite(c));
    double g[MC_MEKF_MODEL_DOUBLES];
    flat(&grad, g);
    for (int j = 0; j < n_comps; ++j) {
        const double fd = central_difference(model, data, comps[j].index, comps[j].h);
        const double err = fabs(g[comps[j].index] - fd);
        const int ok = isfinite(fd) && err <= 1e-6 * fabs(fd);
        if (!ok)
            printf("  %s (mag %d): gradient %.12g, central difference %.12g, relative %.2g\n",
                   comps[j].name, data->use_mag, g[comps[j].index], fd, err / fabs(fd));
        check(ok, comps[j].name, __LINE__);
    }
}

static void test_costs_agree(const mc_mekf_model_t *model, mc_mekf_data_t data)
{
    for (int use_mag = 1; use_mag >= 0; --use_mag) {
        data.use_mag = use_mag;
        if (!use_mag) data.mag = NULL; /* not read without magnetometer */
        mc_mekf_model_t grad;
        const double c = mc_mekf_cost(model, &data, NULL);
        const double cg = mc_mekf_cost_grad(model, &data, tape, sizeof tape / sizeof tape[0], &grad);
        CHECK(isfinite(c));
        CHECK(c == cg);
        if (c != cg) printf("  use_mag %d: cost %.17g, cost_grad %.17g\n", use_mag, c, cg);
        /* NULL acc_extra_var means all zeros. */
        mc_mekf_data_t d0 = data, dz = data;
        d0.acc_extra_var = NULL;
        dz.acc_extra_var = zeros;
        CHECK(mc_mekf_cost(model, &d0, NULL) == mc_mekf_cost(model, &dz, NULL));
        /* The forward outputs. */
        const mc_mekf_outputs_t out = {q_filt, innov, normalised};
        memset(innov, 0xff, sizeof innov); /* NaN patterns: every entry must be written */
        CHECK(mc_mekf_cost(model, &data, &out) == c);
        int finite = 1, mag_zero = 1;
        for (int k = 0; k < N; ++k) {
            for (int i = 0; i < 4; ++i) finite &= isfinite(q_filt[4 * k + i]) != 0;
            for (int i = 0; i < 6; ++i)
                finite &= isfinite(innov[6 * k + i]) && isfinite(normalised[6 * k + i]);
            for (int i = 3; i < 6; ++i)
                mag_zero &= innov[6 * k + i] == 0.0 && normalised[6 * k + i] == 0.0;
        }
        CHECK(finite);
        CHECK(use_mag || mag_zero);
    }
}

/* Masks: a fixed pattern with samples lacking the accelerometer (k % 3 == 1), the
 * magnetometer (k % 2 == 1) and both (k % 6 == 1); absent values are NaN. */
static void make_masks(const mc_mekf_data_t *data, mc_mekf_data_t *masked)
{
    for (int k = 0; k < N; ++k) {
        ones[k] = 1;
        nothing[k] = 0;
        has_acc[k] = k % 3 != 1;
        has_mag[k] = k % 2 != 1;
        extra_gaps[k] = has_acc[k] ? extra[k] : NAN;
        for (int i = 0; i < 3; ++i) {
            acc_gaps[3 * k + i] = has_acc[k] ? acc[3 * k + i] : NAN;
            mag_gaps[3 * k + i] = has_mag[k] ? mag[3 * k + i] : NAN;
        }
    }
    *masked = *data;
    masked->acc = acc_gaps;
    masked->mag = mag_gaps;
    masked->acc_extra_var = extra_gaps;
    masked->has_acc = has_acc;
    masked->has_mag = has_mag;
}

static void test_masks(const mc_mekf_model_t *model, const mc_mekf_data_t *data,
                       const mc_mekf_data_t *masked)
{
    const size_t full = sizeof tape / sizeof tape[0];
    for (int use_mag = 1; use_mag >= 0; --use_mag) {
        /* All present: bit-identical to no masks. */
        mc_mekf_data_t d = *data, d1 = *data;
        d.use_mag = d1.use_mag = use_mag;
        d1.has_acc = d1.has_mag = ones;
        mc_mekf_model_t g0, g1;
        const double c0 = mc_mekf_cost_grad(model, &d, tape, full, &g0);
        const double c1 = mc_mekf_cost_grad(model, &d1, tape, full, &g1);
        CHECK(isfinite(c0) && c0 == c1);
        CHECK(memcmp(&g0, &g1, sizeof g0) == 0);
        CHECK(mc_mekf_cost(model, &d1, NULL) == mc_mekf_cost(model, &d, NULL));

        /* Some absent: both entry points agree; outputs NaN exactly where absent. */
        mc_mekf_data_t m = *masked;
        m.use_mag = use_mag;
        const mc_mekf_outputs_t out = {q_filt, innov, normalised};
        const double c = mc_mekf_cost(model, &m, &out);
        CHECK(isfinite(c));
        CHECK(c == mc_mekf_cost_grad(model, &m, tape, full, &g1));
        CHECK(c != mc_mekf_cost(model, &d, NULL)); /* the masks are not ignored */
        int nan_ok = 1, q_ok = 1;
        for (int k = 0; k < N; ++k) {
            for (int i = 0; i < 4; ++i) q_ok &= isfinite(q_filt[4 * k + i]) != 0;
            for (int i = 0; i < 6; ++i) {
                const int present = i < 3 ? has_acc[k] : has_mag[k];
                const double x = innov[6 * k + i], z = normalised[6 * k + i];
                if (i >= 3 && !use_mag)
                    nan_ok &= x == 0.0 && z == 0.0;
                else if (present)
                    nan_ok &= isfinite(x) && isfinite(z);
                else
                    nan_ok &= isnan(x) && isnan(z);
            }
        }
        CHECK(q_ok);
        CHECK(nan_ok);

        /* No measurement anywhere: pure propagation, cost 0 and a zero gradient. */
        m.has_acc = m.has_mag = nothing;
        fill_garbage(&g1);
        CHECK(mc_mekf_cost_grad(model, &m, tape, full, &g1) == 0.0);
        CHECK(all_zero(&g1));
        CHECK(mc_mekf_cost(model, &m, NULL) == 0.0);
    }
}

static void test_argument_errors(const mc_mekf_model_t *model, const mc_mekf_data_t *data)
{
    const size_t full = sizeof tape / sizeof tape[0];
    mc_mekf_model_t grad;
    mc_mekf_data_t d;

#define EXPECT_NAN_AND_ZERO_GRAD(model_, data_, tape_, len_)                                 \
    do {                                                                                      \
        fill_garbage(&grad);                                                                  \
        CHECK(isnan(mc_mekf_cost_grad((model_), (data_), (tape_), (len_), &grad)));          \
        CHECK(all_zero(&grad));                                                               \
    } while (0)

    CHECK(isnan(mc_mekf_cost(NULL, data, NULL)));
    CHECK(isnan(mc_mekf_cost(model, NULL, NULL)));
    EXPECT_NAN_AND_ZERO_GRAD(NULL, data, tape, full);
    EXPECT_NAN_AND_ZERO_GRAD(model, NULL, tape, full);
    EXPECT_NAN_AND_ZERO_GRAD(model, data, NULL, full);
    CHECK(isnan(mc_mekf_cost_grad(model, data, tape, full, NULL)));

    d = *data;
    d.dt = NULL;
    CHECK(isnan(mc_mekf_cost(model, &d, NULL)));
    EXPECT_NAN_AND_ZERO_GRAD(model, &d, tape, full);
    d = *data;
    d.gyr = NULL;
    CHECK(isnan(mc_mekf_cost(model, &d, NULL)));
    EXPECT_NAN_AND_ZERO_GRAD(model, &d, tape, full);
    d = *data;
    d.acc = NULL;
    CHECK(isnan(mc_mekf_cost(model, &d, NULL)));
    EXPECT_NAN_AND_ZERO_GRAD(model, &d, tape, full);
    d = *data;
    d.mag = NULL; /* with use_mag */
    CHECK(isnan(mc_mekf_cost(model, &d, NULL)));
    EXPECT_NAN_AND_ZERO_GRAD(model, &d, tape, full);
    d = *data;
    d.n = 0;
    CHECK(isnan(mc_mekf_cost(model, &d, NULL)));
    EXPECT_NAN_AND_ZERO_GRAD(model, &d, tape, full);

    /* A tape one double short; and one exactly long enough for fewer samples. */
    EXPECT_NAN_AND_ZERO_GRAD(model, data, tape, full - 1);
    d = *data;
    d.n = N / 2;
    EXPECT_NAN_AND_ZERO_GRAD(model, data, tape, MC_MEKF_TAPE_DOUBLES * d.n);
    fill_garbage(&grad);
    CHECK(isfinite(mc_mekf_cost_grad(model, &d, tape, MC_MEKF_TAPE_DOUBLES * d.n, &grad)));
    CHECK(!all_zero(&grad));

    /* Not positive definite: a noise covariance (caught before the pass) and the prior
     * (caught in the first step, after the tape is partly written). */
    mc_mekf_model_t bad = *model;
    set_diag(bad.Sa, -1.0, 1.0, 1.0, 0.0);
    CHECK(isnan(mc_mekf_cost(&bad, data, NULL)));
    EXPECT_NAN_AND_ZERO_GRAD(&bad, data, tape, full);
    bad = *model;
    set_diag(bad.Sm, 1e-4, 1e-4, 0.0, 0.0);
    CHECK(isnan(mc_mekf_cost(&bad, data, NULL)));
    EXPECT_NAN_AND_ZERO_GRAD(&bad, data, tape, full);
    d = *data;
    set_diag(d.P0, 1e-2, -1e-2, 1e-2, 0.0);
    CHECK(isnan(mc_mekf_cost(model, &d, NULL)));
    EXPECT_NAN_AND_ZERO_GRAD(model, &d, tape, full);
#undef EXPECT_NAN_AND_ZERO_GRAD
}

/* mc_mekf_fisher along the 46 unit directions of the model: the same cost as mc_mekf_cost,
 * the derivative along each direction equal to mc_mekf_cost_grad's gradient to 1e-9 of its
 * largest component, a symmetric information with a non-negative diagonal; and NaN for every
 * argument error, with info and grad zeroed where k itself is valid. */
static double fisher_work[MC_MEKF_FISHER_WORK_DOUBLES(MC_MEKF_MODEL_DOUBLES)];
static double fisher_info[MC_MEKF_MODEL_DOUBLES * MC_MEKF_MODEL_DOUBLES];

static void test_fisher(const mc_mekf_model_t *model, const mc_mekf_data_t *data)
{
    enum { K = MC_MEKF_MODEL_DOUBLES };
    static double dirs[K * K];
    memset(dirs, 0, sizeof dirs);
    for (int i = 0; i < K; ++i) dirs[K * i + i] = 1.0;
    double fgrad[K], rgrad[K];
    const size_t work_len = sizeof fisher_work / sizeof fisher_work[0];
    const double c = mc_mekf_fisher(model, data, dirs, K, fisher_work, work_len, fisher_info,
                                    fgrad);
    mc_mekf_model_t grad;
    const double cg = mc_mekf_cost_grad(model, data, tape, sizeof tape / sizeof tape[0], &grad);
    flat(&grad, rgrad);
    CHECK(isfinite(c) && c == cg);
    double largest = 0.0, worst = 0.0;
    for (int i = 0; i < K; ++i) largest = fmax(largest, fabs(rgrad[i]));
    for (int i = 0; i < K; ++i) worst = fmax(worst, fabs(fgrad[i] - rgrad[i]));
    CHECK(worst <= 1e-9 * largest);
    int symmetric = 1, diagonal = 1;
    for (int i = 0; i < K; ++i) {
        diagonal &= fisher_info[K * i + i] >= 0.0;
        for (int j = 0; j < K; ++j) symmetric &= fisher_info[K * i + j] == fisher_info[K * j + i];
    }
    CHECK(symmetric && diagonal);

    /* Argument errors: NaN, and info and grad zeroed. */
    const size_t need = MC_MEKF_FISHER_WORK_DOUBLES((size_t)K);
    const struct {
        const double *dirs;
        size_t k;
        double *work;
        size_t len;
    } bad[] = {
        {NULL, K, fisher_work, need},
        {dirs, 0, fisher_work, need},
        {dirs, MC_MEKF_FISHER_MAX_DIRECTIONS + 1, fisher_work, need},
        {dirs, K, NULL, need},
        {dirs, K, fisher_work, need - 1},
    };
    for (size_t b = 0; b < sizeof bad / sizeof bad[0]; ++b) {
        const size_t k = bad[b].k <= K ? bad[b].k : 0; /* a k out of range: nothing written */
        for (size_t i = 0; i < k * k; ++i) fisher_info[i] = 1.0;
        for (size_t i = 0; i < k; ++i) fgrad[i] = 1.0;
        const double v = mc_mekf_fisher(model, data, bad[b].dirs, bad[b].k, bad[b].work,
                                        bad[b].len, fisher_info, fgrad);
        int zero = 1;
        for (size_t i = 0; i < k * k; ++i) zero &= fisher_info[i] == 0.0;
        for (size_t i = 0; i < k; ++i) zero &= fgrad[i] == 0.0;
        CHECK(isnan(v) && zero);
    }
}

int main(void)
{
    mc_mekf_model_t truth, model;
    mc_mekf_data_t data;
    make_problem(&truth, &model, &data);

    test_costs_agree(&model, data);
    mc_mekf_data_t unturned = data; /* the turn's variance is not ignored */
    unturned.turn_var = NULL;
    CHECK(mc_mekf_cost(&model, &unturned, NULL) != mc_mekf_cost(&model, &data, NULL));

    /* Steps: about 1e-4 of each quantity's scale. Off-diagonal covariance entries are moved
     * alone: the kernel symmetrises, and its gradient is w.r.t. the raw entries. */
    const component_t with_mag[] = {
        {"D00", IDX(D, 0), 1e-4},        {"D12", IDX(D, 5), 1e-4},
        {"D21", IDX(D, 7), 1e-4},        {"o1", IDX(o, 1), 1e-4},
        {"m0", IDX(m, 0), 1e-4},         {"m2", IDX(m, 2), 1e-4},
        {"bias0", IDX(bias, 0), 1e-6},   {"bias2", IDX(bias, 2), 1e-6},
        {"Sw00", IDX(Sw, 0), 4e-9},      {"Sw01", IDX(Sw, 1), 4e-9},
        {"Sa11", IDX(Sa, 4), 2e-7},      {"Sa02", IDX(Sa, 2), 2e-7},
        {"Sm22", IDX(Sm, 8), 1.5e-8},    {"Sm12", IDX(Sm, 5), 1.5e-8},
        {"delay", IDX(delay, 0), 1e-5},
    };
    check_gradient(&model, &data, with_mag, (int)(sizeof with_mag / sizeof with_mag[0]));
    /* The same with a magnetometer delay in the model: every component, the delay's own and
     * the gyroscope bias's share through the delayed rotation included. */
    mc_mekf_model_t delayed = model;
    delayed.delay = 0.03;
    check_gradient(&delayed, &data, with_mag, (int)(sizeof with_mag / sizeof with_mag[0]));
    mc_mekf_data_t inertial = data;
    inertial.use_mag = 0;
    inertial.mag = NULL;
    const component_t without_mag[] = {
        {"bias1", IDX(bias, 1), 1e-6}, {"Sw11", IDX(Sw, 4), 2e-9},
        {"Sw12", IDX(Sw, 5), 2e-9},    {"Sa00", IDX(Sa, 0), 4e-7},
        {"Sa01", IDX(Sa, 1), 4e-7},
    };
    check_gradient(&model, &inertial, without_mag,
                   (int)(sizeof without_mag / sizeof without_mag[0]));

    test_argument_errors(&model, &data);
    test_fisher(&model, &data);
    test_fisher(&delayed, &data);

    mc_mekf_data_t masked;
    make_masks(&data, &masked);
    test_masks(&model, &data, &masked);
    check_gradient(&model, &masked, with_mag, (int)(sizeof with_mag / sizeof with_mag[0]));
    check_gradient(&delayed, &masked, with_mag, (int)(sizeof with_mag / sizeof with_mag[0]));
    test_fisher(&delayed, &masked);
    masked.use_mag = 0;
    check_gradient(&model, &masked, without_mag,
                   (int)(sizeof without_mag / sizeof without_mag[0]));

    printf("%d passed, %d failed\n", n_passed, n_failed);
    return n_failed == 0 ? 0 : 1;
}
