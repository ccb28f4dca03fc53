"""``ahrs-service log plot``: a quick look at a flight log without Foxglove.

One figure, one time axis (seconds from the first sample): attitude (and the log's ground
truth where it has one), raw gyro, accelerometer and magnetometer, loop timing, lost samples
and overruns, magnetometer rejections and the reduced form, with the /log health events
marked. matplotlib comes from the ``analysis`` extra.

Speed on long logs: the log is read once (:func:`~ahrs_service.logs.fast_scan.scan_messages`,
which also reads a truncated file up to the damage), decoding only the topics drawn; each
series is then *decimated for drawing only*, to a min/max envelope of ``DRAW_BINS`` bins (the
highest and lowest value of every bin are both drawn, so a one-sample spike stays visible).
The numbers in the title (samples, lost samples, overruns, time rejected) come from the full
arrays. A progress bar (tqdm, from the same extra) appears when reading takes over a second.
"""

from __future__ import annotations

import math
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ahrs_service.core.quaternion import euler_of
from ahrs_service.logs.budget import ReadBudgetExceeded
from ahrs_service.logs.fast_scan import scan_messages
from ahrs_service.logs.fields import BadMessage, decoded, integers, number, obj, scalar, vector, vectors
from ahrs_service.logs.reader import MessageSource
from ahrs_service.logs.schemas import CHANNELS

DRAW_BINS = 2000  # envelope bins per series: a few per pixel column of a wide figure
FORMATS = (".png", ".pdf", ".svg")


@dataclass
class LogSeries:
    """The series of a log that the quick look draws; times in s from the first sample."""

    t0_ns: int = 0
    att_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    att_deg: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # roll, pitch, yaw
    truth_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    truth_deg: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    raw_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    gyr: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # rad/s, body FRD
    acc: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # m/s²
    mag: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # µT
    loop_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    jitter_p99_us: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lateness_p99_us: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lost: np.ndarray = field(default_factory=lambda: np.zeros(0))  # source's lost samples, running total
    missed_ticks: np.ndarray = field(default_factory=lambda: np.zeros(0))  # running totals since start
    overruns: np.ndarray = field(default_factory=lambda: np.zeros(0))
    diag_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    mag_rejected: np.ndarray = field(default_factory=lambda: np.zeros(0))  # 0/1
    reduced: np.ndarray = field(default_factory=lambda: np.zeros(0))  # 0/1
    events: list[tuple[float, int, str]] = field(default_factory=list)  # (t s, foxglove level, text)
    damage: str | None = None
    messages: int = 0


class _Stop(Exception):
    """Reading stops at a message that is not what its schema says (the text says which)."""


