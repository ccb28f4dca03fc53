"""Careless and hostile command lines: one line naming what is wrong, exit status 2, no
traceback, and no output file left behind (issue 14, items 3-4, re-probed)."""

from __future__ import annotations

import numpy as np
import pytest

from ahrs_service.cli import main
from ahrs_service.logs.writer import FlightLogWriter


@pytest.fixture(scope="module")
def log_path(tmp_path_factory):
    folder = tmp_path_factory.mktemp("log")
    w = FlightLogWriter(folder)
    w.write_config(0, {"estimator": {"name": "madgwick", "params": {"beta": 0.1}}})
    for i in range(50):
        row = np.zeros(10)
        row[5], row[9] = -9.81, 0.005
        w.write_raw(1_000_000 * (i + 1), row, 3)
        w.write_attitude(1_000_000 * (i + 1), [1.0, 0.0, 0.0, 0.0], "madgwick")
    w.close()
    return w.files[0]


def _run(capsys, argv):
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    return rc, err


@pytest.mark.parametrize(
    "argv, expected",
    [
        (["replay", "{log}", "--estimator", "nope"], "ahrs-service replay: error: unknown estimator 'nope'"),
        (["replay", "{log}", "--param", "beta=nan"], "ahrs-service replay: error: parameter 'beta' of estimator 'madgwick' must be finite"),
        (["replay", "{log}", "--param", "nope=1"], "ahrs-service replay: error: unknown parameter(s) nope"),
        (["replay", "{log}", "--out", "{tmp}/missing/out.mcap"], "{tmp}/missing/out.mcap: its folder {tmp}/missing does not exist"),
        (["replay", "{log}", "--offline", "--offline-blend", "-1"],
         "ahrs-service replay: error: blend_time_s (--offline-blend) must be a positive number of seconds, got -1.0"),
        (["replay", "{log}", "{log}", "--out", "{tmp}/fleet", "--offline", "--offline-blend", "0"],
         "ahrs-service replay: error: blend_time_s (--offline-blend) must be a positive number of seconds, got 0.0"),
        (["log", "recover", "{log}", "{tmp}/missing/out.mcap"], "{tmp}/missing/out.mcap: its folder {tmp}/missing does not exist"),
        (["log", "recover", "{text}"], "{text}: not an MCAP file (bad magic): nothing to recover"),
        (["log", "import-broad", "{text}", "{tmp}/out.mcap"], "ahrs-service: {text}: not a readable HDF5 recording"),
        (["log", "plot", "{tmp}", "--out", "{tmp}/x.png"], "ahrs-service: log plot: {tmp}: is a directory, not a file"),
    ],
)
def test_one_line_naming_the_problem_and_nothing_written(tmp_path, capsys, log_path, argv, expected):
    text = tmp_path / "notes.txt"
    text.write_text("not a log\n")
    fill = {"log": str(log_path), "tmp": str(tmp_path), "text": str(text)}
    rc, err = _run(capsys, [a.format(**fill) for a in argv])
    assert rc == 2 and "\n" not in err and "Traceback" not in err, err
    assert expected.format(**fill) in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]  # no empty output left


def test_no_writable_numba_cache_is_one_line_not_a_traceback():
    """Issue 14 re-probe: as a user who cannot write __pycache__ beside the package (and without
    NUMBA_CACHE_DIR), every command, `config --check` included, ended in numba's RuntimeError
    traceback ("cannot cache function 'quat_mul': no locator available") at import. Here numba
    is left with no cache locator at all, in a fresh interpreter (the kernels are decorated on
    import)."""
    import subprocess
    import sys

    code = ("import sys\nimport numba.core.caching as c\nc.CacheImpl._locator_classes = []\n"
            "from ahrs_service.cli import main\nsys.exit(main(['config', '--print-default']))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr.strip()
    assert "Traceback" not in err and "\n" not in err
    assert err.startswith("ahrs-service: cannot cache the estimator kernels") and "NUMBA_CACHE_DIR" in err


@pytest.mark.parametrize("duration", ["nan", "inf", "1e308", "-1", "0"])
def test_run_duration_that_is_no_time_span_is_refused_before_anything_starts(tmp_path, capsys, duration):
    """Issue 14 re-probe: `run --duration inf` (or 1e308) ended in an OverflowError traceback
    (exit 1), `nan` started the service, wrote a log and then failed, 0 and -1 ran for no time
    and exited 0."""
    with pytest.raises(SystemExit) as exc:
        main(["run", "--log-dir", str(tmp_path / "logs"), "--duration", duration])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"ahrs-service run: error: argument --duration: '{duration}': accepted: a number of seconds above 0")
    assert not any("Traceback" in line for line in err)
    assert not (tmp_path / "logs").exists()  # nothing started


