"""The fast JSON encoders (schemas.encode_*) write exactly what the dict builders + json.dumps write.

The writer thread uses encode_raw/encode_attitude/encode_tf/encode_truth at the sample rate;
the dict builders (raw_message …) remain the reference. Every case here checks the strongest
form of "identical": the same bytes as ``json.dumps(<dict>, allow_nan=False,
separators=(",", ":"))``, which implies that the message decodes to an equal dict and still
validates against its channel's schema (both checked too).
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from mcap.reader import make_reader

from ahrs_service.drivers.base import (
    ACC_SATURATED,
    ACC_VALID,
    GYR_SATURATED,
    GYR_VALID,
    MAG_NEW,
    MAG_SATURATED,
    MAG_VALID,
)
from ahrs_service.logs import schemas
from ahrs_service.logs.schemas import (
    attitude_message,
    encode_attitude,
    encode_raw,
    encode_tf,
    encode_truth,
    raw_message,
    tf_message,
    truth_message,
)
from ahrs_service.logs.writer import FlightLogWriter

NAN, INF = math.nan, math.inf
HUGE, TINY, SUBNORMAL = 1.7976931348623157e308, 2.2250738585072014e-308, 5e-324
ODD_FLOATS = [0.0, -0.0, 1.0, -1.5, 0.1, 1 / 3, HUGE, -HUGE, TINY, SUBNORMAL, -SUBNORMAL, 1e16, 1e-7, 123456789.125]
ALL_FLAG_BITS = (GYR_VALID, ACC_VALID, MAG_VALID, GYR_SATURATED, ACC_SATURATED, MAG_SATURATED, MAG_NEW)


def _dumps(message: dict) -> bytes:
    """What the writer's dict path stores (FlightLogWriter._write)."""
    return json.dumps(message, allow_nan=False, separators=(",", ":")).encode()


def _assert_same(data: bytes, message: dict, schema: dict) -> None:
    assert data == _dumps(message)
    decoded = json.loads(data)
    assert decoded == message
    assert schemas.validate(decoded, schema) == []


def _random_floats(rng: np.random.Generator, n: int) -> list[float]:
    """Any float64 bit pattern: subnormals, huge exponents, NaN payloads, ±inf, ±0."""
    return rng.integers(0, 2**64, size=n, dtype=np.uint64).view(np.float64).tolist()


# --------------------------------------------------------------------------- /imu/raw


def _row(gyr=(0.01, -0.02, 0.03), acc=(0.1, 0.2, -9.81), mag=(20.0, -3.5, 41.25), dt=0.001) -> list[float]:
    return [*map(float, gyr), *map(float, acc), *map(float, mag), float(dt)]


RAW_ROWS = [
    _row(),
    _row(mag=(NAN, NAN, NAN)),  # no magnetometer reading: "mag": null
    _row(mag=(NAN, 1.0, NAN)),  # partly NaN: a list with nulls
    _row(mag=(INF, NAN, NAN)),  # inf is not NaN: a list, all null
    _row(gyr=(NAN, 0.0, -INF), acc=(INF, NAN, 1.0)),
    _row(dt=NAN),
    _row(dt=INF),
    _row(gyr=(-0.0, 0.0, -0.0), acc=(HUGE, -HUGE, TINY), mag=(SUBNORMAL, -SUBNORMAL, 1e-300), dt=1e300),
    _row(gyr=(0.1, 0.2, 0.30000000000000004), acc=(1 / 3, 2 / 3, 1e16), mag=(1e-7, 123456789.125, -1e22)),
]


@pytest.mark.parametrize("row", RAW_ROWS)
def test_raw_rows(row: list[float]) -> None:
    for index in (None, 0, 7, 2**40):
        args = (1_700_000_000_123_456_789, row, GYR_VALID | ACC_VALID | MAG_VALID, None, None, index)
        _assert_same(encode_raw(*args), raw_message(*args), schemas.IMU_RAW)


def test_raw_odd_floats_in_every_position() -> None:
    for pos in range(10):
        for x in ODD_FLOATS + [NAN, INF, -INF]:
            row = RAW_ROWS[0].copy()
            row[pos] = x
            for temperature in (None, x):
                args = (1, row, 7, None, temperature, pos)
                _assert_same(encode_raw(*args), raw_message(*args), schemas.IMU_RAW)


def test_raw_every_flag_combination() -> None:
    for bits in itertools.product((0, 1), repeat=len(ALL_FLAG_BITS)):
        flags = sum(b * f for b, f in zip(bits, ALL_FLAG_BITS))
        for extra in (0, 1 << 12, 1 << 40):  # bits the "valid" object does not decode
            args = (5, RAW_ROWS[1], flags | extra)
            _assert_same(encode_raw(*args), raw_message(*args), schemas.IMU_RAW)


