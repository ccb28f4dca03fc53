"""``ahrs-service calibrate mag|accel|gyro INPUT`` and ``ahrs-service declination``.

INPUT is either

* an ``.npz`` file with raw (uncalibrated, sensor-axes) arrays ``gyr`` (rad/s), ``acc``
  (m/s²) and/or ``mag`` (µT), each (N, 3), optionally ``t_ns`` (N,) timestamps or a scalar
  ``rate_hz``; or
* an ``.mcap`` flight log of the service. A log records the samples *as fed to the
  estimator* — calibrated and rotated into the body frame — so the calibration in force when
  they were recorded (the log's ``/config`` records, which also follow live calibrations) is
  undone first: gyr = Mᵀ·g_b + b_g, acc = A⁻¹·Mᵀ·a_b + b_a, mag = S⁻¹·Mᵀ·m_b + h. The
  magnetometer rows a log holds between two readings are repeats; only fresh readings
  (MAG_NEW) are used.

The result is printed with the ``[calibration]`` section it gives; ``--config FILE --write``
stores it in FILE (in place: its comments and layout are kept; old file kept as FILE.bak). Exit code 0: accepted, 1: refused (the
reason is printed), 2: bad input.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ahrs_service import config as config_mod
from ahrs_service.calibration.accelerometer import fit_accelerometer
from ahrs_service.calibration.declination import field_at
from ahrs_service.calibration.gyro import gyro_bias_at_rest
from ahrs_service.calibration.magnetometer import fit_magnetometer
from ahrs_service.calibration.storage import calibration_from_config_dict, calibration_section, save_calibration
from ahrs_service.core.calibration import SensorCalibration
from ahrs_service.core.samples import MAG_NEW, MAG_VALID
from ahrs_service.estimators import SAMPLE_ROW

_R = SAMPLE_ROW.slices

EXIT_ACCEPTED, EXIT_REFUSED, EXIT_BAD_INPUT = 0, 1, 2


class InputError(ValueError):
    """The input file cannot be used (missing, wrong format, wrong arrays)."""


@dataclass
class RawRecording:
    """Raw sensor-axes readings of one input: (N, 3) arrays or None, and the sample rate.

    mag_fresh: (N,) bool, rows whose magnetometer value is a new reading.
    calibration: the calibration in force in a log (None for .npz).
    """

    gyr: np.ndarray | None
    acc: np.ndarray | None
    mag: np.ndarray | None
    mag_fresh: np.ndarray | None
    rate_hz: float | None
    calibration: SensorCalibration | None = None
    t_ns: np.ndarray | None = None


# ---------------------------------------------------------------------------------- input
def _rate_from_times(t_ns: np.ndarray) -> float | None:
    if t_ns.shape[0] < 2:
        return None
    dt = np.diff(t_ns.astype(np.int64)) * 1e-9
    dt = dt[dt > 0]
    return float(1.0 / np.median(dt)) if dt.size else None


def load_npz(path: Path) -> RawRecording:
    """Raw arrays from an .npz file (see the module docstring)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from None
    arrays: dict[str, np.ndarray | None] = {}
    n = None
    for name in ("gyr", "acc", "mag"):
        a = data.get(name)
        if a is None:
            arrays[name] = None
            continue
        if a.ndim != 2 or a.shape[1] != 3 or not np.issubdtype(a.dtype, np.number):
            raise InputError(f"{path}: array {name!r} must be numeric of shape (N, 3), got {a.dtype} {a.shape}")
        if n is not None and a.shape[0] != n:
            raise InputError(f"{path}: arrays gyr/acc/mag must have the same length N")
        n = a.shape[0]
        arrays[name] = a.astype(float)
    if n is None:
        raise InputError(f"{path}: no array named gyr, acc or mag (found: {', '.join(sorted(data)) or 'none'})")
    t_ns = data.get("t_ns")
    rate = None
    if t_ns is not None:
        if t_ns.shape != (n,):
            raise InputError(f"{path}: t_ns must have shape ({n},), got {t_ns.shape}")
        rate = _rate_from_times(t_ns)
    if "rate_hz" in data:
        r = data["rate_hz"]
        if r.shape != () or not np.isfinite(r) or float(r) <= 0:
            raise InputError(f"{path}: rate_hz must be a positive scalar")
        rate = float(r)
    return RawRecording(arrays["gyr"], arrays["acc"], arrays["mag"], None, rate, None, t_ns)


