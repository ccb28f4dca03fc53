"""Sample blocks end to end: a block of n rows gives the same bits as n blocks of one row —
calibration, sample times, estimator rows and estimates, the log — and a log written in blocks
replays the published attitude bit for bit from its stored (recovered) times."""

from __future__ import annotations

import importlib.util
import itertools
import json
import time
from pathlib import Path

import numpy as np
import pytest

from ahrs_service import estimators
from ahrs_service.core.calibration import SensorCalibration, apply_calibration, apply_calibration_block
from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID, ImuSample, SampleBlock
from ahrs_service.drivers.sim.clock import ManualClock
from ahrs_service.drivers.sim.imu import SimulatedImu
from ahrs_service.drivers.sim.motion import profile
from ahrs_service.drivers.sim.sensor_model import PART_MODELS
from ahrs_service.drivers.sim.source import SimulatedSource
from ahrs_service.estimators import SAMPLE_ROW, STATE_HEADER
from ahrs_service.logs.reader import read_log
from ahrs_service.logs.writer import FlightLogWriter
from ahrs_service.pipeline import EstimationPipeline
from ahrs_service.recorded import RecordedSource
from ahrs_service.replay import replay

_spec = importlib.util.spec_from_file_location(
    "make_fixtures", Path(__file__).resolve().parent / "fixtures" / "make_fixtures.py"
)
make_fixtures = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_fixtures)

# a calibration with every term (so the compiled calibration runs) and a 90° mounting
CAL = SensorCalibration.from_dict({
    "gyro_bias": [0.01, -0.02, 0.003], "acc_bias": [0.1, 0.0, -0.05],
    "acc_scale": [[1.01, 0.002, 0.0], [0.0, 0.99, 0.001], [0.0, 0.0, 1.0]],
    "mag_hard_iron": [3.0, -2.0, 5.0], "mag_soft_iron": [[1.02, 0.01, 0.0], [0.01, 0.98, 0.0], [0.0, 0.0, 1.0]],
    "mounting_rpy_deg": [180.0, 0.0, 90.0],
})
SIZES = (1, 7, 32, 3, 64, 10, 2)  # block sizes the split cycles through: FIFO bursts of all kinds


def _split(block: SampleBlock, sizes=SIZES) -> list[SampleBlock]:
    """``block`` cut into consecutive blocks of the cycled ``sizes`` (rows as samples)."""
    samples = list(block.samples())
    out, i = [], 0
    for n in itertools.cycle(sizes):
        if i >= len(samples):
            return out
        out.append(SampleBlock.from_samples(samples[i:i + n]))
        i += n


def _run(pipeline: EstimationPipeline, blocks: list[SampleBlock]) -> dict[str, np.ndarray]:
    """Every estimated row of ``blocks`` through ``pipeline``, concatenated."""
    done = [d for d in map(pipeline.process_block, blocks) if d is not None]
    return {
        "t_ns": np.concatenate([d.t_ns for d in done]),
        "t_source_ns": np.concatenate([d.t_source_ns for d in done]),
        "rows": np.concatenate([d.rows for d in done]),
        "q": np.concatenate([d.q for d in done]),
        "index": np.concatenate([d.first_index + np.arange(len(d)) for d in done]),
        "state": done[-1].state,
    }


def _pipeline(name: str, rate_hz: float, *, clock: bool, mag_timeout_s: float = 0.5) -> EstimationPipeline:
    p = EstimationPipeline(estimators.create(name), CAL, nominal_dt=1.0 / rate_hz, mag_timeout_s=mag_timeout_s)
    if clock:
        p.use_sample_clock(rate_hz)
    return p


def _assert_same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    for key in a:
        assert a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key], equal_nan=True), key


