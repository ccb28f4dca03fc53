"""Message encoding (schemas.encode / decode, orjson): what the log files hold.

The oracle is the json module on ``jsonable(message)``: NumPy values as plain ones, NaN and
±inf as null, non-str keys as ``str(key)``. Every message must decode to exactly that (floats
compared bit for bit, so -0.0 and the last digit count) and validate against its channel's
schema.
"""

from __future__ import annotations

import itertools
import json
import math
import pathlib

import numpy as np
import pytest
from mcap.reader import make_reader

from ahrs_service.core import samples as B
from ahrs_service.logs import schemas
from ahrs_service.logs.schemas import (
    attitude_message,
    decode,
    encode,
    jsonable,
    raw_message,
    tf_message,
    truth_message,
)
from ahrs_service.logs.writer import FlightLogWriter

NAN, INF = math.nan, math.inf
HUGE, TINY, SUBNORMAL = 1.7976931348623157e308, 2.2250738585072014e-308, 5e-324
ODD_FLOATS = [0.0, -0.0, 1.0, -1.5, 0.1, 1 / 3, HUGE, -HUGE, TINY, SUBNORMAL, -SUBNORMAL, 1e16, 1e-7, 123456789.125]
ALL_FLAG_BITS = (B.GYR_VALID, B.ACC_VALID, B.MAG_VALID, B.GYR_SATURATED, B.ACC_SATURATED, B.MAG_SATURATED, B.MAG_NEW)


def _bits(value):
    """``value`` with every float replaced by its bit pattern: equality then means bit-exact."""
    if isinstance(value, float):
        return ("f", np.float64(value).view(np.int64).item())
    if isinstance(value, dict):
        return {k: _bits(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_bits(v) for v in value]
    return value


def _assert_encodes(message: dict, schema: dict | None) -> dict:
    data = encode(message)
    assert isinstance(data, bytes)
    decoded = decode(data)
    assert _bits(decoded) == _bits(json.loads(json.dumps(jsonable(message))))
    assert json.loads(data) == decoded  # plain JSON for any reader (Foxglove, jq …)
    if schema is not None:
        assert schemas.validate(decoded, schema) == []
    return decoded


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
    _row(gyr=(-0.0, 0.0, -0.0), acc=(HUGE, -HUGE, TINY), mag=(SUBNORMAL, -SUBNORMAL, 1e-300), dt=1e300),
    _row(gyr=(0.1, 0.2, 0.30000000000000004), acc=(1 / 3, 2 / 3, 1e16), mag=(1e-7, 123456789.125, -1e22)),
]


@pytest.mark.parametrize("row", RAW_ROWS)
def test_raw_rows(row: list[float]) -> None:
    for index in (None, 0, 7, 2**40):
        m = _assert_encodes(raw_message(1_700_000_000_123_456_789, row, 7, None, None, index), schemas.IMU_RAW)
        assert m["index"] == index and m["t_ns"] == 1_700_000_000_123_456_789
        assert (m["mag"] is None) == all(math.isnan(v) for v in row[6:9])


def test_raw_odd_floats_in_every_position() -> None:
    for pos in range(10):
        for x in ODD_FLOATS + [NAN, INF, -INF]:
            row = RAW_ROWS[0].copy()
            row[pos] = x
            for temperature in (None, x):
                _assert_encodes(raw_message(1, row, 7, None, temperature, pos), schemas.IMU_RAW)


def test_raw_every_flag_combination() -> None:
    for bits in itertools.product((0, 1), repeat=len(ALL_FLAG_BITS)):
        flags = sum(b * f for b, f in zip(bits, ALL_FLAG_BITS))
        for extra in (0, 1 << 12, 1 << 40):  # bits the "valid" object does not decode
            m = _assert_encodes(raw_message(5, RAW_ROWS[1], flags | extra), schemas.IMU_RAW)
            assert m["flags"] == flags | extra
            assert [m["valid"][k] for k in ("gyr", "acc", "mag", "gyr_saturated", "acc_saturated", "mag_saturated", "mag_new")] == [bool(b) for b in bits]