def _unapply(rows: np.ndarray, cal: SensorCalibration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sensor-axes raw readings of body-frame calibrated rows (N, 10) — the inverse of apply_calibration."""
    Mt = cal.mounting.T
    gyr = rows[:, _R.gyr] @ Mt.T + cal.gyro_bias
    acc = rows[:, _R.acc] @ (np.linalg.inv(cal.acc_scale) @ Mt).T + cal.acc_bias
    mag = rows[:, _R.mag] @ (np.linalg.inv(cal.mag_soft_iron) @ Mt).T + cal.mag_hard_iron
    return gyr, acc, mag


def load_mcap(path: Path) -> RawRecording:
    """Raw readings of a flight log: its rows with the recorded calibration undone."""
    try:
        from ahrs_service.logs.reader import read_log
    except ImportError as exc:  # pragma: no cover - the log reader is part of the package
        raise InputError(f"reading .mcap logs needs ahrs_service.logs.reader ({exc})") from None
    try:
        log = read_log(path)
    except Exception as exc:  # noqa: BLE001 - any failure to read is bad input here
        raise InputError(f"{path}: not a readable flight log ({type(exc).__name__}: {exc})") from None
    if len(log) == 0:
        raise InputError(f"{path}: the log holds no /imu/raw samples")
    rows, t = log.rows, log.t_ns
    configs = sorted((c for c in log.configs if isinstance(c.get("config"), dict)), key=lambda c: int(c.get("t_ns", 0)))
    if not configs:
        configs = [{"t_ns": 0, "config": log.config}]
    gyr = np.empty((len(t), 3))
    acc = np.empty((len(t), 3))
    mag = np.empty((len(t), 3))
    cal = SensorCalibration()
    for i, c in enumerate(configs):
        try:
            cal = calibration_from_config_dict(c["config"])
        except ValueError as exc:
            raise InputError(f"{path}: the recorded calibration is not valid ({exc})") from None
        # each configuration holds from its time until the next one (the first from the start)
        lo = 0 if i == 0 else int(np.searchsorted(t, int(c["t_ns"])))
        hi = len(t) if i + 1 == len(configs) else int(np.searchsorted(t, int(configs[i + 1]["t_ns"])))
        if hi > lo:
            gyr[lo:hi], acc[lo:hi], mag[lo:hi] = _unapply(rows[lo:hi], cal)
    fresh = (log.flags & MAG_NEW) != 0
    if not fresh.any():  # a writer without MAG_NEW: take every change of value as fresh
        fresh = np.concatenate([[True], np.any(np.diff(rows[:, _R.mag], axis=0) != 0, axis=1)])
    fresh &= (log.flags & MAG_VALID) != 0
    has_mag = np.isfinite(rows[:, _R.mag]).any()
    return RawRecording(gyr, acc, mag if has_mag else None, fresh if has_mag else None, _rate_from_times(t), cal, t)


def load_input(path: str | Path) -> RawRecording:
    """An .npz or .mcap input (see the module docstring); InputError when unusable."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a directory, not a file")
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if not p.is_file():
        raise InputError(f"{p}: not a regular file")
    suffix = p.suffix.lower()
    if suffix == ".npz":
        return load_npz(p)
    if suffix == ".mcap":
        return load_mcap(p)
    raise InputError(f"{p}: unknown input type {suffix!r}: give an .mcap flight log or an .npz with gyr/acc/mag arrays")


