# SPDX-License-Identifier: Apache-2.0
"""Step 1b of Kok & Schön (2016), Section 6.1: fit an ellipsoid to the magnetometer data.

The magnetometer model ``y = D R_bn m_n + o`` with ``‖m_n‖ = 1`` puts the data on the
ellipsoid ``‖D⁻¹(y − o)‖ = 1``, i.e. (paper eq. 19–20, all up to one common scale)

    yᵀ A y + bᵀ y + c = 0,   A = D⁻ᵀ D⁻¹,   b = −2 A o,   c = oᵀ A o − 1.

Inverting (the paper's eq. 24 has two misprints; see ``docs/algorithm.md``): for any common scale
``s`` of ``(A, b, c)``,

    o      = −½ A⁻¹ b,
    β      = ¼ bᵀ A⁻¹ b − c          (= s),
    D̃ D̃ᵀ  = β A⁻¹                   (= D Dᵀ),

and ``D̃`` is taken lower-triangular by Cholesky. ``D = D̃ U`` for some orthogonal ``U``;
:mod:`magcal.calib.initial.alignment` finds the rotation.

Numerical choices:

* The data are centred (mean) and scaled (RMS radius) before fitting and the result is
  mapped back exactly; raw counts with offsets several times the field are otherwise badly
  conditioned.
* The N × 10 design matrix never reaches the solver: the SDP objective ``½‖M ξ‖²`` equals
  ``½‖R ξ‖²`` for any ``R`` with ``RᵀR = MᵀM``, so a 10 × 10 factor of the Gram matrix is
  passed instead and the solve time does not depend on N.
* Symmetric ``A`` has 6 unknowns; the off-diagonal columns of ``M`` are doubled so that
  ``M ξ`` is exactly ``yᵀAy + bᵀy + c``.
* Where the constraint ``A ⪰ 0`` is inactive (data all round the ellipsoid: the usual case)
  the SDP's optimum is the least-squares solution under ``tr A = 1`` alone, one 11 × 11
  linear system, and the interior-point solver is not run. It runs when that solution's
  ``A`` is not safely positive definite (readings over too few directions) and for forced
  fits; its positive semidefinite cone then also loads scipy's LAPACK, which takes longer
  than the rest of the calibration's imports.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import clarabel
import numpy as np

from magcal.errors import CalibrationError, InsufficientDataError

#: Fewest samples for a fit (10 unknowns up to scale; anything near this is far too few in
#: practice, the observability check asks for much more).
MIN_SAMPLES = 10

#: Smallest accepted ratio of the smallest to the largest eigenvalue of the fitted ``A``
#: (in the normalised coordinates). The eigenvalues go as 1/axis², so 1e-3 allows axis
#: ratios up to about 30 — far beyond any real soft-iron distortion. Below it the data lie
#: on (or near) a plane or a line: the sensor was not rotated enough.
MIN_A_EIG_RATIO = 1e-3

#: Smallest accepted ratio of the smallest to the largest eigenvalue of the data covariance.
#: Data on a plane (a single circle: yaw-only motion) lie on infinitely many ellipsoids, all
#: fitting exactly, so a positive definite ``A`` alone does not prove the fit is determined.
#: 1e-3 means the thinnest direction of the cloud has a standard deviation of about 3 % of the
#: widest; the observability check refuses much earlier (its threshold is 0.03).
MIN_DATA_EIG_RATIO = 1e-3

#: ``force=True`` on degenerate data: weight ρ of the ridge ``½ρ(‖A − I/3‖² + ε‖b‖²)`` (in
#: the normalised coordinates) that picks, among the many near-equally good quadrics, the one
#: closest to a sphere, relative to the mean eigenvalue of the Gram matrix ``MᵀM/N`` ...
FORCED_RIDGE = 0.1
#: ... and ε, much smaller: it only pins the centre where the data leave it free (for data
#: on a circle, the sphere through the circle centred in its plane).
FORCED_RIDGE_B = 1e-3

#: Relative size of the smallest eigenvalue of ``A`` (trace 1) above which the PSD
#: constraint of the SDP counts as inactive, so that the equality-constrained least-squares
#: solution is the SDP's optimum: taken as it is, or used to polish an interior-point
#: solution to full precision.
PD_INACTIVE_EIG = 1e-6

#: Rows per block when accumulating the Gram matrix (bounds the temporary memory to
#: about 5 MB whatever N is).
_GRAM_BLOCK_ROWS = 65536

_SOLVER_NAME = "CLARABEL"
#: Clarabel's statuses with a solution (its own "almost": solved to its reduced tolerances) ...
_SOLVED = ("Solved", "AlmostSolved")
#: ... and those where the solver itself failed rather than finding the problem infeasible.
_SOLVER_FAILED = ("NumericalError", "InsufficientProgress", "Unsolved")

#: Clarabel's PSD cone holds a symmetric matrix as its upper triangle, column by column, with
#: the off-diagonal entries times √2 (so that inner products are the matrices' ones):
#: (A11, √2 A12, A22, √2 A13, √2 A23, A33). Their positions in ξ and their weights:
_SVEC_XI = np.array([0, 3, 1, 4, 5, 2])
_SVEC_WEIGHT = np.array([1.0, np.sqrt(2.0), 1.0, np.sqrt(2.0), np.sqrt(2.0), 1.0])


@dataclass(frozen=True, eq=False)
class EllipsoidFit:
    """An ellipsoid ``yᵀ A y + bᵀ y + c = 0`` and its centre/shape form.

    A          : (3, 3) float, symmetric positive definite, scaled so that ``tr A = 1``,
                 (raw magnetometer units)⁻²
    b          : (3,) float, same common scale, (raw units)⁻¹
    c          : float, same common scale, dimensionless
    o          : (3,) float, centre (hard-iron offset), raw magnetometer units
    D_tilde    : (3, 3) float, lower-triangular Cholesky factor, ``D̃ D̃ᵀ = D Dᵀ``, raw units
                 (``D̃⁻¹(y − o)`` has unit norm on the ellipsoid)
    method     : ``"sdp"`` or ``"algebraic"`` (or ``"ckf"``, ``"two-step"``: see
                 :func:`magcal.calib.norm_only.norm_ellipsoid.ellipsoid_fit_from`)
    radius_rms : float, dimensionless, RMS of ``‖D̃⁻¹(y_t − o)‖ − 1`` over the data
    a_eig_ratio: float, smallest/largest eigenvalue of ``A`` in the normalised coordinates
                 (1 for a sphere; near 0 for data on a plane)
    warnings   : tuple of str; non-empty only for a fit forced on degenerate data
    """

    A: np.ndarray
    b: np.ndarray
    c: float
    o: np.ndarray
    D_tilde: np.ndarray
    method: str
    radius_rms: float
    a_eig_ratio: float
    warnings: tuple[str, ...] = ()


# --------------------------------------------------------------------------- helpers


def _check_mag(mag: np.ndarray) -> np.ndarray:
    mag = np.asarray(mag, dtype=float)
    if mag.ndim != 2 or mag.shape[1] != 3:
        raise ValueError(f"mag must have shape (N, 3), got {mag.shape}")
    n = mag.shape[0]
    if n < MIN_SAMPLES:
        raise InsufficientDataError(
            f"ellipsoid fit: {n} magnetometer samples; the fit needs at least {MIN_SAMPLES} "
            "(in practice thousands): record longer while rotating the sensor"
        )
    if not np.all(np.isfinite(mag)):
        raise CalibrationError(
            "ellipsoid fit: the magnetometer data contain NaN or infinite values: "
            "remove or interpolate the bad samples first"
        )
    return mag


def _normalise(mag: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre and scale: ``z = (y − μ)/s``, μ the mean, ``s`` the RMS radius about μ."""
    mu = mag.mean(axis=0)
    z = mag - mu
    s = float(np.sqrt(np.mean(np.einsum("ij,ij->i", z, z))))
    if not s > 0.0:
        raise InsufficientDataError(
            "ellipsoid fit: all magnetometer samples are identical: check that the "
            "magnetometer is working and rotate the sensor through all orientations"
        )
    return z / s, mu, s


