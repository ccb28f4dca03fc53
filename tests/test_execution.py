"""The execution layer on real Dask clusters: an embedded LocalCluster of 2 worker processes,
and a ``dask scheduler`` + two ``dask worker`` subprocesses on 127.0.0.1 driven through
``evaluate --scheduler``. Both must give the serial run's results, in its order, with the jobs
grouped into as many tasks as the task floor implies; a worker killed mid-run has its task
retried; an unreachable scheduler is a one-line error."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("distributed")

import cloudpickle  # noqa: E402  (comes with distributed)

from ahrs_service.cli import main as cli_main  # noqa: E402
from ahrs_service.evaluation import report  # noqa: E402
from ahrs_service.execution import Runner, RunnerError, open_runner  # noqa: E402
from tests.dask_cluster import free_port, hand_started_cluster  # noqa: E402

TRIALS = ["02_undisturbed_slow_rotation_B", "32_disturbed_attached_magnet_1cm"]
ESTIMATORS = ["madgwick", "mahony_passive"]

pytestmark = pytest.mark.timeout(180)


def _deterministic(results: dict) -> dict:
    """The results without what is measured (per-sample cost) or stamped (creation time)."""
    per_trial = {
        c: {t: {k: v for k, v in row.items() if k != "us_per_sample"} for t, row in rows.items()}
        for c, rows in results["per_trial"].items()
    }
    return {"trials": results["trials"], "per_trial": per_trial, "per_group": results["per_group"],
            "imu_delay": results["imu_delay"], "columns": [c["name"] for c in results["columns"]]}


def _columns():
    return report.make_columns(ESTIMATORS, [], {})


@pytest.fixture(scope="module")
def serial(broad_dir) -> dict:
    return report.evaluate(broad_dir, _columns(), TRIALS, runner=Runner())


def test_local_cluster_of_two_processes_gives_the_serial_results(broad_dir, serial):
    with open_runner(workers=2) as runner:
        assert runner.info.mode == "local" and runner.info.workers == 2
        pids = set(runner.client.run(os.getpid).values())
        assert len(pids) == 2 and os.getpid() not in pids  # worker processes, not threads here
        parallel = report.evaluate(broad_dir, _columns(), TRIALS, runner=runner)
    assert json.dumps(_deterministic(parallel), sort_keys=False) == json.dumps(_deterministic(serial), sort_keys=False)
    # the order of the per-trial tables is the serial one too
    assert [list(parallel["per_trial"][c]) for c in ESTIMATORS] == [TRIALS, TRIALS]


def test_evaluate_through_a_scheduler_and_two_worker_subprocesses(broad_dir, serial, tmp_path):
    with hand_started_cluster(workers=2) as address:
        out = tmp_path / "out"
        assert cli_main([
            "evaluate", "--data", str(broad_dir), "--estimators", ",".join(ESTIMATORS),
            "--trials", "02_*", "--out", str(out), "--scheduler", address, "--quiet",
        ]) == 0
        got = json.loads((out / "results.json").read_text())
        report.to_json(serial, tmp_path / "serial.json")  # the same JSON writing (NaN → null)
        want_all = json.loads((tmp_path / "serial.json").read_text())
        # the CLI ran one trial (the glob); the serial fixture's rows for it must match exactly
        assert got["trials"] == [TRIALS[0]]
        for c in ESTIMATORS:
            want = {k: v for k, v in want_all["per_trial"][c][TRIALS[0]].items() if k != "us_per_sample"}
            row = {k: v for k, v in got["per_trial"][c][TRIALS[0]].items() if k != "us_per_sample"}
            assert row == want
        assert got["imu_delay"][TRIALS[0]] == want_all["imu_delay"][TRIALS[0]]
        # the tasks the floor implies, counted by the workers that ran them
        this = sys.modules[__name__]
        cloudpickle.register_pickle_by_value(this)
        try:
            with open_runner(scheduler=address, connect_timeout_s=60) as runner:
                _check_granularity(runner)
        finally:
            cloudpickle.unregister_pickle_by_value(this)


def _square_or_die(job: tuple[int, str]) -> int:
    """A job that kills its worker process the first time job 3 runs (a marker file says so)."""
    value, marker = job
    if value == 3 and not os.path.exists(marker):
        Path(marker).write_text(str(os.getpid()))
        os._exit(1)  # the worker process dies mid-task, as a crash or an OOM kill would
    return value * value


def test_a_killed_workers_task_is_retried_and_the_result_is_complete(tmp_path):
    this = sys.modules[__name__]
    cloudpickle.register_pickle_by_value(this)  # workers cannot import the tests
    marker = str(tmp_path / "died")
    try:
        with open_runner(workers=2) as runner:
            pids_before = set(runner.client.run(os.getpid).values())
            got = runner.map(_square_or_die, [(i, marker) for i in range(8)])
    finally:
        cloudpickle.unregister_pickle_by_value(this)
    assert got == [i * i for i in range(8)]
    assert int(Path(marker).read_text()) in pids_before  # one of the workers did die


def _prepare_input(key: tuple[str, str]) -> bool:
    """Records each call as a file (the calls run in the worker processes)."""
    folder, name = key
    (Path(folder) / f"{name}.{os.getpid()}.{time.monotonic_ns()}").touch()
    return True


def _job_on(job: tuple[tuple[str, str], int]) -> tuple[str, int]:
    (_, name), value = job
    return name, value * value


def test_placed_jobs_prepare_each_input_once_in_the_whole_cluster(tmp_path):
    """``place_by``/``prepare``, inputs cut over tasks (nothing measured yet: a task per job):
    one prepare task per input for the runner's lifetime (not one per worker, nor per map),
    the jobs' results still in the jobs' order."""
    this = sys.modules[__name__]
    cloudpickle.register_pickle_by_value(this)
    jobs = [((str(tmp_path), name), i) for name in ("a", "b", "c", "d") for i in range(6)]
    try:
        with open_runner(workers=2) as runner:
            first = runner.map(_job_on, jobs, place_by=lambda job: job[0], prepare=_prepare_input)
            again = runner.map(_job_on, jobs[::-1], place_by=lambda job: job[0], prepare=_prepare_input)
    finally:
        cloudpickle.unregister_pickle_by_value(this)
    assert first == [(name, i * i) for (_, name), i in jobs]
    assert again == first[::-1]
    assert sorted(p.name.split(".")[0] for p in tmp_path.iterdir()) == ["a", "b", "c", "d"]
    with pytest.raises(ValueError, match="together"):
        Runner().map(_job_on, jobs, place_by=lambda job: job[0])


def test_local_workers_keep_glibcs_adaptive_allocator():
    """Dask's nannies set MALLOC_TRIM_THRESHOLD_ by default, which also freezes glibc's mmap
    threshold: every array over 128 KiB is then a fresh mmap, and the estimators' tasks ran
    2-4x slower in the workers (page faults: 18x, system time 15x, measured in docs/fleet.md).
    The embedded cluster's workers start without it."""
    with open_runner(workers=2) as runner:
        env = runner.client.run(os.environ.get, "MALLOC_TRIM_THRESHOLD_")
    assert len(env) == 2 and set(env.values()) == {None}