def test_a_calibrated_block_is_the_samples_calibrated_one_by_one():
    rng = np.random.default_rng(1)
    samples = [ImuSample(k, rng.normal(0, 1, 3), rng.normal(0, 9, 3), None if k % 3 else rng.normal(0, 40, 3),
                         GYR_VALID | ACC_VALID | (MAG_VALID | MAG_NEW if k % 3 == 0 else 0)) for k in range(50)]
    block = apply_calibration_block(SampleBlock.from_samples(samples), CAL)
    for k, s in enumerate(samples):
        one = apply_calibration(s, CAL)
        assert np.array_equal(block.gyr[k], one.gyr) and np.array_equal(block.acc[k], one.acc)
        assert np.isnan(block.mag[k]).all() if s.mag is None else np.array_equal(block.mag[k], one.mag)
    assert not np.array_equal(block.gyr, SampleBlock.from_samples(samples).gyr)  # it did calibrate


@pytest.mark.parametrize("name", ["madgwick", "robust"])
def test_broad_through_the_recorded_source_in_blocks_is_bit_identical_to_blocks_of_one(broad_dir, name):
    path = sorted(broad_dir.glob("*.hdf5"))[0]
    source = RecordedSource(path, realtime=False, duration_s=20.0)
    source.open()
    assert not source.times_on_sensor_clock  # the recording's stamps: recovered, as the service does
    whole = source.read_block(10**6)
    rate = 1e9 / float(np.median(np.diff(whole.t_ns)))
    ones = _run(_pipeline(name, rate, clock=True), _split(whole, (1,)))
    blocks = _run(_pipeline(name, rate, clock=True), _split(whole))
    _assert_same(ones, blocks)
    assert len(ones["q"]) > 0.9 * len(whole) and np.isfinite(ones["q"]).all()
    # this recording's stamps lie on a uniform grid: the sample clock passes them bit for bit
    assert np.array_equal(ones["t_ns"], ones["t_source_ns"])


def _simulated_flight(seconds: float = 6.0, rate_hz: float = 400.0) -> SampleBlock:
    """A simulated figure-eight flight read from the simulator's source on a manual clock, the
    magnetometer at a tenth of the rate, then hardened: a field missing at the start (the
    start is held back), a field outage longer than the hold (reduced form and back), a
    stretch of invalid gyro readings and a time gap of 40 lost samples."""
    models = {"gyr": PART_MODELS["MPU9250_GYRO"].analog(), "acc": PART_MODELS["MPU9250_ACC"].analog(),
              "mag": PART_MODELS["AK8963"].analog()}
    clock = ManualClock()
    imu = SimulatedImu(profile("figure8", period=8.0), models, clock=clock, seed=5)
    source = SimulatedSource(imu, rate_hz=rate_hz, mag_rate_hz=rate_hz / 10)
    samples = []
    for _ in range(int(seconds * rate_hz)):
        clock.advance(1.0 / rate_hz)
        samples.append(source.read())
    n = len(samples)
    for i, s in enumerate(samples):
        if i < 25:
            s.mag, s.flags = None, s.flags & ~(MAG_VALID | MAG_NEW)
        if n // 3 <= i < n // 3 + int(0.8 * rate_hz):  # 0.8 s without field: longer than the hold
            s.flags &= ~(MAG_VALID | MAG_NEW)
        if n // 2 <= i < n // 2 + 5:
            s.flags &= ~GYR_VALID
        if i >= 2 * n // 3:
            s.t_ns += int(40e9 / rate_hz)  # 40 samples lost: one long dt
    return SampleBlock.from_samples(samples)


@pytest.mark.parametrize("clock", [False, True], ids=["sensor-clock times", "recovered times"])
def test_a_simulated_flight_in_blocks_is_bit_identical_to_blocks_of_one(clock):
    flight = _simulated_flight()
    a, b = _pipeline("madgwick", 400.0, clock=clock), _pipeline("madgwick", 400.0, clock=clock)
    ones, blocks = _run(a, _split(flight, (1,))), _run(b, _split(flight))
    _assert_same(ones, blocks)
    assert a.reduced_switches == b.reduced_switches == 2 and a.samples == b.samples == len(ones["q"])
    # what the hardening did, seen in the rows: the held-back start, the outage, the gap
    assert len(ones["q"]) == len(flight) - 25
    assert np.isnan(ones["rows"][:, 6]).sum() > 0.3 * 400
    assert ones["rows"][:, 9].max() == pytest.approx(41 / 400.0, rel=1e-6)
    np.testing.assert_array_equal(a.recent_gyro_mean(), b.recent_gyro_mean())


