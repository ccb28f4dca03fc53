"""FlightLogWriter: round trip through mcap's indexed reader, schemas, errors, rotation."""

from __future__ import annotations

import errno
import json
import math
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from ahrs_service.core.samples import ACC_VALID, GYR_SATURATED, GYR_VALID, MAG_NEW, MAG_VALID
from ahrs_service.logs import mcap_file as mcap_file_mod
from ahrs_service.logs import schemas
from ahrs_service.logs import writer as writer_mod
from ahrs_service.logs.mcap_file import McapLogFile
from ahrs_service.logs.reader import read_log
from ahrs_service.logs.writer import FlightLogWriter

RNG = np.random.default_rng(3)


def _rows(n: int) -> np.ndarray:
    rows = RNG.normal(size=(n, 10))
    rows[:, 9] = 0.001 + RNG.uniform(0, 1e-4, n)
    rows[::3, 6:9] = np.nan  # no magnetometer on every third sample
    rows[5, 1] = np.nan  # one invalid gyro reading
    return rows


def _wait_for(predicate, seconds: float = 10.0) -> bool:
    for _ in range(int(seconds / 0.01)):
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def _write_all_channels(w: FlightLogWriter, rows: np.ndarray) -> None:
    w.write_config(0, {"estimator": {"name": "madgwick", "params": {"beta": 0.1}}, "rate_hz": 1000})
    for i, row in enumerate(rows):
        t = 1_000_000 * (i + 1)
        flags = GYR_VALID | ACC_VALID | (0 if np.isnan(row[6]) else MAG_VALID | MAG_NEW)
        w.write_raw(t, row, flags, raw={"gyr": [i, -i, 3]} if i % 2 else None, temperature=25.5 if i % 2 else None)
        q = np.array([math.cos(i * 1e-3), math.sin(i * 1e-3), 0.0, 0.0])
        w.write_attitude(t, q, "madgwick", np.array([1e-3, 0.0, -2e-3]), {"initialised": True, "acc_skipped": i})
        if i % 10 == 0:
            w.write_truth(t, q, movement=bool(i % 20), source="test")
    w.write_loop(
        5_000_000,
        {"rate_hz": 1000.0, "ticks": 500, "overruns": 1, "period_jitter_p99_us": 20.5, "load_percent": 30.0,
         "source": {"bus_errors": 2}, "log": w.stats()},
    )
    w.write_param_change(6_000_000, None, "beta", 0.1, 0.2, "mavlink")
    w.write_mavlink(7_000_000, {"tx": 10, "rx": 4, "heartbeats": 1})


def test_round_trip_with_indexed_reader_is_bit_exact(tmp_path):
    rows = _rows(500)
    w = FlightLogWriter(tmp_path / "logs", tf_rate_hz=None)
    _write_all_channels(w, rows)
    w.close()
    assert w.status == "closed" and w.dropped == 0 and len(w.files) == 1
    path = w.files[0]
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes  # indexed, finished file
        topics = {c.topic: c for c in summary.channels.values()}
        assert summary.statistics.channel_message_counts[topics["/imu/raw"].id] == len(rows)
        raw = [json.loads(m.data) for _, c, m in reader.iter_messages(topics=["/imu/raw"])]
        log_times = [m.log_time for _, _, m in reader.iter_messages(topics=["/imu/raw"])]
    assert log_times == [1_000_000 * (i + 1) for i in range(len(rows))]
    for i, m in enumerate(raw):
        assert m["t_ns"] == log_times[i] and m["index"] == i
        for key, cols in (("gyr", slice(0, 3)), ("acc", slice(3, 6))):
            expect = [None if math.isnan(v) else v for v in rows[i, cols].tolist()]
            assert m[key] == expect  # floats compare exactly: repr round-trips
        assert m["mag"] is None if i % 3 == 0 else m["mag"] == rows[i, 6:9].tolist()
        assert m["dt"] == rows[i, 9]
    log = read_log(path)
    assert log.indexed and log.damage is None
    assert np.array_equal(log.rows, rows, equal_nan=True)
    assert log.estimator == "madgwick" and log.params == {"beta": 0.1}
    assert log.param_changes[0]["sample_index"] == len(rows)  # None = samples written so far
    assert log.counts["/tf"] == len(rows)  # tf_rate_hz=None: one per attitude


