# SPDX-License-Identifier: Apache-2.0
"""Algorithm 1, step 2: the maximum-likelihood estimate.

``params`` (the vector θ) → ``mekf`` (the orientation filter and its C kernel) →
``problem`` (V(θ) with its priors and gradient, built once for every caller) →
``optimize`` (damped BFGS) → ``ml`` (the estimate).
"""