def test_a_block_log_holds_every_sample_and_replays_bit_for_bit(tmp_path):
    flight = _simulated_flight(seconds=4.0)
    p = _pipeline("madgwick", 400.0, clock=True)
    # small rotation: several files, each starting from a state snapshot taken at a block's end
    writer = FlightLogWriter(tmp_path, chunk_size=8192, rotate_bytes=40_000, flush_interval_s=0.05, fsync=False)
    writer.write_config(int(flight.t_ns[0]), {"estimator": {"name": "madgwick", "params": p.estimator.get_params()}})
    q_all, t_all, src_all = [], [], []
    for block in _split(flight):
        done = p.process_block(block)
        if done is None:
            continue
        writer.write_block(done.t_ns, done.rows, done.flags, q=done.q, estimator="madgwick",
                           t_source_ns=done.t_source_ns, bias=done.state[STATE_HEADER.slices.bias], state=done.state,
                           temperature=done.temperature_c, truth_q=done.truth_q)
        q_all.append(done.q), t_all.append(done.t_ns), src_all.append(done.t_source_ns)
        time.sleep(0.005)  # a real-time loop leaves the writer thread time (rotations happen)
    writer.close()
    q_all, t_all, src_all = np.concatenate(q_all), np.concatenate(t_all), np.concatenate(src_all)
    assert writer.dropped == 0 and len(writer.files) >= 3
    logs = [read_log(f) for f in writer.files]
    assert sum(len(log) for log in logs) == len(q_all)  # every sample, each in one file
    assert all(log.initial_state is not None for log in logs[1:])
    t = np.concatenate([log.t_ns for log in logs])
    assert np.array_equal(t, t_all) and np.array_equal(np.concatenate([log.t_source_ns for log in logs]), src_all)
    # the 40 lost samples are placed at their own step (the sensor clock, docs/timing.md "Gaps"):
    # the simulator's clean stamps come back unchanged, the gap in one step of 41 periods
    assert np.array_equal(t_all, src_all)
    assert np.diff(t_all).max() == 41 * 2_500_000
    at = 0
    for log in logs:
        assert int(log.index[0]) == at  # the writer numbered the samples across blocks and files
        assert np.array_equal(log.attitudes, q_all[at:at + len(log)])
        assert np.array_equal(replay(log), log.attitudes)  # from the stored times: no recovery again
        at += len(log)
    assert np.array_equal(np.concatenate([log.truth for log in logs]), flight.truth_q[25:])


def test_write_block_writes_the_messages_of_write_sample(tmp_path):
    """One writer call per block puts the same per-sample messages in the file as one call per
    sample; only the gyro bias (and diagnostics) is the block's, on its last row."""
    t_ns, rows, q_true = make_fixtures.analytic_trajectory(200.0, 1.0)
    est = estimators.create("madgwick")
    q = est.run_rows(rows)
    flags = np.full(len(t_ns), GYR_VALID | ACC_VALID | MAG_VALID | MAG_NEW, dtype=np.int64)
    per_sample = FlightLogWriter(tmp_path / "a", fsync=False)
    per_block = FlightLogWriter(tmp_path / "b", fsync=False)
    for i in range(len(t_ns)):
        per_sample.write_sample(int(t_ns[i]), rows[i], int(flags[i]), q=q[i], estimator="madgwick", truth_q=q_true[i])
    for i in range(0, len(t_ns), 16):
        s = slice(i, i + 16)
        per_block.write_block(t_ns[s], rows[s], flags[s], q=q[s], estimator="madgwick", truth_q=q_true[s])
    per_sample.close(), per_block.close()
    a, b = read_log(per_sample.files[0]), read_log(per_block.files[0])
    for key in ("t_ns", "rows", "flags", "index", "attitudes", "truth", "t_source_ns"):
        assert np.array_equal(getattr(a, key), getattr(b, key), equal_nan=True), key
    assert a.counts == b.counts