def test_every_message_matches_its_json_schema(tmp_path):
    w = FlightLogWriter(tmp_path, tf_rate_hz=200.0)
    _write_all_channels(w, _rows(200))
    w.close()
    seen = set()
    with open(w.files[0], "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages():
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            assert schema.name == schemas.CHANNELS[channel.topic][0]
            doc = json.loads(schema.data)
            msg = json.loads(message.data)
            assert schemas.validate(msg, doc) == [], (channel.topic, msg)
            seen.add(channel.topic)
            if channel.topic == "/tf":
                # Foxglove order x, y, z, w; ours is w, x, y, z
                assert msg["parent_frame_id"] == "ned" and msg["child_frame_id"] == "body"
                t = message.log_time
                assert msg["timestamp"] == {"sec": t // 10**9, "nsec": t % 10**9}
                i = t // 1_000_000 - 1
                assert msg["rotation"]["w"] == math.cos(i * 1e-3) and msg["rotation"]["x"] == math.sin(i * 1e-3)
    assert seen == {"/config", "/imu/raw", "/attitude", "/attitude/truth", "/loop", "/params", "/mavlink", "/tf"}


def test_validator_rejects_what_the_schemas_forbid():
    good = schemas.raw_message(1, [0.0] * 9 + [0.01], GYR_VALID)
    assert schemas.validate(good, schemas.IMU_RAW) == []
    bad = dict(good, gyr=[0.0, 0.0], flags="3")
    del bad["dt"]
    errors = schemas.validate(bad, schemas.IMU_RAW)
    assert any("dt" in e for e in errors) and any("gyr" in e for e in errors) and any("flags" in e for e in errors)
    assert schemas.validate({"t_ns": True, "q": [1, 0, 0, 0]}, schemas.TRUTH) != []  # bool is not an integer


def test_flags_are_decoded_and_saturation_kept():
    m = schemas.raw_message(1, [0.0] * 10, GYR_SATURATED | ACC_VALID)
    assert m["valid"]["gyr"] is False and m["valid"]["gyr_saturated"] is True and m["valid"]["acc"] is True


def test_file_name_carries_utc_start_and_directory_is_created(tmp_path):
    target = tmp_path / "a" / "b"
    w = FlightLogWriter(target, prefix="rov")
    w.write_raw(1, np.zeros(10), 0)
    w.close()
    (path,) = w.files
    assert path.parent == target
    m = re.fullmatch(r"rov-(\d{8}T\d{6})Z\.mcap", path.name)
    assert m is not None
    started = time.strptime(m.group(1), "%Y%m%dT%H%M%S")
    assert abs(time.mktime(started) - time.mktime(time.gmtime())) < 3600


def test_unwritable_directory_is_reported_not_raised_and_retried(tmp_path):
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("a file where the log folder should be")
    w = FlightLogWriter(blocker / "logs", retry_first_s=0.05, retry_max_s=0.1)
    for i in range(50):
        w.write_raw(i, np.zeros(10), 0)  # must not raise
        w.write_attitude(i, [1.0, 0.0, 0.0, 0.0], "madgwick")
    assert _wait_for(lambda: w.dropped >= 100)
    assert w.status == "error" and w.files == [] and w.samples_not_logged == 50
    # the path and the system's text, not a Python class name
    assert w.last_error == f"{blocker / 'logs'}: Not a directory (ENOTDIR)"
    # the folder becomes writable: the writer starts a file on its own
    blocker.unlink()
    assert _wait_for(lambda: (w.write_raw(10**6, np.zeros(10), 0), w.status == "ok")[1])
    w.close()
    assert len(w.files) == 1 and read_log(w.files[0]).counts["/imu/raw"] >= 1
    assert w.outages == 1 and w.last_outage.samples == w.samples_not_logged >= 50


def test_back_off_doubles_from_the_first_delay_up_to_the_cap(tmp_path):
    w = FlightLogWriter(tmp_path, retry_first_s=0.5, retry_factor=2.0, retry_max_s=30.0)
    assert [w.retry_delay(k) for k in range(8)] == [0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0]
    assert w.retry_delay(10**6) == 30.0  # no overflow after a very long outage
    w.close()


class _FullDisk:
    """os.pwrite of a disk that fills: while ``full`` each call writes at most ``room`` bytes
    (a torn write) and then raises ENOSPC, as the kernel does."""

    def __init__(self, monkeypatch) -> None:
        self.full = False
        self.room = 100
        self.calls = 0
        self._pwrite = mcap_file_mod.os.pwrite
        monkeypatch.setattr(mcap_file_mod.os, "pwrite", self)

    def __call__(self, fd, data, offset):
        self.calls += 1
        if not self.full:
            return self._pwrite(fd, data, offset)
        if self.room and len(data) > 0:
            n = self._pwrite(fd, bytes(data[: self.room]), offset)
            self.room = 0
            return n
        raise OSError(errno.ENOSPC, "No space left on device")


def test_disk_full_keeps_one_valid_file_and_goes_on_in_it(tmp_path, monkeypatch):
    disk = _FullDisk(monkeypatch)
    w = FlightLogWriter(tmp_path, flush_interval_s=0.05, retry_first_s=0.05, retry_max_s=0.1)
    w.write_config(0, {"estimator": {"name": "madgwick", "params": {"beta": 0.1}}})
    for i in range(20):
        w.write_raw(i + 1, np.full(10, float(i)), 0)
    assert _wait_for(lambda: w.status == "ok" and w._log_files.current.committed_bytes > 0 and w._log_files.current.unflushed == 0)
    disk.full = True
    i = 20
    while w.status != "error" and i < 2000:  # bounded
        w.write_raw(i + 1, np.full(10, float(i)), 0)
        i += 1
        time.sleep(0.002)
    assert w.status == "error"
    (path,) = w.files
    assert w.last_error == f"{path}: No space left on device (ENOSPC)"
    # the torn write was cut off: what is on disk is a valid MCAP prefix, first samples in it
    on_disk = read_log(path)
    assert on_disk.index.tolist() == list(range(20)) and on_disk.damage is not None
    calls = disk.calls
    for _ in range(50):  # the outage goes on: samples counted, not one new file
        w.write_raw(i + 1, np.full(10, float(i)), 0)
        i += 1
        time.sleep(0.004)
    assert disk.calls > calls and w.files == [path] and sorted(tmp_path.iterdir()) == [path]
    disk.full = False
    while w.status != "ok" and i < 4000:
        w.write_raw(i + 1, np.full(10, float(i)), 0)
        i += 1
        time.sleep(0.002)
    total = i
    w.close()
    assert w.files == [path] and sorted(tmp_path.iterdir()) == [path]
    log = read_log(path)
    assert log.damage is None and log.indexed and log.estimator == "madgwick"
    # every sample is either in the file (in order, exact) or counted as not logged
    assert len(log) + w.samples_not_logged == total and w.samples_not_logged >= 50
    assert np.array_equal(log.rows[:, 0], log.index.astype(float))
    assert w.outages == 1 and w.last_outage.samples == w.samples_not_logged
    assert w.not_logged().seconds == pytest.approx(w.last_outage.seconds) and w.last_outage.seconds > 0


def test_close_during_an_outage_leaves_a_recoverable_file_or_none(tmp_path, monkeypatch):
    from ahrs_service.logs.recover import recover

    disk = _FullDisk(monkeypatch)
    w = FlightLogWriter(tmp_path / "a", flush_interval_s=0.05, retry_first_s=0.05)
    for i in range(30):
        w.write_raw(i + 1, np.full(10, float(i)), 0)
    assert _wait_for(lambda: w._log_files.current is not None and w._log_files.current.committed_bytes > 0 and w._log_files.current.unflushed == 0)
    disk.full = True
    for i in range(30, 60):
        w.write_raw(i + 1, np.full(10, float(i)), 0)
    w.close()
    (path,) = w.files
    assert sorted(path.parent.iterdir()) == [path] and w.samples_not_logged == 30
    assert read_log(path).index.tolist() == list(range(30))
    out = recover(path, tmp_path / "fixed.mcap")
    assert out is not None
    with open(tmp_path / "fixed.mcap", "rb") as f:
        assert sum(1 for _ in make_reader(f).iter_messages(topics=["/imu/raw"])) == 30
    # a disk full from the first byte: nothing on disk, so no empty "bad magic" file is left
    w = FlightLogWriter(tmp_path / "b", flush_interval_s=0.05, retry_first_s=0.05)
    for i in range(30):
        w.write_raw(i + 1, np.zeros(10), 0)
    assert _wait_for(lambda: w.status == "error")
    w.close()
    assert len(w.files) == 1 and list((tmp_path / "b").iterdir()) == [] and w.samples_not_logged == 30


def test_log_folder_deleted_then_a_file_in_its_place_mid_run(tmp_path):
    """rm -rf of the log folder while a file is open, then a regular file where the folder was:
    the deleted file is noticed at its next flush (not written on into a nameless inode), its
    samples are counted as not logged, the writer waits out the blocked path with back-off and
    starts one new file once the folder can be made again."""
    import shutil

    folder = tmp_path / "logs"
    w = FlightLogWriter(folder, flush_interval_s=0.05, retry_first_s=0.05, retry_max_s=0.1)
    i = 0

    def feed(n: int) -> None:
        nonlocal i
        for _ in range(n):
            w.write_raw(i + 1, np.full(10, float(i)), 0)
            i += 1
            time.sleep(0.002)

    feed(30)
    assert _wait_for(lambda: w._log_files.current is not None and w._log_files.current.committed_bytes > 0)
    (first,) = w.files
    shutil.rmtree(folder)
    folder.write_text("a file where the log folder was")
    while w.status != "error" and i < 2000:
        feed(1)
    assert w.last_error == f"{first}: deleted while being written (ENOENT)"
    while "ENOTDIR" not in w.last_error and i < 4000:  # the path is blocked: counted, retried
        feed(1)
    feed(10)
    assert w.status == "error" and w.last_error == f"{folder}: Not a directory (ENOTDIR)" and w.files == [first]
    folder.unlink()
    while w.status != "ok" and i < 4000:
        feed(1)
    feed(20)
    total = i
    w.close()
    (second,) = folder.iterdir()
    assert w.files == [first, second] and w.outages == 1
    log = read_log(second)
    assert log.damage is None and len(log) + w.samples_not_logged == total
    # the deleted file's 30 first samples at least, and the 10 fed while the path was blocked
    assert w.samples_not_logged >= 30 + 10


def test_rotation_by_size_keeps_every_sample_and_restates_config(tmp_path):
    rows = _rows(3000)
    w = FlightLogWriter(tmp_path, chunk_size=4096, rotate_bytes=40_000, flush_interval_s=0.05)
    w.write_config(0, {"estimator": {"name": "madgwick", "params": {"beta": 0.1}}})
    for i, row in enumerate(rows):
        if i == 10:
            w.write_param_change(i, i, "beta", 0.1, 0.25, "mavlink")
            # a ground station's other writes are on /params too, but no estimator parameter
            w.write_param_change(i, i, "MAG_DECL_DEG", 0.0, 5.0, "mavlink 255/190 unsigned")
        w.write_raw(i + 1, row, 0)
        w.write_attitude(i + 1, [1.0, 0.0, 0.0, 0.0], "madgwick")
        if i % 500 == 0:
            time.sleep(0.1)  # let the writer thread reach the size limit mid-recording
    w.close()
    assert len(w.files) >= 2 and w.dropped == 0
    logs = [read_log(p) for p in w.files]
    assert all(log.damage is None and log.indexed for log in logs)
    assert np.array_equal(np.concatenate([log.rows for log in logs]), rows, equal_nan=True)
    assert np.array_equal(np.concatenate([log.index for log in logs]), np.arange(len(rows)))
    assert logs[0].params == {"beta": 0.1}
    # a later file starts from the parameters in force, the live change folded in
    assert all(log.params == {"beta": 0.25} and log.configs[0]["reason"] == "rotation" for log in logs[1:])


def test_rotation_by_duration(tmp_path):
    w = FlightLogWriter(tmp_path, rotate_seconds=0.2, flush_interval_s=0.05)
    for i in range(200):  # bounded: ~0.6 s of samples
        w.write_raw(i + 1, np.zeros(10), 0)
        time.sleep(0.003)
    w.close()
    assert len(w.files) >= 2
    assert sum(len(read_log(p)) for p in w.files) == 200


def test_full_queue_drops_and_counts_without_blocking(tmp_path, monkeypatch):
    import threading

    release = threading.Event()
    handle = FlightLogWriter._handle

    def slow_handle(self, item):
        release.wait(10.0)  # a stalled disk
        handle(self, item)

    monkeypatch.setattr(FlightLogWriter, "_handle", slow_handle)
    w = FlightLogWriter(tmp_path, queue_size=10)
    w.write_raw(0, np.zeros(10), 0)
    assert _wait_for(lambda: len(w._q) == 0)  # the thread holds the first sample
    for i in range(1, 16):
        w.write_raw(i, np.zeros(10), 0)  # 10 fit in the queue, 5 do not
    assert w.dropped == 5 and w.samples_not_logged == 5
    release.set()
    w.close()
    log = read_log(w.files[0])
    assert log.index.tolist() == list(range(11))


def test_idle_writer_thread_is_woken_by_a_filling_queue_and_by_close(tmp_path, monkeypatch):
    """The writer thread sleeps up to 0.2 s when idle; a queue an eighth full and close()
    wake it at once (counted on the event, so the test does not depend on timing)."""
    release = threading.Event()
    handle = FlightLogWriter._handle

    def held_handle(self, item):
        release.wait(10.0)  # keeps the queue where the test puts it
        handle(self, item)

    monkeypatch.setattr(FlightLogWriter, "_handle", held_handle)
    w = FlightLogWriter(tmp_path, queue_size=64)
    assert w._idle_wait_s == pytest.approx(0.2) and w._wake_at == 8
    sets = []
    wake_set = w._wake.set
    monkeypatch.setattr(w._wake, "set", lambda: (sets.append(len(w._q)), wake_set()))
    w.write_raw(0, np.zeros(10), 0)
    assert _wait_for(lambda: len(w._q) == 0)  # the thread holds the first sample
    for i in range(1, 20):
        w.write_raw(i, np.zeros(10), 0)
    assert sets == [8]  # once, when the ninth entry found eight waiting
    release.set()
    w.close()
    assert len(sets) == 2  # close() woke it too
    assert read_log(w.files[0]).index.tolist() == list(range(20))
    fast_flush = FlightLogWriter(tmp_path / "fast", flush_interval_s=0.25)
    assert fast_flush._idle_wait_s == pytest.approx(0.05)  # the next look still comes within the interval
    fast_flush.close()


def test_writer_default_directory_is_relative_to_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    w = FlightLogWriter()
    w.write_raw(1, np.zeros(10), 0)
    w.close()
    assert w.files[0].resolve().parent == (tmp_path / "flight-logs").resolve()
    assert Path(writer_mod.__file__).resolve().parent not in w.files[0].resolve().parents


def test_new_file_on_estimator_rebuild_and_sample_numbering(tmp_path):
    w = FlightLogWriter(tmp_path, first_sample_index=1000)
    w.write_config(1, {"estimator": {"name": "madgwick", "params": {"beta": 0.1}}})
    for i in range(5):
        w.write_raw(10 + i, np.full(10, float(i)), 0)
    w.write_param_change(20, None, "beta", 0.1, 0.2, "mavlink")
    w.new_file()  # the service rebuilt its estimator
    w.write_config(30, {"estimator": {"name": "mahony_passive", "params": {"kp": 1.0}}}, reason="reload")
    for i in range(5, 8):
        w.write_raw(40 + i, np.full(10, float(i)), 0)
    w.close()
    first, second = (read_log(p) for p in w.files)
    assert first.index.tolist() == [1000, 1001, 1002, 1003, 1004]
    assert first.param_changes[0]["sample_index"] == 1005 and first.local_index(1005) == 5
    assert second.estimator == "mahony_passive" and second.configs[0]["reason"] == "reload"
    assert second.index.tolist() == [1005, 1006, 1007] and len(second.configs) == 1


def test_raw_index_null_reads_as_the_row_number(tmp_path):
    path = tmp_path / "null-index.mcap"
    with McapLogFile(path) as f:
        for i in range(3):
            msg = schemas.raw_message(i + 1, [0.0] * 9 + [0.001], GYR_VALID, index=None)
            assert msg["index"] is None and schemas.validate(msg, schemas.IMU_RAW) == []
            f.write("/imu/raw", i + 1, msg)
    log = read_log(path)
    assert log.damage is None and log.index.tolist() == [0, 1, 2] and log.t_ns.tolist() == [1, 2, 3]


@pytest.mark.parametrize("snapshot_before_new_file", [True, False], ids=["snapshot-late", "snapshot-none"])
def test_new_file_during_a_pending_rotation_leaves_no_one_sample_file(tmp_path, monkeypatch, snapshot_before_new_file):
    # a rotation (by duration) is due and waits for the loop's state snapshot when the service
    # calls new_file(): the new file must not be rotated again by that snapshot after one sample
    gate = threading.Event()
    handle = FlightLogWriter._on_new_file

    def gated_handle(self, item):
        gate.wait(10.0)
        handle(self, item)

    monkeypatch.setattr(FlightLogWriter, "_on_new_file", gated_handle)
    w = FlightLogWriter(tmp_path, rotate_seconds=3600.0, tf_rate_hz=None)
    state = np.arange(4.0)

    def sample(i: int, with_state: bool = True) -> None:
        w.write_raw(i, np.full(10, float(i)), 0)
        w.write_attitude(i, [1.0, 0.0, 0.0, 0.0], "madgwick", state=state if with_state else None)

    w.write_config(0, {"estimator": {"name": "madgwick", "params": {"beta": 0.1}}})
    for i in range(5):
        sample(i)
    assert _wait_for(lambda: not w._q)  # the last item may be in hand: an attitude, not a sample
    w.rotate_seconds = 0.0
    w.write_raw(5, np.full(10, 5.0), 0)
    assert _wait_for(lambda: w._rotation == 1)  # due: the writer asks for a snapshot
    w.rotate_seconds = 3600.0
    w.write_attitude(5, [1.0, 0.0, 0.0, 0.0], "madgwick")  # the loop answers with a later sample
    w.new_file()  # the service rebuilt its estimator
    if not snapshot_before_new_file:
        gate.set()
        assert _wait_for(lambda: w._log_files.current is None)  # new_file() handled before the next sample
    w.write_config(6, {"estimator": {"name": "madgwick", "params": {"beta": 0.2}}}, reason="reload")
    for i in range(6, 10):
        sample(i)  # with the gate closed, sample 6 answers the request: a snapshot is queued
    gate.set()
    w.close()
    logs = [read_log(p) for p in w.files]
    assert [len(log) for log in logs] == [6, 4]
    assert np.array_equal(np.concatenate([log.index for log in logs]), np.arange(10))
    assert logs[1].configs[0]["reason"] == "reload" and logs[1].params == {"beta": 0.2}
    assert logs[1].initial_state is None and logs[1].counts.get("/estimator/state", 0) == 0  # a fresh estimator
    assert w._rotation == 0 and w.dropped == 0


def test_log_file_writes_the_same_bytes_as_the_mcap_library(tmp_path):
    """McapLogFile (logs/mcap_file.py) against mcap's own Writer driven by hand: byte-identical
    files over several chunks, channels registered on first use, out-of-order log times and a
    flush in the middle, so the file layer adds nothing the library would not write."""
    import io

    from mcap.writer import CompressionType, Writer

    from ahrs_service.logs import schemas
    from ahrs_service.logs.mcap_file import LIBRARY

    topics = ["/imu/raw", "/attitude", "/loop"]
    r = np.random.default_rng(3)
    messages = []
    t = 1_000_000
    for i in range(2000):
        t += int(r.integers(-3_000, 1_000_000))  # now and then a message older than the last
        messages.append((topics[i % 3], t, bytes(r.integers(0, 256, size=int(r.integers(0, 300)), dtype=np.uint8))))

    path = tmp_path / "ours.mcap"
    with McapLogFile(path, chunk_size=4096, metadata={"k": 1}) as f:
        for i, (topic, t, data) in enumerate(messages):
            f.write_encoded(topic, t, data, t + 17)
            if i == 1234:
                f.flush(fsync=False)

    out = io.BytesIO()
    w = Writer(out, chunk_size=4096, compression=CompressionType.ZSTD)
    w.start(profile="", library=LIBRARY)
    w.add_metadata("ahrs-service", {"k": "1"})
    channels, seq = {}, {}
    for i, (topic, t, data) in enumerate(messages):
        if topic not in channels:
            sid = w.register_schema(schemas.CHANNELS[topic][0], schemas.SCHEMA_ENCODING, schemas.schema_bytes(topic))
            channels[topic] = w.register_channel(topic, schemas.MESSAGE_ENCODING, sid)
        seq[topic] = seq.get(topic, 0) + 1
        w.add_message(channels[topic], t, data, t + 17, seq[topic])
        if i == 1234:
            w.flush()
    w.finish()
    ours = path.read_bytes()
    assert len(ours) > 100_000 and ours == out.getvalue()


def test_a_file_written_without_flushes_streams_to_disk(tmp_path, monkeypatch):
    """Imports and replays never flush: past COMMIT_BYTES the staged bytes go to disk as
    written (whole records), not all at close."""
    monkeypatch.setattr(mcap_file_mod, "COMMIT_BYTES", 16_384)
    path = tmp_path / "big.mcap"
    f = McapLogFile(path, chunk_size=4096)
    rows = _rows(2000)
    for i, row in enumerate(rows):
        f.write("/imu/raw", i + 1, schemas.raw_message(i + 1, row.tolist(), 0, None, None, i))
        assert f.size - f.committed_bytes < 16_384 + 8192  # never much more than the threshold staged
    assert f.committed_bytes > 0
    f.close()
    log = read_log(path)
    assert log.damage is None and np.array_equal(log.rows, rows, equal_nan=True)


def test_a_block_s_unknown_temperature_is_null_as_write_sample_s_none(tmp_path):
    """write_block hands NaN temperatures to encode (which writes null): the same /imu/raw
    ``temperature`` as write_sample with None."""
    rows = np.zeros((3, 10))
    rows[:, 9] = 0.005
    q = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    w = FlightLogWriter(tmp_path / "block", fsync=False)
    w.write_block(np.array([1, 2, 3]), rows, np.full(3, 3), q=q, estimator="madgwick",
                  temperature=np.array([25.5, np.nan, -3.0]))
    w.close()
    ref = FlightLogWriter(tmp_path / "sample", fsync=False)
    for i, temp in enumerate((25.5, None, -3.0)):
        ref.write_sample(i + 1, rows[i], 3, q=q[i], estimator="madgwick", temperature=temp)
    ref.close()

    def temperatures(path):
        with open(path, "rb") as f:
            return [json.loads(m.data)["temperature"] for _, ch, m in make_reader(f).iter_messages() if ch.topic == "/imu/raw"]

    assert temperatures(w.files[0]) == temperatures(ref.files[0]) == [25.5, None, -3.0]


def test_a_dropped_record_counts_every_message_it_carries(tmp_path):
    """A full queue (here: a closed writer, which drops the same way) counts what a record
    carries, as the disk's side does: an autopilot comparison is /autopilot/attitude, /tf and
    /monitor; a block is its rows' /imu/raw, /attitude and /attitude/truth."""
    from types import SimpleNamespace

    w = FlightLogWriter(tmp_path)
    w.close()
    q = [1.0, 0.0, 0.0, 0.0]
    w.write_autopilot_attitude(SimpleNamespace(t_ns=1, q_autopilot=q, q_estimate=q, total_deg=0.0,
                                               inclination_deg=0.0, heading_deg=0.0))
    assert w.dropped == 3 and w.samples_not_logged == 0
    qs = np.tile(q, (2, 1))
    w.write_block(np.array([1, 2]), np.zeros((2, 10)), np.zeros(2, dtype=int), q=qs, estimator="madgwick", truth_q=qs)
    assert w.dropped == 3 + 6 and w.samples_not_logged == 2
    w.write_log(3, 6, "text")
    assert w.dropped == 3 + 6 + 1


def test_a_write_that_drops_the_file_loses_the_rest_of_its_record_counted(tmp_path, monkeypatch):
    """A failure that gives the file up (not the disk's: a new file comes next) in the first of
    a record's messages: the others are counted as lost, not written to no file (which would
    be a second and third error hiding the first)."""
    from types import SimpleNamespace

    real = McapLogFile.write_encoded

    def write_encoded(self, topic, *args, **kwargs):
        if topic == "/autopilot/attitude":
            raise RuntimeError("the file's own state is broken")
        return real(self, topic, *args, **kwargs)

    monkeypatch.setattr(McapLogFile, "write_encoded", write_encoded)
    w = FlightLogWriter(tmp_path, retry_first_s=60.0, flush_interval_s=3600.0)  # the sample stays unflushed
    w.write_raw(1, np.zeros(10), 0)
    assert _wait_for(lambda: w._log_files.current is not None and w.written == 1)
    q = [1.0, 0.0, 0.0, 0.0]
    w.write_autopilot_attitude(SimpleNamespace(t_ns=2, q_autopilot=q, q_estimate=q, total_deg=0.0,
                                               inclination_deg=0.0, heading_deg=0.0))
    assert _wait_for(lambda: w._log_files.current is None)
    w.close()
    assert w.errors == 1 and w.last_error.startswith("RuntimeError"), (w.errors, w.last_error)
    # the sample the given-up file held, and /tf and /monitor of the record (the write that
    # raised inside the file layer is not counted: it never reached the file's counters)
    assert w.dropped == 1 + 2 and w.samples_not_logged == 1


class _Loop:
    """A service loop's scheduler as the writer sees it: its next wake-up and period."""

    def __init__(self, next_wake_ns, period_ns):
        self.next_wake_ns, self.period_ns = next_wake_ns, period_ns


def test_the_writer_thread_leaves_the_loops_wake_up_free(tmp_path):
    # the writer does not start a record it may not finish before the loop wakes: it sleeps
    # until just after the wake-up, so the loop's thread finds the interpreter free
    loop = _Loop(None, 1_000_000)
    w = FlightLogWriter(tmp_path, fsync=False, loop=loop)
    try:
        w._record_ns = 100_000.0  # recent records took 100 µs
        now = 5_000_000_000
        assert w._pause_for_the_loop(now) == 0.0  # wake-up unknown (a data-ready line)
        loop.next_wake_ns = now + 200_000  # wakes in 200 µs: 2 × 100 µs + 50 µs would not fit
        assert w._pause_for_the_loop(now) == pytest.approx(250e-6)
        loop.next_wake_ns = now + 300_000  # 300 µs is room enough
        assert w._pause_for_the_loop(now) == 0.0
        loop.next_wake_ns = now - 10_000  # the loop is late already: nothing to keep free
        assert w._pause_for_the_loop(now) == 0.0
        w._record_ns = 5_000_000.0  # records slower than the period: never more than half of it
        loop.next_wake_ns = now + 600_000
        assert w._pause_for_the_loop(now) == 0.0
        loop.next_wake_ns = now + 400_000
        assert w._pause_for_the_loop(now) == pytest.approx(450e-6)
    finally:
        w.close()


def test_a_paced_writer_records_every_sample_beside_a_running_scheduler(tmp_path):
    from ahrs_service.scheduler import FixedRateScheduler

    sched = FixedRateScheduler(1000.0)
    w = FlightLogWriter(tmp_path, fsync=False, loop=sched)
    n = 0
    for _ in range(300):  # 0.3 s of a 1 kHz loop, a block of 8 rows a tick
        woke = sched.wait()
        # what the writer reads: the next deadline, at most a period after this wake-up
        assert sched.next_wake_ns - woke <= sched.period_ns
        rows = _rows(8)
        t = np.arange(n, n + 8, dtype=np.int64) * 125_000 + 1_000_000_000
        w.write_block(t, rows, np.full(8, GYR_VALID | ACC_VALID), q=np.tile([1.0, 0, 0, 0], (8, 1)), estimator="m")
        n += 8
        sched.done()
    w.close()
    log = read_log(w.files[0])
    assert len(log) == n and w.dropped == 0
