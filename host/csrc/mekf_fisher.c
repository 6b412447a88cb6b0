/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Forward sensitivities of the multiplicative EKF and the Fisher information of its
 * prediction-error likelihood. See mekf_likelihood.h for the interface and
 * mekf_likelihood.c for the filter.
 *
 * Each sample's cost is ½ (εᵀS⁻¹ε + log det S). For a Gaussian innovation ε ~ N(0, S) the
 * expected second derivative of that term along directions i, j of the model is
 *     F_ij = ∂_i εᵀ S⁻¹ ∂_j ε + ½ tr(S⁻¹ ∂_i S S⁻¹ ∂_j S),
 * the Fisher information, which needs only first derivatives of ε and S. With S = L Lᵀ
 * (Cholesky), a_i = L⁻¹ ∂_i ε and W_i = L⁻¹ ∂_i S L⁻ᵀ (symmetric) this is
 *     F_ij = a_iᵀ a_j + ½ Σ_ab W_i,ab W_j,ab,
 * an inner product of per-direction feature vectors φ_i = (a_i, W_i,aa / √2, W_i,ab (a < b)):
 * F = Σ_t Φ_t Φ_tᵀ, accumulated on its upper triangle. The same quantities give the gradient
 *     ∂_i V_t = a_iᵀ w − ½ wᵀ W_i w + ½ tr W_i,   w = L⁻¹ ε,
 * which must agree with the reverse pass's (a check the tests make).
 *
 * The derivatives of ε and S come from the filter's state derivatives, carried forward
 * with the state (forward mode): per direction the orientation error's tangent dφ (a
 * navigation-frame rotation vector, R → [dφ×] R, as the filter's own error state) and the
 * covariance's dP. Through one step (R₁ = R Exp(θ), θ = T (ω − δω)):
 *     dφ₁ = dφ + R₁ Jr(θ) dθ,                  dθ = −T dδω
 *     dPp = dP + T² ([dφ₁×] Q − Q [dφ₁×] + R₁ dΣω R₁ᵀ),   Q = R₁ Σω R₁ᵀ
 * and through the update, in the textbook form with the gain K = Pp Hᵀ S⁻¹ (the nominal
 * filter is the information form of mekf_likelihood.c; both are the same function):
 *     dS  = dH M + (dH M)ᵀ + H dPp Hᵀ + dRₜ,        M = Pp Hᵀ
 *     G   = dPp Hᵀ + Pp dHᵀ
 *     dη  = G z − K (dS z) + K dε,                  z = S⁻¹ ε
 *     dPu = dPp − G Kᵀ − K Gᵀ + K dS Kᵀ
 *     dφ⁺ = Exp(η) dφ₁ + Jl(η) dη                   (R⁺ = Exp(η) R₁)
 * The magnetometer sees Rm = R₁ Exp(−v), v = τ ω, whose tangent is dψ = dφ₁ − Rm Jr(−v) dv
 * with dv = dτ ω − τ dδω. Renormalising the quaternion is the identity to first order.
 *
 * The cost is about 2 + K/6 times a forward pass (K directions); nothing is taped, and the
 * memory is O(K) whatever the number of samples.
 *
 * The directions are carried in groups of VLANES side by side: every tangent quantity is a
 * vector of VLANES doubles (GCC's and clang's vector extension; one double elsewhere), the
 * nominal quantities they combine with are scalars, and the code of one group reads as the
 * code of one direction. Each lane is computed by the same IEEE operations in the same
 * order as a direction alone (no FMA: the build has -ffp-contract=off), so the results do
 * not depend on VLANES or on the instruction set; a pass costs about a quarter of what the
 * directions took one at a time.
 */
#include "mekf_step.h"

#if defined(__GNUC__) && defined(__SIZEOF_DOUBLE__) && !defined(MC_MEKF_FISHER_SCALAR)
#define VLANES 4
typedef double vd __attribute__((vector_size(VLANES * sizeof(double))));
#else
#define VLANES 1
typedef double vd;
#endif
/* The same vector at any double's alignment and aliasing doubles, for the block's rows
 * (memcpy into a vector goes through the stack, where the halves' stores do not forward to
 * the whole vector's load). */
#if VLANES > 1
typedef double vd_unaligned
    __attribute__((vector_size(VLANES * sizeof(double)), aligned(sizeof(double)), may_alias));
#else
typedef double vd_unaligned;
#endif
#if MC_MEKF_FISHER_LANES % VLANES != 0
#error "a group of directions in the workspace must hold whole vectors"
#endif
/* Fully unrolled small loops whose bounds depend on an outer index (the triangular
 * products below): GCC unrolls loops of constant trip count only. */
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 8
#define UNROLL_6 _Pragma("GCC unroll 6")
#else
#define UNROLL_6
#endif
/* The hot functions of this pass, compiled for AVX as well (HOT_PASS), except under
 * AddressSanitizer: the native tests' instrumented build of both clones of the vector code
 * took four times as long to compile as the rest of the kernel, and the clones compute the
 * same results. */