def _one_message_blocks(directory: Path, t_ns, rows, flags, q, q_true, n: int = 16, **writer_options) -> FlightLogWriter:
    writer = FlightLogWriter(directory, fsync=False, block_messages_above_hz=100.0, **writer_options)
    for i in range(0, len(t_ns), n):
        s = slice(i, i + n)
        writer.write_block(t_ns[s], rows[s], flags[s], q=q[s], estimator="madgwick", truth_q=q_true[s],
                           bias=np.array([0.01, 0.02, 0.03]))
    writer.close()
    return writer


def _per_sample_log(directory: Path, t_ns, rows, q_true) -> tuple[np.ndarray, np.ndarray, FlightLogWriter]:
    """Madgwick's estimate of ``rows``, their flags, and the closed writer of their per-sample log."""
    q = estimators.create("madgwick").run_rows(rows)
    flags = np.full(len(t_ns), GYR_VALID | ACC_VALID | MAG_VALID | MAG_NEW, dtype=np.int64)
    per_sample = FlightLogWriter(directory, fsync=False)
    for i in range(len(t_ns)):
        per_sample.write_sample(int(t_ns[i]), rows[i], int(flags[i]), q=q[i], estimator="madgwick", truth_q=q_true[i])
    per_sample.close()
    return q, flags, per_sample


