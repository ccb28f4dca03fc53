"""Magnetic declination and field strength from the World Magnetic Model (via ``pygeomag``).

The estimators work against magnetic north; the service turns the published heading to true
north by the declination (``estimator.declination_deg`` in the config, east positive). The
field strength is the F to pass to :func:`ahrs_service.calibration.magnetometer.fit_magnetometer`.

The WMM is valid for five years per release; ``pygeomag`` ships WMM-2010, -2015v2, -2020 and
-2025, so dates from 2010-01-01 to 2029-12-31 are covered. The model is defined for
altitudes from −1 km to 850 km above the WGS-84 ellipsoid.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from ahrs_service.core.settings import ConfigError, Section, number, optional

__all__ = ["LOCATION", "FieldAtPlace", "check_location_section", "declination_deg", "field_at"]

#: the altitudes the model is defined for, km above the WGS-84 ellipsoid
ALT_MIN_KM = -1.0
ALT_MAX_KM = 850.0

#: the ``[location]`` section of the configuration: where the vehicle flies. When latitude and
#: longitude are set, the magnetic declination comes from the World Magnetic Model for today
#: (it replaces estimator.declination_deg)
LOCATION: Section = {
    "latitude_deg": (None, optional(number(-90.0, 90.0))),
    "longitude_deg": (None, optional(number(-180.0, 180.0))),
    "altitude_km": (0.0, number(ALT_MIN_KM, ALT_MAX_KM)),
}


def check_location_section(section: dict[str, Any]) -> None:
    """The checked ``[location]`` section as a whole: a place is both coordinates or none."""
    if (section["latitude_deg"] is None) != (section["longitude_deg"] is None):
        raise ConfigError("location: give both latitude_deg and longitude_deg, or neither")


@dataclass(frozen=True)
class FieldAtPlace:
    """WMM field at a place and date: declination_deg (east positive), inclination_deg (down
    positive), total intensity field_ut (µT), and the model used (e.g. "WMM-2025")."""

    declination_deg: float
    inclination_deg: float
    field_ut: float
    model: str
    decimal_year: float


@lru_cache(maxsize=8)
def _model(coefficients_file: str) -> Any:
    try:
        from pygeomag import GeoMag
    except ImportError:
        # pygeomag is an optional dependency (the "analysis" extra)
        raise RuntimeError("the World Magnetic Model needs pygeomag: pip install 'ahrs-service[analysis]'") from None

    return GeoMag(coefficients_file=coefficients_file)


def _coefficients_for(year: float) -> str | None:
    # one file per five-year release; WMM-2015v2 supersedes WMM-2015
    for start, name in ((2025, "WMM_2025.COF"), (2020, "WMM_2020.COF"), (2015, "WMM_2015v2.COF"), (2010, "WMM_2010.COF")):
        if start <= year < start + 5:
            return "wmm/" + name
    return None


def _decimal_year(date: _dt.date) -> float:
    start = _dt.date(date.year, 1, 1)
    days = (_dt.date(date.year + 1, 1, 1) - start).days
    return date.year + (date - start).days / days


def _parse_date(date: _dt.date | str | None) -> _dt.date:
    if date is None:
        return _dt.datetime.now(_dt.timezone.utc).date()
    if isinstance(date, _dt.datetime):
        return date.date()
    if isinstance(date, _dt.date):
        return date
    if isinstance(date, str):
        try:
            return _dt.date.fromisoformat(date)
        except ValueError:
            raise ValueError(f"date must be YYYY-MM-DD, got {date!r}") from None
    raise ValueError(f"date must be a datetime.date or YYYY-MM-DD, got {date!r}")


def _finite(name: str, v: Any) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {v!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite, got {v!r}")
    return x


def field_at(lat_deg: float, lon_deg: float, alt_km: float = 0.0, date: _dt.date | str | None = None) -> FieldAtPlace:
    """The WMM field at geodetic latitude/longitude (degrees, north/east positive), altitude
    above the WGS-84 ellipsoid (km) and date (``datetime.date``, "YYYY-MM-DD", None = today UTC).

    Raises ValueError for latitude outside [−90, 90], longitude outside [−180, 180], altitude
    outside [−1, 850] km, or a date outside 2010.0–2030.0 (no WMM release covers it);
    RuntimeError when ``pygeomag`` is not installed.
    """
    lat = _finite("latitude", lat_deg)
    lon = _finite("longitude", lon_deg)
    alt = _finite("altitude", alt_km)
    if not -90.0 <= lat <= 90.0:
        raise ValueError(f"latitude must be within [-90, 90] degrees, got {lat_deg!r}")
    if not -180.0 <= lon <= 180.0:
        raise ValueError(f"longitude must be within [-180, 180] degrees, got {lon_deg!r}")
    if not ALT_MIN_KM <= alt <= ALT_MAX_KM:
        raise ValueError(f"altitude must be within [{ALT_MIN_KM:g}, {ALT_MAX_KM:g}] km (WMM), got {alt_km!r}")
    day = _parse_date(date)
    year = _decimal_year(day)
    coefficients = _coefficients_for(year)
    if coefficients is None:
        raise ValueError(f"date {day.isoformat()} is outside the World Magnetic Models available "
                         "(2010-01-01 to 2029-12-31)")
    model = _model(coefficients)
    r = model.calculate(glat=lat, glon=lon, alt=alt, time=year)
    return FieldAtPlace(float(r.d), float(r.i), float(r.f) / 1000.0, str(model.model), year)  # nT → µT


def declination_deg(lat_deg: float, lon_deg: float, alt_km: float = 0.0, date: _dt.date | str | None = None) -> float:
    """Magnetic declination in degrees, east positive (see :func:`field_at` for the inputs)."""
    return field_at(lat_deg, lon_deg, alt_km, date).declination_deg