def read_series(path: str | Path, progress: bool = True) -> LogSeries:
    """Reads the drawn series of ``path`` (a truncated log: up to the damage, see ``damage``)."""
    att_t, att, tr_t, tr, raw_t, gyr, acc, mag = [], [], [], [], [], [], [], []
    loop_t, jit, late, lost, missed, over = [], [], [], [], [], []
    diag_t, rej, red, events = [], [], [], []
    bar = _progress(path, progress)
    count = [0]

    def on_raw(log_time: int, data: bytes) -> None:
        m = decoded(data)
        row = (vector(m, "gyr", 3), vector(m, "acc", 3), vector(m, "mag", 3, nullable=True))
        raw_t.append(log_time)
        gyr.append(row[0])
        acc.append(row[1])
        mag.append(row[2])
        count[0] += 1
        if bar is not None and count[0] % 8192 == 0:
            bar.update(8192)

    def on_attitude(log_time: int, data: bytes) -> None:
        m = decoded(data)
        euler = tuple(scalar(m, k) for k in ("roll", "pitch", "yaw"))
        d = obj(m, "diagnostics", optional=True)
        att_t.append(log_time)
        att.append(euler)
        if d:
            diag_t.append(log_time)
            rej.append(bool(d.get("mag_disturbed", False)))
            red.append(bool(d.get("reduced", False)))

    def on_raw_block(log_time: int, data: bytes) -> None:  # one FIFO burst: its rows
        m = decoded(data)
        times = integers(m, "t_ns")
        n = len(times)
        rows = (vectors(m, "gyr", n, 3), vectors(m, "acc", n, 3), vectors(m, "mag", n, 3, nullable=True))
        raw_t.extend(times)
        gyr.extend(rows[0])
        acc.extend(rows[1])
        mag.extend(rows[2])
        count[0] += n
        if bar is not None and count[0] % 8192 < n:
            bar.update(8192)

    def block_angles(data: bytes) -> tuple[list[int], list[tuple[float, float, float]]]:
        """Row times and ZYX angles of an /attitude_block or /attitude/truth_block message."""
        m = decoded(data)
        times = integers(m, "t_ns")
        return times, [euler_of(q) for q in vectors(m, "q", len(times), 4)]

    def on_attitude_block(log_time: int, data: bytes) -> None:
        # the rows' attitude; the block log's /attitude (at the /tf rate) carries the diagnostics
        times, angles = block_angles(data)
        att_t.extend(times)
        att.extend(angles)

    def on_truth_block(log_time: int, data: bytes) -> None:
        times, angles = block_angles(data)
        tr_t.extend(times)
        tr.extend(angles)

    def on_truth(log_time: int, data: bytes) -> None:
        m = decoded(data)
        euler = tuple(number(m.get(k), f"$.{k}") for k in ("roll", "pitch", "yaw"))
        tr_t.append(log_time)
        tr.append(euler)

    def on_loop(log_time: int, data: bytes) -> None:
        m = decoded(data)
        values = [number(m.get(k), f"$.{k}") for k in ("period_jitter_p99_us", "lateness_p99_us", "missed_ticks", "overruns")]
        source_lost = obj(m, "source", optional=True).get("lost")
        total = number(source_lost.get("total"), "$.source.lost.total") if isinstance(source_lost, dict) else math.nan
        loop_t.append(log_time)
        jit.append(values[0])
        late.append(values[1])
        missed.append(values[2])
        lost.append(total)
        over.append(values[3])

    def on_log(log_time: int, data: bytes) -> None:
        m = decoded(data)
        level = m.get("level", 0)
        if not isinstance(level, int) or isinstance(level, bool):
            raise BadMessage("$.level", "expected an integer")
        events.append((log_time, level, str(m.get("message", ""))))

    handlers = {"/imu/raw": on_raw, "/attitude": on_attitude, "/attitude/truth": on_truth, "/loop": on_loop,
                "/log": on_log, "/imu/raw_block": on_raw_block, "/attitude_block": on_attitude_block,
                "/attitude/truth_block": on_truth_block}
    topics = {handler: topic for topic, handler in handlers.items()}

    def checked(handler: Any) -> Any:
        def run(log_time: int, data: bytes) -> None:
            try:
                handler(log_time, data)
            except BadMessage as exc:  # a message its schema does not describe: plotted up to it
                raise _Stop(f"{topics[handler]} message at log time {log_time} ns is not a valid "
                            f"{CHANNELS[topics[handler]][0]}: {exc}") from None
        return run

    handlers = {topic: checked(handler) for topic, handler in handlers.items()}
    damage: str | None = None
    try:
        try:
            scan = scan_messages(path, handlers)
            damage, n = scan.damage, scan.messages
        except ReadBudgetExceeded:
            raise  # refused before anything was read: the other way would refuse it too
        except ValueError:  # a chunk compression the fast scan does not read: the mcap library's way
            source = MessageSource(path)
            n = 0
            for topic, log_time, _, data in source:
                handler = handlers.get(topic)
                if handler is not None:
                    handler(log_time, data)
                    n += 1
            damage = None if source.damage is None else str(source.damage)
    except _Stop as stop:
        damage, n = str(stop), len(raw_t) + len(att_t) + len(tr_t) + len(loop_t) + len(events)
    if bar is not None:
        bar.close()
    times = [t[0] for t in (raw_t, att_t, loop_t) if t]
    t0 = min(times) if times else 0

    def sec(t: list[int]) -> np.ndarray:
        return (np.asarray(t, dtype=np.int64) - t0) * 1e-9

    def arr(v: list, cols: int = 3) -> np.ndarray:
        return np.asarray(v, dtype=float).reshape(-1, cols)

    return LogSeries(
        t0_ns=t0, att_t=sec(att_t), att_deg=np.degrees(arr(att)), truth_t=sec(tr_t), truth_deg=np.degrees(arr(tr)),
        raw_t=sec(raw_t), gyr=arr(gyr), acc=arr(acc), mag=arr(mag),
        loop_t=sec(loop_t), jitter_p99_us=np.asarray(jit), lateness_p99_us=np.asarray(late),
        lost=np.asarray(lost), missed_ticks=np.asarray(missed), overruns=np.asarray(over),
        diag_t=sec(diag_t), mag_rejected=np.asarray(rej, dtype=float), reduced=np.asarray(red, dtype=float),
        events=[((t - t0) * 1e-9, level, text) for t, level, text in events],
        damage=damage, messages=n,
    )


