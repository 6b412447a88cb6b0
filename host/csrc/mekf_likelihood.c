/*
 * Multiplicative EKF likelihood and its reverse-mode gradient. See mekf_likelihood.h and
 * magcal/calib/ekf.py for the model.
 *
 * Numerical choices:
 * - Information form of the update. With R_t = blockdiag(Sa_t, Sm) and the 3-dimensional
 *   error state, S_t = H P Hᵀ + R_t is 6×6 but only rank-3 away from R_t, so
 *     εᵀS⁻¹ε   = εᵀR⁻¹ε − uᵀ Λ⁻¹ u,        u = HᵀR⁻¹ε,  Λ = P⁻¹ + HᵀR⁻¹H,
 *     log det S = log det R + log det P + log det Λ,
 *   and the posterior is P⁺ = Λ⁻¹, η = Λ⁻¹u (matrix inversion and determinant lemmas).
 *   Every inverse is then 3×3 and symmetric positive definite.
 * - The quaternion is renormalised after each update. Parameter perturbations move it only
 *   along the unit sphere, where renormalisation is the identity to first order, so the
 *   reverse pass omits it and stays exact.
 * - The reverse pass recomputes each step's intermediates from the taped attitude and
 *   covariance (10 doubles per sample) instead of storing them: memory is O(n · state).
 */
#include "mekf_likelihood.h"

#include <math.h>
#include <string.h>

/* ---------------------------------------------------------------- 3×3 helpers */

