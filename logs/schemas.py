"""Channels of a flight log and their JSON Schemas, defined once for writer, reader and tests.

Every channel is JSON-encoded (MCAP message encoding ``"json"``) and carries a JSON Schema
(schema encoding ``"jsonschema"``), which is what Foxglove expects for JSON data.

Conventions (docs/design.md): earth NED, body FRD, quaternions Hamilton [w, x, y, z]
q_earth←body, gyroscope rad/s, specific force m/s², field µT, times in ns. Numbers that are
not finite (NaN: "no magnetometer", an invalid reading) are written as ``null`` because JSON
has no NaN; readers turn ``null`` back into NaN. Floats are written in their shortest
round-trip form, so every float64 reads back bit-exact.

The ``*_message`` functions build the messages of the main channels from plain values;
:func:`encode` turns any message into its bytes (orjson) and :func:`decode` back.

The one exception to our quaternion order is ``/tf``: it uses Foxglove's own
``foxglove.FrameTransform`` schema, whose rotation is {x, y, z, w}.

:func:`validate` checks a message against these schemas; it implements the small subset of
JSON Schema used here (type, properties, required, items, minItems, maxItems,
additionalProperties, enum), because the ``jsonschema`` package is not a dependency.
"""

from __future__ import annotations

import collections.abc
import json
import math
from typing import Any

import numpy as np
import orjson

from ahrs_service.core.quaternion import euler_of as euler
from ahrs_service.core.samples import (
    ACC_SATURATED,
    ACC_VALID,
    GYR_SATURATED,
    GYR_VALID,
    MAG_NEW,
    MAG_SATURATED,
    MAG_VALID,
)
from ahrs_service.estimators import SAMPLE_ROW

_R = SAMPLE_ROW.slices

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"

_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
_INT = {"type": "integer"}


def _vec(n: int, item: dict[str, Any], description: str) -> dict[str, Any]:
    return {"type": "array", "items": item, "minItems": n, "maxItems": n, "description": description}


_T_NS = {"type": "integer", "description": "sample timestamp, ns, monotonic clock of the host"}
_QUAT = _vec(4, _NUM_OR_NULL, "q_earth←body [w, x, y, z], Hamilton, earth NED, body FRD")

IMU_RAW = {
    "title": "ahrs.ImuRaw",
    "description": "One IMU sample exactly as fed to the estimator (calibrated, body frame FRD).",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer", "description": "the sample's time, ns, monotonic clock of the host: "
                 "its instant on the sensor's clock (recovered from the source's stamps), the times dt comes from"},
        "t_source_ns": {"type": ["integer", "null"], "description": "the source's own stamp of the sample, ns "
                        "(a polling source: the host's read time); null or absent: the same as t_ns"},
        "index": {"type": ["integer", "null"], "description": "sample number since the writer started"},
        "dt": {"type": ["number", "null"], "description": "time step fed to the estimator, s"},
        "gyr": _vec(3, _NUM_OR_NULL, "angular rate, rad/s, body FRD"),
        "acc": _vec(3, _NUM_OR_NULL, "specific force, m/s², body FRD"),
        "mag": {
            "type": ["array", "null"],
            "items": _NUM_OR_NULL,
            "minItems": 3,
            "maxItems": 3,
            "description": "magnetic field, µT, body FRD; null when there is no reading",
        },
        "flags": {"type": "integer", "description": "validity bit mask (ahrs_service.core.samples)"},
        "valid": {
            "type": "object",
            "description": "the flag bits decoded",
            "properties": {
                "gyr": {"type": "boolean"},
                "acc": {"type": "boolean"},
                "mag": {"type": "boolean"},
                "gyr_saturated": {"type": "boolean"},
                "acc_saturated": {"type": "boolean"},
                "mag_saturated": {"type": "boolean"},
                "mag_new": {"type": "boolean"},
            },
            "required": ["gyr", "acc", "mag"],
        },
        "raw": {"type": ["object", "null"], "description": "uncalibrated readings (counts) when the driver has them"},
        "temperature": {"type": ["number", "null"], "description": "sensor temperature, °C"},
    },
    "required": ["t_ns", "dt", "gyr", "acc", "mag", "flags", "valid"],
}

