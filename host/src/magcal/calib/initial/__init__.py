"""Algorithm 1, step 1: the initial estimate θ₀ (rest detection, ellipsoid, alignment)."""
