# SPDX-License-Identifier: Apache-2.0
"""The field strength for autopilot parameters: World Magnetic Model and --field / --location."""

from __future__ import annotations

import datetime as dt

import pytest

from magcal.autopilot import wmm

#: NOAA's WMM2025 test values (WMM2025 report, "test values" table; the same rows ship as
#: WMM2025_TEST_VALUES.txt with the model): date, height km, lat, lon, F nT, I deg, D deg.
WMM2025_TEST_VALUES = [
    (2025.0, 0.0, 80.0, 0.0, 55178.5, 83.21, 1.28),
    (2025.0, 0.0, 0.0, 120.0, 41064.3, -14.93, -0.16),
    (2025.0, 0.0, -80.0, 240.0, 54698.2, -72.00, 68.78),
    (2025.0, 100.0, 80.0, 0.0, 52964.9, 83.26, 0.85),
    (2027.5, 0.0, 0.0, 120.0, 41036.9, -14.65, -0.24),
    (2027.5, 100.0, -80.0, 240.0, 51825.7, -72.10, 67.93),
]


@pytest.mark.parametrize(("year", "alt", "lat", "lon", "F", "incl", "decl"), WMM2025_TEST_VALUES)
def test_world_magnetic_model_matches_noaa_test_values(year, alt, lat, lon, F, incl, decl):
    f = wmm.wmm_field_at(lat, (lon + 180) % 360 - 180, alt, year)
    # the table is rounded to 0.1 nT and 0.01°
    assert f.total_nT == pytest.approx(F, abs=0.051)
    assert f.inclination_deg == pytest.approx(incl, abs=0.0051)
    assert f.declination_deg == pytest.approx(decl, abs=0.0051)
    assert "WMM-2025" in f.source


def test_a_date_is_its_decimal_year():
    assert wmm.decimal_year(dt.date(2025, 1, 1)) == 2025.0
    assert wmm.decimal_year(dt.date(2027, 7, 2)) == pytest.approx(2027 + 182 / 365)
    by_date = wmm.wmm_field(80.0, 0.0, 0.0, dt.date(2025, 1, 1))
    assert by_date.total_nT == wmm.wmm_field_at(80.0, 0.0, 0.0, 2025.0).total_nT
    assert "2025-01-01" in by_date.source


def test_units_convert_exactly():
    assert wmm.convert(1.0, "gauss", "mG") == 1000.0
    assert wmm.convert(48.5, "uT", "mG") == pytest.approx(485.0, rel=1e-15)
    assert wmm.parse_field("0.485gauss").strength("mG") == pytest.approx(485.0, rel=1e-15)
    assert wmm.parse_field("48.5 µT").total_nT == pytest.approx(48500.0)
    assert wmm.parse_field("485mG").strength("gauss") == pytest.approx(0.485)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("485", "with its unit"),
        ("485 furlongs", "unknown unit 'furlongs'"),
        ("485uT", "not an Earth field"),
        ("0.485mG", "not an Earth field"),
    ],
)
def test_field_without_a_sensible_unit_is_refused(text, match):
    with pytest.raises(wmm.FieldError, match=match):
        wmm.parse_field(text)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("47.4", "LAT,LON"),
        ("95,8", "latitude 95.0"),
        ("47,8,1200", "altitude 1200.0 km"),
        ("north,8", "numbers"),
    ],
)
def test_bad_locations_are_refused(text, match):
    with pytest.raises(wmm.FieldError, match=match):
        wmm.parse_location(text)


def test_location_wraps_longitude_and_defaults_altitude():
    assert wmm.parse_location("47.37,188.54") == pytest.approx((47.37, -171.46, 0.0))


def test_date_outside_the_shipped_models_is_refused():
    with pytest.raises(wmm.FieldError, match="--date"):
        wmm.wmm_field(47.0, 8.0, 0.0, dt.date(2031, 1, 1))
