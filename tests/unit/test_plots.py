# SPDX-License-Identifier: Apache-2.0
"""Plots: each writes a PNG, leaves pyplot alone, and rejects mismatched inputs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from magcal.report.plots import (
    plot_ellipsoid_sphere,
    plot_heading_rmse_histograms,
    plot_innovation_histogram,
    plot_norms,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
REPO_ROOT = Path(__file__).resolve().parents[2]


def assert_png(path):
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    assert len(data) > 1000


@pytest.fixture
def rng():
    return np.random.default_rng(3)


def sphere_data(rng, n):
    cal = rng.normal(size=(n, 3))
    cal /= np.linalg.norm(cal, axis=1, keepdims=True)
    D = np.array([[0.74, -0.13, 0.01], [-0.12, 0.68, 0.01], [-0.03, 0.43, 1.00]])
    raw = 48.0 * (cal @ D.T + [1.36, 1.22, -0.94])
    return raw, cal


def test_ellipsoid_sphere_writes_png(tmp_path, rng):
    raw, cal = sphere_data(rng, 200)
    out = plot_ellipsoid_sphere(raw, cal, tmp_path / "fig1.png")
    assert out == tmp_path / "fig1.png"
    assert_png(out)


def test_ellipsoid_sphere_uncentred_and_subsampled(tmp_path, rng):
    raw, cal = sphere_data(rng, 7000)  # more than MAX_SCATTER_POINTS
    out = plot_ellipsoid_sphere(raw, cal, str(tmp_path / "fig1.png"), center_raw=False)
    assert_png(out)


def test_norms_writes_png(tmp_path, rng):
    raw, cal = sphere_data(rng, 300)
    t = 0.01 * np.arange(300)
    out = plot_norms(
        t, np.linalg.norm(raw, axis=1), np.linalg.norm(cal, axis=1), tmp_path / "n.png"
    )
    assert_png(out)


def test_innovation_histogram_writes_png(tmp_path, rng):
    x = rng.normal(size=(500, 6))  # flattened like the paper's stacked residuals
    x[0, 0] = 40.0  # an outlier outside the plotted range
    out = plot_innovation_histogram(x, tmp_path / "h.png", title="estimation data")
    assert_png(out)


def test_heading_rmse_histograms_write_png(tmp_path, rng):
    init = np.abs(rng.normal(scale=5.0, size=150))
    ml = np.abs(rng.normal(scale=0.3, size=150))
    assert_png(plot_heading_rmse_histograms(init, ml, tmp_path / "fig8.png"))


def test_pyplot_is_not_used(tmp_path):
    # Importing pyplot selects a backend globally; the module must not need it. In a fresh
    # interpreter: in this one, another test of the same process may have imported pyplot.
    code = (
        "import sys, numpy as np\n"
        "from magcal.report.plots import plot_ellipsoid_sphere\n"
        "from tests.unit.test_plots import sphere_data\n"
        "raw, cal = sphere_data(np.random.default_rng(3), 50)\n"
        f"plot_ellipsoid_sphere(raw, cal, {str(tmp_path / 'a.png')!r})\n"
        "print('matplotlib.pyplot' in sys.modules)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO_ROOT
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["False"]
    assert_png(tmp_path / "a.png")


def test_matplotlib_is_loaded_only_to_draw(tmp_path, rng):
    # The report's modules import this one; matplotlib takes most of a second to load.
    code = (
        "import sys, numpy as np\n"
        "from magcal.report import contents, html, plots\n"
        "print('matplotlib' in sys.modules)\n"
        f"plots.plot_norms(np.arange(9.0), np.ones(9), np.ones(9), {str(tmp_path / 'n.png')!r})\n"
        "print('matplotlib' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["False", "True"]
    assert_png(tmp_path / "n.png")


@pytest.mark.parametrize(
    ("raw_shape", "cal_shape", "pattern"),
    [
        ((10, 2), (10, 3), r"raw_mag must have shape \(N, 3\), got \(10, 2\)"),
        ((10, 3), (10,), r"calibrated must have shape \(N, 3\), got \(10,\)"),
        (
            (10, 3),
            (9, 3),
            "raw_mag and calibrated must have the same number of samples",
        ),
        ((0, 3), (0, 3), "raw_mag is empty"),
    ],
)
def test_ellipsoid_sphere_rejects_shapes(tmp_path, raw_shape, cal_shape, pattern):
    with pytest.raises(ValueError, match=pattern):
        plot_ellipsoid_sphere(np.ones(raw_shape), np.ones(cal_shape), tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_ellipsoid_sphere_rejects_non_finite_and_zero(tmp_path):
    raw = np.ones((5, 3))
    raw[2, 1] = np.nan
    with pytest.raises(ValueError, match="raw_mag has non-finite values"):
        plot_ellipsoid_sphere(raw, np.ones((5, 3)), tmp_path / "x.png")
    with pytest.raises(ValueError, match="zero mean norm"):
        plot_ellipsoid_sphere(np.ones((5, 3)), np.ones((5, 3)), tmp_path / "x.png")


@pytest.mark.parametrize(
    ("n_t", "n_raw", "n_cal", "pattern"),
    [
        (
            10,
            9,
            10,
            "t and raw_norm must have the same number of samples, got 10 and 9",
        ),
        (10, 10, 11, "t and calibrated_norm must have the same number of samples"),
    ],
)
def test_norms_rejects_mismatched_lengths(tmp_path, n_t, n_raw, n_cal, pattern):
    with pytest.raises(ValueError, match=pattern):
        plot_norms(np.arange(n_t), np.ones(n_raw), np.ones(n_cal), tmp_path / "x.png")


def test_norms_rejects_2d_and_non_positive(tmp_path):
    with pytest.raises(ValueError, match=r"raw_norm must have shape \(N,\), got \(10, 3\)"):
        plot_norms(np.arange(10), np.ones((10, 3)), np.ones(10), tmp_path / "x.png")
    with pytest.raises(ValueError, match="raw_norm must be positive"):
        plot_norms(np.arange(3), np.zeros(3), np.ones(3), tmp_path / "x.png")


def test_innovation_histogram_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="normalised is empty"):
        plot_innovation_histogram(np.zeros(0), tmp_path / "x.png")
    with pytest.raises(ValueError, match="normalised has 2 non-finite values"):
        plot_innovation_histogram([0.0, np.nan, np.inf, 1.0], tmp_path / "x.png")


@pytest.mark.parametrize(
    ("init_shape", "ml_shape", "pattern"),
    [
        (
            (150,),
            (149,),
            "rmse_init_deg and rmse_ml_deg must have the same number of samples",
        ),
        ((150, 1), (150,), r"rmse_init_deg must have shape \(N,\), got \(150, 1\)"),
        ((150,), (), r"rmse_ml_deg must have shape \(N,\), got \(\)"),
    ],
)
def test_heading_rmse_rejects_shapes(tmp_path, init_shape, ml_shape, pattern):
    with pytest.raises(ValueError, match=pattern):
        plot_heading_rmse_histograms(np.ones(init_shape), np.ones(ml_shape), tmp_path / "x.png")