def test_blocks_faster_than_the_threshold_read_back_as_their_rows(tmp_path):
    """Above ``block_messages_above_hz`` a block is one message per channel; the log reads back
    into exactly the rows, indexes, attitudes and truth that per-sample messages give, and
    every message validates against its schema."""
    from mcap.reader import make_reader

    from ahrs_service.logs import schemas

    t_ns, rows, q_true = make_fixtures.analytic_trajectory(200.0, 1.0)
    rows[::7, 6:9] = np.nan  # samples without a magnetometer reading
    q, flags, per_sample = _per_sample_log(tmp_path / "a", t_ns, rows, q_true)
    blocks = _one_message_blocks(tmp_path / "b", t_ns, rows, flags, q, q_true)
    a, b = read_log(per_sample.files[0]), read_log(blocks.files[0])
    for key in ("t_ns", "rows", "flags", "index", "attitudes", "truth", "t_source_ns"):
        assert np.array_equal(getattr(a, key), getattr(b, key), equal_nan=True), key
    n_blocks = -(-len(t_ns) // 16)
    assert b.counts["/imu/raw_block"] == b.counts["/attitude_block"] == b.counts["/attitude/truth_block"] == n_blocks
    assert "/imu/raw" not in b.counts
    # /attitude (and /tf) for Foxglove at the /tf rate, 50 Hz: one per 4 rows at 200 Hz, so one per block here
    assert b.counts["/attitude"] == b.counts["/tf"] == n_blocks
    assert blocks.written == sum(b.counts.values()) and blocks.samples_not_logged == 0
    with open(blocks.files[0], "rb") as f:
        checked = 0
        for schema, channel, message in make_reader(f).iter_messages():
            assert schemas.validate(json.loads(message.data), json.loads(schema.data)) == [], channel.topic
            checked += 1
    assert checked == sum(b.counts.values())


def test_queued_bursts_of_a_fast_part_are_joined_into_messages_of_one_tf_period(tmp_path):
    """8 kHz bursts of 8 rows queued behind one another are written as one /imu/raw_block +
    /attitude_block per /tf period (20 ms), each ending with the /attitude preview: the same
    rows as per-sample messages; a block with diagnostics ends its message (they go with a
    message's last row)."""
    from mcap.reader import make_reader

    t_ns, rows, q_true = make_fixtures.analytic_trajectory(8000.0, 0.5)
    q, flags, per_sample = _per_sample_log(tmp_path / "a", t_ns, rows, q_true)
    writer = FlightLogWriter(tmp_path / "b", fsync=False, block_messages_above_hz=1500.0)  # the service's default
    n_blocks, diagnosed = len(t_ns) // 8, 101
    for b in range(n_blocks):
        s = slice(8 * b, 8 * b + 8)
        writer.write_block(t_ns[s], rows[s], flags[s], q=q[s], estimator="madgwick", truth_q=q_true[s],
                           diagnostics={"rejections": b} if b == diagnosed else None)
    writer.close()
    a, b = read_log(per_sample.files[0]), read_log(writer.files[0])
    for key in ("t_ns", "rows", "flags", "index", "attitudes", "truth"):
        assert np.array_equal(getattr(a, key), getattr(b, key), equal_nan=True), key
    with open(writer.files[0], "rb") as f:
        blocks = [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/attitude_block"])]
    assert sum(len(m["t_ns"]) for m in blocks) == len(t_ns)
    assert len(blocks) < n_blocks  # joined: fewer messages than bursts
    # at most a /tf period and the burst that makes the next /attitude preview due
    assert all(m["t_ns"][-1] - m["t_ns"][0] < 20_000_000 + 8 * 125_000 and len(m["t_ns"]) <= 256 for m in blocks)
    assert abs(b.counts["/attitude"] - 0.5 * 50) <= 2  # the previews stay at 50 Hz
    with_diagnostics = [m for m in blocks if "diagnostics" in m]
    assert [m["diagnostics"] for m in with_diagnostics] == [{"rejections": diagnosed}]
    assert with_diagnostics[0]["t_ns"][-1] == t_ns[8 * diagnosed + 7]  # the message ends with that burst


def test_a_block_log_replays_and_plots_like_a_per_sample_log(tmp_path):
    """``replay`` of a block log writes blocks again (new /attitude_block, the recorded one
    kept as /attitude/original_block); ``log plot``'s series hold every row."""
    from ahrs_service.logs.plot import read_series
    from ahrs_service.replay import replay, write_replay

    t_ns, rows, q_true = make_fixtures.analytic_trajectory(200.0, 1.0)
    q = estimators.create("madgwick").run_rows(rows)
    flags = np.full(len(t_ns), GYR_VALID | ACC_VALID | MAG_VALID | MAG_NEW, dtype=np.int64)
    log = read_log(_one_message_blocks(tmp_path / "b", t_ns, rows, flags, q, q_true).files[0])
    assert np.array_equal(replay(log), q)  # the recorded rows give the recorded estimate, bit for bit
    q_new = replay(log, "mahony_passive")
    out = read_log(write_replay(log, q_new, tmp_path / "replayed.mcap", "mahony_passive"))
    assert np.array_equal(out.attitudes, q_new) and np.array_equal(out.original, q)
    assert np.array_equal(out.rows, log.rows, equal_nan=True) and out.estimator == "mahony_passive"
    assert out.counts["/attitude_block"] == out.counts["/attitude/original_block"] == log.counts["/imu/raw_block"]
    series = read_series(log.path, progress=False)
    assert len(series.raw_t) == len(t_ns) and np.array_equal(series.gyr, rows[:, 0:3])
    assert len(series.truth_t) == len(t_ns)


def test_a_lost_block_message_counts_its_samples(tmp_path):
    """A block refused by a full queue counts its messages (one per channel) and all its
    samples as not logged."""
    t_ns, rows, q_true = make_fixtures.analytic_trajectory(200.0, 0.5)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t_ns), 1))
    flags = np.full(len(t_ns), GYR_VALID | ACC_VALID, dtype=np.int64)
    writer = FlightLogWriter(tmp_path, fsync=False, block_messages_above_hz=100.0, queue_size=0)
    writer.write_block(t_ns[:10], rows[:10], flags[:10], q=q[:10], estimator="m", truth_q=q_true[:10])
    writer.write_block(t_ns[10:14], rows[10:14], flags[10:14], q=q[10:14], estimator="m")
    writer.close()
    assert (writer.dropped, writer.samples_not_logged) == (3 + 2, 14)


def test_blocks_slower_than_the_threshold_stay_per_sample(tmp_path):
    t_ns, rows, q_true = make_fixtures.analytic_trajectory(200.0, 0.2)  # dt 5 ms ± 20 %: 200 Hz
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t_ns), 1))
    flags = np.full(len(t_ns), GYR_VALID | ACC_VALID, dtype=np.int64)
    writer = FlightLogWriter(tmp_path, fsync=False, block_messages_above_hz=400.0)
    writer.write_block(t_ns, rows, flags, q=q, estimator="m")
    writer.close()
    counts = read_log(writer.files[0]).counts
    assert counts["/imu/raw"] == len(t_ns) and "/imu/raw_block" not in counts


