# SPDX-License-Identifier: Apache-2.0
"""magcal.device.coverage: the equal-area partition, cell indices, the running centre, the
coverage of simulated sessions (tumbling ~100 %, yaw-only low) and the hint."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magcal.device import coverage as cv
from magcal.errors import MagcalError
from magcal.sim.scenarios import preset, simulate


@pytest.mark.parametrize("n", [2, 10, 50, 100, 200, 500])
def test_partition_has_n_equal_area_cells(n):
    cells = cv.make_cells(n)
    assert cells.n == n and cells.centres.shape == (n, 3)
    assert cells.counts[0] == 1 and cells.counts[-1] == 1
    # Area of band b = 2 pi dz; each of its cells: 2 pi dz / count = 4 pi / n exactly.
    dz = -np.diff(cells.z_edges)
    assert np.allclose(2 * math.pi * dz / cells.counts, 4 * math.pi / n, rtol=1e-12)
    assert np.allclose(np.linalg.norm(cells.centres, axis=1), 1.0)
    # Each centre lies in its own cell.
    assert cv.cell_index(cells, cells.centres).tolist() == list(range(n))


def test_uniform_directions_fill_cells_equally():
    cells = cv.make_cells(100)
    u = np.random.default_rng(1).normal(size=(400_000, 3))
    counts = cv.cell_counts(cells, u)
    # Multinomial: 4000 expected per cell, std ~63; 6 sigma.
    assert np.all(np.abs(counts - 4000) < 380)
    assert cv.coverage_fraction(counts) == 1.0


def test_partition_refuses_fewer_than_two_cells():
    with pytest.raises(MagcalError, match="at least 2 cells"):
        cv.make_cells(1)


def test_cell_index_edges_and_unnormalised_vectors():
    cells = cv.make_cells(100)
    assert cv.cell_index(cells, np.array([[0, 0, 5.0]]))[0] == 0
    assert cv.cell_index(cells, np.array([[0, 0, -0.1]]))[0] == 99
    u = np.random.default_rng(2).normal(size=(1000, 3))
    assert np.array_equal(cv.cell_index(cells, u), cv.cell_index(cells, 37.0 * u))


def test_sphere_fit_and_mid_range_find_a_large_offset():
    rng = np.random.default_rng(3)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    o = np.array([400.0, -250.0, 90.0])  # offset 10x the field
    y = 50.0 * u + o + rng.normal(scale=0.3, size=u.shape)
    assert np.allclose(cv.sphere_fit(y), o, atol=0.5)
    assert np.allclose(cv.mid_range(y), o, atol=2.0)
    # Half a sphere: the sphere fit stays right (the mid-range would not).
    half = y[u[:, 2] > 0]
    assert np.allclose(cv.estimate_centre(half, 10.0), o, atol=1.0)


def test_no_centre_at_rest_and_mid_range_on_a_circle():
    rng = np.random.default_rng(4)
    rest = np.array([100.0, 20.0, -30.0]) + rng.normal(scale=0.2, size=(500, 3))
    assert cv.estimate_centre(rest, 10.0) is None
    phi = rng.uniform(0, 2 * math.pi, 500)
    circle = np.column_stack([30 * np.cos(phi), 30 * np.sin(phi), np.full(500, -45.0)])
    assert cv.sphere_fit(circle) is None  # degenerate along the axis
    assert np.allclose(cv.estimate_centre(circle, 10.0), [0, 0, -45.0], atol=1.0)


def _tracked(session, refresh=50):
    t = cv.CoverageTracker(min_extent=0.2, refresh_samples=refresh)
    for start in range(0, len(session), 100):
        t.add(session.mag[start : start + 100])
        t.state()
    return t.state(force=True)


def test_full_tumbling_covers_nearly_everything():
    # (The simulator's 60 s tumble at 1 rad/s visits about 75 % of the cells, even with the
    # true centre; two minutes at 2 rad/s visit them all.)
    session, truth = simulate(preset("mems", duration_s=120.0, max_rate_rad_s=2.0), seed=11)
    assert np.linalg.norm(truth.sensor.o) > 0.5  # an offset the centre must find
    st = _tracked(session)
    assert st.coverage >= 0.95
    assert np.linalg.norm(st.centre - truth.sensor.o) < 0.05


def test_yaw_only_covers_little_and_the_hint_names_the_z_axis():
    session, truth = simulate(preset("mems", duration_s=60.0, motion="yaw-only"), seed=12)
    st = _tracked(session)
    assert st.coverage < 0.35
    assert "z axis" in st.hint and ("+z" in st.hint or "-z" in st.hint)


def test_half_tumble_hint_names_the_missing_side():
    # Directions only with the field's sensor-frame z component negative: +z is missing.
    rng = np.random.default_rng(5)
    u = rng.normal(size=(5000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] < -0.2]
    y = 45.0 * u + np.array([-300.0, 120.0, 60.0])
    t = cv.CoverageTracker(min_extent=10.0)
    t.add(y)
    st = t.state(force=True)
    assert 0.35 < st.coverage < 0.55  # 40 % of the area; edge cells count
    assert st.hint.startswith("point the sensor's +z")


def test_tracker_before_motion_asks_to_rotate():
    t = cv.CoverageTracker(min_extent=10.0)
    assert t.state().coverage == 0.0
    t.add(np.full((60, 3), 7.0))
    st = t.state()
    assert st.coverage == 0.0 and st.centre is None and st.hint == "rotate the sensor"


def test_hint_when_everything_is_covered():
    cells = cv.make_cells(100)
    assert cv.missing_hint(cells, np.ones(100, int)) == "all directions covered"
    assert cv.axis_phrase(np.array([0.1, -0.05, 0.99])) == "+z"
    assert cv.axis_phrase(np.array([0.7, 0.0, -0.7])) in ("+x-z", "-z+x")