static void mat_mul(const double *a, const double *b, double *c) /* c = a b */
{
    double r[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            r[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
    memcpy(c, r, sizeof r);
}

static void mat_mul_tn(const double *a, const double *b, double *c) /* c = aᵀ b */
{
    double r[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            r[3 * i + j] = a[i] * b[j] + a[3 + i] * b[3 + j] + a[6 + i] * b[6 + j];
    memcpy(c, r, sizeof r);
}

static void mat_mul_nt(const double *a, const double *b, double *c) /* c = a bᵀ */
{
    double r[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            r[3 * i + j] =
                a[3 * i] * b[3 * j] + a[3 * i + 1] * b[3 * j + 1] + a[3 * i + 2] * b[3 * j + 2];
    memcpy(c, r, sizeof r);
}

static void mat_vec(const double *a, const double *x, double *y) /* y = a x */
{
    double r[3];
    for (int i = 0; i < 3; ++i) r[i] = a[3 * i] * x[0] + a[3 * i + 1] * x[1] + a[3 * i + 2] * x[2];
    memcpy(y, r, sizeof r);
}

static void mat_tvec(const double *a, const double *x, double *y) /* y = aᵀ x */
{
    double r[3];
    for (int i = 0; i < 3; ++i) r[i] = a[i] * x[0] + a[3 + i] * x[1] + a[6 + i] * x[2];
    memcpy(y, r, sizeof r);
}

static void mat_add_outer(double *a, double s, const double *x, const double *y) /* a += s x yᵀ */
{
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) a[3 * i + j] += s * x[i] * y[j];
}

static void mat_axpy(double *a, double s, const double *b) /* a += s b */
{
    for (int i = 0; i < 9; ++i) a[i] += s * b[i];
}

static double dot3(const double *a, const double *b)
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static void skew3(const double *v, double *s)
{
    s[0] = 0.0;   s[1] = -v[2]; s[2] = v[1];
    s[3] = v[2];  s[4] = 0.0;   s[5] = -v[0];
    s[6] = -v[1]; s[7] = v[0];  s[8] = 0.0;
}

/* Adjoint of v ↦ [v×]: accumulate into v̄ from S̄. */
static void skew3_adjoint(const double *s_bar, double *v_bar)
{
    v_bar[0] += s_bar[7] - s_bar[5];
    v_bar[1] += s_bar[2] - s_bar[6];
    v_bar[2] += s_bar[3] - s_bar[1];
}

/* Inverse of a symmetric positive definite 3×3 matrix and its log-determinant. Returns 0
 * when the matrix is not positive definite (a leading minor ≤ 0). */
static int spd_inverse(const double *a, double *inv, double *logdet)
{
    const double m1 = a[0];
    const double m2 = a[0] * a[4] - a[1] * a[3];
    const double c00 = a[4] * a[8] - a[5] * a[7];
    const double c01 = a[2] * a[7] - a[1] * a[8];
    const double c02 = a[1] * a[5] - a[2] * a[4];
    const double det = a[0] * c00 + a[3] * c01 + a[6] * c02;
    if (!(m1 > 0.0) || !(m2 > 0.0) || !(det > 0.0)) return 0;
    const double r = 1.0 / det;
    inv[0] = c00 * r;
    inv[1] = c01 * r;
    inv[2] = c02 * r;
    inv[3] = (a[5] * a[6] - a[3] * a[8]) * r;
    inv[4] = (a[0] * a[8] - a[2] * a[6]) * r;
    inv[5] = (a[2] * a[3] - a[0] * a[5]) * r;
    inv[6] = (a[3] * a[7] - a[4] * a[6]) * r;
    inv[7] = (a[1] * a[6] - a[0] * a[7]) * r;
    inv[8] = (a[0] * a[4] - a[1] * a[3]) * r;
    /* Symmetrise: the cofactor formula is symmetric only up to rounding. */
    inv[1] = inv[3] = 0.5 * (inv[1] + inv[3]);
    inv[2] = inv[6] = 0.5 * (inv[2] + inv[6]);
    inv[5] = inv[7] = 0.5 * (inv[5] + inv[7]);
    *logdet = log(det);
    return 1;
}

/* Adjoint of B = A⁻¹ (A symmetric): Ā += −B B̄ B. */
static void inverse_adjoint(const double *B, const double *B_bar, double *A_bar)
{
    double t[9];
    mat_mul(B, B_bar, t);
    mat_mul(t, B, t);
    mat_axpy(A_bar, -1.0, t);
}

/* ---------------------------------------------------------------- quaternions */

static void quat_mul(const double *p, const double *q, double *r)
{
    double t[4];
    t[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3];
    t[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2];
    t[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1];
    t[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0];
    memcpy(r, t, sizeof t);
}

static void quat_conj(const double *q, double *c)
{
    c[0] = q[0];
    c[1] = -q[1];
    c[2] = -q[2];
    c[3] = -q[3];
}

/* Adjoint of r = p ⊙ q: p̄ += r̄ ⊙ q*, q̄ += p* ⊙ r̄ (the transpose of left/right
 * multiplication by a quaternion is multiplication by its conjugate). */
static void quat_mul_adjoint(const double *p, const double *q, const double *r_bar, double *p_bar,
                             double *q_bar)
{
    double c[4], t[4];
    if (p_bar) {
        quat_conj(q, c);
        quat_mul(r_bar, c, t);
        for (int i = 0; i < 4; ++i) p_bar[i] += t[i];
    }
    if (q_bar) {
        quat_conj(p, c);
        quat_mul(c, r_bar, t);
        for (int i = 0; i < 4; ++i) q_bar[i] += t[i];
    }
}

/* exp_q(v) = (cos|v|, sin|v| v/|v|), with series near 0. */
static void quat_exp(const double *v, double *q)
{
    const double a2 = dot3(v, v);
    const double a = sqrt(a2);
    /* Series below 1e-2: the direct formulas lose digits to cancellation there. */
    const double s = a < 1e-2 ? 1.0 - a2 / 6.0 + a2 * a2 / 120.0 - a2 * a2 * a2 / 5040.0 : sin(a) / a;
    q[0] = cos(a);
    q[1] = s * v[0];
    q[2] = s * v[1];
    q[3] = s * v[2];
}

/* Adjoint of q = exp_q(v): v̄ += Jᵀ q̄. */
static void quat_exp_adjoint(const double *v, const double *q_bar, double *v_bar)
{
    const double a2 = dot3(v, v);
    const double a = sqrt(a2);
    double s, k; /* s = sin a / a, k = (a cos a − sin a) / a³ = (ds/da) / a */
    if (a < 1e-2) {
        s = 1.0 - a2 / 6.0 + a2 * a2 / 120.0 - a2 * a2 * a2 / 5040.0;
        k = -1.0 / 3.0 + a2 / 30.0 - a2 * a2 / 840.0;
    } else {
        s = sin(a) / a;
        k = (a * cos(a) - sin(a)) / (a2 * a);
    }
    const double vq = dot3(v, q_bar + 1);
    for (int i = 0; i < 3; ++i) v_bar[i] += -s * v[i] * q_bar[0] + s * q_bar[1 + i] + k * v[i] * vq;
}

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

/* Adjoint of R = quat_to_mat(q): q̄ += Σ R̄ ⊙ ∂R/∂q. */
static void quat_to_mat_adjoint(const double *q, const double *Rb, double *q_bar)
{
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    q_bar[0] += 2 * (-z * Rb[1] + y * Rb[2] + z * Rb[3] - x * Rb[5] - y * Rb[6] + x * Rb[7]);
    q_bar[1] += 2 * (y * Rb[1] + z * Rb[2] + y * Rb[3] - 2 * x * Rb[4] - w * Rb[5] + z * Rb[6] +
                     w * Rb[7] - 2 * x * Rb[8]);
    q_bar[2] += 2 * (-2 * y * Rb[0] + x * Rb[1] + w * Rb[2] + x * Rb[3] + z * Rb[5] - w * Rb[6] +
                     z * Rb[7] - 2 * y * Rb[8]);
    q_bar[3] += 2 * (-2 * z * Rb[0] - w * Rb[1] + x * Rb[2] + w * Rb[3] - 2 * z * Rb[4] + y * Rb[5] +
                     x * Rb[6] + y * Rb[7]);
}

/* ---------------------------------------------------------------- one filter step */

/* Constants of a pass that do not change from sample to sample. */
typedef struct {
    double gn[3];  /* gravity in n            */
    double Gx[9];  /* [g_n×]                  */
    double Mx[9];  /* [m_n×]                  */
    double Mi[9];  /* Sm⁻¹                    */
    double ld_Sm;  /* log det Sm              */
} pass_consts_t;

/* Every intermediate of one step, kept so the reverse pass can use them. */
typedef struct {
    int predicted;
    double phi[3], Delta[4], q1[4], R[9], Pp[9];
    double gb[3], mb[3], Ha[9], Hm[9], ea[3], em[3];
    double Sa_t[9], Ai[9], ld_Sa;
    double za[3], zm[3]; /* Ai εa, Mi εm */
    double J[9], u[3], e2;
    double Y[9], ld_Pp, Lam[9], Pu[9], ld_Lam, eta[3], half_eta[3], E[4];
    double q_out[4], cost;
} step_t;

static int step_forward(const mc_mekf_model_t *m, const mc_mekf_data_t *d, const pass_consts_t *c,
                        size_t k, const double *q, const double *P, step_t *s)
{
    const int use_mag = d->use_mag;
    s->predicted = k > 0;
    if (s->predicted) {
        const double dt = d->dt[k];
        const double *w = d->gyr + 3 * (k - 1);
        for (int i = 0; i < 3; ++i) s->phi[i] = 0.5 * dt * (w[i] - m->bias[i]);
        quat_exp(s->phi, s->Delta);
        quat_mul(q, s->Delta, s->q1);
        quat_to_mat(s->q1, s->R);
        double t[9];
        mat_mul(s->R, m->Sw, t);
        mat_mul_nt(t, s->R, t);
        for (int i = 0; i < 9; ++i) s->Pp[i] = P[i] + dt * dt * t[i];
    } else {
        memcpy(s->q1, q, sizeof s->q1);
        quat_to_mat(s->q1, s->R);
        memcpy(s->Pp, P, sizeof s->Pp);
    }
    /* Predicted measurements and Jacobians (nav-frame error: R_bn = R̃_bn (I − [η×])). */
    mat_tvec(s->R, c->gn, s->gb);
    mat_tvec(s->R, m->m, s->mb);
    mat_mul_tn(s->R, c->Gx, s->Ha);
    for (int i = 0; i < 9; ++i) s->Ha[i] = -s->Ha[i];
    {
        double t[9];
        mat_mul_tn(s->R, c->Mx, t);
        mat_mul(m->D, t, s->Hm);
    }
    const double *ya = d->acc + 3 * k;
    const double *ym = d->mag + 3 * k;
    double ym_pred[3];
    mat_vec(m->D, s->mb, ym_pred);
    for (int i = 0; i < 3; ++i) {
        s->ea[i] = ya[i] + s->gb[i]; /* ŷ_a = −R_bn g_n */
        s->em[i] = ym[i] - ym_pred[i] - m->o[i];
    }
    memcpy(s->Sa_t, m->Sa, sizeof s->Sa_t);
    const double cx = d->acc_extra_var ? d->acc_extra_var[k] : 0.0;
    s->Sa_t[0] += cx;
    s->Sa_t[4] += cx;
    s->Sa_t[8] += cx;
    if (!spd_inverse(s->Sa_t, s->Ai, &s->ld_Sa)) return 0;

    /* Information-form update. */
    double t[9];
    mat_vec(s->Ai, s->ea, s->za);
    mat_tvec(s->Ha, s->za, s->u);
    mat_mul(s->Ai, s->Ha, t);
    mat_mul_tn(s->Ha, t, s->J);
    s->e2 = dot3(s->ea, s->za);
    if (use_mag) {
        double um[3];
        mat_vec(c->Mi, s->em, s->zm);
        mat_tvec(s->Hm, s->zm, um);
        for (int i = 0; i < 3; ++i) s->u[i] += um[i];
        mat_mul(c->Mi, s->Hm, t);
        double Jm[9];
        mat_mul_tn(s->Hm, t, Jm);
        mat_axpy(s->J, 1.0, Jm);
        s->e2 += dot3(s->em, s->zm);
    }
    if (!spd_inverse(s->Pp, s->Y, &s->ld_Pp)) return 0;
    for (int i = 0; i < 9; ++i) s->Lam[i] = s->Y[i] + s->J[i];
    if (!spd_inverse(s->Lam, s->Pu, &s->ld_Lam)) return 0;
    mat_vec(s->Pu, s->u, s->eta);
    double ld_S = s->ld_Sa + s->ld_Pp + s->ld_Lam + (use_mag ? c->ld_Sm : 0.0);
    s->cost = 0.5 * (s->e2 - dot3(s->u, s->eta) + ld_S);

    for (int i = 0; i < 3; ++i) s->half_eta[i] = 0.5 * s->eta[i];
    quat_exp(s->half_eta, s->E);
    quat_mul(s->E, s->q1, s->q_out);
    return 1;
}

/* Reverse of step_forward. Inputs: q̄_out (4) and P̄_out (= P̄u) accumulated from later steps.
 * Outputs: q̄ and P̄ of the step's inputs; model adjoints are accumulated into g, the adjoint
 * of Sm⁻¹ into Mi_bar (converted once at the end), and dV/dc_k is returned. */
static double step_reverse(const mc_mekf_model_t *m, const mc_mekf_data_t *d, const pass_consts_t *c,
                           size_t k, const step_t *s, const double *q, const double *q_out_bar,
                           const double *P_out_bar, double *q_bar, double *P_bar,
                           mc_mekf_model_t *g, double *Mi_bar)
{
    const int use_mag = d->use_mag;
    double q1_bar[4] = {0, 0, 0, 0}, E_bar[4] = {0, 0, 0, 0};
    double R_bar[9] = {0}, Pu_bar[9], Lam_bar[9] = {0}, Pp_bar[9] = {0}, Ai_bar[9] = {0};
    double Ha_bar[9] = {0}, Hm_bar[9] = {0};
    double eta_bar[3] = {0, 0, 0}, u_bar[3] = {0, 0, 0}, ea_bar[3] = {0, 0, 0},
           em_bar[3] = {0, 0, 0};
    double t[9];

    memcpy(Pu_bar, P_out_bar, sizeof Pu_bar);

    /* q_out = E ⊙ q1, E = exp_q(η/2) */
    quat_mul_adjoint(s->E, s->q1, q_out_bar, E_bar, q1_bar);
    {
        double he_bar[3] = {0, 0, 0};
        quat_exp_adjoint(s->half_eta, E_bar, he_bar);
        for (int i = 0; i < 3; ++i) eta_bar[i] = 0.5 * he_bar[i];
    }
    /* cost = ½(e2 − uᵀη + ld_Sa + ld_Pp + ld_Λ [+ ld_Sm]) */
    const double e2_bar = 0.5;
    for (int i = 0; i < 3; ++i) {
        eta_bar[i] += -0.5 * s->u[i];
        u_bar[i] += -0.5 * s->eta[i];
    }
    /* η = Pu u */
    mat_add_outer(Pu_bar, 1.0, eta_bar, s->u);
    {
        double v[3];
        mat_vec(s->Pu, eta_bar, v); /* Pu symmetric */
        for (int i = 0; i < 3; ++i) u_bar[i] += v[i];
    }
    /* Pu = Λ⁻¹, ld_Λ: Λ̄ += −Pu P̄u Pu + ½ Pu */
    inverse_adjoint(s->Pu, Pu_bar, Lam_bar);
    mat_axpy(Lam_bar, 0.5, s->Pu);
    /* Λ = Y + J; Y = Pp⁻¹; ld_Pp */
    inverse_adjoint(s->Y, Lam_bar, Pp_bar);
    mat_axpy(Pp_bar, 0.5, s->Y);
    const double *J_bar = Lam_bar;
    double Js[9]; /* J̄ + J̄ᵀ */
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) Js[3 * i + j] = J_bar[3 * i + j] + J_bar[3 * j + i];

    /* Accelerometer block: J_a = Haᵀ Ai Ha, u_a = Haᵀ za, za = Ai εa, e2_a = εaᵀ za. */
    {
        double AH[9];
        mat_mul(s->Ai, s->Ha, AH);
        mat_mul(AH, Js, t);
        mat_axpy(Ha_bar, 1.0, t);          /* H̄a += Ai Ha (J̄ + J̄ᵀ) */
        mat_mul(s->Ha, J_bar, t);
        mat_mul_nt(t, s->Ha, t);
        mat_axpy(Ai_bar, 1.0, t);          /* Āi += Ha J̄ Haᵀ */
        mat_add_outer(Ha_bar, 1.0, s->za, u_bar); /* H̄a += za ūᵀ */
        double za_bar[3];
        mat_vec(s->Ha, u_bar, za_bar);
        for (int i = 0; i < 3; ++i) za_bar[i] += e2_bar * s->ea[i];
        /* za = Ai εa; e2 also reads εa directly */
        mat_add_outer(Ai_bar, 1.0, za_bar, s->ea);
        double v[3];
        mat_vec(s->Ai, za_bar, v);
        for (int i = 0; i < 3; ++i) ea_bar[i] += v[i] + e2_bar * s->za[i];
    }
    if (use_mag) {
        double MH[9];
        mat_mul(c->Mi, s->Hm, MH);
        mat_mul(MH, Js, t);
        mat_axpy(Hm_bar, 1.0, t);
        mat_mul(s->Hm, J_bar, t);
        mat_mul_nt(t, s->Hm, t);
        mat_axpy(Mi_bar, 1.0, t);
        mat_add_outer(Hm_bar, 1.0, s->zm, u_bar);
        double zm_bar[3];
        mat_vec(s->Hm, u_bar, zm_bar);
        for (int i = 0; i < 3; ++i) zm_bar[i] += e2_bar * s->em[i];
        mat_add_outer(Mi_bar, 1.0, zm_bar, s->em);
        double v[3];
        mat_vec(c->Mi, zm_bar, v);
        for (int i = 0; i < 3; ++i) em_bar[i] += v[i] + e2_bar * s->zm[i];
    }
    /* Ai = Sa_t⁻¹ and ½ ld_Sa: Σ̄a += −Ai Āi Ai + ½ Ai */
    double Sa_bar[9] = {0};
    inverse_adjoint(s->Ai, Ai_bar, Sa_bar);
    mat_axpy(Sa_bar, 0.5, s->Ai);
    mat_axpy(g->Sa, 1.0, Sa_bar);
    const double c_bar = Sa_bar[0] + Sa_bar[4] + Sa_bar[8];

    /* εa = ya + gb, gb = Rᵀ g_n: R̄ += g_n ḡbᵀ */
    mat_add_outer(R_bar, 1.0, c->gn, ea_bar);
    if (use_mag) {
        /* εm = ym − D mb − o, mb = Rᵀ m */
        double mb_bar[3];
        for (int i = 0; i < 3; ++i) g->o[i] -= em_bar[i];
        mat_add_outer(g->D, -1.0, em_bar, s->mb);
        mat_tvec(m->D, em_bar, mb_bar);
        for (int i = 0; i < 3; ++i) mb_bar[i] = -mb_bar[i];
        mat_add_outer(R_bar, 1.0, m->m, mb_bar);
        double v[3];
        mat_vec(s->R, mb_bar, v);
        for (int i = 0; i < 3; ++i) g->m[i] += v[i];
        /* Hm = D Rᵀ [m×] */
        double RtMx[9], Mx_bar[9], DRt[9];
        mat_mul_tn(s->R, c->Mx, RtMx);
        mat_mul_nt(Hm_bar, RtMx, t);
        mat_axpy(g->D, 1.0, t);            /* D̄ += H̄m (Rᵀ Mx)ᵀ */
        mat_mul_nt(m->D, s->R, DRt);       /* D Rᵀ */
        mat_mul_nt(c->Mx, Hm_bar, t);      /* Mx H̄mᵀ */
        mat_mul(t, m->D, t);
        mat_axpy(R_bar, 1.0, t);           /* R̄ += Mx H̄mᵀ D */
        mat_mul_tn(DRt, Hm_bar, Mx_bar);   /* [m×]‾ = (D Rᵀ)ᵀ H̄m */
        skew3_adjoint(Mx_bar, g->m);
    }
    /* Ha = −Rᵀ [g_n×]: R̄ += −G H̄aᵀ */
    mat_mul_nt(c->Gx, Ha_bar, t);
    mat_axpy(R_bar, -1.0, t);

    /* Prediction */
    for (int i = 0; i < 9; ++i) P_bar[i] = Pp_bar[i];
    if (s->predicted) {
        const double dt = d->dt[k];
        /* Pp = P + dt² R Σω Rᵀ */
        double RS[9], Rt_Q_R[9];
        mat_mul(s->R, m->Sw, RS);
        mat_mul_tn(s->R, Pp_bar, t);
        mat_mul(t, s->R, Rt_Q_R);
        mat_axpy(g->Sw, dt * dt, Rt_Q_R);  /* Σ̄ω += dt² Rᵀ Q̄ R */
        double RSt[9];
        mat_mul_nt(s->R, m->Sw, RSt);      /* R Σωᵀ */
        mat_mul(Pp_bar, RSt, t);
        mat_axpy(R_bar, dt * dt, t);       /* R̄ += dt² Q̄ R Σωᵀ */
        mat_mul_tn(Pp_bar, RS, t);
        mat_axpy(R_bar, dt * dt, t);       /* R̄ += dt² Q̄ᵀ R Σω */
    }
    quat_to_mat_adjoint(s->q1, R_bar, q1_bar);
    if (s->predicted) {
        double Delta_bar[4] = {0, 0, 0, 0};
        for (int i = 0; i < 4; ++i) q_bar[i] = 0.0;
        quat_mul_adjoint(q, s->Delta, q1_bar, q_bar, Delta_bar);
        double phi_bar[3] = {0, 0, 0};
        quat_exp_adjoint(s->phi, Delta_bar, phi_bar);
        const double dt = d->dt[k];
        for (int i = 0; i < 3; ++i) g->bias[i] -= 0.5 * dt * phi_bar[i];
    } else {
        memcpy(q_bar, q1_bar, 4 * sizeof(double));
    }
    return c_bar;
}

/* ---------------------------------------------------------------- passes */

static int make_consts(const mc_mekf_model_t *m, const mc_mekf_data_t *d, pass_consts_t *c)
{
    c->gn[0] = 0.0;
    c->gn[1] = 0.0;
    c->gn[2] = -d->g;
    skew3(c->gn, c->Gx);
    skew3(m->m, c->Mx);
    if (d->use_mag) return spd_inverse(m->Sm, c->Mi, &c->ld_Sm);
    memset(c->Mi, 0, sizeof c->Mi);
    c->ld_Sm = 0.0;
    return 1;
}

static void normalise_quat(double *q)
{
    const double r = 1.0 / sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    for (int i = 0; i < 4; ++i) q[i] *= r;
}

/* Cholesky-whitened innovation L⁻¹ε with S = H Pp Hᵀ + R = L Lᵀ (6×6 or 3×3). */
static void whiten(const mc_mekf_model_t *m, const step_t *s, int ny, double *out)
{
    double H[18], S[36], L[36], eps[6], w[6];
    for (int i = 0; i < 9; ++i) {
        H[i] = s->Ha[i];
        H[9 + i] = s->Hm[i];
    }
    for (int i = 0; i < 3; ++i) {
        eps[i] = s->ea[i];
        eps[3 + i] = s->em[i];
    }
    for (int i = 0; i < ny; ++i)
        for (int j = 0; j < ny; ++j) {
            double v = 0.0;
            for (int a = 0; a < 3; ++a)
                for (int b = 0; b < 3; ++b) v += H[3 * i + a] * s->Pp[3 * a + b] * H[3 * j + b];
            if (i < 3 && j < 3) v += s->Sa_t[3 * i + j];
            if (i >= 3 && j >= 3) v += m->Sm[3 * (i - 3) + (j - 3)];
            S[ny * i + j] = v;
        }
    for (int j = 0; j < ny; ++j) {
        double v = S[ny * j + j];
        for (int a = 0; a < j; ++a) v -= L[ny * j + a] * L[ny * j + a];
        L[ny * j + j] = sqrt(v > 0.0 ? v : 0.0);
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
    for (int i = 0; i < 6; ++i) out[i] = i < ny ? w[i] : 0.0;
}

double mc_mekf_cost(const mc_mekf_model_t *model, const mc_mekf_data_t *data,
                    const mc_mekf_outputs_t *out)
{
    if (!model || !data || data->n == 0) return NAN;
    pass_consts_t c;
    if (!make_consts(model, data, &c)) return NAN;
    double q[4], P[9];
    memcpy(q, data->q0, sizeof q);
    memcpy(P, data->P0, sizeof P);
    double cost = 0.0;
    step_t s;
    for (size_t k = 0; k < data->n; ++k) {
        if (!step_forward(model, data, &c, k, q, P, &s)) return NAN;
        cost += s.cost;
        memcpy(q, s.q_out, sizeof q);
        normalise_quat(q);
        memcpy(P, s.Pu, sizeof P);
        if (out) {
            if (out->q_filt) memcpy(out->q_filt + 4 * k, q, sizeof q);
            if (out->innov) {
                for (int i = 0; i < 3; ++i) {
                    out->innov[6 * k + i] = s.ea[i];
                    out->innov[6 * k + 3 + i] = data->use_mag ? s.em[i] : 0.0;
                }
            }
            if (out->normalised) whiten(model, &s, data->use_mag ? 6 : 3, out->normalised + 6 * k);
        }
    }
    return cost;
}

double mc_mekf_cost_grad(const mc_mekf_model_t *model, const mc_mekf_data_t *data, double *tape,
                         mc_mekf_model_t *grad, double *grad_acc_scale)
{
    if (!model || !data || !tape || !grad || data->n == 0) return NAN;
    pass_consts_t c;
    if (!make_consts(model, data, &c)) return NAN;
    memset(grad, 0, sizeof *grad);
    double q[4], P[9];
    memcpy(q, data->q0, sizeof q);
    memcpy(P, data->P0, sizeof P);
    double cost = 0.0;
    step_t s;
    const size_t n = data->n;
    for (size_t k = 0; k < n; ++k) {
        double *rec = tape + 10 * k;
        memcpy(rec, q, 4 * sizeof(double));
        rec[4] = P[0]; rec[5] = P[1]; rec[6] = P[2];
        rec[7] = P[4]; rec[8] = P[5]; rec[9] = P[8];
        if (!step_forward(model, data, &c, k, q, P, &s)) return NAN;
        cost += s.cost;
        memcpy(q, s.q_out, sizeof q);
        normalise_quat(q);
        memcpy(P, s.Pu, sizeof P);
    }
    /* The final state does not enter the cost. */
    double q_bar[4] = {0, 0, 0, 0}, P_bar[9] = {0};
    double Mi_bar[9] = {0};
    double acc_scale_bar = 0.0;
    for (size_t kk = n; kk-- > 0;) {
        const double *rec = tape + 10 * kk;
        double qk[4], Pk[9];
        memcpy(qk, rec, 4 * sizeof(double));
        Pk[0] = rec[4]; Pk[1] = Pk[3] = rec[5]; Pk[2] = Pk[6] = rec[6];
        Pk[4] = rec[7]; Pk[5] = Pk[7] = rec[8]; Pk[8] = rec[9];
        step_forward(model, data, &c, kk, qk, Pk, &s);
        double qb_in[4], Pb_in[9];
        const double c_bar = step_reverse(model, data, &c, kk, &s, qk, q_bar, P_bar, qb_in, Pb_in,
                                          grad, Mi_bar);
        if (data->acc_extra_var) acc_scale_bar += c_bar * data->acc_extra_var[kk];
        memcpy(q_bar, qb_in, sizeof q_bar);
        memcpy(P_bar, Pb_in, sizeof P_bar);
    }
    if (data->use_mag) {
        /* Mi = Sm⁻¹ and n·½ log det Sm */
        inverse_adjoint(c.Mi, Mi_bar, grad->Sm);
        mat_axpy(grad->Sm, 0.5 * (double)n, c.Mi);
    }
    if (grad_acc_scale) *grad_acc_scale = acc_scale_bar;
    return cost;
}
