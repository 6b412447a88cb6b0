# SPDX-License-Identifier: Apache-2.0
"""What the live page draws, as plain JSON-ready dictionaries.

:class:`CompassView` keeps one compass's picture from the progress reports of a recorder
(:class:`magcal.device.collect.CollectProgress`): the figures and the coverage exactly as
the terminal shows them (the report's own :meth:`~magcal.device.collect.CollectProgress.figures`
and :meth:`~magcal.device.collect.CollectProgress.coverage_percent`), the coverage's cells
(:func:`magcal.device.coverage.make_cells`, the partition the tracker counts in) with their
counts, the field directions seen (readings about the tracker's centre, a bounded
sample of them), the instruction, and the direction of the largest hole with the sensor
face to turn towards the field (:func:`magcal.device.coverage.largest_hole`,
:func:`~magcal.device.coverage.axis_phrase`, the same as the hint's).

:func:`result_spheres` is the picture once collection has ended: the readings before and
after the ellipsoid fit of :mod:`magcal.calib.initial.ellipsoid`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magcal.device.collect import CollectProgress
from magcal.device.coverage import axis_phrase, largest_hole, make_cells
from magcal.errors import MagcalError

#: Field directions a panel keeps at most (every k-th reading, k doubling as it fills): a
#: sphere of this many points shows every hole and stays light to send a few times a second.
MAX_POINTS = 1500
#: Decimals of the unit vectors sent to the page (0.001 of the field: well below a pixel).
DIRECTION_DECIMALS = 3


def _directions(y: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Unit vectors (N, 3) of the readings y (N, 3) about ``centre`` (3,), same unit."""
    d = np.asarray(y, dtype=np.float64) - centre
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)


def _thin(y: np.ndarray, limit: int = MAX_POINTS) -> np.ndarray:
    """At most ``limit`` rows of y, evenly spaced over it."""
    if len(y) <= limit:
        return y
    return y[np.linspace(0, len(y) - 1, limit).round().astype(np.int64)]


class CompassView:
    """One compass's panel (see the module docstring). ``add(progress)`` each report;
    ``snapshot()`` the panel as a dictionary for the page.

    name : the panel's title ("magnetometer", "compass 2 (external)")
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._kept = np.empty((0, 3))  # readings kept for display, session units
        self._stride = 1  # keep every stride-th reading
        self._skip = 0  # readings to skip before the next one kept
        self._latest: CollectProgress | None = None

    def add(self, progress: CollectProgress) -> None:
        if progress.readings is not None and len(progress.readings):
            self._keep(np.asarray(progress.readings, dtype=np.float64).reshape(-1, 3))
        self._latest = progress

    def _keep(self, y: np.ndarray) -> None:
        y = y[np.isfinite(y).all(axis=1)]
        picked = y[self._skip :: self._stride]
        self._skip = (self._skip - len(y)) % self._stride
        self._kept = np.concatenate([self._kept, picked])
        while len(self._kept) > MAX_POINTS:  # every other one, from now on half as many
            self._kept = self._kept[::2]
            self._stride *= 2
            self._skip = 0

    def snapshot(self) -> dict[str, Any]:
        p = self._latest
        if p is None:
            return {"name": self.name, "samples": 0, "instruction": "waiting for samples"}
        panel: dict[str, Any] = {
            "name": self.name,
            "samples": p.samples,
            "elapsed_s": round(p.elapsed_s, 2),
            "figures": " ".join(p.figures().split()),
            "coverage_pct": p.coverage_percent(),
            "residual": p.live.text() if p.live is not None else "live estimate off",
            "ok_to_stop": bool(p.live is not None and p.live.ok_to_stop),
            "instruction": p.instruction or p.hint,
            "points": [],
            "target": None,
            "face": None,
        }
        state = p.coverage_state
        if state is not None:
            cells = make_cells(len(state.counts))
            panel["cells"] = {
                "z_edges": [round(float(z), 6) for z in cells.z_edges],
                "band_counts": [int(k) for k in cells.counts],
            }
            panel["counts"] = [int(c) for c in state.counts]
            if state.centre is not None:
                hole = largest_hole(cells, state.counts)
                if hole is not None:
                    panel["target"] = [round(float(v), 4) for v in hole]
                    panel["face"] = axis_phrase(hole)
                if len(self._kept):
                    u = _directions(self._kept, state.centre)
                    panel["points"] = np.round(u, DIRECTION_DECIMALS).tolist()
        return panel


def result_spheres(mag: np.ndarray) -> dict[str, Any]:
    """The collection's readings before and after an ellipsoid fit, for the page.

    mag : (N, 3) float, the session's magnetometer readings (session units); rows that are
        not finite (a MAVLink session's rows without a new magnetometer value) are left out

    before: the readings divided by their median distance from the fitted centre (the offset
    shows as a sphere off the origin, soft iron as an ellipsoid); after: ``D̃⁻¹ (y − o)``, on
    the unit sphere when the fit holds. The field strength's spread (std / mean, %) of each.
    When the fit is refused (too few directions), ``error`` says why and only ``before``
    (about the readings' mean) is given.
    """
    from magcal.calib.initial.ellipsoid import fit_ellipsoid_sdp

    mag = np.asarray(mag, dtype=np.float64).reshape(-1, 3)
    mag = mag[np.isfinite(mag).all(axis=1)]
    if len(mag) == 0:
        return {"before": [], "error": "no magnetometer readings"}
    y = _thin(mag)
    raw = np.linalg.norm(mag, axis=1)
    out: dict[str, Any] = {"before_spread_pct": f"{100 * raw.std() / raw.mean():.2f}"}
    try:
        fit = fit_ellipsoid_sdp(mag)
    except MagcalError as exc:
        r = float(np.median(np.linalg.norm(y - y.mean(axis=0), axis=1))) or 1.0
        out.update(before=np.round(y / r, DIRECTION_DECIMALS).tolist(), error=str(exc))
        return out
    r = float(np.median(np.linalg.norm(y - fit.o, axis=1))) or 1.0
    after = np.linalg.solve(fit.D_tilde, (mag - fit.o).T).T
    norms = np.linalg.norm(after, axis=1)
    out.update(
        before=np.round(y / r, DIRECTION_DECIMALS).tolist(),
        after=np.round(_thin(after), DIRECTION_DECIMALS).tolist(),
        after_spread_pct=f"{100 * norms.std() / norms.mean():.2f}",
    )
    return out
