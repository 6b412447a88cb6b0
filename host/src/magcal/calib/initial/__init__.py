# SPDX-License-Identifier: Apache-2.0
"""Algorithm 1, step 1: the initial estimate θ₀ (rest detection, ellipsoid, alignment)."""