def _planarity_problem(z: np.ndarray) -> str | None:
    """A message if the (normalised) data lie close to a plane or a line, else None."""
    eig = np.linalg.eigvalsh(z.T @ z / z.shape[0])
    if eig[0] >= MIN_DATA_EIG_RATIO * eig[-1]:
        return None
    return (
        f"ellipsoid fit: the magnetometer data lie close to a plane or a line (covariance "
        f"eigenvalue ratio {eig[0] / eig[-1]:.2g} < {MIN_DATA_EIG_RATIO:g}), which many "
        "ellipsoids fit equally well: the sensor was rotated too little; rotate it through "
        "all orientations (tilt it nose up/down and roll it over, not only yaw)"
    )


def _design_rows(z: np.ndarray, off_diag_weight: float) -> np.ndarray:
    """Rows ``[z1², z2², z3², w z1z2, w z1z3, w z2z3, z1, z2, z3, 1]``, (n, 10)."""
    x, y, w = z[:, 0], z[:, 1], z[:, 2]
    k = off_diag_weight
    return np.column_stack(
        [x * x, y * y, w * w, k * x * y, k * x * w, k * y * w, x, y, w, np.ones_like(x)]
    )


def _gram(z: np.ndarray, off_diag_weight: float) -> np.ndarray:
    """``MᵀM / N`` (10, 10), accumulated in blocks."""
    g = np.zeros((10, 10))
    for start in range(0, z.shape[0], _GRAM_BLOCK_ROWS):
        m = _design_rows(z[start : start + _GRAM_BLOCK_ROWS], off_diag_weight)
        g += m.T @ m
    g /= z.shape[0]
    return 0.5 * (g + g.T)


