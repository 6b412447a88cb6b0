# SPDX-License-Identifier: Apache-2.0
"""Coverage of the sphere of field directions while a magnetometer is rotated.

A calibration determines the ellipsoid ``y = D R m + o`` well only when the field has been
seen from many directions in the sensor frame. This module measures that, on raw readings,
while they are being recorded:

1. **Centre.** A raw reading is not a direction: the hard-iron offset ``o`` may be several
   times the field. Directions are taken relative to a running estimate ``c`` of the centre
   of the readings (:func:`estimate_centre`), refreshed every few samples by
   :class:`CoverageTracker`:

   - a linear least-squares sphere fit ``|y|^2 = 2 y.c + k`` (Kåsa fit, one 4x4 solve) when
     the readings spread in all three dimensions. It is unbiased on part of the sphere (a
     half-rotated sensor), which the mid-range is not, and the soft iron of a MEMS sensor
     (a few %) moves it by a few % of the field, not enough to move a direction to another
     cell;
   - otherwise (a yaw-only motion puts the readings on a circle, for which every centre on
     the circle's axis fits equally well) the mid-range of each axis, from the 1st and 99th
     percentiles so a few spikes do not move it. The mid-range of a full ellipsoid is exactly
     its centre; for a planar circle it puts the centre in the circle's plane, so the
     directions seen lie on a great circle and the uncovered poles are named by the hint,
     which is the right advice (tilt the sensor).

   Until the readings span at least ``min_extent`` (in the readings' unit) along some axis,
   there is no centre and no coverage: a sensor at rest gives one point, no direction.

2. **Cells.** An equal-area partition of the unit sphere (:func:`make_cells`), Leopardi's
   recursive zonal equal-area partition (EQSP, "A partition of the unit sphere into regions
   of equal area and small diameter", 2006) for the 2-sphere: two polar caps and collars of
   cells between circles of constant latitude, each cell of area exactly ``4 pi / n``, cells
   nearly square. The default is 100 cells (each about 20 degrees across), fine enough for
   a hint and coarse enough for one minute of hand rotation at 100 Hz to fill.

3. **Coverage** is the fraction of cells with at least ``min_count`` directions.

4. **Hint** (:func:`missing_hint`): the centre of the uncovered cell with the most uncovered
   cells within 45 degrees of it (the middle of the largest hole), phrased as the sensor axis
   (or pair of axes) that should point along the field: "point the sensor's +z axis along
   the field (north and steeply down in the northern hemisphere)". A direction ``d`` of the
   field in the sensor frame is the sensor axis ``d`` pointing along the field.

Everything is a pure function of numpy arrays except :class:`CoverageTracker`, which keeps the
readings and calls them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from magcal.errors import MagcalError

DEFAULT_CELLS = 100
#: Readings between two centre refreshes of CoverageTracker (at 100 Hz, twice a second).
CENTRE_REFRESH_SAMPLES = 50
#: Readings used by a centre refresh at most (evenly spaced over the history): the fit's
#: cost stays bounded in a long session.
CENTRE_MAX_SAMPLES = 4000
#: The sphere fit is used when the smallest principal spread of the readings is at least this
#: fraction of the largest (standard deviations); below, the mid-range.
SPHERE_FIT_MIN_SPREAD_RATIO = 0.15
#: Half-angle of the cap that measures a hole's size for the hint, degrees.
HINT_CAP_DEG = 45.0
#: Percentiles of the robust mid-range.
MID_RANGE_PERCENTILES = (1.0, 99.0)


# ------------------------------------------------------------------------------ partition
@dataclass(frozen=True)
class Cells:
    """An equal-area partition of the unit sphere into ``n`` cells.

    z_edges : (B + 1,) float, decreasing from 1 to -1: band b holds 1 >= z_edges[b] >= z >
        z_edges[b + 1] (the first band is the north polar cap, the last the south one)
    counts : (B,) int, cells per band (1 in each cap); sum = n
    first : (B,) int, index of each band's first cell; cells are numbered north to south,
        then by longitude from +x towards +y
    centres : (n, 3) float, unit vectors, each cell's centre (mid z, mid longitude)
    """

    z_edges: np.ndarray
    counts: np.ndarray
    first: np.ndarray
    centres: np.ndarray

    @property
    def n(self) -> int:
        return int(self.counts.sum())


def make_cells(n: int = DEFAULT_CELLS) -> Cells:
    """Leopardi's EQSP partition of the 2-sphere into ``n`` cells of area ``4 pi / n``.

    The polar caps have colatitude ``theta_c = 2 asin(sqrt(1/n))`` (area 4 pi / n each); the
    rest is divided into ``round((pi - 2 theta_c) / sqrt(4 pi / n))`` collars of equal
    colatitude height, whose ideal cell counts (collar area / cell area) are rounded with
    the rounding error carried to the next collar, so the counts add up to ``n``. Each
    collar's edges are then moved so its area is exactly its count times the cell area (by
    Archimedes, the area between two latitudes is 2 pi times the difference of z).
    """
    if n < 2:
        raise MagcalError(f"coverage: a partition needs at least 2 cells, got {n}")
    area = 4.0 * math.pi / n
    theta_c = 2.0 * math.asin(math.sqrt(1.0 / n))
    n_collars = max(0, round((math.pi - 2.0 * theta_c) / math.sqrt(area))) if n > 2 else 0
    counts = [1]
    if n_collars:
        height = (math.pi - 2.0 * theta_c) / n_collars
        carry = 0.0
        for i in range(n_collars):
            top, bottom = theta_c + i * height, theta_c + (i + 1) * height
            ideal = 2.0 * math.pi * (math.cos(top) - math.cos(bottom)) / area + carry
            k = max(1, round(ideal))
            carry = ideal - k
            counts.append(k)
    counts.append(1)
    counts_a = np.array(counts, dtype=np.int64)
    if counts_a.sum() != n:  # rounding carried to the end: fix the last collar
        counts_a[-2] += n - counts_a.sum()
    # Exact equal areas: z drops by 2 * count / n across each band.
    z_edges = 1.0 - 2.0 * np.concatenate([[0], np.cumsum(counts_a)]) / n
    z_edges[-1] = -1.0
    first = np.concatenate([[0], np.cumsum(counts_a)[:-1]])
    centres = []
    for b, k in enumerate(counts_a):
        if b == 0:
            z = 1.0  # a cap's centre is its pole
        elif b == len(counts_a) - 1:
            z = -1.0
        else:
            z = 0.5 * (z_edges[b] + z_edges[b + 1])
        r = math.sqrt(max(0.0, 1.0 - z * z))
        phi = (np.arange(k) + 0.5) * 2.0 * math.pi / k
        centres.append(np.column_stack([r * np.cos(phi), r * np.sin(phi), np.full(k, z)]))
    return Cells(z_edges, counts_a, first.astype(np.int64), np.concatenate(centres))


def cell_index(cells: Cells, u: np.ndarray) -> np.ndarray:
    """The cell of each direction.

    u : (N, 3) float, directions (need not be unit: only the direction counts; zero vectors
        go to the north cap). Returns (N,) int64 in [0, cells.n).
    """
    u = np.asarray(u, dtype=np.float64).reshape(-1, 3)
    norm = np.linalg.norm(u, axis=1)
    z = np.divide(u[:, 2], norm, out=np.ones_like(norm), where=norm > 0)
    # band b: z_edges[b] >= z > z_edges[b + 1]; searchsorted on the increasing -z_edges.
    band = np.searchsorted(-cells.z_edges, -z, side="left") - 1
    band = np.clip(band, 0, len(cells.counts) - 1)
    phi = np.mod(np.arctan2(u[:, 1], u[:, 0]), 2.0 * math.pi)
    k = cells.counts[band]
    sector = np.minimum((phi / (2.0 * math.pi) * k).astype(np.int64), k - 1)
    return cells.first[band] + sector


def cell_counts(cells: Cells, u: np.ndarray) -> np.ndarray:
    """(n,) int64: how many of the directions u (N, 3) fall in each cell."""
    return np.bincount(cell_index(cells, u), minlength=cells.n)


def coverage_fraction(counts: np.ndarray, min_count: int = 1) -> float:
    """Fraction of cells with at least ``min_count`` directions (counts: (n,) int)."""
    counts = np.asarray(counts)
    return float(np.count_nonzero(counts >= min_count)) / counts.size if counts.size else 0.0


# ------------------------------------------------------------------------------ centre
def mid_range(y: np.ndarray) -> np.ndarray:
    """(3,) the robust mid-range of each axis of y (N, 3): the mean of its 1st and 99th
    percentiles (same unit as y)."""
    lo, hi = np.percentile(np.asarray(y, dtype=np.float64), MID_RANGE_PERCENTILES, axis=0)
    return 0.5 * (lo + hi)


def sphere_fit(y: np.ndarray) -> np.ndarray | None:
    """The centre (3,) of the least-squares sphere ``|y - c|^2 = r^2`` through y (N, 3), or
    None when the readings do not spread in three dimensions (see the module docstring).

    Linear in (c, k = r^2 - |c|^2): ``2 y.c + k = |y|^2``. The readings are centred on their
    mean first (the fit is then well scaled whatever the offset) and solved with lstsq.
    """
    y = np.asarray(y, dtype=np.float64)
    if y.shape[0] < 10:
        return None
    mean = y.mean(axis=0)
    x = y - mean
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(x.T)), 0.0))
    if spread[-1] <= 0 or spread[0] < SPHERE_FIT_MIN_SPREAD_RATIO * spread[-1]:
        return None
    a = np.column_stack([2.0 * x, np.ones(len(x))])
    sol, *_ = np.linalg.lstsq(a, np.einsum("ij,ij->i", x, x), rcond=None)
    return mean + sol[:3]


def estimate_centre(y: np.ndarray, min_extent: float) -> np.ndarray | None:
    """The centre of the readings y (N, 3) (sphere fit, else mid-range; module docstring), or
    None while their largest per-axis extent (99th - 1st percentile) is below ``min_extent``
    (same unit as y)."""
    y = np.asarray(y, dtype=np.float64)
    if y.shape[0] < 2:
        return None
    lo, hi = np.percentile(y, MID_RANGE_PERCENTILES, axis=0)
    if float(np.max(hi - lo)) < min_extent:
        return None
    c = sphere_fit(y)
    return c if c is not None else 0.5 * (lo + hi)


# ------------------------------------------------------------------------------ hint
_AXES = ("x", "y", "z")


def axis_phrase(d: np.ndarray) -> str:
    """The sensor axis, or pair of axes, nearest the direction d (3,): "+z", "+x-z"."""
    d = np.asarray(d, dtype=np.float64)
    d = d / np.linalg.norm(d)
    order = np.argsort(-np.abs(d))
    parts = [order[0]]
    # A second axis when the direction lies between two (more than ~25 degrees off the first).
    if abs(d[order[1]]) >= 0.42:
        parts.append(order[1])
    return "".join(("+" if d[i] >= 0 else "-") + _AXES[i] for i in parts)


def largest_hole(cells: Cells, counts: np.ndarray, min_count: int = 1) -> np.ndarray | None:
    """The centre (3,) of the uncovered cell with the most uncovered cells within
    HINT_CAP_DEG of it, or None when every cell is covered."""
    empty = np.asarray(counts) < min_count
    if not empty.any():
        return None
    c = cells.centres
    near = (c[empty] @ c[empty].T) >= math.cos(math.radians(HINT_CAP_DEG))
    best = int(np.argmax(near.sum(axis=1)))
    return c[empty][best]


def missing_hint(cells: Cells, counts: np.ndarray, min_count: int = 1) -> str:
    """A short instruction naming the largest uncovered region of field directions."""
    d = largest_hole(cells, counts, min_count)
    if d is None:
        return "all directions covered"
    return f"point the sensor's {axis_phrase(d)} axis along the field"


# ------------------------------------------------------------------------------ tracker
@dataclass(frozen=True)
class CoverageState:
    """coverage : fraction of cells covered (0..1); hint : what to do next; centre : (3,)
    the running centre (reading units) or None before there is one."""

    coverage: float
    hint: str
    centre: np.ndarray | None
    counts: np.ndarray


class CoverageTracker:
    """Running coverage of raw magnetometer readings (see the module docstring).

    min_extent : readings must span this much along some axis (their unit) before they give
        directions; for readings in uT, 10 uT (a quarter turn in the Earth's field)
    """

    def __init__(
        self,
        min_extent: float,
        n_cells: int = DEFAULT_CELLS,
        min_count: int = 1,
        refresh_samples: int = CENTRE_REFRESH_SAMPLES,
    ) -> None:
        self.cells = make_cells(n_cells)
        self.min_extent = min_extent
        self.min_count = min_count
        self.refresh_samples = refresh_samples
        self._chunks: list[np.ndarray] = []
        self._n = 0
        self._n_at_refresh = 0
        self._state = CoverageState(0.0, "rotate the sensor", None, np.zeros(self.cells.n, int))

    def add(self, y: np.ndarray) -> None:
        """Add readings y (N, 3) in the tracker's unit."""
        y = np.asarray(y, dtype=np.float64).reshape(-1, 3)
        if len(y):
            self._chunks.append(y)
            self._n += len(y)

    @property
    def readings(self) -> int:
        """Readings added so far."""
        return self._n

    def state(self, force: bool = False) -> CoverageState:
        """The coverage now; the centre and cells are recomputed every refresh_samples."""
        if self._n and (force or self._n - self._n_at_refresh >= self.refresh_samples):
            self._refresh()
        return self._state

    def _refresh(self) -> None:
        if len(self._chunks) > 1:
            self._chunks = [np.concatenate(self._chunks)]
        y = self._chunks[0]
        self._n_at_refresh = self._n
        step = max(1, len(y) // CENTRE_MAX_SAMPLES)
        centre = estimate_centre(y[::step], self.min_extent)
        if centre is None:
            counts = np.zeros(self.cells.n, dtype=np.int64)
            self._state = CoverageState(0.0, "rotate the sensor", None, counts)
            return
        counts = cell_counts(self.cells, y - centre)
        self._state = CoverageState(
            coverage_fraction(counts, self.min_count),
            missing_hint(self.cells, counts, self.min_count),
            centre,
            counts,
        )


class AttitudeCoverage:
    """Coverage of the field directions the vehicle really took, from its attitude.

    A centre fitted to raw readings can be fooled: around a small cloud of noisy readings of
    a still sensor, the noise points everywhere. Here the directions come from the attitude
    integrated from the gyroscope instead: each sample i brings its rotation ``R_i`` (body to
    the start frame) with its reading ``y_i``; the field's direction in the start frame is
    ``f = normalise(mean_i R_i u_i)`` with ``u_i`` the unit reading about the raw tracker's
    centre (:class:`CoverageTracker`), and the directions counted are ``R_iᵀ f``, the field in
    the body frame at the orientations the vehicle took. A still vehicle gives one direction,
    a yaw-only motion one circle, whatever its readings do. Without a raw centre (readings
    spanning less than ``min_extent``) there is no coverage, as for :class:`CoverageTracker`.

    ``add(y, rotations)`` the readings (N, 3) and their rotations (N, 3, 3); ``state()`` as
    CoverageTracker's.
    """

    def __init__(self, min_extent: float, n_cells: int = DEFAULT_CELLS, min_count: int = 1):
        self.raw = CoverageTracker(min_extent, n_cells, min_count)
        self.cells = self.raw.cells
        self.min_count = min_count
        self._y: list[np.ndarray] = []
        self._R: list[np.ndarray] = []
        self._n_at_refresh = 0
        self._state = self.raw.state()

    def add(self, y: np.ndarray, rotations: np.ndarray) -> None:
        y = np.asarray(y, dtype=np.float64).reshape(-1, 3)
        R = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        if y.shape[0] != R.shape[0]:
            raise MagcalError(f"coverage: {y.shape[0]} readings but {R.shape[0]} rotations")
        if len(y):
            self.raw.add(y)
            self._y.append(y)
            self._R.append(R)

    def state(self, force: bool = False) -> CoverageState:
        raw = self.raw.state(force)
        n = self.raw.readings
        if not n or not (force or n - self._n_at_refresh >= self.raw.refresh_samples):
            return self._state
        self._n_at_refresh = n
        if raw.centre is None:
            self._state = raw
            return raw
        y, R = np.concatenate(self._y), np.concatenate(self._R)
        self._y, self._R = [y], [R]
        u = y - raw.centre
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
        f = np.einsum("nij,nj->i", R, u)
        f /= max(float(np.linalg.norm(f)), 1e-300)
        counts = cell_counts(self.cells, np.einsum("nji,j->ni", R, f))
        self._state = CoverageState(
            coverage_fraction(counts, self.min_count),
            missing_hint(self.cells, counts, self.min_count),
            raw.centre,
            counts,
        )
        return self._state
