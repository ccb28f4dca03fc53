"""A real ``ahrs-service run`` on the simulated MPU-9250 with its FIFO, stopped with SIGSTOP.

A stop shorter than the FIFO holds (42 samples: 210 ms at 200 Hz) loses nothing — every
sample the part produced is in the log, one after the other; a longer one loses samples,
and every lost one is counted by cause in the log's /loop records. The assertions are on
counts (samples logged + lost against the periods the recording spans), never on how long
anything took.
"""

from __future__ import annotations

import json
import signal
import time

import numpy as np
import pytest
from mcap.reader import make_reader

from tests.test_daemon import FakeSystemd, running, write_config

pytestmark = pytest.mark.timeout(180)

from ahrs_service.drivers.sim.mpu9250 import SimulatedMPU9250

# the part's output period at 200 Hz, on the simulated unit's own (off-nominal) oscillator
PERIOD_NS = 5_000_000 / (1.0 + SimulatedMPU9250.CLOCK_ERROR)


MPU9250 = ('type = "simulated_i2c"\nboard = "mpu9250"\n'
           'board_options = { rate_hz = 200, fifo_read_hz = 50 }\n')
# the ICM-42688-P at 1 kHz: its 102-sample FIFO holds 101.6 ms (the twin runs 0.42 % fast)
ICM42688P = ('type = "simulated_spi"\nboard = "icm42688p"\n'
             'board_options = { odr_hz = 1000, fifo_read_hz = 100 }\n')
ICM_PERIOD_NS = 1e9 / 1004.2


def _config(tmp_path, port, source=MPU9250):
    path = tmp_path / "config.toml"
    write_config(path, tmp_path / "logs", port, beta=None, source=source)
    return path