ATTITUDE = {
    "title": "ahrs.Attitude",
    "description": "The estimate after one sample.",
    "type": "object",
    "properties": {
        "t_ns": _T_NS,
        "q": _QUAT,
        "roll": {"type": ["number", "null"], "description": "rad, ZYX Euler (null: q not finite)"},
        "pitch": {"type": ["number", "null"], "description": "rad, ZYX Euler"},
        "yaw": {"type": ["number", "null"], "description": "rad, ZYX Euler, (−π, π]"},
        "estimator": {"type": "string"},
        "gyro_bias": _vec(3, _NUM_OR_NULL, "gyro-bias estimate, rad/s, body FRD"),
        "diagnostics": {
            "type": "object",
            "description": "estimator counters (initialised, *_skipped …)",
            "properties": {
                # optional: in the diagnostics the service writes at log.diagnostics_hz
                "attitude_variance": {
                    "type": "object",
                    "description": "variances of roll, pitch, yaw (ZYX), rad²; null: unknown (estimators.uncertainty)",
                    "properties": {k: {"type": ["number", "null"]} for k in ("roll", "pitch", "yaw")},
                },
                "gaps": {"type": "integer", "description": "sample gaps the estimator bridged since its start"},
                "gap_error_deg": {"type": "number",
                                  "description": "1σ (roll, pitch) of the rotation the gaps may have left uncorrected, deg, as attitude_variance adds it"},
                "realignments": {"type": "integer",
                                 "description": "tilt realignments from the averaged specific force after gaps"},
                # the service's divergence monitor (core/divergence.py), when [divergence] enabled
                "diverged": {"type": "boolean", "description": "the attitude is flagged as not trustworthy"},
                "innovation_test_ratio": {"type": ["number", "null"],
                                          "description": "the monitor's larger test ratio (> 1 flags); null: too few samples"},
                "tilt_innovation_deg": {"type": ["number", "null"],
                                        "description": "mean specific force's angle from the estimated vertical, deg"},
                "heading_innovation_deg": {"type": ["number", "null"],
                                           "description": "mean field's direction east of the estimated north, deg"},
                "divergence_flags": {"type": "integer", "description": "times the monitor flagged since the start"},
            },
        },
    },
    "required": ["t_ns", "q", "roll", "pitch", "yaw", "estimator"],
}

TRUTH = {
    "title": "ahrs.AttitudeTruth",
    "description": "Ground-truth attitude where known (simulator, optical tracking).",
    "type": "object",
    "properties": {
        "t_ns": _T_NS,
        "q": _QUAT,
        "roll": _NUM_OR_NULL,
        "pitch": _NUM_OR_NULL,
        "yaw": _NUM_OR_NULL,
        "movement": {"type": ["boolean", "null"], "description": "BROAD: sample is scored"},
        "source": {"type": "string"},
    },
    "required": ["t_ns", "q"],
}

# Block channels: one message per FIFO burst, for sources faster than
# ``log.block_messages_above_hz`` (the per-sample channels' cost, two MCAP messages a sample,
# is what a log of an 8 kHz part cannot afford; PX4 logs its FIFO bursts the same way, as
# ``sensor_gyro_fifo``). Row i of every array is sample i of the burst.
def _rows_of(item: dict[str, Any], description: str) -> dict[str, Any]:
    return {"type": "array", "items": item, "description": description}