def test_the_layout_follows_a_block_s_spacing_not_one_row_s_dt(tmp_path):
    """A row that came 0.3 ms after the one before (a sensor clock's correction) in a stream
    slower than the threshold: a CI run's log of the simulated GY-80 (800 Hz rows) held such a
    row as a one-row /imu/raw_block, the layout decided by that row's dt alone (``log
    recover``'s per-topic counts then no longer matched the rows). A lone row is per sample; a
    block goes by its rows' mean spacing after the first — an 8 kHz burst with an odd row stays
    one message, a 200 Hz block with one stays per sample."""
    t_ns, rows, _ = make_fixtures.analytic_trajectory(200.0, 0.2)
    t_ns, rows = t_ns.copy(), rows.copy()
    t_ns[20] = t_ns[19] + 300_000
    rows[20, SAMPLE_ROW.index.dt] = 0.0003
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t_ns), 1))
    flags = np.full(len(t_ns), GYR_VALID | ACC_VALID, dtype=np.int64)
    writer = FlightLogWriter(tmp_path / "slow", fsync=False, block_messages_above_hz=1500.0)
    writer.write_block(t_ns[:20], rows[:20], flags[:20], q=q[:20], estimator="m")
    writer.write_block(t_ns[20:21], rows[20:21], flags[20:21], q=q[20:21], estimator="m")  # the odd row alone
    writer.write_block(t_ns[19:23], rows[19:23], flags[19:23], q=q[19:23], estimator="m")  # and in the middle
    writer.close()
    counts = read_log(writer.files[0]).counts
    assert counts["/imu/raw"] == 20 + 1 + 4 and "/imu/raw_block" not in counts

    fast_t, fast_rows, _ = make_fixtures.analytic_trajectory(8000.0, 0.01)
    fast_t, fast_rows = fast_t[:8].copy(), fast_rows[:8].copy()
    fast_t[4] = fast_t[3] + 1_000  # 1 µs after the one before
    fast_rows[4, SAMPLE_ROW.index.dt] = 1e-6
    fast_q = np.tile([1.0, 0.0, 0.0, 0.0], (8, 1))
    writer = FlightLogWriter(tmp_path / "fast", fsync=False, block_messages_above_hz=1500.0)
    writer.write_block(fast_t, fast_rows, flags[:8], q=fast_q, estimator="m")
    writer.write_block(fast_t[:1] + 10_000_000, fast_rows[:1], flags[:1], q=fast_q[:1], estimator="m")  # lone row
    writer.close()
    counts = read_log(writer.files[0]).counts
    assert counts["/imu/raw_block"] == 1 and counts["/imu/raw"] == 1


def test_a_block_s_gyro_bias_is_written_with_its_last_row_only(tmp_path):
    from mcap.reader import make_reader

    from ahrs_service.logs import schemas

    t_ns, rows, _ = make_fixtures.analytic_trajectory(200.0, 0.1)
    flags = np.full(len(t_ns), GYR_VALID | ACC_VALID, dtype=np.int64)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t_ns), 1))
    writer = FlightLogWriter(tmp_path, fsync=False)
    writer.write_block(t_ns[:5], rows[:5], flags[:5], q=q[:5], estimator="madgwick", bias=np.array([0.1, 0.2, 0.3]))
    writer.close()
    with open(writer.files[0], "rb") as f:
        found = [(json.loads(m.data), json.loads(s.data)) for s, c, m in make_reader(f).iter_messages(topics=["/attitude"])]
    assert [("gyro_bias" in m) for m, _ in found] == [False] * 4 + [True]
    assert found[-1][0]["gyro_bias"] == [0.1, 0.2, 0.3]
    assert all(schemas.validate(m, schema) == [] for m, schema in found)


