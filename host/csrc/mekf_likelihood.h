/*
 * Negative log-likelihood of the multiplicative EKF (Kok & Schön 2016, eq. 6) and its exact
 * gradient by a reverse (adjoint) pass. Plain C99, no Python: the CPython glue is
 * _mekf_module.c. The model and conventions are documented in magcal/calib/ekf.py.
 */
#ifndef MAGCAL_MEKF_LIKELIHOOD_H
#define MAGCAL_MEKF_LIKELIHOOD_H

#include <stddef.h>

/* Model quantities; matrices row-major. The gradient has the same layout. */
typedef struct {
    double D[9];      /* magnetometer distortion                    */
    double o[3];      /* magnetometer offset                        */
    double m[3];      /* unit field in n                            */
    double bias[3];   /* gyroscope bias, rad/s                      */
    double Sw[9];     /* gyroscope noise covariance                 */
    double Sa[9];     /* accelerometer noise covariance             */
    double Sm[9];     /* magnetometer noise covariance              */
} mc_mekf_model_t;

typedef struct {
    size_t n;
    const double *dt;            /* (n)                                  */
    const double *gyr;           /* (n, 3)                               */
    const double *acc;           /* (n, 3)                               */
    const double *mag;           /* (n, 3)                               */
    const double *acc_extra_var; /* (n), added to the diagonal of Sa     */
    double g;                    /* gravity magnitude                    */
    double q0[4];                /* prior attitude q_nb                  */
    double P0[9];                /* prior error covariance               */
    int use_mag;                 /* 0: inertial-only filter              */
} mc_mekf_data_t;

/* Optional per-sample outputs of the forward pass (any pointer may be NULL). */
typedef struct {
    double *q_filt;     /* (n, 4) attitude after each update          */
    double *innov;      /* (n, 6) innovations                         */
    double *normalised; /* (n, 6) Cholesky-whitened innovations       */
} mc_mekf_outputs_t;

/* Forward pass. Returns the cost, or NaN when a covariance stops being positive
 * definite. */
double mc_mekf_cost(const mc_mekf_model_t *model, const mc_mekf_data_t *data,
                    const mc_mekf_outputs_t *out);

/* Doubles of reverse-mode tape per sample (attitude, Pp⁻¹, Λ⁻¹, u, η and magnetometer terms). */
#define MC_MEKF_TAPE_DOUBLES 40

/* Cost and gradient. `tape` is caller-owned workspace of MC_MEKF_TAPE_DOUBLES*n doubles.
 * Returns the cost, or NaN on failure (the gradient is then zero). */
double mc_mekf_cost_grad(const mc_mekf_model_t *model, const mc_mekf_data_t *data,
                         double *tape, mc_mekf_model_t *grad);

#endif