IMU_RAW_BLOCK = {
    "title": "ahrs.ImuRawBlock",
    "description": "The samples of one FIFO burst exactly as fed to the estimator (calibrated, body FRD), "
    "row i of every array being sample first_index + i; the same values as that many ahrs.ImuRaw.",
    "type": "object",
    "properties": {
        "t_ns": _rows_of(_INT, "each sample's time, ns, monotonic clock of the host (as ahrs.ImuRaw t_ns)"),
        "t_source_ns": {"type": ["array", "null"], "items": _INT,
                        "description": "the source's own stamps, ns; null: the same as t_ns"},
        "first_index": {"type": "integer", "description": "sample number (since the writer started) of row 0"},
        "dt": _rows_of(_NUM_OR_NULL, "time step fed to the estimator, s"),
        "gyr": _rows_of(_vec(3, _NUM_OR_NULL, "rad/s"), "angular rate, rad/s, body FRD"),
        "acc": _rows_of(_vec(3, _NUM_OR_NULL, "m/s²"), "specific force, m/s², body FRD"),
        "mag": _rows_of(_vec(3, _NUM_OR_NULL, "µT"), "magnetic field, µT, body FRD; nulls: no reading"),
        "flags": _rows_of(_INT, "validity bit mask (ahrs_service.core.samples)"),
        "raw": {"type": ["object", "null"], "description": "uncalibrated readings (counts), {name: one entry per row}"},
        "temperature": {"type": ["array", "null"], "items": _NUM_OR_NULL, "description": "°C per row"},
    },
    "required": ["t_ns", "first_index", "dt", "gyr", "acc", "mag", "flags"],
}

ATTITUDE_BLOCK = {
    "title": "ahrs.AttitudeBlock",
    "description": "The estimate after each sample of one burst (row i: after sample i of the "
    "ahrs.ImuRawBlock at the same log time); bias and diagnostics after the last row.",
    "type": "object",
    "properties": {
        "t_ns": _rows_of(_INT, "each sample's time, ns"),
        "q": _rows_of(_QUAT, "q_earth←body [w, x, y, z] after each sample"),
        "estimator": {"type": "string"},
        "gyro_bias": _vec(3, _NUM_OR_NULL, "gyro-bias estimate after the last row, rad/s, body FRD"),
        "diagnostics": ATTITUDE["properties"]["diagnostics"],
    },
    "required": ["t_ns", "q", "estimator"],
}

TRUTH_BLOCK = {
    "title": "ahrs.AttitudeTruthBlock",
    "description": "Ground-truth attitude of each sample of one burst (simulator).",
    "type": "object",
    "properties": {
        "t_ns": _rows_of(_INT, "each sample's time, ns"),
        "q": _rows_of(_QUAT, "q_earth←body [w, x, y, z], NED"),
        "source": {"type": "string"},
    },
    "required": ["t_ns", "q"],
}

LOOP = {
    "title": "ahrs.LoopStats",
    "description": "Scheduler statistics over the last window of ticks (times in µs), estimator "
    "and sensor fault counters. Further keys are allowed.",
    "type": "object",
    "properties": {
        "t_ns": _T_NS,
        "rate_hz": _NUM_OR_NULL,
        "ticks": _INT,
        "overruns": _INT,
        "missed_ticks": _INT,
        "period_jitter_p50_us": _NUM_OR_NULL,
        "period_jitter_p99_us": _NUM_OR_NULL,
        "period_jitter_max_us": _NUM_OR_NULL,
        "lateness_p99_us": _NUM_OR_NULL,
        "load_percent": _NUM_OR_NULL,
        "reduced": {"type": "boolean", "description": "estimating without magnetometer"},
        "estimator": {"type": "object", "description": "the estimator's diagnostics counters"},
        "source": {"type": "object", "description": "the sensor source's fault counters"},
        "log": {"type": "object", "description": "the log writer's own counters (FlightLogWriter.stats)"},
        "process_cpu_s": {"type": "number", "description": "the service process's CPU time since its start, s"},
        "simulation_cpu_s": {"type": "number", "description": "of process_cpu_s, the simulated hardware's "
                             "(a simulated bus's transfers and its parts' samples), s"},
    },
    "required": ["t_ns"],
}

