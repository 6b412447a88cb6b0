# SPDX-License-Identifier: Apache-2.0
"""Real-time magnetometer calibration with a cubature Kalman filter (Zhao et al.).

Zhao, Lin, Zhang, Zhai, *Real-time Calibration Algorithm for Three-axis Magnetometer*
(``docs/algorithm.md`` §2).

Model (paper eq. 5–14). The readings lie on ``(y − b)ᵀ A (y − b) = B_m²`` with
``A = Tᵀ T``. The state is constant (eq. 7, 15),

    x = [A11 A22 A33 A12 A13 A23 b_x b_y b_z],

and every sample is the scalar pseudo-measurement (eq. 8–12)

    z = B_m² = h(x; y) + v,   h(x; y) = (y − b)ᵀ A (y − b).

magcal normalises the field to ``B_m = 1`` (``docs/contracts.md``: ``D⁻¹(y − o)`` has unit norm), so
``A = D⁻ᵀ D⁻¹`` in the session's unit. With sensor noise ``n ~ N(0, σ² I)`` on ``y``, eq. 13's
``v = 2(b − y)ᵀ A n + nᵀ A n`` (``y`` the reading, which carries ``n`` itself:
``y − b = (y − n − b) + n``) has mean ``−σ² tr A`` and variance

    r = 4 σ² ‖A (y − b)‖² + 2 σ⁴ tr(A²)          (Gaussian n; r_k of eq. 17)

The mean is added to each cubature point's prediction. The paper leaves it out, which biases
the field norm by 1.5σ² relative: small (4e-5 for σ = 0.5 % of the field) but over 100k
samples many times the estimate's own uncertainty (tested).

Filter (eq. 15–18): cubature points ``x̂ ± √n S e_j`` (n = 9, 2n = 18 points, ``P = S Sᵀ``),
``ẑ`` their mean prediction, ``P_zz`` their spread plus ``r``, ``P_xz`` their cross spread,
``K = P_xz / P_zz``. Numerical choices:

* **Square-root form.** ``P`` is kept as a factor ``S``. With ``w = (1/2n) Σ ξ_i (Z_i − ẑ)``
  (so ``P_xz = S w``) the update ``P − K P_zz Kᵀ = S (I − w wᵀ / P_zz) Sᵀ`` is applied as
  ``S ← S (I − β w wᵀ)``, ``β = 1 / (P_zz (1 + √(1 − ‖w‖²/P_zz)))``, the symmetric square root
  of that middle factor. Cauchy–Schwarz on the cubature sums gives ``‖w‖² ≤ P_zz − r``, so the
  factor's smallest eigenvalue is at least ``√(r / P_zz) > 0``: ``P`` stays symmetric positive
  definite by construction, with no subtraction of covariances (tested over 100k samples).
  The product is then brought back to the lower-triangular root (Cholesky of ``S Sᵀ``; kept
  as it is should that fail): the rule ``±√n`` along the columns of any root ``S Q`` is a
  third-degree rule, but ``P_zz`` and ``P_xz`` are of higher degree in the state and their
  approximation depends on the root. The Cholesky root, the paper's ``√P``, gave the better
  estimates: on 12 MEMS simulations the worst error in ``A`` noise-free was 2e-7 against
  2e-5 with the product form, on 12 hand-held ones 9e-4 against 2e-2.
* **Normalised coordinates.** The filter runs on ``u = (y − c) / s`` with ``c`` the centre
  of the starting ellipsoid and ``s`` its mean radius ``det(A)^(−1/6)``, so the state is O(1)
  whatever the unit and the update is invariant to the data's scale and offset (raw counts
  calibrate like µT; tested to 1e-9).
* **Start (no prior given).** The measurement is cubic in the state and a session's samples
  are strongly correlated in time (a slow rotation sweeps a small arc for seconds). Started
  from a diffuse prior on such an arc, the filter collapses ``P`` along the few directions
  the arc excites while its estimate is still far off, and the linearisation error is then
  frozen in (on the MEMS simulation: 1–10 % errors in ``A`` that never go away, although the
  same filter recovers ``A`` to 1e-10 on the paper's independent random orientations). So the
  first samples are kept in a reservoir (at most :data:`RESERVOIR_SAMPLES`, evenly thinned as
  it fills) until they span enough directions (:func:`start_ready`); the filter then starts
  from the ellipsoid fitted to them by the plain algebraic fit (:func:`algebraic_ellipsoid`;
  Kåsa's sphere if that is no real ellipsoid) with a wide prior (:data:`PRIOR_STD_A` etc.),
  runs through the reservoir in a fixed pseudo-random order (which breaks the correlation),
  and then takes every sample as it comes. A sample that arrives
  before the start is used only through the reservoir. Alternatively a :class:`CkfPrior`
  (an ellipsoid or a sphere, and the noise) starts the filter at once. For a whole session
  that ends before the start, :func:`run_ckf` runs the filter in a pseudo-random order.
* **Noise level.** ``σ`` is estimated from second differences of the samples seen before the
  start (:func:`~magcal.calib.initial.rest.white_noise_std`) unless
  given, floored at :data:`MIN_NOISE_FRACTION` of the field (noise-free data).

At the end, ``T = Q √Σ Qᵀ`` from ``A = Q Σ Qᵀ`` (eq. 19–20): ``D_sym = T⁻¹``, ``o = b``.
The rotation between magnetometer and inertial axes is invisible to this model;
:mod:`magcal.calib.calibrate` adds it with Algorithm 1's alignment step (see
:mod:`magcal.calib.norm_only.norm_ellipsoid`).

Cost: one update is a fixed number of 9-vector and 9 × 9 operations: constant time and
memory per sample (``bench/run_bench.py`` reports µs per sample).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib.initial import rest
from magcal.calib.initial.ellipsoid import EllipsoidFit
from magcal.calib.norm_only import norm_ellipsoid
from magcal.errors import InsufficientDataError

N_STATE = 9
ROOT_N = 3.0  # √N_STATE: the cubature points' distance in whitened coordinates
#: Upper bound on the samples kept before the start; when full, every other one is dropped
#: and from then on only every second (fourth, ...) sample is kept: an even thinning of
#: everything seen so far in bounded memory.
RESERVOIR_SAMPLES = 512
#: Fewest reservoir samples for a start.
START_MIN_SAMPLES = 100
#: The start is tested every this many reservoir additions (a 4 × 4 solve and a 3 × 3
#: eigenvalue problem on ≤ RESERVOIR_SAMPLES samples).
START_CHECK_EVERY = 25
#: Start when the field directions seen (readings about the fitted sphere's centre, as unit
#: vectors) have principal standard deviations with smallest / largest ≥ this: 0.5 is a
#: hemisphere, 0.4 a cap of about 75° half-angle, 1 the whole sphere. Earlier starts cost
#: accuracy: on 12 MEMS simulations (seeds 1-12) the worst relative error in A was 2.3e-7
#: noise-free and 9.7e-4 with noise at 0.5, against 1.3e-3 and 4.2e-3 at 0.4 and 2.3e-3 and
#: 4.4e-2 at 0.3. The MEMS tumble (1 rad/s) reaches 0.5 after 15-45 s, the hand-held one
#: (3 rad/s) after 5-25 s.
START_MIN_DIRECTION_SPREAD = 0.5
#: ... and when the readings' smallest principal standard deviation is at least this many
#: times the noise σ (a sensor at rest gives a noise cloud, which has "all directions").
START_MIN_SPREAD_OVER_NOISE = 5.0
#: Kåsa's sphere through a noise cloud (a sensor at rest) has a radius of about √3 σ: 1.6-1.9 σ
#: in 20 simulated at-rest sessions of 400 samples. A sphere this many σ or more is taken as
#: the field's (Zhao et al.'s Table 2 sessions: 2.6-10.8 σ over seeds 1-40), for telling
#: noise from rest in :func:`spread_problem`.
NOISE_CLOUD_MAX_RADIUS_OVER_NOISE = 2.5
#: Second differences kept for the noise estimate before the start (the most recent ones).
NOISE_WINDOW = 512
#: Fewest second differences for a noise estimate.
NOISE_MIN_DIFFERENCES = 30
#: σ is at least this fraction of the field (noise-free data would give r = 0).
MIN_NOISE_FRACTION = 1e-6
#: Prior standard deviations at the start, in the normalised coordinates (where the starting
#: ellipsoid is about the unit sphere): A's diagonal (relative), its off-diagonal, the centre
#: (in radii). Wide for a start fitted to a hemisphere of data; enough for a Kåsa sphere
#: start on a soft iron of ±50 % and an offset a third of the field from its centre.
PRIOR_STD_A = 0.5
PRIOR_STD_A_OFFDIAG = 0.25
PRIOR_STD_B = 0.3
#: The reservoir's processing order at the start (a fixed seed: the same data always give
#: the same estimate).
SHUFFLE_SEED = 0

_OFF = ((0, 1), (0, 2), (1, 2))
# state[..., _SYM_INDEX] is A as a (…, 3, 3) matrix.
_SYM_INDEX = np.array([[0, 3, 4], [3, 1, 5], [4, 5, 2]])


@dataclass(frozen=True, eq=False)
class CkfPrior:
    """A starting point for :class:`CubatureCalibrator`: the ellipsoid
    ``(y − b)ᵀ A (y − b) = 1`` and the noise level (the prior spread around it is
    :data:`PRIOR_STD_A` etc., in the coordinates where it is a unit sphere).

    A         : (3, 3) float, symmetric positive definite, (raw units)⁻²
    b         : (3,) float, raw units
    noise_std : float ≥ 0, raw units, σ of each axis' white noise
    """

    A: np.ndarray
    b: np.ndarray
    noise_std: float

    def __post_init__(self) -> None:
        A = np.asarray(self.A, dtype=float)
        b = np.asarray(self.b, dtype=float)
        if A.shape != (3, 3) or b.shape != (3,):
            raise ValueError(f"ckf prior: A must be (3, 3) and b (3,), got {A.shape}, {b.shape}")
        ok = np.all(np.isfinite(A)) and np.all(np.isfinite(b)) and np.allclose(A, A.T)
        if not ok or np.linalg.eigvalsh(0.5 * (A + A.T))[0] <= 0.0:
            raise ValueError("ckf prior: A must be finite, symmetric and positive definite")
        if not (np.isfinite(self.noise_std) and self.noise_std >= 0.0):
            raise ValueError(f"ckf prior: noise_std must be finite and ≥ 0, got {self.noise_std}")

    @classmethod
    def sphere(cls, centre: np.ndarray, radius: float, noise_std: float) -> CkfPrior:
        """The sphere ``‖y − centre‖ = radius`` (raw units)."""
        if not (np.isfinite(radius) and radius > 0.0):
            raise ValueError(f"ckf prior: the radius must be finite and > 0, got {radius!r}")
        return cls(np.eye(3) / radius**2, np.asarray(centre, dtype=float), noise_std)

    @classmethod
    def from_readings(cls, mag: np.ndarray) -> CkfPrior:
        """The readings' algebraic ellipsoid when it is a real one, else Kåsa's sphere when
        they span three dimensions, else their mean and RMS distance from it; the noise from
        second differences. mag : (N, 3) raw units."""
        mag = norm_ellipsoid.check_readings(mag, "ckf")
        sigma = rest.white_noise_std(mag)
        ellipsoid = algebraic_ellipsoid(mag)
        if ellipsoid is not None:
            return cls(ellipsoid[0], ellipsoid[1], sigma)
        sphere = kasa_sphere(mag)
        if sphere is None:
            centre = mag.mean(axis=0)
            sphere = (centre, float(np.sqrt(np.mean(np.sum((mag - centre) ** 2, axis=1)))))
        if not sphere[1] > 0.0:
            raise InsufficientDataError(
                "ckf: all magnetometer samples are identical: check that the magnetometer is "
                "working and rotate the sensor through all orientations"
            )
        return cls.sphere(sphere[0], sphere[1], sigma)


def kasa_sphere(y: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Kåsa's linear sphere fit ``‖y‖² = 2 cᵀy + k``: (centre (3,), radius), or None when the
    readings do not determine it (planar data, fewer than 4 points, an empty sphere).

    y : (N, 3) float, any unit. Solved on data centred on their mean (conditioning).
    """
    if y.shape[0] < 4:
        return None
    mu = y.mean(axis=0)
    z = y - mu
    M = np.column_stack([2.0 * z, np.ones(z.shape[0])])
    sol, _, rank, sv = np.linalg.lstsq(M, np.einsum("ij,ij->i", z, z), rcond=None)
    if rank < 4 or sv[-1] < 1e-9 * sv[0]:
        return None
    c = sol[:3]
    r2 = float(sol[3] + c @ c)
    if not r2 > 0.0:
        return None
    return mu + c, float(np.sqrt(r2))


