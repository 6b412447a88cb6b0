# SPDX-License-Identifier: Apache-2.0
"""The local field strength for an autopilot's compass parameters.

magcal's correction has unit norm; an autopilot wants the field in its unit (ArduPilot mG,
PX4 gauss), so the mapping multiplies by the local field strength ``F``. It comes from the
World Magnetic Model at the user's location (pygeomag, NOAA's WMM coefficients: WMM2025 for
2025–2030, WMM2020 before; its total intensity F) or from a value the user gives with its
unit.

Unit sizes (exact): 1 gauss = 10⁻⁴ T = 10⁵ nT, 1 mG = 100 nT, 1 µT = 1000 nT.
"""

from __future__ import annotations

import datetime as dt
import math
import re
from dataclasses import dataclass

from magcal.errors import MagcalError

#: Nanotesla per unit, exact.
NT_PER_UNIT = {"nT": 1.0, "uT": 1e3, "mG": 1e2, "gauss": 1e5, "T": 1e9}
UNIT_ALIASES = {
    "nt": "nT",
    "ut": "uT",
    "µt": "uT",
    "μt": "uT",
    "microtesla": "uT",
    "mg": "mG",
    "mgauss": "mG",
    "milligauss": "mG",
    "g": "gauss",
    "ga": "gauss",
    "gauss": "gauss",
    "t": "T",
    "tesla": "T",
}
#: The Earth's surface field lies within about 22–67 µT; a value outside this is refused
#: (a unit mistake) unless it is what the user insists on with a unit that says so.
EARTH_FIELD_MIN_NT, EARTH_FIELD_MAX_NT = 15_000.0, 80_000.0
#: Heights the WMM is valid for, km (pygeomag: -1 to 850 km).
ALT_MIN_KM, ALT_MAX_KM = -1.0, 850.0


class FieldError(MagcalError):
    """The field strength cannot be determined from what was given."""


def canonical_unit(text: str) -> str | None:
    """A unit's canonical name (NT_PER_UNIT's keys), or None when unknown."""
    t = text.strip()
    if t in NT_PER_UNIT:
        return t
    return UNIT_ALIASES.get(t.lower())


def convert(value: float, from_unit: str, to_unit: str) -> float:
    """``value`` in ``from_unit`` expressed in ``to_unit`` (both canonical)."""
    return value * NT_PER_UNIT[from_unit] / NT_PER_UNIT[to_unit]


@dataclass(frozen=True)
class Field:
    """The local field: total intensity (nT), inclination (deg, positive down; None when not
    known), declination (deg; None when not known) and where it came from (text)."""

    total_nT: float
    inclination_deg: float | None
    declination_deg: float | None
    source: str

    def strength(self, unit: str) -> float:
        return convert(self.total_nT, "nT", unit)


def parse_field(text: str) -> Field:
    """``--field`` text: a number with its unit, "48.5uT", "485 mG", "0.485gauss"."""
    m = re.fullmatch(r"\s*([-+0-9.eE]+)\s*([A-Za-zµμ]+)\s*", text)
    if m is None:
        raise FieldError(
            f"--field {text!r}: give the field strength with its unit, e.g. 48.5uT, 485mG or "
            "0.485gauss (a bare number is refused: mG and gauss differ by 1000)"
        )
    try:
        value = float(m.group(1))
    except ValueError:
        raise FieldError(f"--field {text!r}: {m.group(1)!r} is not a number") from None
    unit = canonical_unit(m.group(2))
    if unit is None:
        raise FieldError(
            f"--field {text!r}: unknown unit {m.group(2)!r}: use uT, mG, gauss, nT or T"
        )
    nT = convert(value, unit, "nT")
    if not EARTH_FIELD_MIN_NT <= nT <= EARTH_FIELD_MAX_NT:
        raise FieldError(
            f"--field {text}: {nT / 1000:.4g} µT is not an Earth field (about 22–67 µT at the "
            "surface): check the number and its unit"
        )
    return Field(nT, None, None, f"--field {text.strip()}")


def parse_location(text: str) -> tuple[float, float, float]:
    """``--location`` text "LAT,LON[,ALT_KM]" (degrees north, east; km above sea level)."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (2, 3):
        raise FieldError(
            f"--location {text!r}: give LAT,LON or LAT,LON,ALT_KM in degrees (north and east "
            "positive) and km, e.g. 47.37,8.54,0.4"
        )
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise FieldError(f"--location {text!r}: the values must be numbers") from None
    lat, lon = values[0], values[1]
    alt = values[2] if len(values) == 3 else 0.0
    if not -90.0 <= lat <= 90.0:
        raise FieldError(f"--location {text}: latitude {lat} is outside −90…90°")
    if not -180.0 <= lon <= 360.0:
        raise FieldError(f"--location {text}: longitude {lon} is outside −180…360°")
    if not ALT_MIN_KM <= alt <= ALT_MAX_KM:
        raise FieldError(
            f"--location {text}: altitude {alt} km is outside the model's {ALT_MIN_KM:g}…"
            f"{ALT_MAX_KM:g} km (the third value is in km, not m)"
        )
    return lat, (lon + 180.0) % 360.0 - 180.0, alt


def decimal_year(day: dt.date) -> float:
    """The date as a decimal year (start of the day): 2025-07-02 → 2025.4986…"""
    start = dt.date(day.year, 1, 1)
    length = (dt.date(day.year + 1, 1, 1) - start).days
    return day.year + (day - start).days / length


def wmm_field(lat_deg: float, lon_deg: float, alt_km: float, day: dt.date) -> Field:
    """The World Magnetic Model's field at a place and date (pygeomag).

    lat_deg, lon_deg : geodetic degrees (north, east positive); alt_km : height, km.
    FieldError when the date lies outside the models pygeomag ships."""
    return wmm_field_at(lat_deg, lon_deg, alt_km, decimal_year(day), day.isoformat())


def wmm_field_at(
    lat_deg: float, lon_deg: float, alt_km: float, year: float, when: str = ""
) -> Field:
    """:func:`wmm_field` at a decimal year (2027.5); ``when`` names the date in messages."""
    from pygeomag import GeoMag

    when = when or f"{year:.3f}"
    try:
        model = GeoMag(base_year=int(year))
        r = model.calculate(glat=lat_deg, glon=lon_deg, alt=alt_km, time=year)
    except ValueError as exc:
        raise FieldError(
            f"World Magnetic Model for {when}: {exc}: give --date within the models' years "
            "(2010–2029) or the field with --field"
        ) from exc
    if not math.isfinite(r.f) or r.f <= 0:
        raise FieldError(f"World Magnetic Model at {lat_deg}, {lon_deg}: no field ({r.f})")
    where = f"{lat_deg:.4f}°, {lon_deg:.4f}°, {alt_km:g} km"
    return Field(
        float(r.f),
        float(r.i),
        float(r.d),
        f"World Magnetic Model {model.model} at {where} on {when}",
    )