CONFIG = {
    "title": "ahrs.Config",
    "description": "Effective configuration; written at the start of every file and on reload.",
    "type": "object",
    "properties": {
        "t_ns": _T_NS,
        "reason": {"type": "string", "description": "start | reload | rotation"},
        "config": {"type": "object", "description": "config['estimator'] = {'name', 'params'}"},
    },
    "required": ["t_ns", "config"],
}

PARAM_CHANGE = {
    "title": "ahrs.ParamChange",
    "description": "A live parameter change; it applies from sample number sample_index on.",
    "type": "object",
    "properties": {
        "t_ns": _T_NS,
        "sample_index": {"type": "integer", "description": "samples fed to the estimator before the change"},
        "name": {"type": "string"},
        "old": {},
        "new": {},
        "source": {"type": "string", "description": "mavlink | config | cli …"},
    },
    "required": ["t_ns", "sample_index", "name", "old", "new", "source"],
}

MAVLINK = {
    "title": "ahrs.MavlinkStats",
    "description": "MAVLink traffic summary counters.",
    "type": "object",
    "properties": {"t_ns": _T_NS, "counters": {"type": "object"}},
    "required": ["t_ns", "counters"],
}

ESTIMATOR_STATE = {
    "title": "ahrs.EstimatorState",
    "description": "The estimator's full state at a file start after rotation: replaying the file "
    "from it reproduces the recorded estimate exactly.",
    "type": "object",
    "properties": {
        "t_ns": _T_NS,
        "sample_index": {"type": "integer", "description": "the first sample processed from this state"},
        "estimator": {"type": "string"},
        "state": {"type": "array", "items": _NUM_OR_NULL, "description": "Estimator.state (float64)"},
    },
    "required": ["t_ns", "sample_index", "estimator", "state"],
}

_XYZ = {
    "type": "object",
    "properties": {"x": _NUM, "y": _NUM, "z": _NUM},
    "required": ["x", "y", "z"],
}

FRAME_TRANSFORM = {
    "title": "foxglove.FrameTransform",
    "description": "A transform between two reference frames in 3D space",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "title": "time",
            "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
            "required": ["sec", "nsec"],
        },
        "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"},
        "translation": _XYZ,
        "rotation": {
            "type": "object",
            "description": "Foxglove order: x, y, z, w",
            "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM},
            "required": ["x", "y", "z", "w"],
        },
    },
    "required": ["timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"],
}

LOG = {
    "title": "foxglove.Log",
    "description": "A health event (sensor fault, reduced form, rejection, overrun, calibration, "
    "parameter change): Foxglove's own log schema, shown by its Log panel",
    "type": "object",
    "properties": {
        "timestamp": FRAME_TRANSFORM["properties"]["timestamp"],
        "level": {
            "type": "integer",
            "enum": [0, 1, 2, 3, 4, 5],
            "description": "0 unknown, 1 debug, 2 info, 3 warning, 4 error, 5 fatal",
        },
        "message": {"type": "string"},
        "name": {"type": "string", "description": "who logged it (ahrs-service)"},
        "file": {"type": "string"},
        "line": {"type": "integer", "minimum": 0},
    },
    "required": ["timestamp", "level", "message", "name", "file", "line"],
}

MONITOR = {
    "title": "ahrs.AttitudeMonitor",
    "description": "The autopilot's attitude against the service's estimate at the autopilot's time "
    "(ahrs_service/attitude_monitor.py).",
    "type": "object",
    "properties": {
        "t_ns": _T_NS,
        "total_deg": _NUM_OR_NULL,
        "inclination_deg": _NUM_OR_NULL,
        "heading_deg": {"type": ["number", "null"], "description": "autopilot yaw - ours, deg, [-180, 180)"},
        "q_autopilot": _QUAT,
        "q_estimate": _QUAT,
    },
    "required": ["t_ns", "total_deg", "inclination_deg", "heading_deg"],
}

