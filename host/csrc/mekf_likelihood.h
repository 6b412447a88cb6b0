/* SPDX-License-Identifier: Apache-2.0 */
/*
 * Negative log-likelihood of the multiplicative EKF (Kok & Schön 2016, eq. 6) and its exact
 * gradient by a reverse (adjoint) pass. Plain C99, no Python: the CPython glue is
 * _mekf_module.c. The model and conventions are documented in
 * host/src/magcal/calib/likelihood/mekf.py.
 */
#ifndef MAGCAL_MEKF_LIKELIHOOD_H
#define MAGCAL_MEKF_LIKELIHOOD_H

#include <stddef.h>

/* Model quantities; matrices row-major. The gradient has the same layout.
 *
 * The covariances Sw, Sa and Sm are symmetrised, (S + Sᵀ)/2, before use, so only their
 * symmetric part matters; the gradient w.r.t. them is the gradient w.r.t. their raw
 * entries, which is then symmetric. */
typedef struct {
    double D[9];      /* magnetometer distortion                    */
    double o[3];      /* magnetometer offset                        */
    double m[3];      /* unit field in n                            */
    double bias[3];   /* gyroscope bias, rad/s                      */
    double Sw[9];     /* gyroscope noise covariance, (rad/s)²       */
    double Sa[9];     /* accelerometer noise covariance, (m/s²)²    */
    double Sm[9];     /* magnetometer noise covariance              */
    double delay;     /* magnetometer delay τ, s: the magnetometer at sample k measures
                       * the field at t_k − τ, m^b(t_k − τ) = Exp(τ ω_k) m^b(t_k) with
                       * ω_k = gyr[k−1] − bias (gyr[0] at k = 0), the rate held over the
                       * delay. τ = 0 is the plain model, and costs nothing.        */
} mc_mekf_model_t;

/* Doubles in mc_mekf_model_t. The struct is exactly this many doubles without padding
 * (checked below at compile time), so it can be copied from and to a flat array. */
#define MC_MEKF_MODEL_DOUBLES 46
typedef char
    mc_mekf_model_is_flat[sizeof(mc_mekf_model_t) == MC_MEKF_MODEL_DOUBLES * sizeof(double) ? 1 : -1];

/* The data of one session; arrays row-major. Magnetometer values are in the model's units
 * (D, o; the host normalises them).
 *
 * Every sample k is a time step (the gyroscope drives it) followed by an update with the
 * measurements present at k: has_acc[k] and has_mag[k] say which (0 or 1; a NULL mask means
 * present at every sample). A sample with one of them is updated with that one alone; a
 * sample with neither is a pure time update: the predicted attitude and covariance are
 * carried on and it adds nothing to the cost. An absent measurement's values (acc[k],
 * acc_extra_var[k]; mag[k]) are not read, so they may be NaN. This is how sensors at
 * different rates share one time base. */
typedef struct {
    size_t n;                    /* samples, ≥ 1                                        */
    const double *dt;            /* (n) s; dt[k] = time of sample k − time of k−1; dt[0]
                                  * is not read                                         */
    const double *gyr;           /* (n, 3) rad/s; gyr[k−1] drives the step to sample k   */
    const double *acc;           /* (n, 3) m/s²                                         */
    const double *mag;           /* (n, 3); not read (may be NULL) when use_mag is 0    */
    const double *acc_extra_var; /* (n) (m/s²)², c_t added to the diagonal of Sa; NULL
                                  * means all zeros                                     */
    const double *turn_var;      /* (n) rad², added to the diagonal of the predicted
                                  * covariance in the step to sample k: how uncertain the
                                  * turn is that the held rate integrates (the rate left
                                  * a straight line within the step); NULL: all zeros   */
    const unsigned char *has_acc; /* (n) 0/1: accelerometer present at sample k; NULL:
                                   * at every sample                                    */
    const unsigned char *has_mag; /* (n) 0/1: magnetometer present at sample k; NULL: at
                                   * every sample. Not read when use_mag is 0           */
    double g;                    /* gravity magnitude, m/s²                             */
    double q0[4];                /* prior attitude q_nb (normalised before use)         */
    double P0[9];                /* prior error covariance, rad² (symmetrised before use) */
    int use_mag;                 /* 0: inertial-only filter (no magnetometer anywhere)  */
} mc_mekf_data_t;

