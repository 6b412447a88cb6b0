/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Multiplicative EKF likelihood and its reverse-mode gradient. See mekf_likelihood.h and
 * host/src/magcal/calib/likelihood/mekf.py for the model.
 *
 * Numerical choices:
 * - Information form of the update. With R_t = blockdiag(Sa_t, Sm) and the 3-dimensional
 *   error state, S_t = H P Hᵀ + R_t is 6×6 but only rank-3 away from R_t, so
 *     εᵀS⁻¹ε   = εᵀR⁻¹ε − uᵀ Λ⁻¹ u,        u = HᵀR⁻¹ε,  Λ = P⁻¹ + HᵀR⁻¹H,
 *     log det S = log det R + log det P + log det Λ,
 *   and the posterior is P⁺ = Λ⁻¹, η = Λ⁻¹u (matrix inversion and determinant lemmas).
 *   Every inverse is then 3×3 and symmetric positive definite.
 * - The information J = HᵀR⁻¹H and u are formed in the navigation frame without building H:
 *   with Ha = −Rᵀ[g_n×] and Hm = D Rᵀ[m×],
 *     J = [g_n×]ᵀ (R Ai Rᵀ) [g_n×] + [m×]ᵀ (R K Rᵀ) [m×],   K = Dᵀ Sm⁻¹ D (once per pass),
 *     u = g_n × (R za) + (R Dᵀ zm) × m,                       za = Ai εa, zm = Sm⁻¹ εm.
 *   g_n = (0, 0, −g), so the accelerometer term only fills the upper-left 2×2 block.
 * - Masks (has_acc, has_mag): a measurement absent at a sample is the omission of its terms
 *   (its share of J and u, of εᵀR⁻¹ε and of log det R), and a sample with neither skips
 *   the update (Pu = Pp, q_out = q1, no cost). The reverse pass omits the same terms; the
 *   pass constants below are counted over the samples that use them.
 * - Ai = (Sa + c_t I)⁻¹ is the constant Sa⁻¹ for the (many) samples with c_t = 0: it is
 *   inverted once per pass, and in the reverse pass its adjoint is summed over those samples
 *   (those with the accelerometer) and turned into a Sa adjoint once at the end.
 * - The quaternion is renormalised after each update (one Newton step: it is unit to a few
 *   ulps). Parameter perturbations move it only along the unit sphere, where renormalisation
 *   is the identity to first order, so the reverse pass omits it and stays exact; it carries
 *   attitude adjoints as body-frame torques (3-vectors), see step_reverse.
 * - Adjoints of symmetric matrices are kept symmetric. Every perturbation of a symmetric
 *   quantity (P, the noise covariances) is symmetric, so only the symmetric part of its
 *   adjoint is ever contracted: dropping the skew part is exact and halves the work.
 * - The forward pass tapes, per sample, the quantities that are costly to recompute
 *   (MC_MEKF_TAPE_DOUBLES = 40 doubles: the predicted attitude, Pp⁻¹, Λ⁻¹, u, η and the
 *   magnetometer terms). The reverse pass recomputes the rest: the rotation matrix and its
 *   rotation-vector coefficients, the accelerometer terms εa and za = Ai εa, mb = Rᵀ m,
 *   and, for samples with c_t ≠ 0, Ai = (Σa + c_t I)⁻¹ (one more 3×3 inverse each; the
 *   common c_t = 0 samples share the pass constant Σa⁻¹). Taping Ai instead would add 6
 *   doubles to every record (records have one size) to save an inverse on the few inflated
 *   samples. Memory is O(n · state) and independent of the number of parameters (600,000
 *   samples: 192 MB). A sample's record is written only as far as the reverse pass reads
 *   it (the magnetometer terms with the magnetometer, the update's with any measurement).
 * - The magnetometer's delay τ (see mc_mekf_model_t) enters only the magnetometer's terms,
 *   through the rotation Rm = R Exp(−τ ω) it sees in place of R; at τ = 0 that is R itself
 *   and the forward pass skips the rotation. Its adjoint, and the gyroscope bias's share
 *   through ω, come from the torque on Rm (step_reverse), so ∂V/∂τ is as exact as the rest.
 * - log det S: the constant parts (log det Σa, log det Σm) are logged once per pass and
 *   added per sample that has the measurement (in the gradient: times the count of those
 *   samples); the per-step determinants are multiplied and logged about once per hundred
 *   steps.
 */
#include "mekf_step.h"

/* Layout of one sample's tape record: what the reverse pass would otherwise recompute at
 * the price of a matrix product or an inverse. */
enum {
    TAPE_Q1 = 0,   /* predicted attitude q1 (4)       */
    TAPE_Y = 4,    /* Pp⁻¹, packed (6)                 */
    TAPE_PU = 10,  /* Λ⁻¹, packed (6)                  */
    TAPE_U = 16,   /* u (3)                            */
    TAPE_ETA = 19, /* η (3)                            */
    TAPE_KN = 22,  /* R K Rᵀ, packed (6; magnetometer) */
    TAPE_EM = 28,  /* εm (3)                           */
    TAPE_ZM = 31,  /* Σm⁻¹ εm (3)                      */
    TAPE_XM = 34,  /* Dᵀ zm (3)                        */
    TAPE_VM = 37,  /* R xm (3)                         */
    TAPE_END = 40
};
typedef char tape_size_matches_header[TAPE_END == MC_MEKF_TAPE_DOUBLES ? 1 : -1];

/* Adjoints summed over the samples. */
typedef struct {
    mc_mekf_model_t g; /* D, o, m, bias, Sw and the Sa of samples with c_t ≠ 0; its Sm
                        * stays zero (Σm's adjoint is formed from Mi_bar and K_bar) */
    double Ai0_bar[9]; /* Σ of Āi over the samples with c_t = 0 */
    double Mi_bar[9];  /* Σ m̄ of Σm⁻¹ (besides K)              */
    double K_bar[9];   /* Σ of K̄                                */
    size_t n0;         /* samples with the accelerometer and c_t = 0 */
} grad_acc_t;

/* The accelerometer's share of the reverse of step_forward's update at sample k (present
 * there, its information Ai): from the adjoints ū of u and J̄ of J (Jb, symmetric) into the
 * torque tq, and the adjoint of Ai into Ai_bar (for acc_information_reverse). */
static ALWAYS_INLINE void acc_reverse(const pass_t *p, size_t k, const double *restrict Ai,
                                      const double *restrict R, const double *restrict u_bar,
                                      const double *restrict Jb, double *restrict tq,
                                      double *restrict Ai_bar)
{
    const mc_mekf_data_t *d = p->d;
    const double g = p->g;
    const double *r0 = R, *r1 = R + 3, *r2 = R + 6;
    const double *ya = d->acc + 3 * k;
    double ea[3], za[3], za_bar[3], ea_bar[3], p0[3], p1[3], t3[3];
    for (int i = 0; i < 3; ++i) ea[i] = ya[i] - g * r2[i];
    mat_vec(Ai, ea, za);
    /* u_a = (g r1·za, −g r0·za, 0) = g_n × (R za): the rows 0, 1 of R get v̄a zaᵀ,
     * v̄a = (−g ū1, g ū0), so z̄a = Rᵀ v̄a (+ ½ εa from e2) and δ̄ += za × Rᵀv̄a. */
    const double va0 = -g * u_bar[1], va1 = g * u_bar[0];
    for (int i = 0; i < 3; ++i) za_bar[i] = va0 * r0[i] + va1 * r1[i];
    cross3(za, za_bar, t3);
    for (int i = 0; i < 3; ++i) {
        tq[i] += t3[i];
        za_bar[i] += 0.5 * ea[i];
    }
    /* J_a = g² [[r1ᵀAi r1, −r1ᵀAi r0], [·, r0ᵀAi r0]] (upper-left block). With Ā its
     * adjoint and pᵢ = Σⱼ Āᵢⱼ rⱼ: Āi += W = Σᵢ rᵢ pᵢᵀ (symmetric), and RᵀR̄ = 2 W Ai. */
    const double g2 = g * g;
    const double A00 = g2 * Jb[4], A01 = -g2 * Jb[1], A11 = g2 * Jb[0];
    for (int i = 0; i < 3; ++i) {
        p0[i] = A00 * r0[i] + A01 * r1[i];
        p1[i] = A01 * r0[i] + A11 * r1[i];
    }
    for (int i = 0; i < 3; ++i)
        for (int j = i; j < 3; ++j) Ai_bar[3 * i + j] = r0[i] * p0[j] + r1[i] * p1[j];
    sym_fill(Ai_bar);
    tq[0] += 2.0 * (dot3(Ai_bar + 6, Ai + 3) - dot3(Ai_bar + 3, Ai + 6));
    tq[1] += 2.0 * (dot3(Ai_bar, Ai + 6) - dot3(Ai_bar + 6, Ai));
    tq[2] += 2.0 * (dot3(Ai_bar + 3, Ai) - dot3(Ai_bar, Ai + 3));
    /* za = Ai εa and e2 = εaᵀ za; εa = ya − g r2: row 2 of R̄ is −g ε̄a */
    sym_add_outer(Ai_bar, za_bar, ea);
    mat_vec(Ai, za_bar, ea_bar);
    for (int i = 0; i < 3; ++i) ea_bar[i] = -g * (ea_bar[i] + 0.5 * za[i]);
    cross3(ea_bar, r2, t3);
    for (int i = 0; i < 3; ++i) tq[i] += t3[i];
}

/* Ai = (Σa + c I)⁻¹ and ½ log det(Σa + c I): the adjoints of Σa from Āi. */
static ALWAYS_INLINE void acc_information_reverse(double cx, const double *restrict Ai,
                                                  const double *restrict Ai_bar,
                                                  grad_acc_t *restrict acc)
{
    mc_mekf_model_t *gm = &acc->g;
    if (cx == 0.0) {
        for (int t = 0; t < 6; ++t) acc->Ai0_bar[UPPER[t]] += Ai_bar[UPPER[t]];
        acc->n0 += 1;
    } else {
        double Sa_bar[9];
        sym_sandwich(Ai, Ai_bar, Sa_bar);
        for (int t = 0; t < 6; ++t) {
            const int i = UPPER[t];
            Sa_bar[i] = 0.5 * Ai[i] - Sa_bar[i];
            gm->Sa[i] += Sa_bar[i];
        }
    }
}

/* The magnetometer's share of the reverse of step_forward's update at sample k (present
 * there), from its tape record; as acc_reverse. */
static ALWAYS_INLINE void mag_reverse(const pass_t *p, const double *restrict rec,
                                      const double *restrict R, const double *restrict u_bar,
                                      const double *restrict Jb, double *restrict tq,
                                      grad_acc_t *restrict acc)
{
    const mc_mekf_model_t *m = p->m;
    mc_mekf_model_t *gm = &acc->g;
    double t3[3];
    const double *em = rec + TAPE_EM, *zm = rec + TAPE_ZM, *xm = rec + TAPE_XM,
                 *vm = rec + TAPE_VM;
    double Kn[9], mb[3];
    sym_unpack(rec + TAPE_KN, Kn);
    mat_tvec(R, m->m, mb);

    /* u_m = vm × m: v̄m = m × ū, m̄ += ū × vm; vm = R xm: δ̄ += xm × x̄m; xm = Dᵀ zm */
    double vm_bar[3], xm_bar[3], zm_bar[3], em_bar[3], mb_bar[3], m_bar[3];
    cross3(m->m, u_bar, vm_bar);
    cross3(u_bar, vm, m_bar);
    mat_tvec(R, vm_bar, xm_bar);
    cross3(xm, xm_bar, t3);
    for (int i = 0; i < 3; ++i) tq[i] += t3[i];
    mat_vec(m->D, xm_bar, zm_bar);
    for (int i = 0; i < 3; ++i) zm_bar[i] += 0.5 * em[i];
    /* zm = Mi εm (and e2 reads εm) */
    sym_add_outer_upper(acc->Mi_bar, zm_bar, em);
    mat_vec(p->Mi, zm_bar, em_bar);
    for (int i = 0; i < 3; ++i) em_bar[i] += 0.5 * zm[i];
    /* εm = ym − D mb − o; mb = Rᵀ m: m̄ −= R (Dᵀ ε̄m), δ̄ += mb × Dᵀε̄m */
    mat_tvec(m->D, em_bar, mb_bar); /* −m̄b */
    for (int i = 0; i < 3; ++i) {
        gm->o[i] -= em_bar[i];
        for (int j = 0; j < 3; ++j) gm->D[3 * i + j] += zm[i] * xm_bar[j] - em_bar[i] * mb[j];
    }
    mat_vec(R, mb_bar, t3);
    for (int i = 0; i < 3; ++i) m_bar[i] -= t3[i];
    cross3(mb, mb_bar, t3);
    for (int i = 0; i < 3; ++i) tq[i] += t3[i];

    /* J_m = [m×]ᵀ Kn [m×], Kn = R K Rᵀ: [m×]‾ = 2 Kn [m×] J̄ (only its skew part reaches
     * m; row i of Kn [m×] is Knᵢ × m), and K̄ += Z = Rᵀ [m×] J̄ [m×]ᵀ R = B J̄ Bᵀ with
     * B = Rᵀ[m×] = [mb×] Rᵀ, whose column j is mb × rⱼ. RᵀR̄ = 2 Z K. */
    double T[9], Bt[9], Z[9];
    for (int i = 0; i < 3; ++i) cross3(Kn + 3 * i, m->m, T + 3 * i);
    m_bar[0] += 2.0 * (dot3(T + 6, Jb + 3) - dot3(T + 3, Jb + 6));
    m_bar[1] += 2.0 * (dot3(T, Jb + 6) - dot3(T + 6, Jb));
    m_bar[2] += 2.0 * (dot3(T + 3, Jb) - dot3(T, Jb + 3));
    for (int i = 0; i < 3; ++i) gm->m[i] += m_bar[i];
    for (int j = 0; j < 3; ++j) cross3(mb, R + 3 * j, Bt + 3 * j); /* rows of Bᵀ */
    sym_sandwich_t(Bt, Jb, Z);
    for (int t = 0; t < 6; ++t) acc->K_bar[UPPER[t]] += Z[UPPER[t]];
    const double *K = p->K;
    tq[0] += 2.0 * (dot3(Z + 6, K + 3) - dot3(Z + 3, K + 6));
    tq[1] += 2.0 * (dot3(Z, K + 6) - dot3(Z + 6, K));
    tq[2] += 2.0 * (dot3(Z + 3, K) - dot3(Z, K + 3));
}

/* Reverse of step_forward for sample k from its tape record.
 *
 * Attitude adjoints are body-frame torques: δ̄ such that dV = δ̄·δ when an attitude q
 * moves to q ⊙ exp_q(δ/2) (R(q) to R(q)(I + [δ×])). The quaternion stays on the unit
 * sphere, so this is all of its adjoint; it also makes renormalisation the identity. Along
 * the chain q → q1 = q ⊙ Δ → q_out = exp_q(η/2) ⊙ q1:
 *   δ_q1 = R(Δ)ᵀ δ_q + Jr(2φ) 2dφ,   δ_out = δ_q1 + R(q1)ᵀ Jr(η) dη.
 * A term R̄ of R = R(q1) adds vex(RᵀR̄ − R̄ᵀR): Σᵢ R̄ᵢ × rᵢ over its rows, b × (Rᵀa) for
 * R̄ = a bᵀ, and (M₂₁ − M₁₂, M₀₂ − M₂₀, M₁₀ − M₀₁) for RᵀR̄ = M. Most such M are products
 * the gradient forms anyway, which saves building R̄.
 *
 * δ̄_out and P̄_out (= P̄u) arrive from later steps; δ̄_q and P̄ of the step's inputs are
 * assigned. */
static ALWAYS_INLINE void step_reverse(const pass_t *p, size_t k, int ha, int hm,
                                       const double *restrict rec,
                                       const double *restrict tq_out,
                                       const double *restrict Pu_bar_in, double *restrict tq_in,
                                       double *restrict P_bar, grad_acc_t *restrict acc)
{
    const mc_mekf_model_t *m = p->m;
    const mc_mekf_data_t *d = p->d;
    mc_mekf_model_t *gm = &acc->g;
    double R[9], tq[3];

    if (ha || hm) {
        /* q_out = exp_q(η/2) ⊙ q1: η̄ = Jr(η)ᵀ R δ̄_out; and the cost's −½ uᵀη. The torque
         * on q1 starts as δ̄_out. */
        const double *u = rec + TAPE_U, *eta = rec + TAPE_ETA;
        double Y[9], Pu[9], w[3], eta_bar[3];
        sym_unpack(rec + TAPE_Y, Y);
        sym_unpack(rec + TAPE_PU, Pu);
        quat_to_mat(rec + TAPE_Q1, R);
        memcpy(tq, tq_out, sizeof tq);
        mat_vec(R, tq_out, w);
        rotvec_apply(eta, w, NULL, eta_bar);
        for (int i = 0; i < 3; ++i) eta_bar[i] -= 0.5 * u[i];
        /* η = Pu u; the cost's −½ uᵀη */
        double u_bar[3], Pu_bar[9], Lam_bar[9], Pp_bar[9];
        mat_vec(Pu, eta_bar, u_bar);
        for (int i = 0; i < 3; ++i) u_bar[i] -= 0.5 * eta[i];
        memcpy(Pu_bar, Pu_bar_in, sizeof Pu_bar);
        sym_add_outer(Pu_bar, eta_bar, u);
        /* Pu = Λ⁻¹ and ½ log det Λ: Λ̄ = −Pu P̄u Pu + ½ Pu; J̄ = Λ̄ */
        sym_sandwich(Pu, Pu_bar, Lam_bar);
        for (int i = 0; i < 9; ++i) Lam_bar[i] = 0.5 * Pu[i] - Lam_bar[i];
        /* Λ = Y + J, Y = Pp⁻¹ and ½ log det Pp: P̄p = −Y Λ̄ Y + ½ Y */
        sym_sandwich(Y, Lam_bar, Pp_bar);
        for (int i = 0; i < 9; ++i) P_bar[i] = 0.5 * Y[i] - Pp_bar[i];
        /* J = J_a + J_m, u = u_a + u_m: each measurement present takes J̄ = Λ̄ and ū. */
        double cx = 0.0, Ai_buf[9], det_Sa, Ai_bar[9];
        const double *Ai = NULL;
        if (ha) {
            cx = acc_extra(d, k);
            Ai = acc_information(p, cx, Ai_buf, &det_Sa); /* succeeded forwards */
            acc_reverse(p, k, Ai, R, u_bar, Lam_bar, tq, Ai_bar);
        }
        if (hm) {
            /* The magnetometer's terms saw Rm = R Exp(−v), v = τ ω: its torque tm on Rm is
             * Exp(v) δ for a torque δ on R, so δ̄ += Exp(−v) tm; and Rm moves by
             * −Jr(−v) dv for dv, so v̄ = −Jr(−v)ᵀ tm, τ̄ = v̄·ω, δ̄ω = −τ v̄. */
            double v[3], minus_v[3], Rm[9], tm[3] = {0.0, 0.0, 0.0}, rv[3], jv[3];
            delay_rotation(p, k, v);
            delayed_attitude(p, k, R, Rm);
            mag_reverse(p, rec, Rm, u_bar, Lam_bar, tm, acc);
            for (int i = 0; i < 3; ++i) minus_v[i] = -v[i];
            rotvec_apply(minus_v, tm, rv, jv);
            const double *w = d->gyr + 3 * (k > 0 ? k - 1 : 0);
            for (int i = 0; i < 3; ++i) {
                tq[i] += rv[i];
                gm->delay -= jv[i] * (w[i] - m->bias[i]);
                gm->bias[i] += m->delay * jv[i];
            }
        }
        if (ha) acc_information_reverse(cx, Ai, Ai_bar, acc);
    } else {
        /* No update: q_out = q1, Pu = Pp. */
        quat_to_mat(rec + TAPE_Q1, R);
        memcpy(tq, tq_out, sizeof tq);
        memcpy(P_bar, Pu_bar_in, 9 * sizeof(double));
    }

    if (k > 0) {
        /* Pp = P + T² R Σω Rᵀ: Σ̄ω += T² X with X = Rᵀ P̄p R; RᵀR̄ = 2 T² X Σω */
        const double dt = d->dt[k], dt2 = dt * dt;
        double X[9];
        sym_sandwich_t(R, P_bar, X);
        for (int t = 0; t < 6; ++t) gm->Sw[UPPER[t]] += dt2 * X[UPPER[t]];
        const double *Sw = p->Sw, h = 2.0 * dt2;
        tq[0] += h * (dot3(X + 6, Sw + 3) - dot3(X + 3, Sw + 6));
        tq[1] += h * (dot3(X, Sw + 6) - dot3(X + 6, Sw));
        tq[2] += h * (dot3(X + 3, Sw) - dot3(X, Sw + 3));
        /* q1 = q ⊙ Δ, Δ = exp_q(φ) (rotation vector 2φ), φ = ½ T (ω − δω). 2φ = T (ω − δω)
         * bit for bit: scaling by ½ and 2 is exact (barring underflow). */
        const double *wg = d->gyr + 3 * (k - 1);
        double rv[3], rv_bar[3];
        for (int i = 0; i < 3; ++i) rv[i] = dt * (wg[i] - m->bias[i]);
        rotvec_apply(rv, tq, tq_in, rv_bar); /* φ̄ = 2 r̄v, δ̄ω = −½ T φ̄ */
        for (int i = 0; i < 3; ++i) gm->bias[i] -= dt * rv_bar[i];
    } else {
        memcpy(tq_in, tq, sizeof tq);
    }
}

/* ---------------------------------------------------------------- passes */

/* Cholesky-whitened innovation L⁻¹ε with S = H Pp Hᵀ + blockdiag(Σa + c I, Σm) = L Lᵀ
 * over the measurements present (ha, hm: 6×6, 3×3 or none), the noise from the pass's
 * symmetrised covariances; an absent measurement's entries are NaN (0 for the magnetometer
 * without use_mag). Diagnostics only: H is rebuilt here, Ha = −Rᵀ[g_n×], Hm = D Rmᵀ[m×].
 * All NaN when a pivot of S is not positive (S is positive definite whenever the step
 * succeeded, so only rounding can get here). */
static void whiten(const pass_t *p, const step_t *s, size_t k, int ha, int hm, double *out)
{
    const mc_mekf_model_t *m = p->m;
    const double g = p->g;
    const double *R = s->R;
    double H[18], S[36], L[36], eps[6], w[6];
    for (int i = 0; i < 3; ++i) {
        /* [g_n×] = [[0, g, 0], [−g, 0, 0], [0, 0, 0]]: row i of −Rᵀ[g_n×] */
        H[3 * i + 0] = g * R[3 + i];
        H[3 * i + 1] = -g * R[i];
        H[3 * i + 2] = 0.0;
    }
    if (hm) {
        const double *mm = m->m;
        const double Mx[9] = {0.0, -mm[2], mm[1], mm[2], 0.0, -mm[0], -mm[1], mm[0], 0.0};
        const double *Rm = s->Rm;
        double RtMx[9];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                RtMx[3 * i + j] = Rm[i] * Mx[j] + Rm[3 + i] * Mx[3 + j] + Rm[6 + i] * Mx[6 + j];
        mat_mul(m->D, RtMx, H + 9);
    }
    /* rows[i]: the row of the full 6-vector (acc 0–2, mag 3–5) that entry i stands for */
    int rows[6], ny = 0;
    for (int i = 0; i < 3; ++i)
        if (ha) rows[ny++] = i;
    for (int i = 3; i < 6; ++i)
        if (hm) rows[ny++] = i;
    for (int i = 0; i < ny; ++i) eps[i] = rows[i] < 3 ? s->ea[rows[i]] : s->em[rows[i] - 3];
    const double cx = ha ? acc_extra(p->d, k) : 0.0;
    for (int i = 0; i < ny; ++i)
        for (int j = 0; j < ny; ++j) {
            const int ri = rows[i], rj = rows[j];
            double v = 0.0;
            for (int a = 0; a < 3; ++a)
                for (int b = 0; b < 3; ++b) v += H[3 * ri + a] * s->Pp[3 * a + b] * H[3 * rj + b];
            if (ri < 3 && rj < 3) v += p->Sa[3 * ri + rj] + (ri == rj ? cx : 0.0);
            if (ri >= 3 && rj >= 3) v += p->Sm[3 * (ri - 3) + (rj - 3)];
            S[ny * i + j] = v;
        }
    for (int j = 0; j < ny; ++j) {
        double v = S[ny * j + j];
        for (int a = 0; a < j; ++a) v -= L[ny * j + a] * L[ny * j + a];
        if (!(v > 0.0)) {
            for (int i = 0; i < 6; ++i) out[i] = NAN;
            return;
        }
        L[ny * j + j] = sqrt(v);
        for (int i = j + 1; i < ny; ++i) {
            double x = S[ny * i + j];
            for (int a = 0; a < j; ++a) x -= L[ny * i + a] * L[ny * j + a];
            L[ny * i + j] = x / L[ny * j + j];
        }
    }
    for (int i = 0; i < ny; ++i) {
        double v = eps[i];
        for (int a = 0; a < i; ++a) v -= L[ny * i + a] * w[a];
        w[i] = v / L[ny * i + i];
    }
    for (int i = 0; i < 3; ++i) {
        out[i] = NAN;
        out[3 + i] = p->d->use_mag ? NAN : 0.0;
    }
    for (int i = 0; i < ny; ++i) out[rows[i]] = w[i];
}




/* The forward pass without tape; outputs are filled when out is not NULL. */
static ALWAYS_INLINE double cost_loop(const pass_t *p, const mc_mekf_outputs_t *out, int masked)
{
    const mc_mekf_data_t *data = p->d;
    double q[4], P[9];
    load_prior(data, q, P);
    double cost = 0.0;
    logdet_acc_t ld = {1.0, 0.0};
    step_t s;
    const int want = out && (out->q_filt || out->innov || out->normalised);
    for (size_t k = 0; k < data->n; ++k) {
        int ha, hm;
        sample_has(data, k, masked, &ha, &hm);
        if (!step_forward(p, k, ha, hm, q, P, &s)) return NAN;
        cost += s.cost;
        logdet_add(&ld, s.det);
        memcpy(q, s.q_out, sizeof q);
        renormalise_quat(q);
        memcpy(P, s.Pu, sizeof P);
        if (want) {
            if (out->q_filt) memcpy(out->q_filt + 4 * k, q, sizeof q);
            if (out->innov) {
                for (int i = 0; i < 3; ++i) {
                    out->innov[6 * k + i] = s.ea[i];
                    out->innov[6 * k + 3 + i] = s.em[i];
                }
            }
            if (out->normalised) whiten(p, &s, k, ha, hm, out->normalised + 6 * k);
        }
    }
    return cost + 0.5 * logdet_total(&ld);
}

static HOT_PASS double cost_pass_unmasked(const pass_t *p, const mc_mekf_outputs_t *out)
{
    return cost_loop(p, out, 0);
}

static HOT_PASS double cost_pass_masked(const pass_t *p, const mc_mekf_outputs_t *out)
{
    return cost_loop(p, out, 1);
}


double mc_mekf_cost(const mc_mekf_model_t *model, const mc_mekf_data_t *data,
                    const mc_mekf_outputs_t *out)
{
    if (!valid_arguments(model, data)) return NAN;
    pass_t p;
    if (!make_pass(model, data, &p)) return NAN;
    return any_mask(data) ? cost_pass_masked(&p, out) : cost_pass_unmasked(&p, out);
}

/* Forward pass writing the tape. Returns the cost, or NaN on failure. */
static ALWAYS_INLINE double forward_tape_loop(const pass_t *p, double *tape, int masked)
{
    const mc_mekf_data_t *data = p->d;
    double q[4], P[9];
    load_prior(data, q, P);
    double cost = 0.0;
    logdet_acc_t ld = {1.0, 0.0};
    step_t s;
    const size_t n = data->n;
    for (size_t k = 0; k < n; ++k) {
        double *rec = tape + MC_MEKF_TAPE_DOUBLES * k;
        int ha, hm;
        sample_has(data, k, masked, &ha, &hm);
        if (!step_forward(p, k, ha, hm, q, P, &s)) return NAN;
        /* The record's fields the reverse pass reads for this sample: q1 always, the update's
         * with any measurement, the magnetometer's with it. */
        memcpy(rec + TAPE_Q1, s.q1, 4 * sizeof(double));
        if (ha || hm) {
            sym_pack(s.Y, rec + TAPE_Y);
            sym_pack(s.Pu, rec + TAPE_PU);
            memcpy(rec + TAPE_U, s.u, 3 * sizeof(double));
            memcpy(rec + TAPE_ETA, s.eta, 3 * sizeof(double));
        }
        if (hm) {
            sym_pack(s.Kn, rec + TAPE_KN);
            memcpy(rec + TAPE_EM, s.em, 3 * sizeof(double));
            memcpy(rec + TAPE_ZM, s.zm, 3 * sizeof(double));
            memcpy(rec + TAPE_XM, s.xm, 3 * sizeof(double));
            memcpy(rec + TAPE_VM, s.vm, 3 * sizeof(double));
        }
        cost += s.cost;
        logdet_add(&ld, s.det);
        memcpy(q, s.q_out, sizeof q);
        renormalise_quat(q);
        memcpy(P, s.Pu, sizeof P);
    }
    return cost + 0.5 * logdet_total(&ld);
}

static HOT_PASS double forward_tape_pass_unmasked(const pass_t *p, double *tape)
{
    return forward_tape_loop(p, tape, 0);
}

static HOT_PASS double forward_tape_pass_masked(const pass_t *p, double *tape)
{
    return forward_tape_loop(p, tape, 1);
}

/* Reverse pass over the tape; the final state does not enter the cost. */
static ALWAYS_INLINE void reverse_loop(const pass_t *p, const double *tape, grad_acc_t *acc,
                                       int masked)
{
    const mc_mekf_data_t *data = p->d;
    double tq[3] = {0, 0, 0}, P_bar[9] = {0};
    for (size_t kk = data->n; kk-- > 0;) {
        double tq_in[3], Pb_in[9];
        int ha, hm;
        sample_has(data, kk, masked, &ha, &hm);
        step_reverse(p, kk, ha, hm, tape + MC_MEKF_TAPE_DOUBLES * kk, tq, P_bar, tq_in, Pb_in,
                     acc);
        memcpy(tq, tq_in, sizeof tq);
        memcpy(P_bar, Pb_in, sizeof P_bar);
    }
}

static HOT_PASS void reverse_pass_unmasked(const pass_t *p, const double *tape, grad_acc_t *acc)
{
    reverse_loop(p, tape, acc, 0);
}

static HOT_PASS void reverse_pass_masked(const pass_t *p, const double *tape, grad_acc_t *acc)
{
    reverse_loop(p, tape, acc, 1);
}

double mc_mekf_cost_grad(const mc_mekf_model_t *model, const mc_mekf_data_t *data, double *tape,
                         size_t tape_len, mc_mekf_model_t *grad)
{
    /* A zero gradient on every failure: callers that test only the cost never see garbage. */
    if (grad) memset(grad, 0, sizeof *grad);
    if (!grad || !valid_arguments(model, data) || !tape ||
        tape_len / MC_MEKF_TAPE_DOUBLES < data->n) /* tape_len < TAPE · n, without overflow */
        return NAN;
    pass_t p;
    if (!make_pass(model, data, &p)) return NAN;
    const int masked = any_mask(data);
    const double cost =
        masked ? forward_tape_pass_masked(&p, tape) : forward_tape_pass_unmasked(&p, tape);
    /* NaN: a covariance broke down mid-pass and the tape is incomplete. ±inf: the adjoints
     * would be inf or NaN. Either way the gradient stays zero. */
    if (!isfinite(cost)) return cost;
    grad_acc_t acc;
    memset(&acc, 0, sizeof acc);
    if (masked)
        reverse_pass_masked(&p, tape, &acc);
    else
        reverse_pass_unmasked(&p, tape, &acc);

    /* The reverse pass accumulated symmetric adjoints on their upper triangle only. */
    sym_fill(acc.g.Sw);
    sym_fill(acc.g.Sa);
    sym_fill(acc.Ai0_bar);
    sym_fill(acc.Mi_bar);
    sym_fill(acc.K_bar);
    *grad = acc.g;
    double t[9];
    /* Samples with the accelerometer and c_t = 0: Ai = Σa⁻¹ and n0 · ½ log det Σa */
    sym_sandwich(p.Ai0, acc.Ai0_bar, t);
    for (int i = 0; i < 9; ++i) grad->Sa[i] += 0.5 * (double)acc.n0 * p.Ai0[i] - t[i];
    if (data->use_mag) {
        /* K = Dᵀ Mi D: D̄ += 2 Mi D K̄, M̄i += D K̄ Dᵀ */
        double MiD[9], DKb[9];
        mat_mul(p.Mi, model->D, MiD);
        mat_mul(MiD, acc.K_bar, t);
        for (int i = 0; i < 9; ++i) grad->D[i] += 2.0 * t[i];
        sym_sandwich(model->D, acc.K_bar, DKb);
        for (int i = 0; i < 9; ++i) acc.Mi_bar[i] += DKb[i];
        /* Mi = Σm⁻¹ and nm · ½ log det Σm (nm: samples with the magnetometer) */
        size_t nm = data->n;
        if (data->has_mag) {
            nm = 0;
            for (size_t k = 0; k < data->n; ++k) nm += data->has_mag[k] != 0;
        }
        sym_sandwich(p.Mi, acc.Mi_bar, t);
        for (int i = 0; i < 9; ++i) grad->Sm[i] += 0.5 * (double)nm * p.Mi[i] - t[i];
    }
    return cost;
}