def start_ready(reservoir: np.ndarray, noise_std: float) -> tuple[np.ndarray, float] | None:
    """Kåsa's sphere (centre, radius) of the reservoir's readings if they span enough
    directions (:data:`START_MIN_DIRECTION_SPREAD`) well above the noise
    (:data:`START_MIN_SPREAD_OVER_NOISE`), else None. reservoir : (N, 3) raw units."""
    if reservoir.shape[0] < START_MIN_SAMPLES:
        return None
    spread = np.linalg.eigvalsh(np.cov(reservoir, rowvar=False))
    if not np.sqrt(max(spread[0], 0.0)) >= START_MIN_SPREAD_OVER_NOISE * noise_std:
        return None
    sphere = kasa_sphere(reservoir)
    if sphere is None:
        return None
    v = reservoir - sphere[0]
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    if np.any(norm == 0.0):
        return None
    lam = np.linalg.eigvalsh(np.cov(v / norm, rowvar=False))
    if not lam[-1] > 0.0 or np.sqrt(max(lam[0], 0.0) / lam[-1]) < START_MIN_DIRECTION_SPREAD:
        return None
    return sphere


def spread_problem(mag: np.ndarray, noise_std: float) -> str | None:
    """Why the readings fail :func:`start_ready`'s spread test, or None when they pass it.

    mag : (N, 3) float, raw units; noise_std : σ, raw units.

    The test (smallest principal standard deviation ≥ :data:`START_MIN_SPREAD_OVER_NOISE` σ)
    fails for one of two reasons, told apart by Kåsa's sphere (radius R) through the
    readings. Turned through all orientations, readings on a sphere of radius R spread by
    R/√3 along every axis, so when ``R/√3 < 5σ`` no motion can pass: the noise is too large
    for the start (Zhao et al.'s Table 2 sessions, σ ≈ 20 % of the field). A noise cloud at
    rest also has a sphere, of radius about √3 σ (RMS distance of a 3-D Gaussian from its
    mean), so R must also exceed :data:`NOISE_CLOUD_MAX_RADIUS_OVER_NOISE` σ to be a field
    sphere. Otherwise the sensor was at rest or turned too little.
    """
    spread = np.sqrt(max(np.linalg.eigvalsh(np.cov(mag, rowvar=False))[0], 0.0))
    if spread >= START_MIN_SPREAD_OVER_NOISE * noise_std:
        return None
    sphere = kasa_sphere(mag)
    if sphere is not None:
        radius = sphere[1]
        full_turn_spread = radius / np.sqrt(3.0)
        is_field = radius > NOISE_CLOUD_MAX_RADIUS_OVER_NOISE * noise_std
        if is_field and full_turn_spread < START_MIN_SPREAD_OVER_NOISE * noise_std:
            return (
                f"ckf: the magnetometer noise (σ ≈ {100.0 * noise_std / radius:.0f} % of the "
                f"field) is too large for the CKF's start: it needs the readings to spread "
                f"beyond {START_MIN_SPREAD_OVER_NOISE:g} σ in every direction, and a turn "
                f"through all orientations spreads them by only {full_turn_spread / noise_std:.1f}"
                " σ here: calibrate with another method (--method ml or two-step) or reduce "
                "the noise (averaging, a lower bandwidth)"
            )
    return (
        f"ckf: the {mag.shape[0]} readings do not spread beyond {START_MIN_SPREAD_OVER_NOISE:g}"
        " times their noise in every direction (the sensor was at rest or barely moved): "
        "rotate it through all orientations (tilt it nose up/down and roll it over)"
    )


