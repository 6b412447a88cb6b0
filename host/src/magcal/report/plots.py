# SPDX-License-Identifier: Apache-2.0
"""PNG figures of a calibration, after Kok & Schön (2016), Figs 1, 4, 5 and 8.

Every function takes arrays and an output path, writes one PNG and returns the path. Colours
follow the paper: raw / initial-estimate data red, calibrated / ML data blue.

Figures are made with ``matplotlib.figure.Figure`` on an explicit Agg canvas, never through
``pyplot``: nothing global (the backend, pyplot's figure registry) is touched, so importing or
calling this module is safe in servers, tests and GUI programs alike, and figures are freed by
the garbage collector without ``plt.close``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

RAW_COLOR = "tab:red"
CALIBRATED_COLOR = "tab:blue"
#: Scatter plots show at most this many points (evenly spaced in time, as the paper does
#: when it downsamples to 1 Hz); more only slows rendering.
MAX_SCATTER_POINTS = 3000
#: Innovation histograms cover ±this many standard deviations.
INNOVATION_RANGE_SIGMA = 5.0
INNOVATION_BINS = 80
DPI = 120


# --------------------------------------------------------------------------------------------
# Figure 1: ellipsoid of raw data and the calibrated unit sphere


def plot_ellipsoid_sphere(
    raw_mag: np.ndarray,
    calibrated: np.ndarray,
    path: str | os.PathLike,
    *,
    center_raw: bool = True,
) -> Path:
    """3-D scatter of raw magnetometer data (red) and calibrated data (blue) on a unit sphere.

    raw_mag    : (N, 3) float, raw magnetometer units
    calibrated : (N, 3) float, calibrated field, unit norm when the calibration fits
    path       : the PNG to write
    center_raw : subtract the raw data's mean before scaling. The raw data is then divided by
                 its mean norm so that it is about the size of the unit sphere; without
                 centring the hard-iron offset can dominate the picture. The title says which.

    At most ``MAX_SCATTER_POINTS`` samples, evenly spaced in time, are drawn.
    """
    raw = _array(raw_mag, "raw_mag", 3)
    cal = _array(calibrated, "calibrated", 3)
    _same_length(raw, "raw_mag", cal, "calibrated")

    # The scaling uses all samples, so the picture does not depend on the subsampling.
    centre = raw.mean(axis=0) if center_raw else np.zeros(3)
    raw = raw - centre
    raw_scale = _mean_norm(raw, "raw_mag")
    raw = raw / raw_scale
    n_total = raw.shape[0]
    index = _subsample(n_total, MAX_SCATTER_POINTS)
    raw, cal = raw[index], cal[index]

    fig = _new_figure((7.0, 6.5))
    ax = fig.add_subplot(projection="3d")
    # Wireframe of the unit sphere: the target of the calibration.
    u, v = np.meshgrid(np.linspace(0.0, 2.0 * np.pi, 25), np.linspace(0.0, np.pi, 13))
    ax.plot_wireframe(
        np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.75", linewidth=0.4
    )
    # Translucent calibrated points: the sphere would otherwise hide the ellipsoid inside it.
    ax.scatter(*raw.T, s=3, color=RAW_COLOR, depthshade=False, label="raw (scaled)")
    ax.scatter(
        *cal.T, s=2, color=CALIBRATED_COLOR, alpha=0.35, depthshade=False, label="calibrated"
    )
    # Equal scales on all axes, or a sphere looks like an ellipsoid and the figure lies.
    limit = max(1.1, float(np.abs(np.concatenate([raw, cal])).max()) * 1.05)
    ax.set_xlim(-limit, limit)
    ax.set_ylim(-limit, limit)
    ax.set_zlim(-limit, limit)
    ax.set_box_aspect((1.0, 1.0, 1.0))
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    how = "minus its mean, " if center_raw else ""
    ax.set_title(
        f"Magnetometer data before (red) and after (blue) calibration\n"
        f"raw data {how}divided by its mean norm {raw_scale:.4g} (raw units); "
        f"{len(index)} of {n_total} samples",
        fontsize=9,
    )
    ax.legend(loc="upper left", fontsize=8)
    return _save(fig, path)


# --------------------------------------------------------------------------------------------
# Figure 4: field norm before and after calibration


def plot_norms(
    t: np.ndarray,
    raw_norm: np.ndarray,
    calibrated_norm: np.ndarray,
    path: str | os.PathLike,
) -> Path:
    """Field norm over time before (red, divided by its mean) and after (blue) calibration.

    t               : (N,) float, s
    raw_norm        : (N,) float, ‖y‖ in raw magnetometer units
    calibrated_norm : (N,) float, ‖D⁻¹(y − o)‖, unitless (1 when calibrated)
    """
    t = _array(t, "t", None)
    raw = _array(raw_norm, "raw_norm", None)
    cal = _array(calibrated_norm, "calibrated_norm", None)
    _same_length(t, "t", raw, "raw_norm")
    _same_length(t, "t", cal, "calibrated_norm")
    raw_mean = float(raw.mean())
    if raw_mean <= 0.0:
        raise ValueError(f"plot_norms: raw_norm must be positive norms, mean is {raw_mean}")
    raw = raw / raw_mean

    fig = _new_figure((8.0, 3.5))
    ax = fig.add_subplot()
    ax.axhline(1.0, color="0.5", linewidth=0.8, linestyle="--")
    ax.plot(t, raw, color=RAW_COLOR, linewidth=0.8, label=f"before (std {raw.std():.3g})")
    ax.plot(t, cal, color=CALIBRATED_COLOR, linewidth=0.8, label=f"after (std {cal.std():.3g})")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("field norm")
    ax.set_title(
        f"Norm of the magnetic field before (red, divided by its mean {raw_mean:.4g}) "
        "and after (blue) calibration",
        fontsize=9,
    )
    ax.legend(loc="best", fontsize=8)
    ax.grid(True, linewidth=0.3)
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------------------------
# Figure 5: histogram of normalised innovations


def plot_innovation_histogram(
    normalised: np.ndarray,
    path: str | os.PathLike,
    title: str = "Normalised innovations",
) -> Path:
    """Histogram (density) of normalised innovations ``S^{-1/2} (y − ŷ)`` with the N(0, 1) pdf.

    normalised : (M,) float, unitless (any shape is flattened, e.g. the paper's stacked (N, 6))
    title      : figure title (e.g. "estimation data" / "validation data")

    The bars cover ±``INNOVATION_RANGE_SIGMA``; values outside are counted in the text box.
    """
    x = np.asarray(normalised, dtype=np.float64).ravel()
    if x.size == 0:
        raise ValueError("plot_innovation_histogram: normalised is empty")
    bad = int(np.count_nonzero(~np.isfinite(x)))
    if bad:
        raise ValueError(f"plot_innovation_histogram: normalised has {bad} non-finite values")
    mean, std = float(x.mean()), float(x.std())
    outside_3 = float(np.mean(np.abs(x) > 3.0))
    outside_range = int(np.count_nonzero(np.abs(x) > INNOVATION_RANGE_SIGMA))

    edges = np.linspace(-INNOVATION_RANGE_SIGMA, INNOVATION_RANGE_SIGMA, INNOVATION_BINS + 1)
    # Weights 1/(M·width) rather than density=True: numpy's density would renormalise over
    # the in-range values only and hide outliers; with these weights the bars integrate to
    # the fraction inside the plotted range, directly comparable with the N(0, 1) pdf.
    weights = np.full(x.size, 1.0 / (x.size * (edges[1] - edges[0])))

    fig = _new_figure((6.0, 4.0))
    ax = fig.add_subplot()
    ax.hist(x, bins=edges, weights=weights, color=CALIBRATED_COLOR, alpha=0.7, label="data")
    grid = np.linspace(edges[0], edges[-1], 400)
    ax.plot(grid, np.exp(-0.5 * grid**2) / np.sqrt(2.0 * np.pi), color=RAW_COLOR, label="N(0, 1)")
    ax.text(
        0.02,
        0.97,
        f"M = {x.size}\nmean = {mean:.3g}\nstd = {std:.3g}\n"
        f"|x| > 3: {100.0 * outside_3:.2f} % (N(0,1): 0.27 %)\n"
        f"outside plot: {outside_range}",
        transform=ax.transAxes,
        verticalalignment="top",
        fontsize=8,
        bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "0.7"},
    )
    ax.set_xlim(edges[0], edges[-1])
    ax.set_xlabel("normalised innovation")
    ax.set_ylabel("density")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------------------------
# Figure 8: heading RMSE over Monte Carlo runs, initial vs ML estimate


def plot_heading_rmse_histograms(
    rmse_init_deg: np.ndarray,
    rmse_ml_deg: np.ndarray,
    path: str | os.PathLike,
) -> Path:
    """Two histograms of heading RMSE over K Monte Carlo runs: initial (red) and ML (blue).

    rmse_init_deg : (K,) float, degrees, heading RMSE with the initial estimate (Step 1)
    rmse_ml_deg   : (K,) float, degrees, heading RMSE with the ML estimate (same runs)

    Each panel has its own x-scale, as in the paper: the two spreads differ by far.
    """
    init = _array(rmse_init_deg, "rmse_init_deg", None)
    ml = _array(rmse_ml_deg, "rmse_ml_deg", None)
    _same_length(init, "rmse_init_deg", ml, "rmse_ml_deg")

    fig = _new_figure((9.0, 3.8))
    panels = [
        ("(a) initial parameter estimate", init, RAW_COLOR),
        ("(b) ML parameter estimate", ml, CALIBRATED_COLOR),
    ]
    for i, (label, values, color) in enumerate(panels):
        ax = fig.add_subplot(1, 2, i + 1)
        ax.hist(values, bins="auto", color=color, alpha=0.8)
        ax.set_xlabel("heading RMSE [°]")
        ax.set_ylabel("runs")
        ax.set_title(label, fontsize=10)
        ax.text(
            0.97,
            0.97,
            f"median {np.median(values):.3g}°\nmax {values.max():.3g}°",
            transform=ax.transAxes,
            horizontalalignment="right",
            verticalalignment="top",
            fontsize=8,
        )
    fig.suptitle(f"Heading RMSE over {init.size} runs (note the different x-scales)", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------------------------
# Helpers


def _new_figure(size_in: tuple[float, float]) -> Figure:
    # matplotlib is imported here, where a figure is drawn: it takes most of a second to load,
    # and the modules that import this one (the report's) need it only once they draw.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size_in)
    FigureCanvasAgg(fig)  # attaches itself to fig: render with Agg, no pyplot, no backend switch
    return fig


def _save(fig: Figure, path: str | os.PathLike) -> Path:
    path = Path(path)
    fig.savefig(path, format="png", dpi=DPI)
    return path


def _array(value: np.ndarray, name: str, width: int | None) -> np.ndarray:
    """``value`` as float64 of shape (N,) (width None) or (N, width), N ≥ 1, all finite."""
    a = np.asarray(value, dtype=np.float64)
    expected = (1,) if width is None else (2, width)
    if a.ndim != expected[0] or (width is not None and a.shape[1] != width):
        text = "(N,)" if width is None else f"(N, {width})"
        raise ValueError(f"{name} must have shape {text}, got {a.shape}")
    if a.size == 0:
        raise ValueError(f"{name} is empty; nothing to plot")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} has non-finite values; remove them before plotting")
    return a


def _same_length(a: np.ndarray, a_name: str, b: np.ndarray, b_name: str) -> None:
    if a.shape[0] != b.shape[0]:
        raise ValueError(
            f"{a_name} and {b_name} must have the same number of samples, "
            f"got {a.shape[0]} and {b.shape[0]}"
        )


def _mean_norm(v: np.ndarray, name: str) -> float:
    scale = float(np.linalg.norm(v, axis=1).mean())
    if scale <= 0.0:
        raise ValueError(f"{name} has zero mean norm; cannot scale it to the unit sphere")
    return scale


def _subsample(n: int, limit: int) -> np.ndarray:
    """Indices of at most ``limit`` samples, evenly spaced over ``range(n)``."""
    if n <= limit:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, limit).round().astype(int))


# --------------------------------------------------------------------------------------------
# Inclination consistency: the dip angle each sample implies, before and after calibration


def plot_dip_angles(
    dip_raw_deg: np.ndarray,
    dip_calibrated_deg: np.ndarray,
    dip_estimate_deg: float,
    path: str | os.PathLike,
    title: str = "Dip angle per sample",
) -> Path:
    """Histograms of the dip angle between the field and the accelerometer's "up" at each
    sample: raw field (red) and calibrated field (blue), with the calibration's dip.

    dip_raw_deg        : (K,) degrees, from the raw magnetometer reading (no correction)
    dip_calibrated_deg : (K,) degrees, from D⁻¹(y − o)
    dip_estimate_deg   : the result's dip angle, degrees (dashed line)

    A calibration that fits gives one angle at every orientation; each panel has its own
    x-scale, since the two spreads differ by orders of magnitude.
    """
    raw = _array(dip_raw_deg, "dip_raw_deg", None)
    cal = _array(dip_calibrated_deg, "dip_calibrated_deg", None)
    if not np.isfinite(dip_estimate_deg):
        raise ValueError(f"dip_estimate_deg must be finite, got {dip_estimate_deg!r}")

    fig = _new_figure((9.0, 3.6))
    panels = [
        ("(a) raw field", raw, RAW_COLOR),
        ("(b) calibrated field", cal, CALIBRATED_COLOR),
    ]
    for i, (label, values, color) in enumerate(panels):
        ax = fig.add_subplot(1, 2, i + 1)
        ax.hist(values, bins=60, color=color, alpha=0.8)
        ax.axvline(dip_estimate_deg, color="0.2", linestyle="--", linewidth=1.0)
        ax.set_xlabel("dip angle [°]")
        ax.set_ylabel("samples")
        ax.set_title(label, fontsize=10)
        ax.text(
            0.97,
            0.97,
            f"mean {values.mean():.4g}°\nstd {values.std():.3g}°",
            transform=ax.transAxes,
            horizontalalignment="right",
            verticalalignment="top",
            fontsize=8,
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "0.7"},
        )
    fig.suptitle(
        f"{title}: {raw.size} samples at rest-like accelerations "
        f"(dashed: the calibration's dip {dip_estimate_deg:.3f}°)",
        fontsize=10,
    )
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------------------------
# magcal study: field norm of several calibrations (Zhao et al. Figure 1), and the heading
# error of every method per scenario

#: Colours of further series after raw (red) and the first calibration (blue).
SERIES_COLORS = (RAW_COLOR, CALIBRATED_COLOR, "tab:green", "tab:purple", "tab:orange")


def plot_norm_series(
    norms: dict[str, np.ndarray],
    reference: float,
    path: str | os.PathLike,
    *,
    unit: str,
    title: str = "Field norm before and after calibration",
) -> Path:
    """Field norm per sample of several series on one axis, with the reference norm.

    norms     : label → (N,) float, norms in ``unit`` (the first is drawn red as the raw
                data, the next blue, ...); all of the same length
    reference : the true field norm, ``unit`` (dashed line)
    unit      : the norms' unit, for the axis label
    """
    if not norms:
        raise ValueError("plot_norm_series: no series to plot")
    if len(norms) > len(SERIES_COLORS):
        raise ValueError(f"plot_norm_series: at most {len(SERIES_COLORS)} series, got {len(norms)}")
    arrays = {label: _array(v, f"norms[{label!r}]", None) for label, v in norms.items()}
    first_label, first = next(iter(arrays.items()))
    for label, v in arrays.items():
        _same_length(first, f"norms[{first_label!r}]", v, f"norms[{label!r}]")
    if not np.isfinite(reference) or reference <= 0.0:
        raise ValueError(f"plot_norm_series: reference must be a positive norm, got {reference}")

    fig = _new_figure((8.0, 3.8))
    ax = fig.add_subplot()
    k = np.arange(1, first.size + 1)
    for i, ((label, v), color) in enumerate(zip(arrays.items(), SERIES_COLORS, strict=False)):
        # Calibrated series overlap closely: translucent, so that one does not hide another.
        ax.plot(
            k,
            v,
            color=color,
            linewidth=0.7,
            alpha=1.0 if i == 0 else 0.7,
            label=f"{label} (std {v.std():.3g} {unit})",
        )
    ax.axhline(reference, color="0.3", linewidth=1.0, linestyle="--", label="reference norm")
    ax.set_xlabel("sample")
    ax.set_ylabel(f"field norm [{unit}]")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="best", fontsize=8)
    ax.grid(True, linewidth=0.3)
    fig.tight_layout()
    return _save(fig, path)


def plot_heading_error_comparison(
    errors_deg: dict[str, dict[str, np.ndarray]],
    path: str | os.PathLike,
) -> Path:
    """Box plots of the heading error of each method, one panel per scenario, log scale.

    errors_deg : scenario → method → (K,) float, degrees (positive), the runs that
                 calibrated; a method with no runs is shown as an empty slot
    """
    if not errors_deg:
        raise ValueError("plot_heading_error_comparison: no scenario to plot")
    fig = _new_figure((3.2 * len(errors_deg) + 0.8, 4.0))
    for i, (scenario, by_method) in enumerate(errors_deg.items()):
        ax = fig.add_subplot(1, len(errors_deg), i + 1)
        labels, data = [], []
        for method, values in by_method.items():
            v = np.asarray(values, dtype=np.float64).ravel()
            if v.size and (not np.isfinite(v).all() or (v <= 0.0).any()):
                raise ValueError(
                    f"plot_heading_error_comparison: {scenario}/{method} has non-finite or "
                    "non-positive errors; a log scale needs positive values"
                )
            labels.append(f"{method}\n({v.size})")
            data.append(v)
        positions = [j + 1 for j, v in enumerate(data) if v.size]
        if positions:
            ax.boxplot(
                [v for v in data if v.size],
                positions=positions,
                widths=0.6,
                showfliers=True,
                flierprops={"markersize": 2},
            )
            ax.set_yscale("log")
        ax.set_xticks(range(1, len(labels) + 1), labels, fontsize=8)
        ax.set_xlim(0.4, len(labels) + 0.6)
        ax.set_title(scenario, fontsize=10)
        ax.grid(True, axis="y", linewidth=0.3, which="both")
        if i == 0:
            ax.set_ylabel("heading error, RMS [°]")
    fig.suptitle("Calibration-induced heading error per method (runs that calibrated)", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)