def _service_on(path: Path, directory: Path, **log_options) -> Path:
    """Plays the flight log ``path`` through the service as fast as it goes; its new log."""
    from ahrs_service import config as config_mod
    from ahrs_service.service import Service

    cfg = config_mod.validate({
        "source": {"type": "recorded", "recorded_path": str(path), "recorded_realtime": False},
        "rates": {"estimation_hz": 200},
        "estimator": {"name": "madgwick"},
        "mavlink": {"endpoints": ["udpout:127.0.0.1:9"]},
        "log": {"directory": str(directory), **log_options},
    })
    service = Service(cfg, duration_s=60.0)
    service.start()
    try:
        assert service.pipeline.clock is None  # a flight log's times are on the sensor's clock
        service.run()
    finally:
        service.close()
    assert service.pipeline.samples == len(read_log(path))
    return service.log_writer.files[0]


def test_the_service_on_its_own_log_reproduces_it_bit_for_bit(tmp_path):
    """A flight log played through the service (up to a block a tick from the recorded
    source) is logged with every sample at its recorded time and replays what the service
    estimated; played again, the service's own log comes back identical — its stored times
    are used as they are, never recovered again."""
    path, *_ = make_fixtures.record_analytic(tmp_path / "rec", seconds=3.0, change=None)
    first = read_log(_service_on(path, tmp_path / "first"))
    again = read_log(_service_on(first.path, tmp_path / "again"))
    assert np.array_equal(first.t_ns, read_log(path).t_ns)
    assert np.array_equal(again.t_ns, first.t_ns) and np.array_equal(again.t_source_ns, first.t_ns)
    assert np.array_equal(again.rows, first.rows, equal_nan=True)
    assert np.array_equal(replay(first), first.attitudes) and np.array_equal(again.attitudes, first.attitudes)


def test_the_service_logs_a_fast_source_one_message_per_burst_and_replays_it(tmp_path):
    """A 4 kHz recording played through the service (blocks of up to 64 rows from the recorded
    source) is logged as /imu/raw_block + /attitude_block (bursts queued behind one another
    joined up to the /attitude preview): the same rows, times, numbers and
    estimates as the service's per-sample log of the same run, the recorded estimate replayed
    bit for bit; played through the service again, the block log gives the same again."""
    path, *_ = make_fixtures.record_analytic(tmp_path / "rec", rate_hz=4000.0, seconds=1.0, change=None)
    recorded = read_log(path)
    first = read_log(_service_on(path, tmp_path / "first"))
    per_sample = read_log(_service_on(path, tmp_path / "per-sample", block_messages_above_hz=1e6))
    # one message a burst of up to 64 rows, or several bursts joined (at most 256 rows)
    assert "/imu/raw" not in first.counts and first.counts["/imu/raw_block"] >= len(recorded) // 256
    assert per_sample.counts["/imu/raw"] == len(recorded) and "/imu/raw_block" not in per_sample.counts
    for key in ("t_ns", "t_source_ns", "rows", "flags", "index", "attitudes"):
        assert np.array_equal(getattr(first, key), getattr(per_sample, key), equal_nan=True), key
    assert np.array_equal(first.t_ns, recorded.t_ns) and np.array_equal(first.index, np.arange(len(recorded)))
    assert np.array_equal(replay(first), first.attitudes)
    again = read_log(_service_on(first.path, tmp_path / "again"))
    assert np.array_equal(again.rows, first.rows, equal_nan=True) and np.array_equal(again.attitudes, first.attitudes)


@pytest.mark.parametrize("truth", [True, False])
def test_the_simulators_truth_is_logged_unless_switched_off(tmp_path, truth):
    """``log.truth = false``: the log holds what a real sensor's holds, raw + estimate."""
    from ahrs_service import config
    from ahrs_service.logs.reader import read_log
    from ahrs_service.service import Service

    cfg = config.validate({
        "source": {"type": "simulated_i2c", "board": "mpu9250"},
        "mavlink": {"endpoints": ["udpout:127.0.0.1:9"]},
        "log": {"directory": str(tmp_path), "truth": truth},
    })
    service = Service(cfg, duration_s=0.5)
    service.start()
    try:
        service.run()
    finally:
        service.close()
    log = read_log(service.log_writer.files[0])
    assert log.counts["/imu/raw"] == log.counts["/attitude"] > 0
    assert log.counts.get("/attitude/truth", 0) == (log.counts["/imu/raw"] if truth else 0)