def _gram_factor(g: np.ndarray) -> np.ndarray:
    """``R`` (10, 10) with ``RᵀR = G``. An eigen-factor rather than Cholesky: ``G`` is
    singular for noise-free data (the ellipsoid is then an exact null vector)."""
    lam, v = np.linalg.eigh(g)
    return np.sqrt(np.clip(lam, 0.0, None))[:, None] * v.T


def _unpack(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    a11, a22, a33, a12, a13, a23 = xi[:6]
    A = np.array([[a11, a12, a13], [a12, a22, a23], [a13, a23, a33]])
    return A, np.array(xi[6:9], dtype=float), float(xi[9])


def _trace_vector() -> np.ndarray:
    t = np.zeros(10)
    t[:3] = 1.0
    return t


def _cho_solve(L: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``A⁻¹ rhs`` from the Cholesky factor ``L`` (3, 3) of ``A``: two triangular solves
    (numpy's general solve: at 3 × 3 as exact as a triangular one)."""
    return np.linalg.solve(L.T, np.linalg.solve(L, rhs))


def _centre_shape(A: np.ndarray, b: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray] | None:
    """``o = −½ A⁻¹ b`` and lower-triangular ``D̃`` with ``D̃D̃ᵀ = (¼ bᵀA⁻¹b − c) A⁻¹``.

    Returns None when ``A`` is not (numerically) positive definite or
    ``β = ¼ bᵀA⁻¹b − c ≤ 0``: the quadric is then not a real ellipsoid.
    """
    try:
        L = np.linalg.cholesky(A)  # solves with the factor rather than inv
    except np.linalg.LinAlgError:
        return None
    a_inv_b = _cho_solve(L, b)
    o = -0.5 * a_inv_b
    beta = 0.25 * float(b @ a_inv_b) - c
    if not beta > 0.0:
        return None
    a_inv = _cho_solve(L, np.eye(3))
    dd = beta * 0.5 * (a_inv + a_inv.T)
    try:
        D_tilde = np.linalg.cholesky(dd)
    except np.linalg.LinAlgError:
        return None
    return o, D_tilde


def _finish(
    xi: np.ndarray, mag: np.ndarray, mu: np.ndarray, s: float, method: str
) -> tuple[EllipsoidFit | None, str | None]:
    """Map a solution in normalised coordinates back to raw units and package it.

    Returns ``(fit, problem)``: ``problem`` names a near-singular ``A`` (the fit is still
    returned) or a quadric that is not a real ellipsoid (``β ≤ 0``; fit None).
    """
    A_s, b_s, c_s = _unpack(xi)
    scale = np.trace(A_s)
    A_s, b_s, c_s = A_s / scale, b_s / scale, c_s / scale
    eig = np.linalg.eigvalsh(A_s)
    ratio = float(eig[0] / eig[-1]) if eig[-1] > 0 else 0.0
    problem = None
    if ratio < MIN_A_EIG_RATIO:
        problem = (
            f"ellipsoid fit ({method}): the fitted ellipsoid is degenerate (eigenvalue ratio "
            f"{ratio:.2g} < {MIN_A_EIG_RATIO:g}): the magnetometer data lie close to a plane "
            "or a line because the sensor was rotated too little; rotate it through all "
            "orientations (tilt it nose up/down and roll it over, not only yaw)"
        )
    if eig[0] <= 0.0:
        return None, problem
    shape = _centre_shape(A_s, b_s, c_s)
    if shape is None:
        return None, (
            "ellipsoid fit: the fitted quadric is not a real ellipsoid (empty set): the "
            "magnetometer data do not cover enough directions; rotate the sensor through all "
            "orientations (tilt it nose up/down and roll it over, not only yaw)"
        )
    o_s, D_s = shape
    # Back to raw units: y = μ + s z. The centre and shape map directly ...
    o = mu + s * o_s
    D_tilde = s * D_s
    # ... and (A, b, c) by substituting z = (y − μ)/s, then renormalising to tr A = 1.
    A = A_s / s**2
    b = b_s / s - 2.0 * A @ mu
    c = float(mu @ A @ mu - b_s @ mu / s + c_s)
    tr = np.trace(A)
    A, b, c = A / tr, b / tr, c / tr
    u = np.linalg.solve(D_tilde, (mag - o).T)  # 3 × 3: a general solve is as exact
    radius_rms = float(np.sqrt(np.mean((np.linalg.norm(u, axis=0) - 1.0) ** 2)))
    fit = EllipsoidFit(
        A=0.5 * (A + A.T),
        b=b,
        c=c,
        o=o,
        D_tilde=D_tilde,
        method=method,
        radius_rms=radius_rms,
        a_eig_ratio=ratio,
    )
    return fit, problem


class _CscMatrix(NamedTuple):
    """A matrix in compressed sparse column form, with the attributes Clarabel's Python
    interface reads from a ``scipy.sparse.csc_matrix`` (built here: scipy.sparse takes
    longer to import than the whole fit). Column by column, rows ascending within a column,
    no duplicates, zeros left out.

    data    : (nnz,) float, the stored entries
    indices : (nnz,) int64, their rows
    indptr  : (ncols + 1,) int64, where each column's entries start in ``data``
    shape   : (nrows, ncols)
    """

    data: np.ndarray
    indices: np.ndarray
    indptr: np.ndarray
    shape: tuple[int, int]
    #: Sorted and without duplicates by construction; Clarabel checks it.
    has_canonical_format: bool = True

    @property
    def nnz(self) -> int:
        return int(self.data.size)

    @classmethod
    def from_dense(cls, a: np.ndarray) -> _CscMatrix:
        """The non-zero entries of ``a`` (nrows, ncols)."""
        a = np.asarray(a, dtype=float)
        cols, rows = np.nonzero(a.T)  # row-major over aᵀ: column by column, rows ascending
        indptr = np.searchsorted(cols, np.arange(a.shape[1] + 1))
        return cls(a.T[cols, rows], rows.astype(np.int64), indptr.astype(np.int64), tuple(a.shape))


def _solve_sdp(r: np.ndarray, ridge: float = 0.0) -> np.ndarray:
    """``min ½‖R ξ‖² s.t. tr A = 1, A ⪰ 0`` with Clarabel (an interior-point solver).

    ``ridge`` > 0 adds ``½ ridge (‖A − I/3‖²_F + FORCED_RIDGE_B ‖b‖²)`` (see
    :data:`FORCED_RIDGE`).

    Clarabel's standard form is ``min ½ xᵀPx + qᵀx s.t. Ax + s = b, s ∈ K`` with ``x = ξ``:
    ``P = RᵀR`` (the ridge adds to ``P`` and ``q``), one zero-cone row for the trace and
    ``s = svec(A)`` in the cone of 3 × 3 positive semidefinite matrices.
    """
    p, q = _sdp_objective(r, ridge)
    # Rows: tr A = 1 (zero cone), then s = svec(A) (PSD cone), i.e. A_con = −svec, b = 0.
    a_con = np.zeros((1 + len(_SVEC_XI), 10))
    a_con[0, :3] = 1.0
    a_con[1 + np.arange(len(_SVEC_XI)), _SVEC_XI] = -_SVEC_WEIGHT
    b_con = np.zeros(a_con.shape[0])
    b_con[0] = 1.0
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    try:
        solver = clarabel.DefaultSolver(
            _CscMatrix.from_dense(np.triu(p)),  # Clarabel reads P's upper triangle
            q,
            _CscMatrix.from_dense(a_con),
            b_con,
            [clarabel.ZeroConeT(1), clarabel.PSDTriangleConeT(3)],
            settings,
        )
        solution = solver.solve()
    except Exception as exc:  # the solver's own refusal, raised as a plain Exception
        raise CalibrationError(
            f"ellipsoid fit: the SDP solver {_SOLVER_NAME} failed ({exc}); check the "
            "magnetometer data for outliers, or install/upgrade clarabel"
        ) from exc
    status = str(solution.status)
    if status in _SOLVER_FAILED:
        raise CalibrationError(
            f"ellipsoid fit: the SDP solver {_SOLVER_NAME} failed ({status}); check the "
            "magnetometer data for outliers, or install/upgrade clarabel"
        )
    if status not in _SOLVED:
        raise CalibrationError(
            f"ellipsoid fit: the SDP solver {_SOLVER_NAME} ended with status "
            f"'{status}'; check the magnetometer data for outliers and rotate the "
            "sensor through all orientations"
        )
    return np.asarray(solution.x, dtype=float)


def _sdp_objective(r: np.ndarray, ridge: float) -> tuple[np.ndarray, np.ndarray]:
    """``P`` (10, 10) and ``q`` (10,) with ``½ ξᵀPξ + qᵀξ`` the SDP's objective (up to a
    constant): ``½‖R ξ‖²``, plus the ridge of :func:`_solve_sdp` when ``ridge`` > 0."""
    p = r.T @ r
    q = np.zeros(10)
    if ridge > 0.0:
        # ‖A − I/3‖²_F = Σ (A_ii − ⅓)² + 2 Σ_{i<j} A_ij² (ξ holds each off-diagonal once).
        p += ridge * np.diag([1.0, 1.0, 1.0, 2.0, 2.0, 2.0, *3 * [FORCED_RIDGE_B], 0.0])
        q[:3] = -ridge / 3.0
    return 0.5 * (p + p.T), q


def _trace_constrained_minimiser(g: np.ndarray) -> np.ndarray | None:
    """The minimiser (10,) of ``ξᵀGξ`` subject only to ``tr A = 1``, from its linear KKT
    system; None when that system is singular or its solution not finite.

    If its ``A`` is positive definite it is feasible for the SDP and, by convexity, the
    SDP's exact optimum (an interior-point solution only approximates it, to about the
    solver's tolerance).
    """
    t = _trace_vector()
    kkt = np.zeros((11, 11))
    kkt[:10, :10] = g
    kkt[:10, 10] = t
    kkt[10, :10] = t
    rhs = np.zeros(11)
    rhs[10] = 1.0
    try:
        sol = np.linalg.solve(kkt, rhs)
    except np.linalg.LinAlgError:
        return None
    cand = sol[:10]
    if not np.all(np.isfinite(cand)):
        return None
    return cand


def _inactive_constraint_optimum(g: np.ndarray) -> np.ndarray | None:
    """The SDP's optimum ξ (10,) without the interior-point solver, when the constraint
    ``A ⪰ 0`` is inactive: :func:`_trace_constrained_minimiser` if its ``A`` has a smallest
    eigenvalue of at least :data:`PD_INACTIVE_EIG` (trace 1), else None."""
    cand = _trace_constrained_minimiser(g)
    if cand is None:
        return None
    A, _, _ = _unpack(cand)
    if np.linalg.eigvalsh(A)[0] < PD_INACTIVE_EIG * np.trace(A):
        return None
    return cand


def _polish(g: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Polish an interior-point SDP solution whose PSD constraint is inactive: returns
    :func:`_trace_constrained_minimiser` where that is the optimum and no worse than ``xi``,
    or ``xi`` itself when the constraint is (nearly) active."""
    A, _, _ = _unpack(xi)
    if np.linalg.eigvalsh(A)[0] < PD_INACTIVE_EIG * np.trace(A):
        return xi
    cand = _trace_constrained_minimiser(g)
    if cand is None:
        return xi
    A_c, _, _ = _unpack(cand)
    if np.linalg.eigvalsh(A_c)[0] <= 0.0:
        return xi
    xi_n = xi / np.trace(A)
    if cand @ g @ cand > xi_n @ g @ xi_n + 1e-12 * (1.0 + abs(xi_n @ g @ xi_n)):
        return xi
    return cand


# --------------------------------------------------------------------------- public API


def fit_ellipsoid_sdp(mag: np.ndarray, *, force: bool = False) -> EllipsoidFit:
    """Ellipsoid fit as the SDP ``min ½‖M ξ‖² s.t. tr A = 1, A ⪰ 0`` (paper eq. 23).

    mag   : (N, 3) float, raw magnetometer units.
    force : on data that do not determine an ellipsoid, return a fit regularised towards a
            sphere (see :data:`FORCED_RIDGE`) with a warning instead of raising; for
            ``--force`` on a session the observability check refused.

    Returns an :class:`EllipsoidFit` in raw units; ``D_tilde`` is lower-triangular and
    ``D_tilde⁻¹ (y − o)`` lies on the unit sphere up to noise. Where ``A ⪰ 0`` is inactive
    the optimum comes from a linear system, without the interior-point solver (see the
    module's numerical choices).

    Raises :class:`InsufficientDataError` when the data do not determine an ellipsoid
    (data on or near a plane or a line, a near-singular ``A``, not a real ellipsoid: too
    little rotation) unless ``force``, and for too few or identical samples; raises
    :class:`CalibrationError` when the solver fails or the data are not finite.
    """
    mag = _check_mag(mag)
    z, mu, s = _normalise(mag)
    g = _gram(z, off_diag_weight=2.0)
    r = _gram_factor(g)
    problem = _planarity_problem(z)
    if problem is None:
        xi = _inactive_constraint_optimum(g)
        if xi is None:  # A ⪰ 0 binds, or nearly: the interior-point solver
            xi = _polish(g, _solve_sdp(r))
        fit, problem = _finish(xi, mag, mu, s, "sdp")
        if problem is None:
            return fit
    if not force:
        raise InsufficientDataError(problem)
    xi = _solve_sdp(r, ridge=FORCED_RIDGE * float(np.trace(g)) / 10.0)
    fit, still = _finish(xi, mag, mu, s, "sdp")
    if fit is None:
        raise InsufficientDataError(f"{problem} (a regularised fit failed too: {still})")
    warning = (
        f"{problem}. Forced: the fit is regularised towards a sphere, so the scale and "
        "offset along the directions the data do not cover are guesses"
    )
    return dataclasses.replace(fit, warnings=(warning,))


def fit_ellipsoid_algebraic(mag: np.ndarray) -> EllipsoidFit | None:
    """Plain algebraic fit: ``min ‖M ξ‖ s.t. ‖ξ‖ = 1`` (smallest eigenvector), no PD constraint.

    mag : (N, 3) float, raw magnetometer units.

    ``‖ξ‖`` is the norm of ``(vec A, b, c)`` with both copies of each off-diagonal of ``A``
    (as in the paper's eq. 22), taken in the same normalised coordinates as the SDP fit.

    Returns None when the fitted ``A`` is not positive definite, or the quadric is not a real
    ellipsoid — the cases the SDP formulation exists to avoid. A positive definite but
    near-singular fit is returned (see ``a_eig_ratio``), not refused: this function is for
    comparison. Raises like :func:`fit_ellipsoid_sdp` for bad input (too few samples,
    non-finite or identical samples, data on a plane or a line).
    """
    mag = _check_mag(mag)
    z, mu, s = _normalise(mag)
    problem = _planarity_problem(z)
    if problem is not None:
        raise InsufficientDataError(problem)
    # With off-diagonal columns scaled by √2 the unknowns are (A11, A22, A33, √2 A12, ...),
    # whose Euclidean norm is ‖(vec A, b, c)‖.
    root2 = np.sqrt(2.0)
    g = _gram(z, off_diag_weight=root2)
    _, vecs = np.linalg.eigh(g)
    xi = vecs[:, 0].copy()
    xi[3:6] /= root2
    A, _, _ = _unpack(xi)
    if np.trace(A) < 0.0:
        xi = -xi
        A = -A
    if np.linalg.eigvalsh(A)[0] <= 0.0:
        return None
    fit, _ = _finish(xi, mag, mu, s, "algebraic")
    return fit


def symmetric_fit(fit: EllipsoidFit) -> np.ndarray:
    """The plain symmetric ellipsoid correction used by simple tools, (3, 3), raw units.

    ``D_sym = (D̃ D̃ᵀ)^½``, the symmetric positive definite square root: the same ellipsoid,
    with no estimate of the rotation between the magnetometer and the inertial axes.
    """
    dd = fit.D_tilde @ fit.D_tilde.T
    lam, v = np.linalg.eigh(0.5 * (dd + dd.T))
    return (v * np.sqrt(np.clip(lam, 0.0, None))) @ v.T