def algebraic_ellipsoid(y: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """A quick ellipsoid ``(y − b)ᵀ A (y − b) = 1`` through readings y (N, 3): the plain
    algebraic fit (smallest eigenvector of the normalised design's Gram matrix, as
    :func:`magcal.calib.initial.ellipsoid.fit_ellipsoid_algebraic` but without its checks and
    packaging). Returns (A (3, 3) in (raw units)⁻², b (3,) raw units), or None when the fit
    is not a real ellipsoid (A not positive definite, empty quadric)."""
    mu = y.mean(axis=0)
    z = y - mu
    s = float(np.sqrt(np.mean(np.einsum("ij,ij->i", z, z))))
    if not s > 0.0:
        return None
    z = z / s
    z0, z1, z2 = z.T
    root2 = np.sqrt(2.0)  # unknowns (A11, A22, A33, √2 A12, ...): ‖ξ‖ counts A's copies
    M = np.column_stack(
        [
            z0 * z0,
            z1 * z1,
            z2 * z2,
            root2 * z0 * z1,
            root2 * z0 * z2,
            root2 * z1 * z2,
            z0,
            z1,
            z2,
            np.ones_like(z0),
        ]
    )
    xi = np.linalg.eigh(M.T @ M)[1][:, 0]
    A = _sym(np.concatenate([xi[:3], xi[3:6] / root2]))
    if np.trace(A) < 0.0:
        A, xi = -A, -xi
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        return None
    a_inv_v = np.linalg.solve(L.T, np.linalg.solve(L, xi[6:9]))
    centre = -0.5 * a_inv_v
    beta = 0.25 * float(xi[6:9] @ a_inv_v) - float(xi[9])
    if not beta > 0.0:
        return None
    return A / (beta * s * s), mu + s * centre


def _sym(a: np.ndarray) -> np.ndarray:
    """(…, 6) state parts [A11 A22 A33 A12 A13 A23] → (…, 3, 3) symmetric matrices."""
    return a[..., _SYM_INDEX]


def _h(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``(u − b)ᵀ A (u − b)`` for states x (…, 9) and points u (…, 3) (broadcast)."""
    d = u - x[..., 6:]
    d0, d1, d2 = d[..., 0], d[..., 1], d[..., 2]
    return (
        x[..., 0] * d0 * d0
        + x[..., 1] * d1 * d1
        + x[..., 2] * d2 * d2
        + 2.0 * (x[..., 3] * d0 * d1 + x[..., 4] * d0 * d2 + x[..., 5] * d1 * d2)
    )


def _jacobian(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``∂h/∂x`` (K, 9) at state x (9,) for points u (K, 3)."""
    d = u - x[6:]
    A = _sym(x[:6])
    J = np.empty((u.shape[0], N_STATE))
    J[:, :3] = d * d
    for k, (i, j) in enumerate(_OFF):
        J[:, 3 + k] = 2.0 * d[:, i] * d[:, j]
    J[:, 6:] = -2.0 * d @ A
    return J


@dataclass(frozen=True, eq=False)
class CkfEstimate:
    """The filter's estimate after ``samples`` updates.

    The state is held in the filter's normalised coordinates (``u = (y − centre)/scale``);
    the properties give it in raw units:

    A : (3, 3) float, (raw units)⁻², ``(y − b)ᵀ A (y − b) = 1`` on the ellipsoid
    b : (3,) float, raw units, the centre (hard-iron offset ``o``)
    P : (9, 9) float, covariance of ``[A11 A22 A33 A12 A13 A23 b_x b_y b_z]`` in raw units
    T : (3, 3) float, (raw units)⁻¹, the symmetric square root of ``A`` (eq. 20)
    """

    x: np.ndarray  # (9,) normalised state
    S: np.ndarray  # (9, 9) factor of the normalised covariance, P = S Sᵀ
    centre: np.ndarray  # (3,) raw units
    scale: float  # raw units
    noise_std: float  # raw units
    samples: int  # updates so far (reservoir included)

    @property
    def A(self) -> np.ndarray:
        return _sym(self.x[:6]) / self.scale**2

    @property
    def b(self) -> np.ndarray:
        return self.centre + self.scale * self.x[6:]

    @property
    def P(self) -> np.ndarray:
        lam = np.concatenate([np.full(6, self.scale**-2), np.full(3, self.scale)])
        Ls = lam[:, None] * self.S
        return Ls @ Ls.T

    @property
    def T(self) -> np.ndarray:
        return norm_ellipsoid.symmetric_root(self.A)[0]

    def normalise(self, y: np.ndarray) -> np.ndarray:
        """Raw readings (…, 3) → the filter's coordinates."""
        return (np.asarray(y, dtype=float) - self.centre) / self.scale

    def norms(self, y: np.ndarray) -> np.ndarray:
        """‖T (y − b)‖ (N,) of raw readings y (N, 3): 1 on the estimated ellipsoid."""
        return np.sqrt(np.maximum(_h(self.x, self.normalise(y)), 0.0))

    def points(self, directions: np.ndarray) -> np.ndarray:
        """Points (K, 3), normalised coordinates, of this ellipsoid in the calibrated unit
        ``directions`` (K, 3): ``b + T⁻¹ d``."""
        T, _ = norm_ellipsoid.symmetric_root(_sym(self.x[:6]))
        return self.x[6:] + np.linalg.solve(T, np.asarray(directions, dtype=float).T).T

    def norm_std(self, points: np.ndarray) -> np.ndarray:
        """Standard deviation (K,) of the calibrated norm ``‖T(y − b)‖`` at ``points`` (K, 3,
        normalised coordinates, e.g. :meth:`points`) due to the state's uncertainty P,
        linearised: ``√(J P Jᵀ) / 2`` (the norm is ``√h`` with ``h ≈ 1``). Dimensionless: a
        fraction of the field."""
        JS = _jacobian(self.x, points) @ self.S
        return 0.5 * np.sqrt(np.einsum("ij,ij->i", JS, JS))


class CubatureCalibrator:
    """Zhao et al.'s CKF, one magnetometer sample at a time (see the module docstring).

    ``ckf = CubatureCalibrator()`` starts from the first samples (once they span enough
    directions); ``CubatureCalibrator(CkfPrior.sphere(centre, radius, noise_std))`` at once.
    ``noise_std`` (raw units) overrides the estimate from second differences.

    ``ckf.update(y)`` takes one reading (3,) in raw units and returns the current
    :class:`CkfEstimate` (its covariance included), or None while the filter has not started.
    Time and memory per update are constant; before the start the reservoir is bounded by
    :data:`RESERVOIR_SAMPLES` and released at the start.
    """

    def __init__(self, prior: CkfPrior | None = None, *, noise_std: float | None = None) -> None:
        if noise_std is not None and not (np.isfinite(noise_std) and noise_std >= 0.0):
            raise ValueError(f"ckf: noise_std must be finite and ≥ 0, got {noise_std!r}")
        self._noise_given = noise_std
        self.samples_seen = 0
        self.updates = 0
        self._x = np.empty(N_STATE)
        self._S = np.empty((N_STATE, N_STATE))
        self._pts = np.empty((2 * N_STATE, N_STATE))
        # LAPACK's Cholesky for the update (see _update), imported here rather than with the
        # module: scipy takes a noticeable part of a second to load, and a calibration that
        # does not run this filter should not pay for it.
        from scipy.linalg.lapack import dpotrf

        self._potrf = dpotrf
        self._centre = np.zeros(3)
        self._scale = 1.0
        self._sigma2 = 0.0  # normalised noise variance
        self._noise_std = 0.0
        self.started = False
        self.start_sample = 0  # samples seen when the filter started
        # Before the start: the reservoir and the last second differences.
        self._reservoir: np.ndarray | None = np.empty((RESERVOIR_SAMPLES, 3))
        self._n_res = 0
        self._stride = 1
        self._diffs: np.ndarray | None = np.zeros((NOISE_WINDOW, 3))
        self._n_diffs = 0
        self._prev = np.zeros((2, 3))
        if prior is not None:
            sigma = prior.noise_std if noise_std is None else noise_std
            self._start(np.asarray(prior.A, dtype=float), np.asarray(prior.b), float(sigma))

    # ------------------------------------------------------------------ public
    @property
    def estimate(self) -> CkfEstimate:
        """The current estimate; raises InsufficientDataError before the start."""
        if not self.started:
            raise InsufficientDataError(
                f"ckf: no estimate yet after {self.samples_seen} samples: the readings have "
                "not yet covered enough directions; keep rotating the sensor"
            )
        return CkfEstimate(
            self._x.copy(),
            self._S.copy(),
            self._centre.copy(),
            self._scale,
            self._noise_std,
            self.updates,
        )

    def update(self, y: np.ndarray) -> CkfEstimate | None:
        """One reading (3,), raw units → the estimate after it (None before the start)."""
        y = np.asarray(y, dtype=float).reshape(3)
        self.samples_seen += 1
        if self.started:
            self._update((y - self._centre) / self._scale)
            return self.estimate
        self._collect(y)
        return self.estimate if self.started else None

    def update_many(self, ys: np.ndarray) -> None:
        """Every reading of ys (N, 3), raw units, in order (what :meth:`update` does for each,
        without building an estimate per sample)."""
        ys = np.asarray(ys, dtype=float).reshape(-1, 3)
        i = 0
        while not self.started and i < ys.shape[0]:
            self.samples_seen += 1
            self._collect(ys[i])
            i += 1
        if i < ys.shape[0]:
            u = (ys[i:] - self._centre) / self._scale
            self.samples_seen += u.shape[0]
            for row in u:
                self._update(row)

    # ------------------------------------------------------------------ start
    def _collect(self, y: np.ndarray) -> None:
        if self.samples_seen >= 3:
            self._diffs[self._n_diffs % NOISE_WINDOW] = y - 2.0 * self._prev[1] + self._prev[0]
            self._n_diffs += 1
        self._prev[0], self._prev[1] = self._prev[1], y
        if (self.samples_seen - 1) % self._stride != 0:
            return
        if self._n_res == RESERVOIR_SAMPLES:
            half = self._reservoir[::2].copy()
            self._n_res = half.shape[0]
            self._reservoir[: self._n_res] = half
            self._stride *= 2
            if (self.samples_seen - 1) % self._stride != 0:
                return
        self._reservoir[self._n_res] = y
        self._n_res += 1
        if self._n_res % START_CHECK_EVERY == 0 and self._n_diffs >= NOISE_MIN_DIFFERENCES:
            res = self._reservoir[: self._n_res]
            sigma = self._noise_estimate()
            sphere = start_ready(res, sigma)
            if sphere is not None:
                res = res.copy()
                start = algebraic_ellipsoid(res)
                if start is None:  # a hemisphere of very noisy data: the sphere will do
                    start = (np.eye(3) / sphere[1] ** 2, sphere[0])
                self._start(start[0], start[1], sigma)
                order = np.random.default_rng(SHUFFLE_SEED).permutation(res.shape[0])
                for row in (res[order] - self._centre) / self._scale:
                    self._update(row)

    def _noise_estimate(self) -> float:
        if self._noise_given is not None:
            return float(self._noise_given)
        n = min(self._n_diffs, NOISE_WINDOW)
        d2 = self._diffs[:n]
        sigma = 1.4826 * np.median(np.abs(d2), axis=0) / np.sqrt(6.0)
        return float(np.sqrt(np.mean(sigma * sigma)))

    def _start(self, A: np.ndarray, b: np.ndarray, noise_std: float) -> None:
        """Start at the ellipsoid ``(y − b)ᵀ A (y − b) = 1`` (raw units); the filter's
        coordinates are centred on ``b`` and scaled by its mean radius ``det(A)^(−1/6)``."""
        self._centre = np.asarray(b, dtype=float).copy()
        self._scale = float(np.linalg.det(A) ** (-1.0 / 6.0))
        self._noise_std = max(float(noise_std), MIN_NOISE_FRACTION * self._scale)
        self._sigma2 = (self._noise_std / self._scale) ** 2
        A_n = A * self._scale**2
        self._x[:6] = (A_n[0, 0], A_n[1, 1], A_n[2, 2], A_n[0, 1], A_n[0, 2], A_n[1, 2])
        self._x[6:] = 0.0
        self._S[:] = np.diag([PRIOR_STD_A] * 3 + [PRIOR_STD_A_OFFDIAG] * 3 + [PRIOR_STD_B] * 3)
        self.started = True
        self.start_sample = self.samples_seen
        self._reservoir = None
        self._diffs = None

    # ------------------------------------------------------------------ the CKF step
    def _update(self, u: np.ndarray) -> None:
        """Eq. 15–18 in square-root form for one normalised reading u (3,). Written for few
        numpy calls: at this size their overhead, not the arithmetic, is the cost."""
        x, S, pts = self._x, self._S, self._pts
        spread = ROOT_N * S.T  # row j: √n S[:, j]
        np.add(x, spread, out=pts[:N_STATE])
        np.subtract(x, spread, out=pts[N_STATE:])
        # h = dᵀ A d at every point, plus the noise's mean −σ² tr A (eq. 13).
        d = u - pts[:, 6:]
        z = np.einsum("ki,kij,kj->k", d, pts[:, _SYM_INDEX], d)
        z -= self._sigma2 * pts[:, :3].sum(axis=1)
        z_hat = float(z.sum()) / (2 * N_STATE)
        dz = z - z_hat
        dx = u - x[6:]
        a00, a11, a22, a01, a02, a12 = x[:6].tolist()
        d0, d1, d2 = dx.tolist()
        ad0 = a00 * d0 + a01 * d1 + a02 * d2
        ad1 = a01 * d0 + a11 * d1 + a12 * d2
        ad2 = a02 * d0 + a12 * d1 + a22 * d2
        tr_a2 = a00 * a00 + a11 * a11 + a22 * a22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
        s2 = self._sigma2
        r = 4.0 * s2 * (ad0 * ad0 + ad1 * ad1 + ad2 * ad2) + 2.0 * s2 * s2 * tr_a2
        p_zz = float(dz @ dz) / (2 * N_STATE) + r
        # w: P_xz = S w (the points are x̂ ± √n S e_j).
        w = (dz[:N_STATE] - dz[N_STATE:]) * (ROOT_N / (2 * N_STATE))
        p_xz = S @ w
        x += p_xz * ((1.0 - z_hat) / p_zz)
        ratio = min(float(w @ w) / p_zz, 1.0)
        S -= p_xz[:, None] * (w / (p_zz * (1.0 + np.sqrt(1.0 - ratio))))
        # Back to the lower-triangular (Cholesky) root, the paper's √P (see the module doc).
        # (LAPACK's dpotrf directly: numpy's wrapper costs more than the 9 × 9 factorisation.)
        root, info = self._potrf(S @ S.T, lower=1, clean=1)
        if info == 0:
            S[:] = root
        # else: the product form is a valid root too, and positive definite
        self.updates += 1


@dataclass(frozen=True, eq=False)
class CkfFit:
    """A whole session through the filter.

    estimate    : the final :class:`CkfEstimate`
    order       : "time": as recorded, started from the first samples (as live);
                  "shuffled": the readings never spanned enough directions in time for that
                  start, so the filter ran once through all of them in a fixed pseudo-random
                  order from their algebraic ellipsoid (:meth:`CkfPrior.from_readings`)
    start_index : with "time", the sample at which the filter started
    """

    estimate: CkfEstimate
    order: str
    start_index: int | None


def run_ckf(mag: np.ndarray, *, force: bool = False) -> CkfFit:
    """A session's readings through :class:`CubatureCalibrator`, one at a time.

    mag : (N, 3) float, raw units.

    First in time order as a live recording would (start from the first samples: see the
    module docstring). A session too short for that start (the field directions never span a
    hemisphere before it ends) is run once in a fixed pseudo-random order instead: that is
    the filter without the time correlation, as in Zhao et al.'s own simulation of random
    attitudes. Raises InsufficientDataError when the readings lie close to a plane or do not
    spread well beyond their noise (too little rotation, rest, or noise too large for the
    start: :func:`spread_problem` says which), unless ``force``. Refused rather than run
    shuffled when only the noise is at fault: the start's test is what keeps a noise cloud
    from being taken for a sphere, and at σ ≈ 20 % of the field the filter's linearised
    start is outside what it was tested on.
    """
    mag = norm_ellipsoid.check_readings(mag, "ckf")
    ckf = CubatureCalibrator()
    ckf.update_many(mag)
    if ckf.started:
        return CkfFit(ckf.estimate, "time", ckf.start_sample)
    prior = CkfPrior.from_readings(mag)
    problem = norm_ellipsoid.planarity_problem(mag, "ckf") or spread_problem(mag, prior.noise_std)
    if problem is not None and not force:
        raise InsufficientDataError(problem)
    ckf = CubatureCalibrator(prior)
    order = np.random.default_rng(SHUFFLE_SEED).permutation(mag.shape[0])
    ckf.update_many(mag[order])
    return CkfFit(ckf.estimate, "shuffled", None)


def calibration_ellipsoid(mag: np.ndarray, *, force: bool = False) -> tuple[EllipsoidFit, dict]:
    """The session's ellipsoid by the CKF (:func:`run_ckf`) in Algorithm 1's form, for the
    alignment step, and what the result file records about the run (JSON-ready dict)."""
    run = run_ckf(mag, force=force)
    e = run.estimate
    notes = ()
    if run.order == "shuffled":
        notes = (
            "ckf: the field directions did not span a hemisphere early enough for the filter "
            "to start in time order as it does live; it ran through the session in a "
            "pseudo-random order instead. Live, this recording would have shown no estimate: "
            "rotate through more orientations sooner",
        )
    fit = norm_ellipsoid.ellipsoid_fit_from(e.A, e.b, mag, "ckf", notes)
    details = {
        "A": e.A.tolist(),
        "b": e.b.tolist(),
        "state_std": np.sqrt(np.diag(e.P)).tolist(),
        "order": run.order,
        "start_sample": run.start_index,
        "noise_std": e.noise_std,
    }
    return fit, details