def _worker_settings(dask_worker) -> dict:
    """What a worker runs with (``client.run`` passes the worker to a parameter of this name)."""
    import dask

    return {"profile": dask.config.get("distributed.worker.profile.enabled"),
            "tick": dask.config.get("distributed.admin.tick.interval"),
            "profile_callback": "profile" in dask_worker.periodic_callbacks}


def test_local_workers_do_not_run_dasks_dashboard_profiler():
    """The embedded cluster has no dashboard, so its workers run without the statistical
    profiler that sampled their stacks every 10 ms for it, and tick their event loops once a
    second (docs/fleet.md: half of each worker's own CPU beside the tasks)."""
    with open_runner(workers=2) as runner:
        settings = runner.client.run(_worker_settings)
    assert len(settings) == 2
    for s in settings.values():
        assert s == {"profile": False, "tick": "1s", "profile_callback": False}


def test_two_embedded_clusters_at_once_warn_nothing():
    """Two commands on embedded clusters at once: the second's scheduler must not find its
    HTTP server's port taken (Dask then warns on stderr that it moved)."""
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with open_runner(workers=2) as first, open_runner(workers=2) as second:
            assert first.client.submit(sum, [1, 2]).result() == 3
            assert second.client.submit(sum, [3, 4]).result() == 7
    assert not [w for w in caught if "already in use" in str(w.message)], [str(w.message) for w in caught]