def test_run_log_dir_empty_is_refused_not_ignored(tmp_path, capsys, monkeypatch):
    """`run --log-dir ""` was ignored (the log went to log.directory); the override is now
    checked as log.directory is."""
    monkeypatch.chdir(tmp_path)
    rc, err = _run(capsys, ["run", "--log-dir", "", "--duration", "0.1"])
    assert rc == 2 and err == "ahrs-service: configuration error: log.directory: '' is empty; accepted: a folder path (e.g. \"flight-logs\")"
    assert not (tmp_path / "flight-logs").exists()


def test_calibrate_on_a_directory_says_it_is_a_directory(tmp_path, capsys):
    """`ahrs-service calibrate gyro /tmp` said "/tmp: no such file" (it exists)."""
    assert main(["calibrate", "gyro", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: {tmp_path}: is a directory, not a file"


def test_run_of_a_recorded_log_without_samples_says_so(tmp_path, capsys):
    """Issue 14 re-probe: source.type = "recorded" on a log cut after its first bytes started,
    stopped at once and exited 0 ("samples 0"), not saying that there was nothing to play."""
    empty = tmp_path / "cut.mcap"
    empty.write_bytes(b"\x89MCAP0\r\n\x01\x02\x03")
    cfg = tmp_path / "ahrs.toml"
    cfg.write_text(f'[source]\ntype = "recorded"\nrecorded_path = "{empty}"\n'
                   '[mavlink]\nendpoints = ["udpout:127.0.0.1:15599"]\n')
    rc, err = _run(capsys, ["run", "-c", str(cfg), "--log-dir", str(tmp_path / "logs"), "--duration", "1"])
    assert rc == 1
    assert err.startswith(f"ahrs-service: cannot start: recorded log {empty}: no samples to play (damaged at byte")
    assert "\n" not in err and "Traceback" not in err
    assert not list(tmp_path.glob("logs/*.mcap"))  # no flight log opened for a run that never started


def test_log_recover_of_a_log_without_one_complete_message_writes_nothing(tmp_path, capsys, log_path):
    """Issue 14 re-probe: a log cut 40 bytes in gave "recovered 0 messages into
    cut.recovered.mcap", exit 0, and left that empty file."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log_path.read_bytes()[:40])
    rc, err = _run(capsys, ["log", "recover", str(cut)])
    assert rc == 2
    assert err.startswith(f"ahrs-service log: error: {cut}: no complete message (damaged at byte") and err.endswith(": nothing to recover")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.mcap"]


@pytest.mark.parametrize(
    "argv, expected",
    [
        (["replay", "{log}", "--param", "beta=1e300"],
         "ahrs-service replay: error: --param beta = 1e+300: must be within 0 … 100000 (1e+06 × its default 0.1)"),
        (["replay", "{log}", "--param", "beta=2e5"], "ahrs-service replay: error: --param beta = 200000.0: must be within 0 …"),
        (["replay", "{log}", "--estimator", "mahony_direct", "--param", "kp=1e300"], "error: --param kp = 1e+300: must be within"),
        (["replay", "{log}", "{log}", "--out", "{tmp}/fleet", "--estimator", "madgwick", "--param", "beta=1e300"],
         "ahrs-service replay: error: --param beta = 1e+300: must be within 0 …"),
        (["evaluate", "--data", "{broad}", "--estimators", "madgwick", "--param", "madgwick.beta=1e300", "--out", "{tmp}/ev"],
         "ahrs-service evaluate: error: --param madgwick.beta = 1e+300: must be within 0 … 100000"),
        (["tune", "madgwick", "--data", "{broad}", "--space", "beta=0.01:1e300", "--out", "{tmp}/t.json"],
         "ahrs-service tune: error: search range of madgwick.beta = 1e+300: must be within 0 … 100000"),
    ],
)
def test_param_values_get_the_configuration_files_ranges(tmp_path, capsys, log_path, broad_dir, argv, expected):
    """Issue 14 re-probe: `replay --param beta=1e300` (and evaluate's --param, tune's --space)
    were accepted, though `estimator.params` in the configuration file refuses the same value
    (config.check_estimator_params: one check, the file's ranges)."""
    fill = {"log": str(log_path), "tmp": str(tmp_path), "broad": str(broad_dir)}
    rc, err = _run(capsys, [a.format(**fill) for a in argv])
    assert rc == 2 and "\n" not in err and "Traceback" not in err, err
    assert expected.format(**fill) in err
    assert list(tmp_path.iterdir()) == []  # refused before anything was written


def test_param_value_refused_in_the_file_is_refused_on_the_command_line_by_the_same_words(tmp_path, capsys, log_path):
    """The file and the command line share the check: the same range in both messages."""
    from ahrs_service import config

    with pytest.raises(config.ConfigError) as exc:
        config.validate({"estimator": {"name": "madgwick", "params": {"beta": 1e300}}})
    in_file = str(exc.value).partition(": ")[2]
    rc, err = _run(capsys, ["replay", str(log_path), "--param", "beta=1e300"])
    assert rc == 2 and err.endswith(in_file), (err, in_file)
    # a value inside the range is replayed
    assert main(["replay", str(log_path), "--param", "beta=0.3"]) == 0



def _special(tmp_path, kind):
    """A FIFO without a writer, or a symbolic link in a loop, at tmp_path/bad."""
    import os

    bad = tmp_path / "bad"
    if kind == "fifo":
        os.mkfifo(bad)
    else:
        os.symlink(tmp_path / "other", bad)
        os.symlink(bad, tmp_path / "other")
    return bad


SPECIAL_TEXT = {"fifo": "not a regular file (a FIFO)", "loop": "Too many levels of symbolic links"}


@pytest.mark.timeout(60)  # before the fix a FIFO blocked open() for good
@pytest.mark.parametrize("kind", ["fifo", "loop"])
@pytest.mark.parametrize("argv", [
    ["log", "info", "{bad}"],
    ["log", "recover", "{bad}", "{tmp}/out.mcap"],
    ["replay", "{bad}", "--estimator", "madgwick"],
    ["config", "--check", "{bad}"],
    ["run", "-c", "{bad}", "--no-log", "--duration", "0.1"],
])
def test_an_input_path_that_is_a_fifo_or_a_symlink_loop_is_one_line(tmp_path, capsys, kind, argv):
    """Issue 14 re-probe (h14): ``log info``, ``log recover``, ``replay``, ``config --check``
    and ``run -c`` of a FIFO hung for good in open() (and a reload of one would hang the
    loop); ``log recover`` of a symbolic-link loop ended in a RuntimeError traceback."""
    bad = _special(tmp_path, kind)
    rc, err = _run(capsys, [a.format(tmp=tmp_path, bad=bad) for a in argv])
    assert rc == 2 and "\n" not in err and "Traceback" not in err, err
    assert str(bad) in err and SPECIAL_TEXT[kind] in err, err
    assert not (tmp_path / "out.mcap").exists()


@pytest.mark.parametrize("argv", [["log", "recover", "{log}", "{bad}"], ["replay", "{log}", "--out", "{bad}"]])
def test_an_output_path_that_is_a_symlink_loop_is_one_line(tmp_path, capsys, log_path, argv):
    """``log recover LOG LOOP`` and ``replay LOG --out LOOP``: a RuntimeError traceback from
    Path.resolve() (the check that the output is not the input). (An output FIFO blocks
    until a reader comes, as for any Unix tool.)"""
    bad = _special(tmp_path, "loop")
    rc, err = _run(capsys, [a.format(log=log_path, bad=bad) for a in argv])
    assert rc == 2 and "\n" not in err and "Traceback" not in err, err
    assert str(bad) in err and SPECIAL_TEXT["loop"] in err, err


@pytest.mark.timeout(120)
@pytest.mark.parametrize("sig, rc, name", [("SIGINT", 130, "SIGINT"), ("SIGTERM", 143, "SIGTERM")])
def test_ctrl_c_or_sigterm_during_a_long_command_is_one_line(tmp_path, sig, rc, name):
    """Issue 14 re-probe (h14): Ctrl-C during ``compile``, ``replay``, ``log recover``,
    ``log plot``, ``evaluate`` ended in a KeyboardInterrupt traceback of 17–215 lines (SIGTERM
    killed them silently, a half-written ``recover`` output left). ``compile`` into an empty
    numba cache runs for tens of seconds: the signal comes while it works."""
    import os
    import signal
    import subprocess
    import sys
    import time

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    proc = subprocess.Popen([sys.executable, "-m", "ahrs_service.cli", "compile", "ekf"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(3.0)
    assert proc.poll() is None, "compile ended before the signal: the test proves nothing"
    proc.send_signal(getattr(signal, sig))
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == rc, err
    assert "Traceback" not in err and err.strip().splitlines()[-1] == (
        f"ahrs-service: interrupted ({name}) before the command finished"), err


@pytest.mark.parametrize("sig, rc, name", [("SIGINT", 130, "SIGINT"), ("SIGTERM", 143, "SIGTERM")])
def test_a_signal_swallowed_inside_a_command_still_ends_it_as_interrupted(capsys, monkeypatch, sig, rc, name):
    """A CI run saw ``compile`` exit 0 after a Ctrl-C: code under the command (a library's
    ``except BaseException``) can swallow the KeyboardInterrupt and let the command finish.
    The signal is noted when it arrives: the command still ends with the one line and 130/143."""
    import os
    import signal

    from ahrs_service import service_cli

    def swallowing(args):
        try:
            os.kill(os.getpid(), getattr(signal, sig))
            for _ in range(1000):  # the handler runs at the next bytecode; the loop gives it room
                pass
        except BaseException:  # noqa: BLE001 - what the command's library does
            pass
        return 0

    # Python's own Ctrl-C handler, as a command line starts with (whatever an earlier test of
    # this process left installed)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        monkeypatch.setattr(service_cli, "cmd_foxglove_layout", swallowing)
        assert _run(capsys, ["foxglove-layout"]) == (
            rc, f"ahrs-service: interrupted ({name}) before the command finished")
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # given back after the command
        monkeypatch.undo()
        assert _run(capsys, ["foxglove-layout"]) == (0, "")  # the next command starts with no signal noted
    finally:
        signal.signal(signal.SIGINT, before)


def test_an_interrupted_recover_leaves_no_half_written_output(tmp_path, capsys, log_path, monkeypatch):
    """Ctrl-C (or SIGTERM) in the middle of ``log recover`` left the output cut short: the
    file is removed and the command says it was interrupted."""
    from mcap.writer import Writer

    calls = {"n": 0}
    add = Writer.add_message

    def interrupted(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 20:
            raise KeyboardInterrupt
        return add(self, *args, **kwargs)

    monkeypatch.setattr(Writer, "add_message", interrupted)
    out = tmp_path / "out.mcap"
    rc, err = _run(capsys, ["log", "recover", str(log_path), str(out)])
    assert rc == 130 and err == "ahrs-service: interrupted (SIGINT) before the command finished", err
    assert calls["n"] == 20 and not out.exists()


@pytest.mark.timeout(120)  # before the fix the FIFO blocked read_text() for good
def test_evaluate_preset_that_is_a_fifo_is_one_line(tmp_path, capsys, broad_dir):
    """Issue 14 re-probe (h14): ``evaluate --preset FIFO`` hung (the file read to find its
    estimator); now refused like any file that is no preset."""
    fifo = _special(tmp_path, "fifo")
    trial = sorted(broad_dir.glob("*.hdf5"))[0].stem
    rc, err = _run(capsys, ["evaluate", "--data", str(broad_dir), "--estimators", "madgwick", "--preset",
                            str(fifo), "--trials", trial, "--quiet", "--workers", "1", "--out", str(tmp_path / "ev")])
    assert rc == 2 and "\n" not in err and "Traceback" not in err, err
    assert f"--preset {str(fifo)!r}: not a preset file" in err, err
    assert not (tmp_path / "ev").exists()


@pytest.mark.parametrize("spec", ["", " , "])
def test_evaluate_with_no_estimator_named_is_one_line_not_every_estimator(tmp_path, capsys, spec):
    """``evaluate --estimators ""`` (an empty shell variable) ran every estimator: a long run
    nobody asked for. Only ``all`` (or no option) means every estimator."""
    rc, err = _run(capsys, ["evaluate", "--estimators", spec, "--quiet", "--workers", "1",
                            "--out", str(tmp_path / "ev")])
    assert rc == 2 and "\n" not in err and "Traceback" not in err, err
    assert f"--estimators {spec.strip()!r}: no estimator named" in err, err
    assert not (tmp_path / "ev").exists()


def test_an_interrupt_inside_a_native_callback_is_raised_a_moment_later(monkeypatch):
    """Ctrl-C while numba compiles can land in llvmlite's object-cache hook, Python code that C
    calls through ctypes: an exception raised there cannot leave it, and Python printed it as
    "Exception ignored" with its traceback. The handler notes the signal and raises it again
    from SIGALRM a moment later, back in ordinary code."""
    import signal
    import sys

    from ahrs_service import cli

    namespace: dict = {"sys": sys}
    hook = "def _raw_object_cache_notify(handler, signum):\n    handler(signum, sys._getframe())\n"
    exec(compile(hook, "/site-packages/llvmlite/binding/executionengine.py", "exec"), namespace)
    monkeypatch.setattr(cli, "_received", None)
    previous = signal.signal(signal.SIGALRM, signal.SIG_IGN)
    try:
        namespace["_raw_object_cache_notify"](cli._interrupt, signal.SIGINT)  # does not raise
        assert cli._received == "SIGINT"
        assert 0.0 < signal.getitimer(signal.ITIMER_REAL)[0] <= cli._CALLBACK_RETRY_S
        with pytest.raises(KeyboardInterrupt):
            cli._interrupt(signal.SIGALRM, sys._getframe())  # the deferred delivery
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, previous)