def _run_with_stall(tmp_path, port, stall_s, source=MPU9250):
    notify = FakeSystemd(tmp_path)
    with running(["run", "--config", str(_config(tmp_path, port, source))], tmp_path, notify) as proc:
        assert notify.wait_for("READY=1", 90)
        notify.wait_for("never", 1.0)
        proc.send_signal(signal.SIGSTOP)
        time.sleep(stall_s)
        proc.send_signal(signal.SIGCONT)
        notify.wait_for("never", 1.5)  # at least one housekeeping second after the stop
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20.0) == 0
    from ahrs_service.logs.reader import read_log

    path = next((tmp_path / "logs").glob("flight-*.mcap"))
    log = read_log(path)
    with open(path, "rb") as f:
        loops = [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/loop"])]
    source = dict(loops[-1]["source"])
    # the longest time between two of the loop's wake-ups (each drains the FIFO), ms: its
    # nominal period plus the largest deviation any second of /loop recorded
    source["longest_loop_gap_ms"] = max(1e3 / m["rate_hz"] + m["period_jitter_max_us"] / 1e3
                                        for m in loops if m["ticks"] > 1)
    source["cpu_s"] = [(m["process_cpu_s"], m.get("simulation_cpu_s")) for m in loops]  # process, simulated part
    return log, source


def _periods(log, period_ns=PERIOD_NS) -> int:
    """Sample periods the log spans, first to last sample inclusive."""
    return int(round((log.t_ns[-1] - log.t_ns[0]) / period_ns)) + 1


def test_a_stop_shorter_than_the_fifo_loses_no_sample(tmp_path):
    log, source = _run_with_stall(tmp_path, 14981, 0.1)
    lost = source["lost"]
    assert (lost["total"], source["sim_fifo_dropped"]) == (0, 0)
    assert np.array_equal(log.index, np.arange(len(log)))
    # each row's time is placed within one period of its true one, so the span in periods
    # can differ from the count by at most one at each end
    assert abs(_periods(log) - len(log)) <= 1
    assert np.max(np.diff(log.t_ns)) < 2 * PERIOD_NS  # no gap anywhere
    # /loop's CPU figures: the process's time and the simulated part's share of it, both growing
    process, simulated = np.array(source["cpu_s"]).T
    assert np.all(np.diff(process) >= 0) and np.all(np.diff(simulated) >= 0)
    assert np.all((simulated > 0) & (simulated < process)) and simulated[-1] > simulated[0]


def test_a_stop_longer_than_the_fifo_counts_every_lost_sample(tmp_path):
    log, source = _run_with_stall(tmp_path, 14982, 0.6)
    lost = source["lost"]
    assert lost["fifo_overflow"] > 0 and lost["total"] == lost["fifo_overflow"]
    # the count is the simulated part's own count of the samples it dropped or had emptied
    # by the FIFO reset (to within one: the sensor clock places the reset within its read
    # latency of a sample), however long a loaded machine made the stop
    dropped = source["sim_fifo_dropped"]
    assert abs(lost["fifo_overflow"] - dropped) <= 1
    # stopped for at least 0.6 s = 120 periods, of which the FIFO keeps 42 (less up to one
    # 20 ms drain period, 4 samples, read just before the stop)
    assert dropped >= 120 - 42 - 4
    # logged + counted = every period the part ran (±1 at each end: each row is placed
    # within one period of its true time)
    assert abs(_periods(log) - (len(log) + lost["total"])) <= 2
    # the gap is in the log as one long dt, not filled in
    assert np.sum(np.diff(log.t_ns) > 2 * PERIOD_NS) >= 1


def test_icm42688p_at_1khz_a_stop_shorter_than_its_fifo_loses_no_sample(tmp_path):
    # issue 15: stalls shorter than the ICM-42688-P's FIFO (about 100 ms at 1 kHz) lose nothing.
    # It lost 2-18 samples with drain windows of 47-57 ms until the FIFO_FULL raised between a
    # burst's level read and its data read was seen with that data, and the simulated bus made
    # its part's samples before a transfer instead of inside the level read (the three
    # "issue 15" tests at the end of test_icm42688p.py, on a simulated clock). On hosts at load
    # 6-9 it then failed 1 run in 21 by 39 periods: a first level read held up around its
    # latch placed the first rows alone (fixed: the data transfer's count bounds the clock
    # too, test_a_host_held_at_the_first_level_read_neither_misplaces_nor_drops_rows)
    log, source = _run_with_stall(tmp_path, 14983, 0.04, ICM42688P)
    window_ms = source["fifo_longest_window_ms"]  # the driver's own: a drain's level read to the next's end
    if source["lost"]["total"] and window_ms > 101.6:
        # the rule: a loss must coincide with a measured host stall longer than the
        # FIFO holds. A busy CI host once held the loop 60 ms more than the 40 ms stop (and a
        # CPU hog beside the suite held a drain 12 ms past a 100 ms loop gap); the count
        # must then be the part's own, and the test cannot show what it is for
        assert abs(source["lost"]["total"] - source["sim_fifo_dropped"]) <= 1
        pytest.skip(f"the FIFO went {window_ms:.0f} ms between drains, longer than its 101.6 ms")
    assert 40.0 < window_ms  # the stop is seen
    assert (source["lost"]["total"], source["sim_fifo_dropped"]) == (0, 0)
    assert np.array_equal(log.index, np.arange(len(log)))
    assert abs(_periods(log, ICM_PERIOD_NS) - len(log)) <= 1
    assert np.max(np.diff(log.t_ns)) < 2 * ICM_PERIOD_NS


def test_icm42688p_at_1khz_a_longer_stop_counts_what_the_part_turned_away(tmp_path):
    log, source = _run_with_stall(tmp_path, 14984, 0.5, ICM42688P)
    lost = source["lost"]
    assert lost["total"] == lost["fifo_overflow"] > 0
    # the part's own count (stop-on-full: turned away, plus anything flushed unread)
    assert abs(lost["fifo_overflow"] - source["sim_fifo_dropped"]) <= 1
    assert source["sim_fifo_dropped"] >= 500 - 102 - 10
    assert abs(_periods(log, ICM_PERIOD_NS) - (len(log) + lost["total"])) <= 2
    assert np.sum(np.diff(log.t_ns) > 2 * ICM_PERIOD_NS) >= 1


# issue 18: a source without FIFO polled once per tick (the MPU-9250 with ``fifo = false``,
# the default simulated IMU) loses the samples of a stall: counted as lost (host_stall),
# not only as overruns
MPU9250_POLLED = ('type = "simulated_i2c"\nboard = "mpu9250"\n'
                  'board_options = { rate_hz = 200, fifo = false }\n')
SIMULATED = 'type = "simulated"\n'


@pytest.mark.parametrize("source, port", [(MPU9250_POLLED, 14985), (SIMULATED, 14986)], ids=["mpu9250-polled", "simulated"])
def test_a_stall_of_a_polled_source_counts_its_lost_samples(tmp_path, source, port):
    log, diag = _run_with_stall(tmp_path, port, 0.5, source)
    lost = diag["lost"]
    assert lost["total"] == lost["host_stall"]
    # stopped 0.5 s at 200 Hz: about 100 − 1 periods went unread (more on a loaded host; the
    # loop's grid and the stop's edges cost a period or two)
    assert lost["host_stall"] >= 97
    if source == SIMULATED:
        # logged + counted = every period the log spans (±1 at each end). Not for the polled
        # MPU-9250: a tick that comes just before the part's next sample reads none new and
        # the next skips one (4–7 periods in 620 measured), the phase of polling, not a stall
        assert abs(_periods(log, 5e6) - (len(log) + lost["total"])) <= 2
    assert np.sum(np.diff(log.t_ns) > 50e6) >= 1  # the gap is a long dt in the log
