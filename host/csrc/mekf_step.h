/* SPDX-License-Identifier: Apache-2.0 */
/*
 * The multiplicative EKF's step and its helpers, shared by the passes of mekf_likelihood.c
 * (cost, reverse-mode gradient) and mekf_fisher.c (forward sensitivities, Fisher
 * information). Internal to the kernel: not a public interface. The model, the numerical
 * choices and the layout are documented at the top of mekf_likelihood.c.
 */
#ifndef MAGCAL_MEKF_STEP_H
#define MAGCAL_MEKF_STEP_H

#include "mekf_likelihood.h"

#include <math.h>
#include <string.h>

/* Everything below is inlined: the 3×3 helpers are a few instructions each, and the step
 * functions are called from two passes each, so inlining lets each pass drop the stores it
 * does not need. GCC's size limits would otherwise leave calls in the hot loops. */
#if defined(__GNUC__)
#define ALWAYS_INLINE inline __attribute__((always_inline))
#else
#define ALWAYS_INLINE inline
#endif

/* ---------------------------------------------------------------- 3×3 helpers
 * Matrices are row-major double[9]; symmetric ones are stored in full with both triangles
 * set. Outputs never alias inputs (restrict), so the compiler keeps everything in
 * registers. */

static ALWAYS_INLINE double dot3(const double *restrict a, const double *restrict b)
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static ALWAYS_INLINE void cross3(const double *restrict a, const double *restrict b, double *restrict c)
{
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

static ALWAYS_INLINE void mat_vec(const double *restrict a, const double *restrict x,
                           double *restrict y) /* y = a x */
{
    for (int i = 0; i < 3; ++i) y[i] = a[3 * i] * x[0] + a[3 * i + 1] * x[1] + a[3 * i + 2] * x[2];
}

static ALWAYS_INLINE void mat_tvec(const double *restrict a, const double *restrict x,
                            double *restrict y) /* y = aᵀ x */
{
    for (int i = 0; i < 3; ++i) y[i] = a[i] * x[0] + a[3 + i] * x[1] + a[6 + i] * x[2];
}

static ALWAYS_INLINE void mat_mul(const double *restrict a, const double *restrict b,
                           double *restrict c) /* c = a b */
{
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            c[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
}

/* Mirror the upper triangle into the lower one. */
static ALWAYS_INLINE void sym_fill(double *s)
{
    s[3] = s[1];
    s[6] = s[2];
    s[7] = s[5];
}

/* c = a bᵀ where the result is known to be symmetric: upper triangle only. */
static ALWAYS_INLINE void sym_mul_nt(const double *restrict a, const double *restrict b, double *restrict c)
{
    for (int i = 0; i < 3; ++i)
        for (int j = i; j < 3; ++j) c[3 * i + j] = dot3(a + 3 * i, b + 3 * j);
    sym_fill(c);
}

/* c = a S aᵀ, S symmetric. */
static ALWAYS_INLINE void sym_sandwich(const double *restrict a, const double *restrict s,
                                double *restrict c)
{
    double t[9];
    mat_mul(a, s, t);
    sym_mul_nt(t, a, c);
}

/* c = aᵀ S a, S symmetric. */
static ALWAYS_INLINE void sym_sandwich_t(const double *restrict a, const double *restrict s,
                                  double *restrict c)
{
    double t[9]; /* t = S a, c_ij = Σ_k a_ki t_kj */
    mat_mul(s, a, t);
    for (int i = 0; i < 3; ++i)
        for (int j = i; j < 3; ++j) c[3 * i + j] = a[i] * t[j] + a[3 + i] * t[3 + j] + a[6 + i] * t[6 + j];
    sym_fill(c);
}

/* c = [m×]ᵀ S [m×] (= [m×] S [m×]ᵀ), S symmetric. Row i of S [m×] is s_i × m, and
 * column j of −[m×] T is t_j × m. */
static ALWAYS_INLINE void skew_sandwich(const double *restrict m, const double *restrict s,
                                 double *restrict c)
{
    double t[9];
    for (int i = 0; i < 3; ++i) cross3(s + 3 * i, m, t + 3 * i);
    for (int j = 0; j < 3; ++j) {
        const double t0 = t[j], t1 = t[3 + j], t2 = t[6 + j];
        const double col[3] = {t1 * m[2] - t2 * m[1], t2 * m[0] - t0 * m[2], t0 * m[1] - t1 * m[0]};
        for (int i = 0; i <= j; ++i) c[3 * i + j] = col[i];
    }
    sym_fill(c);
}

/* Indices of the upper triangle of a row-major 3×3 matrix. Sums of symmetric adjoints are
 * accumulated there only and mirrored once at the end. */
static const int UPPER[6] = {0, 1, 2, 4, 5, 8};

/* s += ½ (x yᵀ + y xᵀ) on the upper triangle: the symmetric part of an outer-product
 * adjoint. */
static ALWAYS_INLINE void sym_add_outer_upper(double *restrict s, const double *restrict x,
                                             const double *restrict y)
{
    for (int i = 0; i < 3; ++i)
        for (int j = i; j < 3; ++j) s[3 * i + j] += 0.5 * (x[i] * y[j] + y[i] * x[j]);
}

/* s += ½ (x yᵀ + y xᵀ). */
static ALWAYS_INLINE void sym_add_outer(double *restrict s, const double *restrict x, const double *restrict y)
{
    sym_add_outer_upper(s, x, y);
    sym_fill(s);
}

/* Inverse of a symmetric positive definite 3×3 matrix (only the upper triangle is read)
 * and its determinant. Returns 0 when the matrix is not positive definite (a leading
 * minor ≤ 0). The caller takes the logarithm, so that several determinants can share
 * one log. */
static ALWAYS_INLINE int sym_inverse(const double *restrict a, double *restrict inv, double *restrict det)
{
    const double a00 = a[0], a01 = a[1], a02 = a[2], a11 = a[4], a12 = a[5], a22 = a[8];
    const double c00 = a11 * a22 - a12 * a12;
    const double c01 = a02 * a12 - a01 * a22;
    const double c02 = a01 * a12 - a02 * a11;
    const double d = a00 * c00 + a01 * c01 + a02 * c02;
    const double m2 = a00 * a11 - a01 * a01;
    if (!(a00 > 0.0) || !(m2 > 0.0) || !(d > 0.0)) return 0;
    const double r = 1.0 / d;
    inv[0] = c00 * r;
    inv[1] = c01 * r;
    inv[2] = c02 * r;
    inv[4] = (a00 * a22 - a02 * a02) * r;
    inv[5] = (a01 * a02 - a00 * a12) * r;
    inv[8] = m2 * r;
    sym_fill(inv);
    *det = d;
    return 1;
}

/* Symmetric 3×3 packed as (xx, xy, xz, yy, yz, zz), for the tape. */
static ALWAYS_INLINE void sym_pack(const double *restrict s, double *restrict p)
{
    p[0] = s[0]; p[1] = s[1]; p[2] = s[2]; p[3] = s[4]; p[4] = s[5]; p[5] = s[8];
}

static ALWAYS_INLINE void sym_unpack(const double *restrict p, double *restrict s)
{
    s[0] = p[0]; s[1] = s[3] = p[1]; s[2] = s[6] = p[2];
    s[4] = p[3]; s[5] = s[7] = p[4]; s[8] = p[5];
}

/* ---------------------------------------------------------------- quaternions */

static ALWAYS_INLINE void quat_mul(const double *restrict p, const double *restrict q, double *restrict r)
{
    r[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3];
    r[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2];
    r[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1];
    r[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0];
}

/* Series below |v| = 1e-2: no sqrt or trigonometric call, and gyroscope increments and
 * filter corrections are almost always this small. The first omitted terms are a⁸/8! in
 * cos a (≤ 2.5e-21) and a⁶/7! in sin(a)/a, which multiplies v: an error ≤ 2e-18 in the
 * vector part at |v| = 1e-2, about one ulp of components of that size. */
#define QUAT_EXP_SERIES_A2 1e-4

/* Series coefficients as products, not quotients: x / 6.0 is a division (tens of cycles)
 * because 1/6 is not exact, and the series run several times per sample. */
static const double C_1_6 = 1.0 / 6.0, C_1_24 = 1.0 / 24.0, C_1_120 = 1.0 / 120.0,
                    C_1_720 = 1.0 / 720.0, C_1_5040 = 1.0 / 5040.0, C_1_40320 = 1.0 / 40320.0;

/* exp_q(v) = (cos|v|, sin|v| v/|v|). */
static ALWAYS_INLINE void quat_exp(const double *restrict v, double *restrict q)
{
    const double a2 = dot3(v, v);
    double c, s; /* cos a, sin a / a */
    if (a2 < QUAT_EXP_SERIES_A2) {
        c = 1.0 + a2 * (-0.5 + a2 * (C_1_24 - a2 * C_1_720));
        s = 1.0 + a2 * (-C_1_6 + a2 * C_1_120);
    } else {
        const double a = sqrt(a2);
        c = cos(a);
        s = sin(a) / a;
    }
    q[0] = c;
    q[1] = s * v[0];
    q[2] = s * v[1];
    q[3] = s * v[2];
}

static ALWAYS_INLINE void quat_to_mat(const double *restrict q, double *restrict R)
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

/* Below this squared rotation angle (|θ| < 0.032: 3 rad/s at 100 Hz) the rotation-vector
 * coefficients come from their series. Each coefficient multiplies a term of size
 * |θ|ᵏ|v|, so what matters is its error times |θ|ᵏ: below 1e-17 |v| for the truncated
 * series, and about 1e-16 |v| for the closed forms just above the threshold. */
#define ROTVEC_SERIES_T 1e-3

/* For a rotation vector θ (angle |θ|) and a vector v:
 *   rv = Exp(θ) v     = v + s [θ×] v + a [θ×]² v   (Rodrigues)
 *   jv = Jr(θ)ᵀ v     = v + a [θ×] v + b [θ×]² v
 * with s = sin|θ|/|θ|, a = (1 − cos|θ|)/|θ|², b = (|θ| − sin|θ|)/|θ|³ and Jr the right
 * Jacobian, Exp(θ + dθ) = Exp(θ) Exp(Jr(θ) dθ): jv turns a body-frame torque on Exp(θ)
 * into the adjoint of θ, rv carries a torque across the rotation. rv may be NULL. */
static ALWAYS_INLINE void rotvec_apply(const double *restrict th, const double *restrict v,
                                       double *restrict rv, double *restrict jv)
{
    const double t = dot3(th, th);
    double s, a, b;
    if (t < ROTVEC_SERIES_T) {
        s = 1.0 + t * (-C_1_6 + t * (C_1_120 - t * C_1_5040));
        a = 0.5 + t * (-C_1_24 + t * (C_1_720 - t * C_1_40320));
        b = C_1_6 + t * (-C_1_120 + t * C_1_5040);
    } else {
        const double th1 = sqrt(t), sh = sin(0.5 * th1);
        s = sin(th1) / th1;
        a = 2.0 * sh * sh / t;
        b = (1.0 - s) / t;
    }
    double c1[3], c2[3];
    cross3(th, v, c1);
    cross3(th, c1, c2);
    for (int i = 0; i < 3; ++i) jv[i] = v[i] + a * c1[i] + b * c2[i];
    if (rv)
        for (int i = 0; i < 3; ++i) rv[i] = v[i] + s * c1[i] + a * c2[i];
}

/* Renormalise a quaternion that is unit to within a few ulps (the product of two unit
 * quaternions): one Newton step for 1/|q|, r = (3 − |q|²)/2, which leaves |q|² − 1 at the
 * rounding level without the square root and division on the filter's critical path. */
static ALWAYS_INLINE void renormalise_quat(double *q)
{
    const double r = 1.5 - 0.5 * (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    for (int i = 0; i < 4; ++i) q[i] *= r;
}

/* ---------------------------------------------------------------- one filter step */

/* Everything a pass needs besides the running state. */
typedef struct {
    const mc_mekf_model_t *m;
    const mc_mekf_data_t *d;
    double g;       /* gravity magnitude; g_n = (0, 0, −g)          */
    double Sw[9];   /* symmetrised Σω                               */
    double Sa[9];   /* symmetrised Σa                               */
    double Sm[9];   /* symmetrised Σm (zero without magnetometer)   */
    double Ai0[9];  /* Σa⁻¹: the accelerometer information at c_t = 0 */
    double ld_Sa0;  /* log det Σa                                   */
    double Mi[9];   /* Σm⁻¹                                         */
    double ld_Sm;   /* log det Σm (0 without magnetometer)          */
    double K[9];    /* Dᵀ Σm⁻¹ D                                    */
} pass_t;

static inline int make_pass(const mc_mekf_model_t *m, const mc_mekf_data_t *d, pass_t *p)
{
    p->m = m;
    p->d = d;
    p->g = d->g;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            p->Sw[3 * i + j] = 0.5 * (m->Sw[3 * i + j] + m->Sw[3 * j + i]);
            p->Sa[3 * i + j] = 0.5 * (m->Sa[3 * i + j] + m->Sa[3 * j + i]);
        }
    double det;
    if (!sym_inverse(p->Sa, p->Ai0, &det)) return 0;
    p->ld_Sa0 = log(det);
    if (d->use_mag) {
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                p->Sm[3 * i + j] = 0.5 * (m->Sm[3 * i + j] + m->Sm[3 * j + i]);
        if (!sym_inverse(p->Sm, p->Mi, &det)) return 0;
        p->ld_Sm = log(det);
        sym_sandwich_t(m->D, p->Mi, p->K);
    } else {
        memset(p->Sm, 0, sizeof p->Sm);
        memset(p->Mi, 0, sizeof p->Mi);
        memset(p->K, 0, sizeof p->K);
        p->ld_Sm = 0.0;
    }
    return 1;
}

static ALWAYS_INLINE double acc_extra(const mc_mekf_data_t *d, size_t k)
{
    return d->acc_extra_var ? d->acc_extra_var[k] : 0.0;
}

/* Whether the accelerometer and the magnetometer measured at sample k. */
static ALWAYS_INLINE int has_acc(const mc_mekf_data_t *d, size_t k)
{
    return d->has_acc ? d->has_acc[k] != 0 : 1;
}

static ALWAYS_INLINE int has_mag(const mc_mekf_data_t *d, size_t k)
{
    return d->use_mag && (d->has_mag ? d->has_mag[k] != 0 : 1);
}

/* Accelerometer information Ai = (Σa + c I)⁻¹ into buf, or the pass constant when c = 0.
 * Returns NULL when Σa + c I is not positive definite; *det receives its determinant. */
static ALWAYS_INLINE const double *acc_information(const pass_t *p, double c, double *restrict buf,
                                            double *restrict det)
{
    if (c == 0.0) return p->Ai0;
    double S[9];
    memcpy(S, p->Sa, sizeof S);
    S[0] += c;
    S[4] += c;
    S[8] += c;
    return sym_inverse(S, buf, det) ? buf : NULL;
}

/* Time update of the attitude, sample k−1 → k: φ = ½ T (ω − δω), Δ = exp_q(φ), q1 = q ⊙ Δ. */
static ALWAYS_INLINE void predict_attitude(const pass_t *p, size_t k, const double *restrict q,
                                    double *restrict phi, double *restrict Delta,
                                    double *restrict q1)
{
    const double dt = p->d->dt[k];
    const double *w = p->d->gyr + 3 * (k - 1);
    for (int i = 0; i < 3; ++i) phi[i] = 0.5 * dt * (w[i] - p->m->bias[i]);
    quat_exp(phi, Delta);
    quat_mul(q, Delta, q1);
}

/* The magnetometer's delay τ at sample k: the body turns by v = τ ω_k (rotation vector,
 * body frame, ω_k = gyr[k−1] − bias, gyr[0] at k = 0) between the field's time and the
 * sample's, so the magnetometer sees m^b(t_k − τ) = Exp(v) Rᵀ m = Rmᵀ m with
 * Rm = R Exp(−v). Within the update the magnetometer's terms are those of the plain model
 * with Rm in place of R. */
static ALWAYS_INLINE void delay_rotation(const pass_t *p, size_t k, double *restrict v)
{
    const double *w = p->d->gyr + 3 * (k > 0 ? k - 1 : 0);
    for (int i = 0; i < 3; ++i) v[i] = p->m->delay * (w[i] - p->m->bias[i]);
}

static ALWAYS_INLINE void delayed_attitude(const pass_t *p, size_t k, const double *restrict R,
                                           double *restrict Rm)
{
    if (p->m->delay == 0.0) {
        memcpy(Rm, R, 9 * sizeof(double));
        return;
    }
    double v[3], half[3], qe[4], Et[9];
    delay_rotation(p, k, v);
    for (int i = 0; i < 3; ++i) half[i] = -0.5 * v[i];
    quat_exp(half, qe); /* Exp(−v) */
    quat_to_mat(qe, Et);
    mat_mul(R, Et, Rm);
}

/* The fraction of εᵀR⁻¹ε that the quadratic term may lose to cancellation before it is
 * recomputed in a stable form: the rounding error is then below 2^-52 · 8 / QUAD_CANCEL
 * relative. */
#define QUAD_CANCEL (1.0 / 64.0)

/* The intermediates of one step that the callers use. */
typedef struct {
    double q1[4], R[9], Pp[9]; /* predicted attitude, its rotation, predicted covariance */
    double Rm[9];              /* the rotation the magnetometer sees: R Exp(τ ω)ᵀ       */
    double ea[3], em[3];       /* innovations                                           */
    double zm[3], xm[3], vm[3];/* Σm⁻¹ εm, Dᵀ zm, R xm                                 */
    double Kn[9];              /* R K Rᵀ                                                */
    double Y[9], Pu[9];        /* Pp⁻¹ and the posterior covariance Λ⁻¹                  */
    double u[3], eta[3];       /* information vector and correction η = Λ⁻¹ u           */
    double q_out[4];           /* exp_q(η/2) ⊙ q1 (not yet renormalised)                 */
    double cost;               /* ½ (εᵀS⁻¹ε + log det S) except ½ log(det)           */
    double det;                /* the remaining factor of det S                         */
} step_t;

/* Σ log xᵢ of the steps' determinant factors with one log per ~100 steps instead of one per
 * step: the factors are multiplied while the product stays within 1e±100, far from
 * overflow (a factor outside that range is logged on its own). NaN propagates. */
typedef struct {
    double prod, sum;
} logdet_acc_t;

static ALWAYS_INLINE void logdet_add(logdet_acc_t *a, double x)
{
    if (!(x > 1e-100 && x < 1e100)) {
        a->sum += log(x);
        return;
    }
    a->prod *= x;
    if (!(a->prod > 1e-100 && a->prod < 1e100)) {
        a->sum += log(a->prod);
        a->prod = 1.0;
    }
}

static ALWAYS_INLINE double logdet_total(const logdet_acc_t *a) { return a->sum + log(a->prod); }

/* One step from (q, P) before sample k, with the measurements present there (ha, hm:
 * has_acc and has_mag at k). Returns 0 when a covariance is not positive definite. Inlined
 * into both passes, so the fields a pass does not read cost nothing. Without measurements
 * only q1, R, Pp, the innovations (NaN) and the outputs (q_out = q1, Pu = Pp, cost 0,
 * det 1) are set. */
static ALWAYS_INLINE int step_forward(const pass_t *p, size_t k, int ha, int hm,
                                      const double *restrict q, const double *restrict P,
                                      step_t *restrict s)
{
    const mc_mekf_model_t *m = p->m;
    const mc_mekf_data_t *d = p->d;
    const double g = p->g;
    if (k > 0) {
        double phi[3], Delta[4], RS[9], Q[9];
        predict_attitude(p, k, q, phi, Delta, s->q1);
        quat_to_mat(s->q1, s->R);
        const double dt2 = d->dt[k] * d->dt[k];
        mat_mul(s->R, p->Sw, RS);
        sym_mul_nt(RS, s->R, Q); /* R Σω Rᵀ */
        for (int i = 0; i < 9; ++i) s->Pp[i] = P[i] + dt2 * Q[i];
        if (d->turn_var) { /* data only: nothing of it reaches the gradient */
            s->Pp[0] += d->turn_var[k];
            s->Pp[4] += d->turn_var[k];
            s->Pp[8] += d->turn_var[k];
        }
    } else {
        memcpy(s->q1, q, sizeof s->q1);
        quat_to_mat(s->q1, s->R);
        memcpy(s->Pp, P, sizeof s->Pp);
    }
    const double *r0 = s->R, *r1 = s->R + 3, *r2 = s->R + 6;
    if (!ha && !hm) {
        /* No measurement: the prediction is carried on. */
        for (int i = 0; i < 3; ++i) {
            s->ea[i] = NAN;
            s->em[i] = d->use_mag ? NAN : 0.0;
        }
        memcpy(s->Pu, s->Pp, sizeof s->Pu);
        memcpy(s->q_out, s->q1, sizeof s->q_out);
        s->cost = 0.0;
        s->det = 1.0;
        return 1;
    }

    /* Accelerometer: εa = ya + Rᵀ g_n = ya − g r2 (r_i: rows of R). Without it, its
     * information, innovation and log det terms are left out (the sums start at 0). */
    double Ai_buf[9], det_Sa = 1.0, cx = 0.0, e2 = 0.0, J[9];
    const double *Ai = NULL;
    if (ha) {
        cx = acc_extra(d, k);
        Ai = acc_information(p, cx, Ai_buf, &det_Sa);
        if (!Ai) return 0;
        const double *ya = d->acc + 3 * k;
        double za[3], s0[3], s1[3];
        for (int i = 0; i < 3; ++i) s->ea[i] = ya[i] - g * r2[i];
        mat_vec(Ai, s->ea, za);
        e2 = dot3(s->ea, za);
        /* u_a = g_n × (R za); J_a = [g_n×]ᵀ (R Ai Rᵀ) [g_n×] needs rows 0 and 1 of R only. */
        s->u[0] = g * dot3(r1, za);
        s->u[1] = -g * dot3(r0, za);
        s->u[2] = 0.0;
        mat_vec(Ai, r0, s0);
        mat_vec(Ai, r1, s1);
        const double g2 = g * g;
        J[0] = g2 * dot3(r1, s1);
        J[1] = -g2 * dot3(r1, s0);
        J[4] = g2 * dot3(r0, s0);
    } else {
        for (int i = 0; i < 3; ++i) {
            s->ea[i] = NAN;
            s->u[i] = 0.0;
        }
        J[0] = J[1] = J[4] = 0.0;
    }
    J[2] = J[5] = J[8] = 0.0;

    if (hm) {
        /* εm = ym − D Rᵀ m − o; u_m = (R Dᵀ zm) × m; J_m = [m×]ᵀ (R K Rᵀ) [m×]. */
        const double *ym = d->mag + 3 * k;
        double mb[3], ym_pred[3], um[3], RK[9], Jm[9];
        double *zm = s->zm, *xm = s->xm, *vm = s->vm, *Kn = s->Kn;
        delayed_attitude(p, k, s->R, s->Rm);
        mat_tvec(s->Rm, m->m, mb);
        mat_vec(m->D, mb, ym_pred);
        for (int i = 0; i < 3; ++i) s->em[i] = ym[i] - ym_pred[i] - m->o[i];
        mat_vec(p->Mi, s->em, zm);
        e2 += dot3(s->em, zm);
        mat_tvec(m->D, zm, xm);
        mat_vec(s->Rm, xm, vm);
        cross3(vm, m->m, um);
        for (int i = 0; i < 3; ++i) s->u[i] += um[i];
        mat_mul(s->Rm, p->K, RK);
        sym_mul_nt(RK, s->Rm, Kn);
        skew_sandwich(m->m, Kn, Jm);
        J[0] += Jm[0];
        J[1] += Jm[1];
        J[2] += Jm[2];
        J[4] += Jm[4];
        J[5] += Jm[5];
        J[8] += Jm[8];
    } else {
        for (int i = 0; i < 3; ++i) s->em[i] = d->use_mag ? NAN : 0.0;
    }
    sym_fill(J);

    double det_Pp, det_Lam, Lam[9];
    if (!sym_inverse(s->Pp, s->Y, &det_Pp)) return 0;
    for (int i = 0; i < 9; ++i) Lam[i] = s->Y[i] + J[i];
    if (!sym_inverse(Lam, s->Pu, &det_Lam)) return 0;
    mat_vec(s->Pu, s->u, s->eta);
    /* log det S = log det Sa_t + log det Sm + log det Pp + log det Λ (of the measurements
     * present): the constant logs go into the cost, the determinants into s->det for the
     * pass's logdet_acc_t. */
    const int acc_const = ha && cx == 0.0; /* the accelerometer with the pass's Σa⁻¹ */
    s->det = ha && !acc_const ? det_Sa * det_Pp * det_Lam : det_Pp * det_Lam;
    /* εᵀS⁻¹ε = εᵀR⁻¹ε − uᵀη. The difference cancels catastrophically when a noise
     * covariance is nearly singular (an optimiser's trial point can make it so) and can then
     * even go negative. When less than QUAD_CANCEL of e2 survives, the same value is formed
     * as a sum of non-negative terms, the minimum of the information form:
     *   εᵀS⁻¹ε = rᵀR⁻¹r + ηᵀPp⁻¹η,   r = ε − Hη (the posterior residual).
     * Mathematically identical, so the reverse pass differentiates the simpler form. */
    const double *eta = s->eta;
    double quad = e2 - dot3(s->u, eta);
    if (!(quad >= QUAD_CANCEL * e2)) {
        double t[3];
        quad = 0.0;
        if (ha) {
            double ra[3];
            for (int i = 0; i < 3; ++i) ra[i] = s->ea[i] + g * (eta[1] * r0[i] - eta[0] * r1[i]);
            mat_vec(Ai, ra, t);
            quad = dot3(ra, t);
        }
        if (hm) {
            double w[3], Rtw[3], Hmeta[3], rm[3];
            cross3(m->m, eta, w); /* Hm η = D Rmᵀ (m × η) */
            mat_tvec(s->Rm, w, Rtw);
            mat_vec(m->D, Rtw, Hmeta);
            for (int i = 0; i < 3; ++i) rm[i] = s->em[i] - Hmeta[i];
            mat_vec(p->Mi, rm, t);
            quad += dot3(rm, t);
        }
        mat_vec(s->Y, eta, t);
        quad += dot3(eta, t);
    }
    s->cost = 0.5 * (quad + (acc_const ? p->ld_Sa0 : 0.0) + (hm ? p->ld_Sm : 0.0));

    double half_eta[3], E[4];
    for (int i = 0; i < 3; ++i) half_eta[i] = 0.5 * s->eta[i];
    quat_exp(half_eta, E);
    quat_mul(E, s->q1, s->q_out);
    return 1;
}

static inline void load_prior(const mc_mekf_data_t *d, double *q, double *P)
{
    const double *q0 = d->q0;
    const double r = 1.0 / sqrt(q0[0] * q0[0] + q0[1] * q0[1] + q0[2] * q0[2] + q0[3] * q0[3]);
    for (int i = 0; i < 4; ++i) q[i] = r * q0[i];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) P[3 * i + j] = 0.5 * (d->P0[3 * i + j] + d->P0[3 * j + i]);
}


/* The passes are kept out of line: each is one hot loop, and compiled apart neither's
 * register allocation or layout depends on another's.
 *
 * With GCC on x86-64 glibc they are also compiled twice, for the baseline and for AVX,
 * and the loader picks one for the CPU (target_clones, an ifunc). AVX here only means the
 * three-operand VEX encoding of the same scalar operations: no FMA, no vectors (the build
 * has no auto-vectorisation), so both versions compute bit-identical results. It removes
 * the register copies SSE2's two-operand form needs, ~6% of the cost+gradient time. */
#if defined(__GNUC__)
#define NOINLINE __attribute__((noinline))
#else
#define NOINLINE
#endif
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 6 && defined(__x86_64__) && \
    defined(__GLIBC__)
#define HOT_PASS NOINLINE __attribute__((target_clones("avx", "default")))
#else
#define HOT_PASS NOINLINE
#endif

/* Each pass is compiled twice more: `masked` is a constant in the inlined loop bodies
 * below, and with 0 (no mask given: every sample has the accelerometer, and the
 * magnetometer with use_mag) the per-sample mask loads and the branches on them fold away,
 * so sessions without masks run the code they ran before masks existed. */
static ALWAYS_INLINE int any_mask(const mc_mekf_data_t *d)
{
    return d->has_acc || (d->use_mag && d->has_mag);
}

/* The measurements at sample k: *ha accelerometer, *hm magnetometer. */
static ALWAYS_INLINE void sample_has(const mc_mekf_data_t *d, size_t k, int masked, int *ha,
                                     int *hm)
{
    *ha = masked ? has_acc(d, k) : 1;
    *hm = masked ? has_mag(d, k) : d->use_mag != 0;
}


/* The checks shared by both entry points: pointers the passes read, and samples. */
static inline int valid_arguments(const mc_mekf_model_t *model, const mc_mekf_data_t *data)
{
    return model && data && data->n > 0 && data->dt && data->gyr && data->acc &&
           (data->mag || !data->use_mag);
}


#endif