def _window(rec: RawRecording, start_s: float | None, end_s: float | None) -> RawRecording:
    """The rows between start_s and end_s seconds after the first sample."""
    if start_s is None and end_s is None:
        return rec
    n = next(a.shape[0] for a in (rec.gyr, rec.acc, rec.mag) if a is not None)
    if rec.t_ns is not None:
        t = (rec.t_ns - rec.t_ns[0]) * 1e-9
    elif rec.rate_hz:
        t = np.arange(n) / rec.rate_hz
    else:
        raise InputError("--start/--end need timestamps (t_ns) or rate_hz in the input")
    keep = np.ones(n, dtype=bool)
    if start_s is not None:
        keep &= t >= start_s
    if end_s is not None:
        keep &= t <= end_s

    def cut(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else a[keep]

    return dataclasses.replace(rec, gyr=cut(rec.gyr), acc=cut(rec.acc), mag=cut(rec.mag),
                               mag_fresh=cut(rec.mag_fresh), t_ns=cut(rec.t_ns))


def _need(rec: RawRecording, *names: str) -> None:
    missing = [n for n in names if getattr(rec, n) is None]
    if missing:
        hint = ""
        if "mag" in missing and rec.calibration is not None:
            hint = " (a flight log holds magnetometer values only when its estimator used them)"
        raise InputError(f"the input has no {' or '.join(missing)} readings{hint}")


# ---------------------------------------------------------------------------------- calibrate
def _fit(kind: str, rec: RawRecording, args: argparse.Namespace) -> tuple[Any, bool, dict[str, np.ndarray]]:
    """Runs the fit; returns (result, accepted, the new sensor terms)."""
    if kind == "mag":
        _need(rec, "mag")
        mag = rec.mag if rec.mag_fresh is None else rec.mag[rec.mag_fresh]
        res = fit_magnetometer(mag, field_strength=args.field_strength, min_coverage=args.min_coverage,
                               max_residual_rel=args.max_residual)
        return res, res.accepted, {"mag_hard_iron": res.hard_iron, "mag_soft_iron": res.soft_iron}
    if kind == "gyro":
        _need(rec, "gyr", "acc")
        res = gyro_bias_at_rest(rec.gyr, rec.acc, max_gyro_std=args.max_gyro_std)
        return res, res.at_rest, {"gyro_bias": res.bias}
    _need(rec, "acc")
    rate = args.rate_hz or rec.rate_hz
    if rate is None:
        raise InputError("the accelerometer fit needs the sample rate: t_ns or rate_hz in the input, or --rate-hz")
    res = fit_accelerometer(rec.acc, rec.gyr, sample_rate_hz=rate, g=args.g)
    return res, res.accepted, {"acc_bias": res.bias, "acc_scale": res.scale}


def _calibrate(args: argparse.Namespace) -> int:
    kind = args.sensor
    try:
        if args.write and not args.config:
            raise InputError("--write needs --config FILE (the configuration to update)")
        current = None
        if args.config:
            current = calibration_from_config_dict(config_mod.load(args.config).raw)
        rec = _window(load_input(args.input), args.start, args.end)
        if current is None:
            current = rec.calibration or SensorCalibration()
        res, accepted, terms = _fit(kind, rec, args)
    except (InputError, config_mod.ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"{kind} calibration of {args.input}")
    print(res.summary())
    if not accepted:
        print(f"REFUSED: {res.reason}")
        return EXIT_REFUSED
    new = dataclasses.replace(current, **terms)
    print("accepted; the [calibration] section becomes:\n")
    print(config_mod.to_toml({"calibration": calibration_section(new)}))
    if args.write:
        try:
            path = save_calibration(args.config, new)
        except (config_mod.ConfigError, OSError) as exc:
            print(f"error: not written: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        print(f"written to {path} (previous file kept as {path.name}.bak)")
    return EXIT_ACCEPTED


# ---------------------------------------------------------------------------------- declination
def _declination(args: argparse.Namespace) -> int:
    try:
        f = field_at(args.lat, args.lon, args.alt_km, args.date)
    except (ValueError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"declination:  {f.declination_deg:+.3f}° ({'east' if f.declination_deg >= 0 else 'west'})")
    print(f"inclination:  {f.inclination_deg:+.3f}°")
    print(f"field:        {f.field_ut:.3f} µT")
    print(f"model:        {f.model} at {f.decimal_year:.3f}")
    print(f"config:       [estimator] declination_deg = {f.declination_deg:.2f}")
    return EXIT_ACCEPTED


def add_subcommands(subparsers: Any) -> None:
    """Adds ``calibrate`` and ``declination`` to the ``ahrs-service`` command line."""
    cal = subparsers.add_parser(
        "calibrate", help="fit a sensor calibration from a recording",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sensors = cal.add_subparsers(dest="sensor", required=True, metavar="SENSOR")
    helps = {
        "mag": "hard/soft iron from readings in all orientations",
        "accel": "six-position bias and scale (each axis up and down, held still)",
        "gyro": "bias from a recording at rest",
    }
    for kind, text in helps.items():
        p = sensors.add_parser(kind, help=text, description=text)
        p.add_argument("input", metavar="INPUT", help=".mcap flight log or .npz with raw gyr/acc/mag arrays")
        p.add_argument("--config", metavar="FILE", help="configuration whose calibration is updated")
        p.add_argument("--write", action="store_true", help="store an accepted result in --config FILE")
        p.add_argument("--start", type=float, metavar="S", help="use samples from S seconds after the first")
        p.add_argument("--end", type=float, metavar="S", help="use samples up to S seconds after the first")
        if kind == "mag":
            p.add_argument("--field-strength", type=float, metavar="UT",
                           help="local field in µT (see `ahrs-service declination`); default: det S = 1")
            p.add_argument("--min-coverage", type=float, default=0.5, help="fraction of directions needed (0.5)")
            p.add_argument("--max-residual", type=float, default=0.05, help="largest rms residual / field (0.05)")
        elif kind == "gyro":
            p.add_argument("--max-gyro-std", type=float, default=0.02, help="largest gyro std at rest, rad/s (0.02)")
        else:
            p.add_argument("--rate-hz", type=float, help="sample rate when the input has no timestamps")
            p.add_argument("--g", type=float, default=9.80665, help="local gravity, m/s² (9.80665)")
        p.set_defaults(func=_calibrate)

    dec = subparsers.add_parser("declination", help="magnetic declination and field from the World Magnetic Model")
    dec.add_argument("--lat", type=float, required=True, help="latitude, degrees north")
    dec.add_argument("--lon", type=float, required=True, help="longitude, degrees east")
    dec.add_argument("--alt-km", type=float, default=0.0, help="altitude above the WGS-84 ellipsoid, km (0)")
    dec.add_argument("--date", help="YYYY-MM-DD (default: today, UTC)")
    dec.set_defaults(func=_declination)