#if defined(__SANITIZE_ADDRESS__)
#define FISHER_HOT NOINLINE
#else
#define FISHER_HOT HOT_PASS
#endif
/* Groups of VLANES directions at most. */
#define MAX_GROUPS ((MC_MEKF_FISHER_MAX_DIRECTIONS + VLANES - 1) / VLANES)

/* Lane l of v, read and written through memory (the same for a vector and a double). */
static ALWAYS_INLINE double get_lane(const vd *v, int l)
{
    double t[VLANES];
    memcpy(t, v, sizeof t);
    return t[l];
}

static ALWAYS_INLINE void set_lane(vd *v, int l, double x)
{
    double t[VLANES];
    memcpy(t, v, sizeof t);
    t[l] = x;
    memcpy(v, t, sizeof t);
}

/* The 3×3 helpers of mekf_step.h with vector operands where the tangents are: the same
 * expressions, evaluated per lane. _sv: scalar first operand, vector second; _vs the
 * reverse. */
static ALWAYS_INLINE void cross3_sv(const double *restrict a, const vd *restrict b, vd *restrict c)
{
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

static ALWAYS_INLINE void cross3_vs(const vd *restrict a, const double *restrict b, vd *restrict c)
{
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

static ALWAYS_INLINE void mat_vec_sv(const double *restrict a, const vd *restrict x, vd *restrict y)
{
    for (int i = 0; i < 3; ++i) y[i] = a[3 * i] * x[0] + a[3 * i + 1] * x[1] + a[3 * i + 2] * x[2];
}

static ALWAYS_INLINE void mat_vec_vs(const vd *restrict a, const double *restrict x, vd *restrict y)
{
    for (int i = 0; i < 3; ++i) y[i] = a[3 * i] * x[0] + a[3 * i + 1] * x[1] + a[3 * i + 2] * x[2];
}

static ALWAYS_INLINE void mat_tvec_sv(const double *restrict a, const vd *restrict x, vd *restrict y)
{
    for (int i = 0; i < 3; ++i) y[i] = a[i] * x[0] + a[3 + i] * x[1] + a[6 + i] * x[2];
}

static ALWAYS_INLINE void sym_fill_v(vd *s)
{
    s[3] = s[1];
    s[6] = s[2];
    s[7] = s[5];
}

/* c = a S aᵀ, a scalar, S symmetric (sym_sandwich). */
static ALWAYS_INLINE void sym_sandwich_sv(const double *restrict a, const vd *restrict s,
                                          vd *restrict c)
{
    vd t[9];
    for (int i = 0; i < 3; ++i) /* t = a S (mat_mul) */
        for (int j = 0; j < 3; ++j)
            t[3 * i + j] = a[3 * i] * s[j] + a[3 * i + 1] * s[3 + j] + a[3 * i + 2] * s[6 + j];
    for (int i = 0; i < 3; ++i) /* c = t aᵀ, upper triangle (sym_mul_nt) */
        for (int j = i; j < 3; ++j)
            c[3 * i + j] = t[3 * i] * a[3 * j] + t[3 * i + 1] * a[3 * j + 1] + t[3 * i + 2] * a[3 * j + 2];
    sym_fill_v(c);
}

/* The rotation-vector coefficients of rotvec_apply for one θ, so that a step applies
 * Exp(θ) and the Jacobians to every direction without recomputing them. */
typedef struct {
    double th[3], s, a, b;
} rotvec_coef_t;

static ALWAYS_INLINE void rotvec_coef(const double *restrict th, rotvec_coef_t *restrict c)
{
    const double t = dot3(th, th);
    if (t < ROTVEC_SERIES_T) {
        c->s = 1.0 + t * (-C_1_6 + t * (C_1_120 - t * C_1_5040));
        c->a = 0.5 + t * (-C_1_24 + t * (C_1_720 - t * C_1_40320));
        c->b = C_1_6 + t * (-C_1_120 + t * C_1_5040);
    } else {
        const double th1 = sqrt(t), sh = sin(0.5 * th1);
        c->s = sin(th1) / th1;
        c->a = 2.0 * sh * sh / t;
        c->b = (1.0 - c->s) / t;
    }
    memcpy(c->th, th, sizeof c->th);
}

/* Jr(θ)ᵀ v (sign +1) or Jr(θ) v = Jr(−θ)ᵀ v (sign −1); Exp(θ) v with rotate set. */
static ALWAYS_INLINE void rotvec_jac(const rotvec_coef_t *restrict c, double sign,
                                     const vd *restrict v, vd *restrict out)
{
    vd c1[3], c2[3];
    cross3_sv(c->th, v, c1);
    cross3_sv(c->th, c1, c2);
    for (int i = 0; i < 3; ++i) out[i] = v[i] + sign * c->a * c1[i] + c->b * c2[i];
}

static ALWAYS_INLINE void rotvec_rotate(const rotvec_coef_t *restrict c, const vd *restrict v,
                                        vd *restrict out)
{
    vd c1[3], c2[3];
    cross3_sv(c->th, v, c1);
    cross3_sv(c->th, c1, c2);
    for (int i = 0; i < 3; ++i) out[i] = v[i] + c->s * c1[i] + c->a * c2[i];
}

/* The model tangents of a group of VLANES directions, one per lane, their covariances
 * symmetrised as the filter uses them. */
typedef struct {
    vd D[9], o[3], m[3], bias[3], delay;
    vd Sw[9], Sa[9], Sm[9];
} tangent_t;

/* Direction `dir` into lane l of t. */
static void load_tangent(const double *dir, tangent_t *t, int l)
{
    mc_mekf_model_t model; /* the struct is flat: see mc_mekf_model_is_flat */
    memcpy(&model, dir, sizeof model);
    const mc_mekf_model_t *d = &model;
    for (int i = 0; i < 9; ++i) set_lane(t->D + i, l, d->D[i]);
    for (int i = 0; i < 3; ++i) {
        set_lane(t->o + i, l, d->o[i]);
        set_lane(t->m + i, l, d->m[i]);
        set_lane(t->bias + i, l, d->bias[i]);
    }
    set_lane(&t->delay, l, d->delay);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            set_lane(t->Sw + 3 * i + j, l, 0.5 * (d->Sw[3 * i + j] + d->Sw[3 * j + i]));
            set_lane(t->Sa + 3 * i + j, l, 0.5 * (d->Sa[3 * i + j] + d->Sa[3 * j + i]));
            set_lane(t->Sm + 3 * i + j, l, 0.5 * (d->Sm[3 * i + j] + d->Sm[3 * j + i]));
        }
}

/* The nominal quantities of one sample's update that every direction reuses. */
typedef struct {
    int ny, rows[6];   /* the measured rows of (acc, mag): 0–2, 3–5                    */
    double H[18];      /* (6, 3) rows of H for every row (the absent ones unused)       */
    double S[36];      /* (ny, ny) innovation covariance                                */
    double L[36];      /* its Cholesky factor                                           */
    double Linv[36];   /* L⁻¹ (lower triangular)                                        */
    double M[18];      /* (3, ny) Pp Hᵀ                                                 */
    double K[18];      /* (3, ny) the gain M S⁻¹                                        */
    double eps[6], w[6], z[6]; /* ε, L⁻¹ε, S⁻¹ε                                          */
    double RtMb[9];    /* Rmᵀ (m × e_j), column j                                       */
    double DRt[9];     /* D Rmᵀ                                                         */
    double mb[3];      /* Rmᵀ m                                                         */
    double omega_k[3]; /* the rate held over the magnetometer's delay                   */
    rotvec_coef_t delay_c; /* of −v = −τ ω_k                                             */
} update_t;

/* x ← L⁻¹ x (lower-triangular L, n × n). */
static ALWAYS_INLINE void forward_solve(const double *restrict L, int n, double *restrict x)
{
    for (int i = 0; i < n; ++i) {
        double v = x[i];
        for (int a = 0; a < i; ++a) v -= L[n * i + a] * x[a];
        x[i] = v / L[n * i + i];
    }
}

/* x ← L⁻ᵀ x. */
static ALWAYS_INLINE void backward_solve(const double *restrict L, int n, double *restrict x)
{
    for (int i = n - 1; i >= 0; --i) {
        double v = x[i];
        for (int a = i + 1; a < n; ++a) v -= L[n * a + i] * x[a];
        x[i] = v / L[n * i + i];
    }
}

/* The update's nominal quantities at sample k from the step's. Returns 0 when S has a
 * non-positive pivot (only rounding can do that where the step succeeded). */
static ALWAYS_INLINE int prepare_update(const pass_t *p, const step_t *s, size_t k, int ha, int hm,
                          update_t *u)
{
    const mc_mekf_model_t *m = p->m;
    const double g = p->g;
    const double *R = s->R;
    for (int i = 0; i < 3; ++i) { /* row i of −Rᵀ[g_n×], [g_n×] = [[0, g, 0], [−g, 0, 0], 0] */
        u->H[3 * i + 0] = g * R[3 + i];
        u->H[3 * i + 1] = -g * R[i];
        u->H[3 * i + 2] = 0.0;
    }
    if (hm) {
        const double *mm = m->m, *Rm = s->Rm;
        const double Mx[9] = {0.0, -mm[2], mm[1], mm[2], 0.0, -mm[0], -mm[1], mm[0], 0.0};
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                u->RtMb[3 * i + j] = Rm[i] * Mx[j] + Rm[3 + i] * Mx[3 + j] + Rm[6 + i] * Mx[6 + j];
        mat_mul(m->D, u->RtMb, u->H + 9);
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                u->DRt[3 * i + j] =
                    m->D[3 * i] * Rm[3 * j] + m->D[3 * i + 1] * Rm[3 * j + 1] + m->D[3 * i + 2] * Rm[3 * j + 2];
        mat_tvec(Rm, m->m, u->mb);
        const double *w = p->d->gyr + 3 * (k > 0 ? k - 1 : 0);
        double minus_v[3];
        for (int i = 0; i < 3; ++i) {
            u->omega_k[i] = w[i] - m->bias[i];
            minus_v[i] = -m->delay * u->omega_k[i];
        }
        rotvec_coef(minus_v, &u->delay_c);
    }
    int ny = 0;
    for (int i = 0; i < 3; ++i)
        if (ha) u->rows[ny++] = i;
    for (int i = 3; i < 6; ++i)
        if (hm) u->rows[ny++] = i;
    u->ny = ny;
    for (int i = 0; i < ny; ++i) {
        const int r = u->rows[i];
        u->eps[i] = r < 3 ? s->ea[r] : s->em[r - 3];
        double hp[3]; /* row r of H Pp */
        for (int b = 0; b < 3; ++b)
            hp[b] = u->H[3 * r] * s->Pp[b] + u->H[3 * r + 1] * s->Pp[3 + b] + u->H[3 * r + 2] * s->Pp[6 + b];
        for (int b = 0; b < 3; ++b) u->M[ny * b + i] = hp[b];
    }
    const double cx = ha ? (p->d->acc_extra_var ? p->d->acc_extra_var[k] : 0.0) : 0.0;
    for (int i = 0; i < ny; ++i)
        for (int j = 0; j < ny; ++j) {
            const int ri = u->rows[i], rj = u->rows[j];
            double v = u->H[3 * ri] * u->M[j] + u->H[3 * ri + 1] * u->M[ny + j] +
                       u->H[3 * ri + 2] * u->M[2 * ny + j];
            if (ri < 3 && rj < 3) v += p->Sa[3 * ri + rj] + (ri == rj ? cx : 0.0);
            if (ri >= 3 && rj >= 3) v += p->Sm[3 * (ri - 3) + (rj - 3)];
            u->S[ny * i + j] = v;
        }
    double *L = u->L;
    for (int j = 0; j < ny; ++j) {
        double v = u->S[ny * j + j];
        for (int a = 0; a < j; ++a) v -= L[ny * j + a] * L[ny * j + a];
        if (!(v > 0.0)) return 0;
        L[ny * j + j] = sqrt(v);
        for (int i = j + 1; i < ny; ++i) {
            double x = u->S[ny * i + j];
            for (int a = 0; a < j; ++a) x -= L[ny * i + a] * L[ny * j + a];
            L[ny * i + j] = x / L[ny * j + j];
        }
        for (int i = 0; i < j; ++i) L[ny * i + j] = 0.0;
    }
    for (int j = 0; j < ny; ++j) { /* L⁻¹, column by column */
        double e[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        e[j] = 1.0;
        forward_solve(L, ny, e);
        for (int i = 0; i < ny; ++i) u->Linv[ny * i + j] = e[i];
    }
    memcpy(u->w, u->eps, sizeof u->w);
    forward_solve(L, ny, u->w);
    memcpy(u->z, u->w, sizeof u->z);
    backward_solve(L, ny, u->z);
    for (int b = 0; b < 3; ++b) { /* row b of K = M S⁻¹: S⁻¹ (row b of M) */
        double r[6];
        for (int i = 0; i < ny; ++i) r[i] = u->M[ny * b + i];
        forward_solve(L, ny, r);
        backward_solve(L, ny, r);
        for (int i = 0; i < ny; ++i) u->K[ny * b + i] = r[i];
    }
    return 1;
}

/* dH (rows of H, 6 × 3; only the measured rows are set) and dŷ (6) of a group of
 * directions, from the orientation tangent dφ₁ of the predicted attitude. */
static ALWAYS_INLINE void measurement_tangent(const pass_t *p, const step_t *s, const update_t *u, int ha,
                                int hm, const tangent_t *t, const vd *restrict dphi1,
                                vd *restrict dH, vd *restrict dy)
{
    const mc_mekf_model_t *m = p->m;
    const double g = p->g;
    const double *R = s->R;
    if (ha) {
        /* ŷa = −Rᵀ g_n: dŷa = Rᵀ (dφ × g_n); column j of dHa = Rᵀ (dφ × (g_n × e_j)), with
         * g_n × e_0 = (0, −g, 0), g_n × e_1 = (g, 0, 0), g_n × e_2 = 0. */
        const double gn[3] = {0.0, 0.0, -g};
        vd c[3], col[3];
        cross3_vs(dphi1, gn, c);
        mat_tvec_sv(R, c, dy);
        const double ge0[3] = {0.0, -g, 0.0}, ge1[3] = {g, 0.0, 0.0};
        cross3_vs(dphi1, ge0, c);
        mat_tvec_sv(R, c, col);
        for (int i = 0; i < 3; ++i) dH[3 * i] = col[i];
        cross3_vs(dphi1, ge1, c);
        mat_tvec_sv(R, c, col);
        const vd zero = {0.0};
        for (int i = 0; i < 3; ++i) {
            dH[3 * i + 1] = col[i];
            dH[3 * i + 2] = zero;
        }
    }
    if (hm) {
        /* dψ = dφ₁ − Rm Jr(−v) dv, dv = dτ ω − τ dδω: the tangent of the rotation the
         * magnetometer sees. */
        vd dv[3], jdv[3], rj[3], dpsi[3];
        for (int i = 0; i < 3; ++i) dv[i] = t->delay * u->omega_k[i] - m->delay * t->bias[i];
        rotvec_jac(&u->delay_c, -1.0, dv, jdv);
        mat_vec_sv(s->Rm, jdv, rj);
        for (int i = 0; i < 3; ++i) dpsi[i] = dphi1[i] - rj[i];
        /* ŷm = D Rmᵀ m + o: dŷm = dD Rmᵀ m + D Rmᵀ (m × dψ) + D Rmᵀ dm + do. */
        vd mxd[3], a[3], rtdm[3], b[3];
        cross3_sv(m->m, dpsi, mxd);
        mat_tvec_sv(s->Rm, mxd, a);
        mat_tvec_sv(s->Rm, t->m, rtdm);
        for (int i = 0; i < 3; ++i) a[i] += rtdm[i];
        mat_vec_sv(m->D, a, b);
        vd dDmb[3];
        mat_vec_vs(t->D, u->mb, dDmb);
        for (int i = 0; i < 3; ++i) dy[3 + i] = dDmb[i] + b[i] + t->o[i];
        /* Column j of Hm = D Rmᵀ (m × e_j); of dHm = dD Rmᵀ (m × e_j)
         * − D Rmᵀ (dψ × (m × e_j)) + D Rmᵀ (dm × e_j). */
        for (int j = 0; j < 3; ++j) {
            double mej[3] = {0.0, 0.0, 0.0}, e[3] = {0.0, 0.0, 0.0};
            vd dmej[3], x[3], y[3], col[3];
            e[j] = 1.0;
            cross3(m->m, e, mej);
            cross3_vs(t->m, e, dmej);
            cross3_vs(dpsi, mej, x);
            for (int i = 0; i < 3; ++i) x[i] = dmej[i] - x[i];
            mat_vec_sv(u->DRt, x, y);
            const double rm[3] = {u->RtMb[j], u->RtMb[3 + j], u->RtMb[6 + j]};
            mat_vec_vs(t->D, rm, col);
            for (int i = 0; i < 3; ++i) dH[9 + 3 * i + j] = col[i] + y[i];
        }
    }
}

/* Samples whose features are gathered before they are multiplied out: a block of up to
 * BLOCK_LEN features per direction, stored feature-major (feature c of direction d at
 * c · stride + d, stride = the directions rounded up to whole groups of
 * MC_MEKF_FISHER_LANES, the padding zero), so that F gains whole tiles of dot products per
 * block instead of a rank-one update per feature. */
#define FEATURES 27 /* 6 + 21: a and the upper triangle of W at most */
#define BLOCK_LEN (MC_MEKF_FISHER_WORK_DOUBLES_PER_DIRECTION)
#if BLOCK_LEN % FEATURES != 0 || BLOCK_LEN < FEATURES
#error "the Fisher workspace per direction must hold whole samples' features"
#endif
/* A tile of F computed together: TILE_I rows by TILE_J = MC_MEKF_FISHER_LANES columns. */
#define TILE_I 4
#define TILE_J MC_MEKF_FISHER_LANES
#if TILE_J % TILE_I != 0
#error "a tile's rows must divide a group of directions"
#endif

/* The accumulators of one pass. */
typedef struct {
    size_t k;      /* directions                                              */
    size_t stride; /* k rounded up to whole groups of MC_MEKF_FISHER_LANES    */
    double *info;  /* (k, k), upper triangle accumulated                      */
    double *grad;  /* (k)                                                     */
    int used;      /* features gathered in `block` per direction so far       */
    double *block; /* (BLOCK_LEN, stride) the caller's workspace, feature-major */
} fisher_acc_t;

/* F += Φ Φᵀ over the gathered features, upper triangle; empties the block.
 *
 * Each F_ij of the block is one sum over the features in their order, started from zero
 * and then added to F_ij, as a plain dot product per pair would compute it: the tiling
 * only makes TILE_I · TILE_J such sums run side by side (independent chains of additions
 * instead of one chain whose latency bounds the loop), and the j's of a tile are adjacent
 * in memory, so that they map onto vector lanes. Every lane is the same IEEE product and
 * sum (no FMA: -ffp-contract=off), so the result does not depend on how the compiler
 * vectorises. The tiles below the diagonal and the padding are computed and dropped. */
static FISHER_HOT void flush_block(fisher_acc_t *acc)
{
    enum { NV = TILE_J / VLANES }; /* vectors per row of a tile */
    const size_t nd = acc->k, stride = acc->stride;
    const int len = acc->used;
    for (size_t i0 = 0; i0 < nd; i0 += TILE_I)
        for (size_t j0 = i0 - i0 % TILE_J; j0 < nd; j0 += TILE_J) {
            vd v[TILE_I][NV];
            for (int a = 0; a < TILE_I; ++a)
                for (int b = 0; b < NV; ++b) v[a][b] = (vd){0.0};
            const double *restrict f = acc->block;
            for (int c = 0; c < len; ++c, f += stride) {
                vd fj[NV];
                for (int b = 0; b < NV; ++b) fj[b] = *(const vd_unaligned *)(f + j0 + VLANES * b);
                for (int a = 0; a < TILE_I; ++a) {
                    const double fi = f[i0 + a];
                    for (int b = 0; b < NV; ++b) v[a][b] += fi * fj[b];
                }
            }
            for (int a = 0; a < TILE_I && i0 + a < nd; ++a) {
                double *restrict row = acc->info + nd * (i0 + a);
                for (int b = 0; b < TILE_J && j0 + b < nd; ++b) {
                    const vd sum = v[a][b / VLANES];
                    if (j0 + b >= i0 + a) row[j0 + b] += get_lane(&sum, b % VLANES);
                }
            }
        }
    acc->used = 0;
}

static const double SQRT_HALF = 0.70710678118654752440;

/* One sample's update along every direction: the features, the gradient, and the state
 * tangents carried through the update (dphi, dP: in, the predicted; out, the updated), a
 * group of VLANES directions at a time. */
static ALWAYS_INLINE void update_tangents(const pass_t *p, const step_t *s, const update_t *u,
                                          int ha, int hm, const tangent_t *tan, vd *dphi,
                                          vd *dP, fisher_acc_t *acc, const int ny,
                                          const int r0)
{
    const size_t ng = (acc->k + VLANES - 1) / VLANES;
    const int nf = ny + ny * (ny + 1) / 2;
    if (acc->used + FEATURES > BLOCK_LEN) flush_block(acc);
    rotvec_coef_t eta_c;
    rotvec_coef(s->eta, &eta_c);
    const size_t st = acc->stride;
    for (size_t gi = 0; gi < ng; ++gi) {
        const tangent_t *t = tan + gi;
        vd *dphi1 = dphi + 3 * gi, *dPp = dP + 9 * gi;
        vd dH[18], dy[6];
        measurement_tangent(p, s, u, ha, hm, t, dphi1, dH, dy);
        vd de[6], dHM[36], dS[36], G[18];
        for (int i = 0; i < ny; ++i) de[i] = -dy[(r0 + i)];
        /* dH M (ny × ny), then dS. */
        for (int i = 0; i < ny; ++i) {
            const vd *h = dH + 3 * (r0 + i);
            for (int j = 0; j < ny; ++j)
                dHM[ny * i + j] = h[0] * u->M[j] + h[1] * u->M[ny + j] + h[2] * u->M[2 * ny + j];
        }
        for (int i = 0; i < ny; ++i) {
            const int ri = (r0 + i);
            const double *h = u->H + 3 * ri;
            vd hp[3]; /* row of H dPp */
            for (int b = 0; b < 3; ++b) hp[b] = h[0] * dPp[b] + h[1] * dPp[3 + b] + h[2] * dPp[6 + b];
            for (int j = i; j < ny; ++j) {
                const int rj = (r0 + j);
                const double *h2 = u->H + 3 * rj;
                vd v = dHM[ny * i + j] + dHM[ny * j + i] + hp[0] * h2[0] + hp[1] * h2[1] +
                       hp[2] * h2[2];
                if (ri < 3 && rj < 3) v += t->Sa[3 * ri + rj];
                if (ri >= 3 && rj >= 3) v += t->Sm[3 * (ri - 3) + (rj - 3)];
                dS[ny * i + j] = dS[ny * j + i] = v;
            }
        }
        /* G = dPp Hᵀ + Pp dHᵀ (3 × ny). */
        for (int b = 0; b < 3; ++b)
            for (int i = 0; i < ny; ++i) {
                const int r = (r0 + i);
                const double *h = u->H + 3 * r;
                const vd *dh = dH + 3 * r;
                G[ny * b + i] = dPp[3 * b] * h[0] + dPp[3 * b + 1] * h[1] + dPp[3 * b + 2] * h[2] +
                                s->Pp[3 * b] * dh[0] + s->Pp[3 * b + 1] * dh[1] + s->Pp[3 * b + 2] * dh[2];
            }
        /* Features and gradient: a = L⁻¹ dε, W = L⁻¹ dS L⁻ᵀ, with L⁻¹ formed once per
         * sample (products instead of triangular solves: no divisions, no chains). */
        const double *Li = u->Linv;
        vd a[6], X[36], W[36];
        for (int i = 0; i < ny; ++i) {
            vd v = {0.0};
            UNROLL_6
            for (int k = 0; k <= i; ++k) v += Li[ny * i + k] * de[k];
            a[i] = v;
        }
        for (int i = 0; i < ny; ++i) /* X = L⁻¹ dS */
            for (int j = 0; j < ny; ++j) {
                vd v = {0.0};
                UNROLL_6
                for (int k = 0; k <= i; ++k) v += Li[ny * i + k] * dS[ny * k + j];
                X[ny * i + j] = v;
            }
        for (int i = 0; i < ny; ++i) /* W = X L⁻ᵀ, upper triangle */
            for (int j = i; j < ny; ++j) {
                vd v = {0.0};
                UNROLL_6
                for (int k = 0; k <= j; ++k) v += X[ny * i + k] * Li[ny * j + k];
                W[ny * i + j] = v;
            }
        /* This group's features of this sample, one row of the block per feature. */
        double *f = acc->block + st * (size_t)acc->used + VLANES * gi;
        vd gq = {0.0}, gw = {0.0}, tr = {0.0};
        size_t c = 0;
        for (int i = 0; i < ny; ++i) {
            *(vd_unaligned *)(f + st * c++) = a[i];
            gq += a[i] * u->w[i];
        }
        for (int i = 0; i < ny; ++i) {
            const vd wii = W[ny * i + i];
            *(vd_unaligned *)(f + st * c++) = wii * SQRT_HALF;
            tr += wii;
            gw += wii * u->w[i] * u->w[i];
            for (int j = i + 1; j < ny; ++j) {
                const vd wij = W[ny * i + j];
                *(vd_unaligned *)(f + st * c++) = wij;
                gw += 2.0 * wij * u->w[i] * u->w[j];
            }
        }
        const vd gd = gq - 0.5 * gw + 0.5 * tr;
        for (int l = 0; l < VLANES && VLANES * gi + l < acc->k; ++l)
            acc->grad[VLANES * gi + l] += get_lane(&gd, l);
        /* dη = G z − K (dS z) + K dε, dPu = dPp − G Kᵀ − K Gᵀ + K dS Kᵀ. */
        vd dSz[6], deta[3], KdS[18];
        for (int i = 0; i < ny; ++i) {
            vd v = {0.0};
            for (int j = 0; j < ny; ++j) v += dS[ny * i + j] * u->z[j];
            dSz[i] = v;
        }
        for (int b = 0; b < 3; ++b) {
            vd v = {0.0};
            for (int i = 0; i < ny; ++i)
                v += G[ny * b + i] * u->z[i] + u->K[ny * b + i] * (de[i] - dSz[i]);
            deta[b] = v;
            for (int j = 0; j < ny; ++j) {
                vd x = {0.0};
                for (int i = 0; i < ny; ++i) x += u->K[ny * b + i] * dS[ny * i + j];
                KdS[ny * b + j] = x;
            }
        }
        vd dPu[9];
        for (int b = 0; b < 3; ++b)
            for (int cc = b; cc < 3; ++cc) {
                vd v = dPp[3 * b + cc];
                for (int i = 0; i < ny; ++i)
                    v += -G[ny * b + i] * u->K[ny * cc + i] - u->K[ny * b + i] * G[ny * cc + i] +
                         KdS[ny * b + i] * u->K[ny * cc + i];
                dPu[3 * b + cc] = v;
            }
        sym_fill_v(dPu);
        for (int i = 0; i < 9; ++i) dPp[i] = dPu[i];
        vd r1[3], r2[3];
        rotvec_rotate(&eta_c, dphi1, r1);
        rotvec_jac(&eta_c, 1.0, deta, r2);
        for (int i = 0; i < 3; ++i) dphi1[i] = r1[i] + r2[i];
    }
    acc->used += nf;
}

/* update_tangents with the number of measured rows and the first one as constants, so that
 * the small loops over them unroll: both sensors (6 rows), the accelerometer alone (rows
 * 0–2) or the magnetometer alone (rows 3–5). */
static FISHER_HOT void update_tangents_both(const pass_t *p, const step_t *s, const update_t *u,
                                          const tangent_t *tan, vd *dphi, vd *dP,
                                          fisher_acc_t *acc)
{
    update_tangents(p, s, u, 1, 1, tan, dphi, dP, acc, 6, 0);
}

static FISHER_HOT void update_tangents_acc(const pass_t *p, const step_t *s, const update_t *u,
                                         const tangent_t *tan, vd *dphi, vd *dP,
                                         fisher_acc_t *acc)
{
    update_tangents(p, s, u, 1, 0, tan, dphi, dP, acc, 3, 0);
}

static FISHER_HOT void update_tangents_mag(const pass_t *p, const step_t *s, const update_t *u,
                                         const tangent_t *tan, vd *dphi, vd *dP,
                                         fisher_acc_t *acc)
{
    update_tangents(p, s, u, 0, 1, tan, dphi, dP, acc, 3, 3);
}

/* The time update of every group's tangents, sample k − 1 → k (k > 0). */
static FISHER_HOT void predict_tangents(const pass_t *p, const step_t *s, size_t k,
                                      const tangent_t *tan, size_t ng, vd *dphi, vd *dP)
{
    const double dt = p->d->dt[k];
    const double *w = p->d->gyr + 3 * (k - 1);
    double th[3], Q[9], RS[9];
    for (int i = 0; i < 3; ++i) th[i] = dt * (w[i] - p->m->bias[i]);
    rotvec_coef_t c;
    rotvec_coef(th, &c);
    mat_mul(s->R, p->Sw, RS);
    sym_mul_nt(RS, s->R, Q);
    const double dt2 = dt * dt;
    for (size_t gi = 0; gi < ng; ++gi) {
        const tangent_t *t = tan + gi;
        vd *f = dphi + 3 * gi, *P = dP + 9 * gi;
        vd dth[3], j[3], rj[3];
        for (int i = 0; i < 3; ++i) dth[i] = -dt * t->bias[i];
        rotvec_jac(&c, -1.0, dth, j);
        mat_vec_sv(s->R, j, rj);
        for (int i = 0; i < 3; ++i) f[i] += rj[i];
        /* [dφ×] Q − Q [dφ×] = A + Aᵀ with A = [dφ×] Q; column j of A is dφ × Q_j. */
        vd A[9], RdS[9];
        for (int jj = 0; jj < 3; ++jj) {
            const double qj[3] = {Q[jj], Q[3 + jj], Q[6 + jj]};
            vd col[3];
            cross3_vs(f, qj, col);
            for (int i = 0; i < 3; ++i) A[3 * i + jj] = col[i];
        }
        sym_sandwich_sv(s->R, t->Sw, RdS);
        for (int a = 0; a < 3; ++a)
            for (int b = 0; b < 3; ++b) P[3 * a + b] += dt2 * (A[3 * a + b] + A[3 * b + a] + RdS[3 * a + b]);
    }
}

static ALWAYS_INLINE double fisher_loop(const pass_t *p, const tangent_t *tan, vd *dphi, vd *dP,
                                        fisher_acc_t *acc, int masked)
{
    const mc_mekf_data_t *data = p->d;
    const size_t ng = (acc->k + VLANES - 1) / VLANES;
    double q[4], P[9];
    load_prior(data, q, P);
    double cost = 0.0;
    logdet_acc_t ld = {1.0, 0.0};
    step_t s;
    update_t u;
    for (size_t k = 0; k < data->n; ++k) {
        int ha, hm;
        sample_has(data, k, masked, &ha, &hm);
        if (!step_forward(p, k, ha, hm, q, P, &s)) return NAN;
        if (k > 0) predict_tangents(p, &s, k, tan, ng, dphi, dP);
        if (ha || hm) {
            if (!prepare_update(p, &s, k, ha, hm, &u)) return NAN;
            if (ha && hm)
                update_tangents_both(p, &s, &u, tan, dphi, dP, acc);
            else if (ha)
                update_tangents_acc(p, &s, &u, tan, dphi, dP, acc);
            else
                update_tangents_mag(p, &s, &u, tan, dphi, dP, acc);
        }
        cost += s.cost;
        logdet_add(&ld, s.det);
        memcpy(q, s.q_out, sizeof q);
        renormalise_quat(q);
        memcpy(P, s.Pu, sizeof P);
    }
    return cost + 0.5 * logdet_total(&ld);
}

static FISHER_HOT double fisher_pass_unmasked(const pass_t *p, const tangent_t *tan, vd *dphi,
                                            vd *dP, fisher_acc_t *acc)
{
    return fisher_loop(p, tan, dphi, dP, acc, 0);
}

static FISHER_HOT double fisher_pass_masked(const pass_t *p, const tangent_t *tan, vd *dphi,
                                          vd *dP, fisher_acc_t *acc)
{
    return fisher_loop(p, tan, dphi, dP, acc, 1);
}

double mc_mekf_fisher(const mc_mekf_model_t *model, const mc_mekf_data_t *data,
                      const double *directions, size_t k, double *work, size_t work_len,
                      double *info, double *grad)
{
    /* Zeroed first, so that callers testing only the cost never see garbage; a k out of
     * range says nothing about the buffers' sizes, so nothing is written then. */
    const int k_valid = k >= 1 && k <= MC_MEKF_FISHER_MAX_DIRECTIONS;
    if (k_valid && info) memset(info, 0, k * k * sizeof *info);
    if (k_valid && grad) memset(grad, 0, k * sizeof *grad);
    if (!k_valid || !valid_arguments(model, data) || !directions || !info || !grad || !work ||
        work_len < MC_MEKF_FISHER_WORK_DOUBLES(k))
        return NAN;
    pass_t p;
    if (!make_pass(model, data, &p)) return NAN;
    /* The padding lanes of the last group are zero directions: their tangents stay zero
     * (every tangent is linear in them) and their results are dropped. The prior (q₀, P₀)
     * is data: its tangents are zero. */
    tangent_t tan[MAX_GROUPS];
    vd dphi[3 * MAX_GROUPS], dP[9 * MAX_GROUPS];
    memset(tan, 0, sizeof tan);
    memset(dphi, 0, sizeof dphi);
    memset(dP, 0, sizeof dP);
    for (size_t d = 0; d < k; ++d)
        load_tangent(directions + MC_MEKF_MODEL_DOUBLES * d, tan + d / VLANES, (int)(d % VLANES));
    const size_t stride = MC_MEKF_FISHER_WORK_DOUBLES(k) / BLOCK_LEN;
    memset(work, 0, stride * BLOCK_LEN * sizeof *work); /* the padding stays zero */
    fisher_acc_t acc_s = {k, stride, info, grad, 0, work}, *acc = &acc_s;
    double cost = any_mask(data) ? fisher_pass_masked(&p, tan, dphi, dP, acc)
                                 : fisher_pass_unmasked(&p, tan, dphi, dP, acc);
    flush_block(acc);
    if (!isfinite(cost)) {
        memset(info, 0, k * k * sizeof *info);
        memset(grad, 0, k * sizeof *grad);
        return cost;
    }
    for (size_t i = 0; i < k; ++i)
        for (size_t j = 0; j < i; ++j) info[k * i + j] = info[k * j + i];
    return cost;
}