TIMESYNC = {
    "title": "ahrs.Timesync",
    "description": "The autopilot's clock against ours after each accepted TIMESYNC sample "
    "(protocols/mavlink/timesync.py, TimesyncStatus).",
    "type": "object",
    "properties": {
        "t_ns": _T_NS,
        "offset_ns": {"type": "integer", "description": "estimated autopilot − our clock at t_ns, ns"},
        "observed_offset_ns": {"type": "integer", "description": "this sample's offset, ns"},
        "drift_ppm": _NUM_OR_NULL,
        "rtt_ns": {"type": "integer", "description": "this sample's round trip, ns"},
        "synced": {"type": "boolean"},
        "samples": {"type": "integer", "description": "accepted samples in the estimate"},
    },
    "required": ["t_ns", "offset_ns", "drift_ppm", "rtt_ns", "synced"],
}

#: topic -> (schema name, JSON Schema)
CHANNELS: dict[str, tuple[str, dict[str, Any]]] = {
    "/imu/raw": ("ahrs.ImuRaw", IMU_RAW),
    "/attitude": ("ahrs.Attitude", ATTITUDE),
    "/attitude/original": ("ahrs.Attitude", ATTITUDE),
    "/attitude/truth": ("ahrs.AttitudeTruth", TRUTH),
    # one message per FIFO burst instead of per sample, above log.block_messages_above_hz
    "/imu/raw_block": ("ahrs.ImuRawBlock", IMU_RAW_BLOCK),
    "/attitude_block": ("ahrs.AttitudeBlock", ATTITUDE_BLOCK),
    "/attitude/original_block": ("ahrs.AttitudeBlock", ATTITUDE_BLOCK),
    "/attitude/truth_block": ("ahrs.AttitudeTruthBlock", TRUTH_BLOCK),
    # beside an autopilot: its own attitude (estimator "autopilot") and the comparison
    "/autopilot/attitude": ("ahrs.Attitude", ATTITUDE),
    "/monitor": ("ahrs.AttitudeMonitor", MONITOR),
    "/timesync": ("ahrs.Timesync", TIMESYNC),
    "/loop": ("ahrs.LoopStats", LOOP),
    "/config": ("ahrs.Config", CONFIG),
    "/params": ("ahrs.ParamChange", PARAM_CHANGE),
    "/mavlink": ("ahrs.MavlinkStats", MAVLINK),
    "/estimator/state": ("ahrs.EstimatorState", ESTIMATOR_STATE),
    "/tf": ("foxglove.FrameTransform", FRAME_TRANSFORM),
    "/log": ("foxglove.Log", LOG),
}


def schema_bytes(topic: str) -> bytes:
    """The schema of ``topic`` as stored in the MCAP Schema record."""
    return json.dumps(CHANNELS[topic][1], ensure_ascii=False).encode()


# --------------------------------------------------------------------------- building messages


def num_or_null(x: float) -> float | None:
    """x, or None (JSON null) when it is not finite."""
    return x if math.isfinite(x) else None