def test_unreachable_scheduler_is_an_error_naming_it():
    address = f"tcp://127.0.0.1:{free_port()}"  # nothing listens there
    with pytest.raises(RunnerError, match=address.replace(".", r"\.")):
        open_runner(scheduler=address, connect_timeout_s=1)


def test_evaluate_cli_reports_an_unreachable_scheduler_in_one_line(broad_dir, tmp_path, capsys):
    address = f"tcp://127.0.0.1:{free_port()}"
    assert cli_main(["evaluate", "--data", str(broad_dir), "--estimators", "madgwick",
                     "--trials", "02_*", "--out", str(tmp_path / "o"), "--scheduler", address]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and address in err[0] and "Traceback" not in err[0]
    assert err[0].startswith("ahrs-service evaluate: error: cannot reach the Dask scheduler")


@pytest.mark.parametrize("command_name", ["evaluate", "tune", "replay"])
def test_every_batch_command_refuses_a_bad_worker_count_in_one_line(command_name, broad_dir, tmp_path, capsys):
    """The runner set-up is cli.main's: one message for every command of the execution layer."""
    logs = Path(__file__).parent / "fixtures" / "logs"
    argv = {
        "evaluate": ["evaluate", "--data", str(broad_dir), "--estimators", "madgwick", "--trials", "02_*",
                     "--out", str(tmp_path / "o")],
        "tune": ["tune", "madgwick", "--data", str(broad_dir), "--trials", "02_*", "--budget", "1",
                 "--out", str(tmp_path / "p.json")],
        "replay": ["replay", str(logs / "analytic_madgwick.mcap"), str(logs / "broad_02_slice.mcap"),
                   "--out", str(tmp_path / "fleet")],
    }[command_name]
    assert cli_main([*argv, "--workers", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"ahrs-service {command_name}: error: --workers must be at least 1, not 0"]


def test_workers_below_one_is_an_error():
    with pytest.raises(RunnerError, match="--workers"):
        open_runner(workers=0)


def _children(pid: int) -> list[int]:
    """Direct child processes of ``pid`` (from /proc)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def _ignores_sigint(pid: int) -> bool:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigIgn:"):
            return bool(int(line.split()[1], 16) & (1 << (signal.SIGINT - 1)))
    return False


@pytest.mark.parametrize("sig, status, name", [(signal.SIGINT, 130, "SIGINT"), (signal.SIGTERM, 143, "SIGTERM")])
def test_ctrl_c_of_a_run_on_a_local_cluster_is_one_line(broad_dir, tmp_path, sig, status, name):
    """Ctrl-C reaches the whole foreground process group, the LocalCluster's worker processes
    too: each printed a KeyboardInterrupt traceback, and the closing cluster's pending gather
    and lost heartbeats printed more (#14 re-probe). Now the command's one line only."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "ahrs_service.cli", "evaluate", "--data", str(broad_dir), "--estimators", "all",
         "--workers", "2", "--quiet", "--out", str(tmp_path / "ev")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120
        # the workers run, and the command answers SIGINT again (it ignores it while it starts them)
        while time.monotonic() < deadline and proc.poll() is None:
            workers = [c for c in _children(proc.pid) if "spawn_main" in Path(f"/proc/{c}/cmdline").read_text()]
            if len(workers) >= 2 and not _ignores_sigint(proc.pid) and all(_ignores_sigint(w) for w in workers):
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()
        time.sleep(1.0)  # tasks under way
        os.killpg(proc.pid, sig)  # as a terminal's Ctrl-C (or a service manager's stop) does
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == status, err
    assert err.strip() == f"ahrs-service: interrupted ({name}) before the command finished", err


def _job_loading(job: tuple[tuple[str, str], int]) -> tuple[str, int]:
    """A job that loads its input through the worker's cache, as ``report.run_trial_job`` does."""
    from ahrs_service.execution import worker_cache

    key, value = job
    worker_cache(("test input", key), lambda: _prepare_input(key))
    return key[1], value * value


def _tenth_of_a_second(job: tuple[tuple[str, str], int]) -> float:
    return 0.1


def test_inputs_kept_whole_in_tasks_are_read_once_in_the_whole_cluster(tmp_path):
    """Six inputs of four 0.1 s jobs (by the guess), a 0.3 s floor: each input's jobs are a
    piece kept whole, a task each, which loads it itself (no prepare task): each input is
    read once in the whole cluster, whichever worker takes the task."""
    this = sys.modules[__name__]
    cloudpickle.register_pickle_by_value(this)
    names = ("a", "b", "c", "d", "e", "f")
    jobs = [((str(tmp_path), name), i) for name in names for i in range(4)]
    try:
        with open_runner(workers=2) as runner:
            got = runner.map(_job_loading, jobs, place_by=lambda job: job[0], prepare=_prepare_input,
                             cost=_tenth_of_a_second, task_floor_s=0.3)
            assert runner.tasks_submitted == 6
    finally:
        cloudpickle.unregister_pickle_by_value(this)
    assert got == [(name, i * i) for (_, name), i in jobs]
    loads = sorted(p.name.split(".")[0] for p in tmp_path.iterdir())
    assert loads == list(names), loads  # once each, and no prepare task beside


# ---------------------------------------------------------------------------- task granularity


def test_plan_tasks_keeps_every_task_above_the_floor_and_an_inputs_jobs_together():
    from ahrs_service.execution import plan_tasks

    keys = [name for name in "abcdef" for _ in range(13)]  # 6 recordings x 13 estimators
    costs = [0.02 + 0.002 * (i % 13) for i in range(len(keys))]  # 20-44 ms jobs, 2.4 s in all
    tasks = plan_tasks(costs, keys, floor_s=0.5, workers=2)
    assert sorted(i for task in tasks for i in task) == list(range(len(keys)))  # each job once
    sizes = [sum(costs[i] for i in task) for task in tasks]
    # a recording's 0.42 s is one piece, kept whole; 4 shares would leave one under the floor,
    # 3 is not a multiple of the workers: 2 tasks of 3 recordings each
    assert len(tasks) == 2 and min(sizes) >= 0.5, sizes  # a multiple of the workers, all above the floor
    assert max(sizes) - min(sizes) < 0.1, sizes  # even: no worker waits for a long last task
    assert [sorted({keys[i] for i in task}) for task in tasks] == [["a", "b", "c"], ["d", "e", "f"]]
    # an input larger than two shares is cut between its jobs
    tasks = plan_tasks([0.1] * 12, ["a"] * 12, floor_s=0.2, workers=2)
    assert [len(task) for task in tasks] == [2] * 6
    # a large workload: tasks grow to about TASKS_PER_WORKER a worker (up to SHARE_CAP_FLOORS
    # floors), the inputs (2 s each) kept whole, the tasks even
    big = [0.1] * 400
    tasks = plan_tasks(big, [i // 20 for i in range(400)], floor_s=0.5, workers=2)
    assert len(tasks) == 20 and all(len(task) == 20 for task in tasks)
    # inputs of two floors and a bit: kept whole, not cut (each read by one task only)
    tasks = plan_tasks([0.1] * 60, [i // 12 for i in range(60)], floor_s=0.6, workers=2)
    assert all(len({i // 12 for i in task}) * 12 == len(task) for task in tasks), tasks
    # a small floor: one task per job; a floor above the whole: one task
    assert plan_tasks(costs, keys, floor_s=0.0, workers=2) == [[i] for i in range(len(keys))]
    assert plan_tasks(costs, keys, floor_s=10.0, workers=2) == [list(range(len(keys)))]
    # an input's jobs come together whatever order they were given in
    interleaved = [keys[i] for i in range(0, len(keys), 13)] * 13
    assert all(len({interleaved[i] for i in task}) <= 3
               for task in plan_tasks(costs, interleaved, floor_s=0.5, workers=2))
    # nothing known yet: every job alone, so that its duration is measured
    assert plan_tasks([0.1, None, 0.1], floor_s=0.5, workers=2) == [[0], [1], [2]]


def _square_in_task(job: tuple[str, int]) -> tuple[str, int, str]:
    """A job's result and the Dask task it ran in (to count the tasks the cluster ran)."""
    from distributed import get_worker

    name, value = job
    return name, value * value, str(get_worker().get_current_task())


def _ten_ms(job: tuple[str, int]) -> float:
    return 0.1  # the caller's first guess: far above what the job takes


def _tasks_of(got: list[tuple[str, int, str]]) -> dict[str, set[str]]:
    """Each task the jobs ran in → the inputs of its jobs."""
    out: dict[str, set[str]] = {}
    for name, _, task in got:
        out.setdefault(task, set()).add(name)
    return out


def _check_granularity(runner: Runner) -> None:
    """24 jobs on 4 inputs, guessed at 0.1 s each: with a 0.5 s floor an input's 0.6 s is a
    piece kept whole, a task each; a 0 floor makes 24; the measured durations (microseconds)
    then shrink the next map's estimate under the floor: one task."""
    jobs = [(name, i) for name in ("a", "b", "c", "d") for i in range(6)]
    want = [(name, i * i) for name, i in jobs]
    before = runner.tasks_submitted
    grouped = runner.map(_square_in_task, jobs[::-1], cost=_ten_ms, task_floor_s=0.5,
                         place_by=lambda job: job[0], prepare=lambda key: key)
    assert [(n, v) for n, v, _ in grouped] == want[::-1]  # the jobs' order, not the tasks'
    tasks = _tasks_of(grouped)
    assert len(tasks) == 4 and all(len(names) == 1 for names in tasks.values()), tasks
    assert runner.tasks_submitted - before == 4
    single = runner.map(_square_in_task, jobs, cost=_ten_ms, task_floor_s=0.0)
    assert [(n, v) for n, v, _ in single] == want and len(_tasks_of(single)) == 24
    refined = runner.map(_square_in_task, jobs, cost=_ten_ms, task_floor_s=0.5)
    assert [(n, v) for n, v, _ in refined] == want and len(_tasks_of(refined)) == 1
    assert runner.tasks_submitted - before == 4 + 24 + 1


def test_jobs_are_grouped_into_tasks_as_the_floor_says_on_a_local_cluster():
    this = sys.modules[__name__]
    cloudpickle.register_pickle_by_value(this)
    try:
        with open_runner(workers=2) as runner:
            _check_granularity(runner)
    finally:
        cloudpickle.unregister_pickle_by_value(this)


def test_evaluate_in_tasks_of_a_recording_gives_the_serial_results(broad_dir, serial):
    """Two recordings x two estimators guessed at about 30 ms a job: with a 40 ms floor a
    recording's jobs (about 60 ms) stay whole: one task per recording, which loads it;
    results as the serial run's."""
    with open_runner(workers=2, task_floor_s=0.04) as runner:
        parallel = report.evaluate(broad_dir, _columns(), TRIALS, runner=runner)
        assert runner.tasks_submitted == 2
    assert json.dumps(_deterministic(parallel)) == json.dumps(_deterministic(serial))


def test_a_killed_workers_batched_task_is_retried_and_the_result_is_complete(tmp_path):
    """The worker dies inside a task of four jobs: the whole task is rerun elsewhere."""
    this = sys.modules[__name__]
    cloudpickle.register_pickle_by_value(this)
    marker = str(tmp_path / "died")
    try:
        with open_runner(workers=2) as runner:
            pids_before = set(runner.client.run(os.getpid).values())
            got = runner.map(_square_or_die, [(i, marker) for i in range(8)], cost=lambda job: 0.1, task_floor_s=0.3)
            assert runner.tasks_submitted == 2  # 0.8 s in shares of at least 0.3 s
    finally:
        cloudpickle.unregister_pickle_by_value(this)
    assert got == [i * i for i in range(8)]
    assert int(Path(marker).read_text()) in pids_before


@pytest.mark.parametrize("command_name", ["evaluate", "tune"])
@pytest.mark.parametrize("value", ["-1", "nan"])
def test_a_bad_task_floor_is_a_one_line_error(command_name, value, broad_dir, tmp_path, capsys):
    argv = {
        "evaluate": ["evaluate", "--data", str(broad_dir), "--estimators", "madgwick", "--trials", "02_*",
                     "--out", str(tmp_path / "o")],
        "tune": ["tune", "madgwick", "--data", str(broad_dir), "--trials", "02_*", "--budget", "1",
                 "--out", str(tmp_path / "p.json")],
    }[command_name]
    assert cli_main([*argv, "--workers", "2", f"--task-floor-s={value}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"ahrs-service {command_name}: error: --task-floor-s must be a number of seconds >= 0, "
                   f"not {float(value)!r}"]