def test_raw_flags_and_time_as_numpy_integers() -> None:
    # both paths int() them
    args = (np.int64(123), RAW_ROWS[0], np.int64(GYR_VALID | MAG_NEW), None, None, 3)
    _assert_same(encode_raw(*args), raw_message(*args), schemas.IMU_RAW)


@pytest.mark.parametrize(
    "raw",
    [
        None,
        {},
        {"gyr": [12, -3, 40], "acc": [1000, -2000, 16384], "mag": [1, 2, 3]},
        {"gyr": np.array([12, -3, 40], dtype=np.int16), "temp": np.int32(-5), "ok": np.bool_(True)},
        {"acc": np.array([0.5, np.nan, np.inf]), "nested": {"a": (1, 2.5), 3: "x"}},
        {"name": "µT sensor", "path": __import__("pathlib").Path("/dev/i2c-1")},
    ],
)
def test_raw_counts(raw) -> None:
    args = (1, RAW_ROWS[0], GYR_VALID | ACC_VALID, raw, 21.5, 9)
    _assert_same(encode_raw(*args), raw_message(*args), schemas.IMU_RAW)


@pytest.mark.parametrize("temperature", [None, 25.0, -0.0, 36.6, NAN, INF, 20, np.float32(21.7), np.float64(-40.125)])
def test_raw_temperature(temperature) -> None:
    args = (1, RAW_ROWS[0], GYR_VALID, None, temperature, 1)
    _assert_same(encode_raw(*args), raw_message(*args), schemas.IMU_RAW)


def test_raw_random_bit_patterns() -> None:
    rng = np.random.default_rng(11)
    for _ in range(3000):
        row = _random_floats(rng, 10)
        if rng.random() < 0.3:
            row[6:9] = [NAN, NAN, NAN]
        args = (int(rng.integers(0, 2**62)), row, int(rng.integers(0, 256)), None, None, int(rng.integers(0, 10**9)))
        _assert_same(encode_raw(*args), raw_message(*args), schemas.IMU_RAW)


def test_raw_rows_from_numpy_tolist_round_trip_bit_exact() -> None:
    # what the writer encodes: row.tolist() of the float64 row fed to the estimator
    rng = np.random.default_rng(12)
    rows = rng.normal(size=(500, 10)) * 10.0 ** rng.integers(-300, 300, size=(500, 10))
    rows[::4, 6:9] = np.nan
    for i, r in enumerate(rows):
        data = encode_raw(i, r.tolist(), 7, None, None, i)
        assert data == _dumps(raw_message(i, r.tolist(), 7, None, None, i))
        m = json.loads(data)
        back = np.array(m["gyr"] + m["acc"] + (m["mag"] or [None] * 3) + [m["dt"]], dtype=float)
        # all ten columns: the numbers bit for bit, the NaN magnetometer rows as null
        nan = np.isnan(r)
        assert (m["mag"] is None) == (i % 4 == 0) and nan.sum() == (3 if i % 4 == 0 else 0)
        assert np.array_equal(np.isnan(back), nan)
        np.testing.assert_array_equal(back.view(np.int64)[~nan], r.view(np.int64)[~nan])


# --------------------------------------------------------------------------- /attitude, /attitude/truth, /tf


def _unit(q) -> list[float]:
    q = np.asarray(q, dtype=float)
    return (q / np.linalg.norm(q)).tolist()


QUATS = [
    [1.0, 0.0, 0.0, 0.0],
    [-1.0, -0.0, 0.0, -0.0],
    [0.0, 0.0, 0.0, 1.0],  # yaw = π exactly
    [0.0, 0.0, 0.0, -1.0],  # yaw = −π, written as π
    _unit([1.0, 0.0, 1.0, 0.0]),  # gimbal lock: pitch +90°
    _unit([1.0, 0.0, -1.0, 0.0]),
    _unit([0.3, -0.2, 0.9, 0.1]),
    [1.0000000000000002, 1e-300, -SUBNORMAL, 0.0],  # asin argument clamped
]


@pytest.mark.parametrize("q", QUATS)
@pytest.mark.parametrize("bias", [None, [0.0, -0.0, 1e-5], [NAN, INF, -2.5e-3]])
@pytest.mark.parametrize(
    "diagnostics",
    [None, {}, {"initialised": True, "mag_skipped": 3, "acc_norm": np.float64(9.81), "bad": NAN, "v": np.arange(3)}],
)
def test_attitude(q, bias, diagnostics) -> None:
    for estimator in ("madgwick", "robust", "µ-filter \"quoted\"\n"):
        args = (1_000_000_007, q, estimator, bias, diagnostics)
        _assert_same(encode_attitude(*args), attitude_message(*args), schemas.ATTITUDE)


@pytest.mark.parametrize("q", QUATS)
def test_truth_and_tf(q) -> None:
    for movement, source in ((None, ""), (True, "broad"), (False, "optitrack µ")):
        _assert_same(encode_truth(42, q, movement, source), truth_message(42, q, movement, source), schemas.TRUTH)
    for t_ns in (0, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789):
        _assert_same(encode_tf(t_ns, q), tf_message(t_ns, q), schemas.FRAME_TRANSFORM)