/* Optional per-sample outputs of the forward pass (any pointer may be NULL). */
typedef struct {
    double *q_filt;     /* (n, 4) attitude after each update (after the time update at a
                         * sample with no measurement)                                */
    double *innov;      /* (n, 6) innovations, accelerometer then magnetometer: NaN for a
                         * measurement absent at that sample (has_acc, has_mag), 0 for
                         * the magnetometer part when use_mag is 0                    */
    double *normalised; /* (n, 6) Cholesky-whitened innovations of the measurements
                         * present (likewise NaN and 0; all NaN where the innovation
                         * covariance has a non-positive pivot)                      */
} mc_mekf_outputs_t;

/* Forward pass: V(θ) = ½ Σ_t (ε_tᵀ S_t⁻¹ ε_t + log det S_t) over the measurements present,
 * without the constant ½ log 2π per measured component. `out` may be NULL.
 * Returns the cost, or NaN when an argument is invalid (model, data, data->dt, data->gyr,
 * data->acc NULL, data->mag NULL with use_mag, n = 0) or a covariance stops being positive
 * definite. */
double mc_mekf_cost(const mc_mekf_model_t *model, const mc_mekf_data_t *data,
                    const mc_mekf_outputs_t *out);

/* Doubles of reverse-mode tape per sample (attitude, Pp⁻¹, Λ⁻¹, u, η and magnetometer terms). */
#define MC_MEKF_TAPE_DOUBLES 40

/* The cost of mc_mekf_cost (the same forward computation) and its gradient ∂V/∂model into
 * `grad` (layout of mc_mekf_model_t; the m entry is ∂V/∂m, with m not constrained to unit
 * length). `tape` is caller-owned workspace of `tape_len` doubles, at least
 * MC_MEKF_TAPE_DOUBLES · n; its contents on entry do not matter.
 * `grad` is zeroed first. Returns the cost; when it is NaN (the arguments of mc_mekf_cost
 * plus tape or grad NULL or tape_len too short, or a covariance not positive definite) or
 * otherwise not finite, the gradient is left zero. */
double mc_mekf_cost_grad(const mc_mekf_model_t *model, const mc_mekf_data_t *data,
                         double *tape, size_t tape_len, mc_mekf_model_t *grad);

/* Most directions mc_mekf_fisher takes in one pass (its tangents are on the stack). */
#define MC_MEKF_FISHER_MAX_DIRECTIONS 64
/* Features of mc_mekf_fisher's workspace per direction: those of 8 samples (27 each),
 * gathered before they are multiplied out. */
#define MC_MEKF_FISHER_WORK_DOUBLES_PER_DIRECTION 216
/* The directions are stored in groups of this many, the last padded with zeros, so that the
 * information is multiplied out in whole tiles (mekf_fisher.c, flush_block). */
#define MC_MEKF_FISHER_LANES 8
/* Doubles of mc_mekf_fisher's workspace for k directions: k rounded up to whole groups of
 * MC_MEKF_FISHER_LANES, times MC_MEKF_FISHER_WORK_DOUBLES_PER_DIRECTION. */
#define MC_MEKF_FISHER_WORK_DOUBLES(k)                                                     \
    ((((k) + MC_MEKF_FISHER_LANES - 1) / MC_MEKF_FISHER_LANES) * MC_MEKF_FISHER_LANES *     \
     MC_MEKF_FISHER_WORK_DOUBLES_PER_DIRECTION)

/* The cost of mc_mekf_cost and, along k directions of the model (the rows of `directions`,
 * k × MC_MEKF_MODEL_DOUBLES, in the layout of mc_mekf_model_t), the Fisher information of
 * the prediction-error likelihood,
 *   info[i][j] = Σ_t (∂_i ε_tᵀ S_t⁻¹ ∂_j ε_t + ½ tr(S_t⁻¹ ∂_i S_t S_t⁻¹ ∂_j S_t)),
 * into `info` (k × k, symmetric), and the cost's derivative along each direction into
 * `grad` (k), both by forward sensitivities of the filter (mekf_fisher.c). A direction's
 * covariance entries are symmetrised as the model's are. Returns the cost; on NaN (the
 * arguments of mc_mekf_cost, `directions`, `info` or `grad` NULL, k = 0 or above
 * MC_MEKF_FISHER_MAX_DIRECTIONS, `work` NULL or shorter than
 * MC_MEKF_FISHER_WORK_DOUBLES(k) (caller-owned; its contents on entry do not
 * matter), or a covariance not positive definite) info and grad are zero, except for a k
 * out of range, where nothing is written. */
double mc_mekf_fisher(const mc_mekf_model_t *model, const mc_mekf_data_t *data,
                      const double *directions, size_t k, double *work, size_t work_len,
                      double *info, double *grad);

#endif