def _progress(path: str | Path, wanted: bool) -> Any:
    if not wanted:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    # samples from the file size: about 190 compressed bytes per logged sample (/imu/raw,
    # /attitude, truth, /tf share) — a guess for the bar only; it stops where the file does
    total = max(1, Path(path).stat().st_size // 190)
    return tqdm(total=total, unit="sample", unit_scale=True, delay=1.0, leave=False, desc="reading log")


def envelope(t: np.ndarray, y: np.ndarray, bins: int = DRAW_BINS) -> tuple[np.ndarray, np.ndarray]:
    """(t, y) decimated for drawing: each of ``bins`` equal-count bins becomes two points, its
    minimum and its maximum (NaN-aware), at the bin's first time. Short series come back as they are."""
    n = len(y)
    if n <= 2 * bins:
        return t, y
    k = n // bins
    m = bins * k
    blocks = y[:m].reshape(bins, k)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN bins stay NaN (a gap)
        lo, hi = np.nanmin(blocks, axis=1), np.nanmax(blocks, axis=1)
    tt = np.repeat(t[:m:k], 2)
    yy = np.empty(2 * bins)
    yy[0::2], yy[1::2] = lo, hi
    return np.concatenate([tt, t[m:]]), np.concatenate([yy, y[m:]])


def summary(s: LogSeries) -> str:
    """One line of full-resolution statistics (not the decimated arrays)."""
    dur = float(s.raw_t[-1]) if len(s.raw_t) else 0.0
    lost = int(np.nanmax(s.lost)) if np.isfinite(s.lost).any() else 0  # running totals
    overruns = int(np.nanmax(s.overruns)) if np.isfinite(s.overruns).any() else 0
    rejected = 100.0 * float(np.mean(s.mag_rejected)) if len(s.mag_rejected) else 0.0
    return (f"{len(s.raw_t)} samples, {dur:.1f} s; lost samples {lost}, overruns {overruns}; "
            f"magnetometer rejected {rejected:.1f}% of the time")


def build_figure(s: LogSeries, title: str = "") -> Any:
    """The quick-look figure (matplotlib ``Figure``; needs the analysis extra)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 13), layout="constrained")
    axes = fig.subplots(7, 1, sharex=True, height_ratios=[1.4, 1, 1, 1, 0.8, 0.7, 0.6])
    colors = ("tab:red", "tab:green", "tab:blue")

    def lines(ax: Any, t: np.ndarray, ys: np.ndarray, labels: tuple[str, ...], **kw: Any) -> None:
        for j, label in enumerate(labels):
            ax.plot(*envelope(t, ys[:, j]), color=colors[j % 3], lw=0.8, label=label, **kw)

    ax = axes[0]
    lines(ax, s.att_t, s.att_deg, ("roll", "pitch", "yaw"))
    if len(s.truth_t):
        lines(ax, s.truth_t, s.truth_deg, ("truth roll", "truth pitch", "truth yaw"), ls="--", alpha=0.7)
    ax.set_ylabel("attitude, deg")
    for ax, data, label in ((axes[1], s.gyr, "gyro, rad/s"), (axes[2], s.acc, "acc, m/s²"), (axes[3], s.mag, "mag, µT")):
        lines(ax, s.raw_t, data, ("x", "y", "z"))
        ax.set_ylabel(label)
    ax = axes[4]
    ax.plot(*envelope(s.loop_t, s.jitter_p99_us), lw=0.9, label="period jitter p99")
    ax.plot(*envelope(s.loop_t, s.lateness_p99_us), lw=0.9, label="lateness p99")
    ax.set_ylabel("loop, µs")
    ax = axes[5]
    ax.step(*envelope(s.loop_t, s.lost), where="post", lw=0.9, label="lost samples (source)")
    ax.step(*envelope(s.loop_t, s.missed_ticks), where="post", lw=0.9, label="missed ticks")
    ax.step(*envelope(s.loop_t, s.overruns), where="post", lw=0.9, label="overruns")
    ax.set_ylabel("total since start")
    ax = axes[6]
    ax.step(*envelope(s.diag_t, s.mag_rejected), where="post", lw=0.9, label="mag rejected")
    ax.step(*envelope(s.diag_t, s.reduced * 0.9), where="post", lw=0.9, label="reduced form (0.9)")
    warn = [t for t, level, _ in s.events if level >= 3]
    if warn:
        ax.plot(warn, np.full(len(warn), 1.1), "v", color="tab:orange", ms=5, label="/log warning+")
    ax.set_ylim(-0.1, 1.25)
    ax.set_ylabel("flags")
    ax.set_xlabel("time since the first sample, s")
    for ax in axes:
        if ax.lines:
            ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=7)  # beside, not over, the data
        ax.grid(True, lw=0.3)
    head = title + ("" if s.damage is None else "  [TRUNCATED: plotted up to the damage]")
    fig.suptitle(f"{head}\n{summary(s)}", fontsize=10)
    return fig


def plot_log(path: str | Path, out: str | Path, progress: bool = True) -> tuple[LogSeries, Any]:
    """Reads ``path`` and writes its quick-look figure to ``out`` (.png, .pdf or .svg)."""
    series = read_series(path, progress)
    fig = build_figure(series, Path(path).name)
    fig.savefig(out, dpi=110)
    return series, fig


def cmd_plot(args: Any) -> int:
    """``ahrs-service log plot LOG --out FILE``: exit 0 (also for a truncated log, said on stderr)."""
    out = Path(args.out)
    if out.suffix.lower() not in FORMATS:
        print(f"ahrs-service: log plot: --out {out}: expected a .png, .pdf or .svg file", file=sys.stderr)
        return 2
    import matplotlib  # noqa: F401  (missing: the command line names the 'analysis' extra)
    if not Path(args.log).is_file():
        what = "is a directory, not a file" if Path(args.log).is_dir() else "no such file"
        print(f"ahrs-service: log plot: {args.log}: {what}", file=sys.stderr)
        return 2
    try:
        series = read_series(args.log)
        if series.messages == 0:
            why = "" if series.damage is None else f" ({series.damage})"
            print(f"ahrs-service: log plot: {args.log}: no readable messages{why}", file=sys.stderr)
            return 2
        build_figure(series, Path(args.log).name).savefig(out, dpi=110)
    except OSError as exc:
        print(f"ahrs-service: log plot: {exc}", file=sys.stderr)
        return 2
    if series.damage is not None:
        print(f"ahrs-service: log plot: {args.log} is damaged ({series.damage}); plotted up to the damage",
              file=sys.stderr)
    print(f"wrote {out}: {summary(series)}")
    return 0