def test_raw_flags_and_time_as_numpy_integers() -> None:
    m = _assert_encodes(raw_message(np.int64(123), RAW_ROWS[0], np.int64(B.GYR_VALID | B.MAG_NEW), None, None, np.int64(3)), schemas.IMU_RAW)
    assert (m["t_ns"], m["flags"], m["index"]) == (123, B.GYR_VALID | B.MAG_NEW, 3)


@pytest.mark.parametrize(
    "raw",
    [
        None,
        {},
        {"gyr": [12, -3, 40], "acc": [1000, -2000, 16384], "mag": [1, 2, 3]},
        {"gyr": np.array([12, -3, 40], dtype=np.int16), "temp": np.int32(-5), "ok": np.bool_(True)},
        {"acc": np.array([0.5, np.nan, np.inf]), "nested": {"a": (1, 2.5)}},
        {"name": "µT sensor", "path": pathlib.Path("/dev/i2c-1")},  # a Path: written as its text
        {"gyr": (12, -3, 40), "acc": [1000, (2, 3)], "t": ()},
        {"nested": {"a": (1, 2.5), "b": [{"c": (True, False)}]}},
        {True: 1, None: 2, "x": {False: (3,)}},  # non-str keys: str(key), as jsonable writes them
        {1: "int key", "1": "str key"},  # one key, never a duplicate in the JSON
        {"a": (1.0, np.float64(0.5), np.int16(3), np.nan)},
        {"strided": np.arange(6.0)[::2]},  # orjson refuses it: the json path writes it
    ],
)
def test_raw_counts_and_diagnostics(raw) -> None:
    _assert_encodes(raw_message(1, RAW_ROWS[0], B.GYR_VALID | B.ACC_VALID, raw, 21.5, 9), schemas.IMU_RAW)
    if isinstance(raw, dict):
        _assert_encodes(attitude_message(7, [1.0, 0.0, 0.0, 0.0], "madgwick", [0.0, 0.0, 0.0], raw), schemas.ATTITUDE)


@pytest.mark.parametrize("temperature", [None, 25.0, -0.0, 36.6, NAN, INF, 20, np.float64(-40.125)])
def test_raw_temperature(temperature) -> None:
    m = _assert_encodes(raw_message(1, RAW_ROWS[0], B.GYR_VALID, None, temperature, 1), schemas.IMU_RAW)
    assert m["temperature"] == (None if temperature is None or not math.isfinite(temperature) else temperature)


def test_float32_temperature_reads_back_as_its_float32_value() -> None:
    m = decode(encode(raw_message(1, RAW_ROWS[0], B.GYR_VALID, None, np.float32(21.7), 1)))
    assert np.float32(m["temperature"]) == np.float32(21.7)


def test_raw_random_bit_patterns() -> None:
    rng = np.random.default_rng(11)
    for _ in range(3000):
        row = _random_floats(rng, 10)
        if rng.random() < 0.3:
            row[6:9] = [NAN, NAN, NAN]
        args = (int(rng.integers(0, 2**62)), row, int(rng.integers(0, 256)), None, None, int(rng.integers(0, 10**9)))
        _assert_encodes(raw_message(*args), schemas.IMU_RAW)


def test_raw_rows_from_numpy_tolist_round_trip_bit_exact() -> None:
    # what the writer encodes: row.tolist() of the float64 row fed to the estimator
    rng = np.random.default_rng(12)
    rows = rng.normal(size=(500, 10)) * 10.0 ** rng.integers(-300, 300, size=(500, 10))
    rows[::4, 6:9] = np.nan
    for i, r in enumerate(rows):
        m = decode(encode(raw_message(i, r.tolist(), 7, None, None, i)))
        back = np.array(m["gyr"] + m["acc"] + (m["mag"] or [None] * 3) + [m["dt"]], dtype=float)
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
        m = _assert_encodes(attitude_message(1_000_000_007, q, estimator, bias, diagnostics), schemas.ATTITUDE)
        assert _bits([m["roll"], m["pitch"], m["yaw"]]) == _bits(list(schemas.euler(q)))
        assert m["estimator"] == estimator
        assert m["gyro_bias"] == ([0.0, 0.0, 0.0] if bias is None else [b if math.isfinite(b) else None for b in bias])