def jsonable(value: Any) -> Any:
    """``value`` with NumPy scalars/arrays turned into Python ones and non-finite floats into None."""
    t = type(value)  # the common plain values first: the Mapping ABC check is slow
    if t is str or t is int or t is bool or value is None:
        return value
    if t is float:
        return num_or_null(value)
    if isinstance(value, collections.abc.Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return num_or_null(float(value))
    if value is None or isinstance(value, str):
        return value
    return str(value)  # paths, enums …: readable rather than a lost message


_VALID_BITS = GYR_VALID | ACC_VALID | MAG_VALID | GYR_SATURATED | ACC_SATURATED | MAG_SATURATED | MAG_NEW
_valid_cache: dict[int, dict[str, bool]] = {}


def _valid(flags: int) -> dict[str, bool]:
    """The /imu/raw "valid" object: the flag bits decoded (one shared dict per bit pattern)."""
    bits = int(flags) & _VALID_BITS
    valid = _valid_cache.get(bits)
    if valid is None:
        valid = _valid_cache[bits] = {
            "gyr": bool(bits & GYR_VALID),
            "acc": bool(bits & ACC_VALID),
            "mag": bool(bits & MAG_VALID),
            "gyr_saturated": bool(bits & GYR_SATURATED),
            "acc_saturated": bool(bits & ACC_SATURATED),
            "mag_saturated": bool(bits & MAG_SATURATED),
            "mag_new": bool(bits & MAG_NEW),
        }
    return valid


# The builders below return the message as :func:`encode` writes it. Floats may be NaN or ±inf
# in the dict: encode writes them as null, which readers turn back into NaN.


def raw_message(
    t_ns: int,
    row: list[float],
    flags: int,
    raw: Any = None,
    temperature: float | None = None,
    index: int | None = None,
    t_source_ns: int | None = None,
) -> dict[str, Any]:
    """The /imu/raw message of one sample row [gx, gy, gz, ax, ay, az, mx, my, mz, dt].

    index: the sample's number since the writer started (what /params sample_index counts).
    t_source_ns: the source's own stamp when it differs in kind from ``t_ns`` (host read time
    of a polling source, whose ``t_ns`` is the recovered time); None: the same as ``t_ns``.
    """
    mx, my, mz = mag = row[_R.mag]
    return {
        "t_ns": int(t_ns),
        "t_source_ns": None if t_source_ns is None else int(t_source_ns),
        "index": index,
        "dt": row[SAMPLE_ROW.index.dt],
        "gyr": row[_R.gyr],
        "acc": row[_R.acc],
        "mag": None if (mx != mx and my != my and mz != mz) else mag,  # all NaN: no reading
        "flags": int(flags),
        "valid": _valid(flags),
        "raw": raw,
        "temperature": temperature,
    }


def attitude_message(
    t_ns: int, q: list[float], estimator: str, bias: list[float] | None = None, diagnostics: Any = None
) -> dict[str, Any]:
    """The /attitude message: q_earth←body [w, x, y, z] (NED/FRD), Euler angles, bias (rad/s)."""
    roll, pitch, yaw = euler(q)
    return {
        "t_ns": int(t_ns),
        "q": q,
        "roll": roll,
        "pitch": pitch,
        "yaw": yaw,
        "estimator": str(estimator),
        "gyro_bias": bias if bias is not None else [0.0, 0.0, 0.0],
        "diagnostics": diagnostics or {},
    }


def truth_message(t_ns: int, q: list[float], movement: bool | None = None, source: str = "") -> dict[str, Any]:
    """The /attitude/truth message (q_earth←body [w, x, y, z], NED/FRD)."""
    roll, pitch, yaw = euler(q)
    return {
        "t_ns": int(t_ns),
        "q": q,
        "roll": roll,
        "pitch": pitch,
        "yaw": yaw,
        "movement": movement,
        "source": source,
    }


def raw_block_message(
    t_ns: list[int],
    rows: np.ndarray,
    flags: list[int],
    first_index: int,
    raw: dict[str, np.ndarray] | None = None,
    temperature: np.ndarray | None = None,
    t_source_ns: list[int] | None = None,
) -> dict[str, Any]:
    """The /imu/raw_block message of a burst's (n, 10) sample rows [gx, gy, gz, ax, ay, az,
    mx, my, mz, dt] (float64); row i is sample number ``first_index + i``."""
    rows = np.asarray(rows, dtype=np.float64)
    return {
        "t_ns": t_ns,
        "t_source_ns": t_source_ns,
        "first_index": int(first_index),
        "dt": rows[:, SAMPLE_ROW.index.dt].tolist(),
        "gyr": rows[:, _R.gyr].tolist(),
        "acc": rows[:, _R.acc].tolist(),
        "mag": rows[:, _R.mag].tolist(),  # NaN (no reading) is written as null
        "flags": flags,
        "raw": None if raw is None else {k: np.asarray(v).tolist() for k, v in raw.items()},
        "temperature": None if temperature is None else np.asarray(temperature, dtype=np.float64).tolist(),
    }


def attitude_block_message(t_ns: list[int], q: np.ndarray, estimator: str, bias: list[float] | None = None,
                           diagnostics: Any = None) -> dict[str, Any]:
    """The /attitude_block message: (n, 4) q_earth←body [w, x, y, z] after each sample of a
    burst; ``bias`` (rad/s) and ``diagnostics`` after the last one (left out when None)."""
    message: dict[str, Any] = {"t_ns": t_ns, "q": np.asarray(q, dtype=np.float64).tolist(), "estimator": str(estimator)}
    if bias is not None:
        message["gyro_bias"] = list(bias)
    if diagnostics:
        message["diagnostics"] = diagnostics
    return message


def truth_block_message(t_ns: list[int], q: np.ndarray, source: str = "") -> dict[str, Any]:
    """The /attitude/truth_block message: (n, 4) true q_earth←body [w, x, y, z] (NED)."""
    return {"t_ns": t_ns, "q": np.asarray(q, dtype=np.float64).tolist(), "source": source}


def monitor_message(t_ns: int, total_deg: float, inclination_deg: float, heading_deg: float,
                    q_autopilot: list[float], q_estimate: list[float]) -> dict[str, Any]:
    """The /monitor message: the autopilot's attitude against ours at the autopilot's time
    (ahrs_service/attitude_monitor.py), degrees; both q_earth←body [w, x, y, z] (NED/FRD)."""
    return {"t_ns": int(t_ns), "total_deg": num_or_null(total_deg), "inclination_deg": num_or_null(inclination_deg),
            "heading_deg": num_or_null(heading_deg), "q_autopilot": list(q_autopilot), "q_estimate": list(q_estimate)}


def autopilot_attitude_messages(t_ns: int, q_autopilot: list[float], q_estimate: list[float], total_deg: float,
                                inclination_deg: float, heading_deg: float) -> dict[str, dict[str, Any]]:
    """One comparison of the attitude monitor as its messages by topic, for the log and the
    live view alike: the autopilot's attitude on /autopilot/attitude and as frame
    ``autopilot`` on /tf, the disagreement on /monitor (:func:`monitor_message`)."""
    return {
        "/autopilot/attitude": attitude_message(t_ns, q_autopilot, "autopilot"),
        "/tf": tf_message(t_ns, q_autopilot, child="autopilot"),
        "/monitor": monitor_message(t_ns, total_deg, inclination_deg, heading_deg, q_autopilot, q_estimate),
    }


def tf_message(t_ns: int, q: list[float], child: str = "body") -> dict[str, Any]:
    """foxglove.FrameTransform of the body frame (or ``child``: ``"autopilot"``, the autopilot's
    attitude beside an autopilot) in the NED frame (rotation in x, y, z, w order)."""
    return {
        "timestamp": {"sec": int(t_ns) // 1_000_000_000, "nsec": int(t_ns) % 1_000_000_000},
        "parent_frame_id": "ned",
        "child_frame_id": child,
        "translation": {"x": 0.0, "y": 0.0, "z": 0.0},
        "rotation": {"x": q[1], "y": q[2], "z": q[3], "w": q[0]},
    }


# MAVLink STATUSTEXT severity (MAV_SEVERITY, 0 EMERGENCY … 7 DEBUG) -> foxglove.Log level
# (1 DEBUG, 2 INFO, 3 WARNING, 4 ERROR, 5 FATAL). The three "act now" severities all map to
# FATAL, NOTICE joins INFO: Foxglove has five levels for MAVLink's eight (docs/live.md).
LOG_LEVEL_OF_SEVERITY: tuple[int, ...] = (5, 5, 5, 4, 3, 2, 2, 1)
LOG_NAME = "ahrs-service"


def log_level(severity: int) -> int:
    """The foxglove.Log level of a MAVLink severity (out-of-range severities: 0, unknown)."""
    return LOG_LEVEL_OF_SEVERITY[severity] if 0 <= severity < len(LOG_LEVEL_OF_SEVERITY) else 0


def log_message(t_ns: int, severity: int, text: str) -> dict[str, Any]:
    """The /log message (foxglove.Log) of a health event reported with a MAVLink severity."""
    return {
        "timestamp": {"sec": int(t_ns) // 1_000_000_000, "nsec": int(t_ns) % 1_000_000_000},
        "level": log_level(int(severity)),
        "message": str(text),
        "name": LOG_NAME,
        "file": "",
        "line": 0,
    }


# --------------------------------------------------------------------------- encoding
#
# The writer thread encodes /imu/raw, /attitude and /attitude/truth at the sample rate (1 kHz),
# some thirty floats a sample. Python's float repr costs about a microsecond here, which made
# json.dumps the largest single cost of the service; orjson formats the same shortest
# round-trip text (ryu) about ten times faster and writes non-finite floats as null, our
# convention. Values orjson does not take (non-str keys, Paths, integers beyond 64 bits,
# non-contiguous arrays) go through jsonable and json instead, so no message is lost.

_ORJSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY


def encode(message: Any) -> bytes:
    """A message as compact UTF-8 JSON: floats in shortest round-trip form (they read back bit
    for bit), NaN and ±inf as null, NumPy arrays and scalars as plain numbers and lists."""
    try:
        return orjson.dumps(message, option=_ORJSON_OPTIONS)
    except TypeError:
        return json.dumps(jsonable(message), allow_nan=False, separators=(",", ":"), ensure_ascii=False).encode()


def decode(data: bytes) -> Any:
    """A JSON message back into Python values (null stays None)."""
    try:
        return orjson.loads(data)
    except ValueError:  # what only json reads (NaN literals of foreign files), or the same error again
        return json.loads(data)


# --------------------------------------------------------------------------- validation

_TYPES = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
    # JSON has one number type; bool is an int in Python but not a number in JSON
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
}


def validate(instance: Any, schema: dict[str, Any], path: str = "$") -> list[str]:
    """Errors of ``instance`` against ``schema`` (empty list when valid).

    Supports type (string or list), properties, required, additionalProperties (bool),
    items (one schema), minItems, maxItems, minimum and enum — the subset these schemas use.
    """
    errors: list[str] = []
    kinds = schema.get("type")
    if kinds is not None:
        kinds = [kinds] if isinstance(kinds, str) else list(kinds)
        if not any(_TYPES[k](instance) for k in kinds):
            return [f"{path}: expected {'/'.join(kinds)}, got {type(instance).__name__}"]
    if "enum" in schema and instance not in schema["enum"]:
        errors.append(f"{path}: {instance!r} not one of {schema['enum']}")
    if "minimum" in schema and _TYPES["number"](instance) and instance < schema["minimum"]:
        errors.append(f"{path}: {instance} < minimum {schema['minimum']}")
    if isinstance(instance, dict):
        props = schema.get("properties", {})
        for key in schema.get("required", []):
            if key not in instance:
                errors.append(f"{path}: missing required {key!r}")
        for key, value in instance.items():
            if key in props:
                errors.extend(validate(value, props[key], f"{path}.{key}"))
            elif schema.get("additionalProperties", True) is False:
                errors.append(f"{path}: unexpected property {key!r}")
    if isinstance(instance, list):
        if "minItems" in schema and len(instance) < schema["minItems"]:
            errors.append(f"{path}: {len(instance)} items < minItems {schema['minItems']}")
        if "maxItems" in schema and len(instance) > schema["maxItems"]:
            errors.append(f"{path}: {len(instance)} items > maxItems {schema['maxItems']}")
        if isinstance(schema.get("items"), dict):
            for i, value in enumerate(instance):
                errors.extend(validate(value, schema["items"], f"{path}[{i}]"))
    return errors