def test_attitude_random_bit_patterns() -> None:
    rng = np.random.default_rng(13)
    for _ in range(3000):
        q = _unit(rng.normal(size=4)) if rng.random() < 0.5 else _random_floats(rng, 4)
        bias = _random_floats(rng, 3) if rng.random() < 0.7 else None
        args = (int(rng.integers(0, 2**62)), q, "madgwick", bias, None)
        _check_both_or_neither(encode_attitude, attitude_message, args)
        _check_both_or_neither(encode_tf, tf_message, args[:2])
        _check_both_or_neither(encode_truth, truth_message, (*args[:2], None, "sim"))


def _check_both_or_neither(encode, build, args) -> None:
    """Same bytes, or both refuse (a non-finite Euler angle or /tf rotation is not JSON)."""
    try:
        expected = _dumps(build(*args))
    except ValueError:
        with pytest.raises(ValueError):
            encode(*args)
        return
    assert encode(*args) == expected


@pytest.mark.parametrize("q", [[NAN, 0.0, 0.0, 0.0], [1.0, INF, 0.0, 0.0]])
def test_non_finite_quaternion_is_refused_like_json(q) -> None:
    with pytest.raises(ValueError):
        _dumps(attitude_message(1, q, "m"))
    with pytest.raises(ValueError):
        encode_attitude(1, q, "m")
    with pytest.raises(ValueError):
        encode_tf(1, q)


def test_values_the_fast_path_leaves_to_the_dict_path() -> None:
    # ints/bools where floats belong, NumPy integer index, wrong lengths: the encoders refuse
    # (the writer then encodes the dict), so they can never write something different
    row = RAW_ROWS[0]
    for args in (
        (1, [1, 0, 0, 0, 0, 9, 0, 0, 0, 0.001], 1),
        (1, [True] + row[1:], 1),
        (1, row, 1, None, None, np.int64(3)),
        (1, row + [0.0], 1),
    ):
        with pytest.raises((TypeError, ValueError)):
            encode_raw(*args)
    with pytest.raises((TypeError, ValueError)):
        encode_attitude(1, [1, 0, 0, 0], "m")
    with pytest.raises((TypeError, ValueError)):
        encode_attitude(1, QUATS[0], "m", [0.0, 0.0])
    # index True is written as JSON true, exactly as json.dumps does
    assert encode_raw(1, row, 1, None, None, True) == _dumps(raw_message(1, row, 1, None, None, True))


# --------------------------------------------------------------------------- through the writer


def test_writer_output_equals_dict_path(tmp_path) -> None:
    """Every /imu/raw, /attitude, /tf and truth message in the file is what the dict path writes,
    including a sample the fast encoder hands to it (an integer row)."""
    rng = np.random.default_rng(14)
    rows = rng.normal(size=(300, 10))
    rows[:, 9] = 0.001
    rows[::3, 6:9] = np.nan
    rows[7, 2] = np.inf
    states = rng.normal(size=(300, 14))
    w = FlightLogWriter(tmp_path, fsync=False, tf_rate_hz=None)
    expected: dict[str, list[bytes]] = {"/imu/raw": [], "/attitude": [], "/tf": [], "/attitude/truth": []}
    for i, (r, s) in enumerate(zip(rows, states)):
        t_ns = 1_000_000 * i
        if i == 11:
            r = np.arange(10)  # ints: encode_raw refuses, the dict path writes them as ints
        raw = {"gyr": np.array([i, -i, 3], dtype=np.int16)} if i % 5 == 0 else None
        w.write_raw(t_ns, r, 0x07 | (i % 128), raw, 20.0 + i / 7)
        q = s[:4] / np.linalg.norm(s[:4])
        bias = [1, 0, 0] if i == 11 else s[8:11]  # write_attitude turns a list into floats
        diag = {"n": i} if i % 2 else None
        w.write_attitude(t_ns, q, "madgwick", bias, diag, state=s)
        w.write_truth(t_ns, q, i % 2 == 0, "sim")
        b = [float(v) for v in bias]
        expected["/imu/raw"].append(_dumps(raw_message(t_ns, r.tolist(), 0x07 | (i % 128), raw, 20.0 + i / 7, i)))
        expected["/attitude"].append(_dumps(attitude_message(t_ns, q.tolist(), "madgwick", b, diag)))
        expected["/tf"].append(_dumps(tf_message(t_ns, q.tolist())))
        expected["/attitude/truth"].append(_dumps(truth_message(t_ns, q.tolist(), i % 2 == 0, "sim")))
    w.close()
    assert w.status == "closed" and w.dropped == 0 and w.errors == 0
    got: dict[str, list[bytes]] = {k: [] for k in expected}
    with open(w.files[0], "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=list(expected)):
            got[channel.topic].append(message.data)
    assert got == expected