@pytest.mark.parametrize("q", QUATS)
def test_truth_and_tf(q) -> None:
    for movement, source in ((None, ""), (True, "broad"), (False, "optitrack µ")):
        m = _assert_encodes(truth_message(42, q, movement, source), schemas.TRUTH)
        assert (m["movement"], m["source"]) == (movement, source)
    for t_ns in (0, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789):
        m = _assert_encodes(tf_message(t_ns, q), schemas.FRAME_TRANSFORM)
        assert m["timestamp"]["sec"] * 1_000_000_000 + m["timestamp"]["nsec"] == t_ns


def test_attitude_random_bit_patterns() -> None:
    rng = np.random.default_rng(13)
    for _ in range(3000):
        q = _unit(rng.normal(size=4)) if rng.random() < 0.5 else _random_floats(rng, 4)
        bias = _random_floats(rng, 3) if rng.random() < 0.7 else None
        _assert_encodes(attitude_message(int(rng.integers(0, 2**62)), q, "madgwick", bias, None), schemas.ATTITUDE)
        _assert_encodes(truth_message(5, q, None, "sim"), schemas.TRUTH)


@pytest.mark.parametrize("q", [[NAN, 0.0, 0.0, 0.0], [1.0, INF, 0.0, 0.0]])
def test_non_finite_quaternion_is_written_as_null_not_lost(q) -> None:
    m = _assert_encodes(attitude_message(1, q, "m"), schemas.ATTITUDE)
    assert None in m["q"]
    assert m["pitch"] is None  # not a clamped ±90° from a NaN


# --------------------------------------------------------------------------- through the writer


@pytest.mark.parametrize("one_call", [False, True], ids=["three calls", "write_sample"])
def test_writer_output_is_the_encoded_message(tmp_path, one_call) -> None:
    """Every /imu/raw, /attitude, /tf and truth message in the file is encode(<builder>), the
    integer row and the non-finite attitude included; /tf skips the non-finite one. The
    service's write_sample writes exactly what write_raw + write_attitude + write_truth do."""
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
            r = np.arange(10)  # ints where floats belong: written as ints
        raw = {"gyr": np.array([i, -i, 3], dtype=np.int16)} if i % 5 == 0 else None
        q = s[:4] / np.linalg.norm(s[:4])
        if i == 13:
            q[0] = np.nan
        bias = [1, 0, 0] if i == 11 else s[8:11]  # write_attitude turns a list into floats
        diag = None
        if one_call:
            w.write_sample(
                t_ns, r, 0x07 | (i % 128), q=q, estimator="madgwick", bias=bias, state=s, raw=raw,
                temperature=20.0 + i / 7, truth_q=q,
            )
        else:
            w.write_raw(t_ns, r, 0x07 | (i % 128), raw, 20.0 + i / 7)
            diag = {"n": i} if i % 2 else None
            w.write_attitude(t_ns, q, "madgwick", bias, diag, state=s)
            w.write_truth(t_ns, q)
        b = [float(v) for v in bias]
        expected["/imu/raw"].append(encode(raw_message(t_ns, r.tolist(), 0x07 | (i % 128), raw, 20.0 + i / 7, i)))
        expected["/attitude"].append(encode(attitude_message(t_ns, q.tolist(), "madgwick", b, diag)))
        if i != 13:
            expected["/tf"].append(encode(tf_message(t_ns, q.tolist())))
        expected["/attitude/truth"].append(encode(truth_message(t_ns, q.tolist())))
    w.close()
    assert w.status == "closed" and w.dropped == 0 and w.errors == 0
    got: dict[str, list[bytes]] = {k: [] for k in expected}
    with open(w.files[0], "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=list(expected)):
            got[channel.topic].append(message.data)
    assert got == expected
    assert len(got["/attitude"]) == 300 and len(got["/tf"]) == 299


def test_integers_beyond_64_bits_are_written_exactly() -> None:
    # orjson refuses them; the json path writes the digits (decode reads them back as a float)
    data = encode({"raw": {"big": 2**70}})
    assert json.loads(data) == {"raw": {"big": 2**70}}
    assert decode(data)["raw"]["big"] == float(2**70)


def test_decode_of_a_damaged_message_raises() -> None:
    with pytest.raises(ValueError):
        decode(b'{"t_ns":12')
