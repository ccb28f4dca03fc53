"""Re-running estimators over a recorded flight, comparing, and writing the result as a log.

:func:`replay` feeds the recorded sample rows — exactly the values the service fed its
estimator — through an estimator, applying each recorded live parameter change at the sample
it took effect. With the recorded estimator and parameters it reproduces the recorded
attitudes bit for bit (same compiled step, same inputs, same order).

Parameter-change semantics: a /params message with ``sample_index`` k means the samples
0 … k−1 were processed with the old value and k onwards with the new one.

:func:`replay_offline` gives the best attitude after the fact instead (non-causal): the same
estimator run forward and backward over the log and fused (``estimators.offline``); the
backward pass applies the same parameter in force at each sample.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ahrs_service import estimators
from ahrs_service.core.divergence import DivergenceEvent, scan
from ahrs_service.estimators import SAMPLE_ROW, offline
from ahrs_service.evaluation.metrics import error_angles, rmse
from ahrs_service.logs.budget import DEFAULT_READ_BUDGET_BYTES
from ahrs_service.logs.mcap_file import McapLogFile
from ahrs_service.logs.reader import MessageSource, RecordedLog
from ahrs_service.logs.redaction import redact_config
from ahrs_service.logs.schemas import attitude_block_message, attitude_message, jsonable, log_message, tf_message

#: where a replayed log keeps the estimate that was recorded
_ORIGINAL = {"/attitude": "/attitude/original", "/attitude_block": "/attitude/original_block"}


def _effective_start(log: RecordedLog, name: str, params: Mapping[str, Any] | None) -> dict[str, Any]:
    """The parameters the replay starts from: the recorded ones (recorded estimator only) with
    ``params`` over them, each override checked as the configuration file's ``estimator.params``
    are (``config.check_estimator_params``: a finite 1e300 would overflow inside the filter)."""
    from ahrs_service.estimators.settings import check_estimator_params

    if params:
        check_estimator_params(name, dict(params), label="parameter {}")
    start: dict[str, Any] = dict(log.params) if name == log.estimator else {}
    start.update(params or {})
    return start


def _create(log: RecordedLog, name: str, params: Mapping[str, Any] | None) -> Any:
    """``name`` at the log's recorded start parameters (its own estimator only) with ``params``
    over them. A name or value the log recorded that the estimator refuses (a foreign, edited
    or damaged /config) is said to be the log's, so it is not taken for the caller's own.
    ``estimators.get`` rather than ``create``: a recorded key ``preset`` is a parameter name
    like any other (refused), never a file to open."""
    start = _effective_start(log, name, params)
    try:
        return estimators.get(name)(**start)
    except ValueError as exc:
        if name == log.estimator and name not in estimators.names():
            raise ValueError(f"{log.path}: the log's estimator {name!r} is not one of this version's; "
                             f"give --estimator NAME") from None
        estimators.get(name)(**dict(params or {}))  # the caller's own values: their error stands
        raise ValueError(f"{log.path}: the parameters recorded in its /config are refused: {exc}") from None


def replay(
    log: RecordedLog,
    estimator: str | None = None,
    params: Mapping[str, Any] | None = None,
    follow_param_changes: bool = True,
    use_recorded_state: bool = True,
) -> np.ndarray:
    """(N, 4) q_earth←body [w, x, y, z] (NED) of ``estimator`` run over the log's rows.

    estimator: a name from ``ahrs_service.estimators.names()``; None replays the recorded one.
    params: overrides. With the recorded estimator they start from its recorded parameters;
        a name given here is pinned, i.e. recorded live changes of it are not applied.
    follow_param_changes: apply the recorded /params changes (recorded estimator only) at
        their sample index.
    use_recorded_state: a file started by rotation carries the estimator's state
        (/estimator/state); the recorded estimator starts from it, so the replay continues
        exactly where the previous file ended. Otherwise the estimator starts fresh.
    """
    name = estimator or log.estimator
    if not name:
        lost = f": its /config was lost to the damage ({log.damage})" if log.damage is not None else " (no /config or /attitude)"
        raise ValueError(f"the log names no estimator{lost}: pass one")
    est = _create(log, name, params)
    snap = log.initial_state
    if use_recorded_state and snap is not None and snap["estimator"] == name:
        if snap["state"].shape != est.state.shape:
            raise ValueError(f"{log.path}: its /estimator/state has {snap['state'].shape[0]} values, "
                             f"{name} needs {est.state.shape[0]}")
        est.state[:] = snap["state"]
    cuts = _param_cuts(log, name, est, params, follow_param_changes)
    return _run_with_cuts(est, log.rows, cuts, log.path)


def replay_offline(
    log: RecordedLog,
    estimator: str | None = None,
    params: Mapping[str, Any] | None = None,
    follow_param_changes: bool = True,
    use_recorded_state: bool = True,
    blend_time_s: float = offline.DEFAULT_BLEND_TIME_S,
) -> offline.OfflineResult:
    """Offline (forward-backward) estimate over the log's rows: ``.q`` is (N, 4) q_earth←body (NED).

    The forward pass is exactly :func:`replay` with the same arguments. The backward pass is a
    fresh instance over the reversed rows (``offline.reverse_rows``) that applies, at each
    sample, the parameter values the forward pass used there; it starts from nothing (a
    recorded state snapshot belongs to the file's start). ``blend_time_s``: time constant (s)
    of the fusion weights. Heading is aligned onto the forward pass's when the estimator or the
    log gives none (see ``estimators.offline``).
    """
    name = estimator or log.estimator
    q_forward = replay(log, name, params, follow_param_changes, use_recorded_state)
    rows = log.rows
    est = _create(log, name, params)
    cuts = _param_cuts(log, name, est, params, follow_param_changes)
    n = rows.shape[0]
    # going backwards, a change made at sample k is undone when the pass steps from k to k − 1,
    # i.e. at backward row n − k; the pass starts with every change applied
    start = est.get_params()
    undo: list[tuple[int, str, Any]] = []
    for k, pname, value in cuts:
        undo.append((n - k, pname, start[pname]))
        start[pname] = value
    est.set_params(**start)
    # in backward row order; changes made at one sample are undone last-first (stable sort)
    undo_in_order = sorted(reversed(undo), key=lambda c: c[0])
    q_backward = _run_with_cuts(est, offline.reverse_rows(rows), undo_in_order, log.path)[::-1]
    observed = offline.heading_observed(name, rows)
    return offline.combine(q_forward, q_backward, rows, blend_time_s=blend_time_s, align=not observed)


def _param_cuts(
    log: RecordedLog, name: str, est: Any, params: Mapping[str, Any] | None, follow: bool
) -> list[tuple[int, str, Any]]:
    """The recorded live changes to apply: (local sample index, name, new value), in order."""
    cuts: list[tuple[int, str, Any]] = []
    if follow and name == log.estimator:
        n = log.rows.shape[0]
        known = set(est.param_names())
        pinned = set(params or {})
        for change in log.param_changes:
            k = log.local_index(change["sample_index"])
            if change["name"] in known and change["name"] not in pinned and 0 <= k <= n:
                cuts.append((k, change["name"], change["new"]))
        cuts.sort(key=lambda c: c[0])
    return cuts


def _run_with_cuts(est: Any, rows: np.ndarray, cuts: list[tuple[int, str, Any]], path: Path) -> np.ndarray:
    """Runs ``est`` over ``rows``, setting each cut's parameter before the row it names. A
    recorded value the estimator refuses is named as the log's (``path``)."""
    n = rows.shape[0]
    out = np.empty((n, 4))
    start = 0
    for k, pname, value in cuts + [(n, "", None)]:
        if k > start:
            out[start:k] = est.run_rows(rows[start:k])
            start = k
        if pname:
            try:
                est.set_params(**{pname: value})
            except ValueError as exc:
                raise ValueError(f"{path}: its /params change of {pname} to {value!r} (before row {k}) "
                                 f"is refused: {exc}") from None
    return out


def divergence_events(log: RecordedLog, q: np.ndarray) -> tuple[str, list[DivergenceEvent]]:
    """The divergence monitor (``core/divergence.py``) run over the log's rows and the estimate
    ``q`` (N, 4), as the running service runs it: its summary line and every change of its flag
    (event times in s of the log's sample clock). The field goes in where the rows have one."""
    rows = log.rows
    monitor, events = scan(log.t_ns * 1e-9, rows[:, SAMPLE_ROW.slices.acc], q, rows[:, SAMPLE_ROW.slices.mag])
    return monitor.summary(), events


def _divergence(log: RecordedLog, q: np.ndarray) -> dict[str, Any]:
    summary, events = divergence_events(log, q)
    t0 = float(log.t_ns[0]) * 1e-9 if len(log) else 0.0
    return {"summary": summary, "flags": sum(e.diverged for e in events),
            "events": [{"t_s": round(e.t_s - t0, 3), "diverged": e.diverged} for e in events]}


def _rms_deg(values: np.ndarray, mask: np.ndarray) -> float | None:
    r = rmse(values, mask)
    return None if np.isnan(r) else float(np.degrees(r))


def compare(log: RecordedLog, q: np.ndarray) -> dict[str, Any]:
    """Comparison of an estimate ``q`` (N, 4) with the recorded estimate and with the truth.

    Returns degrees: ``vs_recorded`` {rms_deg, max_deg, max_abs_diff (largest quaternion
    component difference), identical (bit-exact), samples} (None without a recorded estimate), and when truth exists ``vs_truth`` {total, heading, inclination} RMSE over the
    samples with truth (and in the movement mask when the log has one), plus the same for the
    recorded estimate as ``recorded_vs_truth``. ``divergence`` (and ``recorded_divergence``):
    the divergence monitor over ``q`` (over the recorded estimate) — its summary line, the
    number of flags and each change of the flag (``t_s`` after the first sample).
    """
    out: dict[str, Any] = {"samples": int(q.shape[0]), "vs_recorded": None, "vs_truth": None}
    rec = log.attitudes if log.attitudes is not None else log.original
    if len(log):
        out["divergence"] = _divergence(log, q)
        if rec is not None:
            out["recorded_divergence"] = _divergence(log, rec)
    if rec is not None:
        ok = np.all(np.isfinite(rec), axis=1) & np.all(np.isfinite(q), axis=1)
        # q and −q are the same attitude: compare against the nearer sign. The chord between
        # two unit quaternions is 2·sin(θ/4) of the angle θ between the attitudes — exactly
        # zero for identical estimates, unlike acos/atan2 of a product that carries rounding.
        chord = np.minimum(np.linalg.norm(q[ok] - rec[ok], axis=1), np.linalg.norm(q[ok] + rec[ok], axis=1))
        total = 4.0 * np.arcsin(np.clip(chord / 2.0, 0.0, 1.0))
        diff = np.minimum(np.abs(q[ok] - rec[ok]).max(axis=1), np.abs(q[ok] + rec[ok]).max(axis=1))
        out["vs_recorded"] = {
            "rms_deg": _rms_deg(total, np.ones(total.shape, bool)),
            "max_deg": float(np.degrees(total.max())) if total.size else None,
            "max_abs_diff": float(diff.max()) if diff.size else None,
            "identical": bool(ok.any() and np.array_equal(q[ok], rec[ok])),
            "samples": int(ok.sum()),
        }
    if log.truth is not None:
        mask = np.all(np.isfinite(log.truth), axis=1)
        if log.movement is not None:
            mask &= log.movement
        for key, est in (("vs_truth", q), ("recorded_vs_truth", rec)):
            if est is None:
                continue
            m = mask & np.all(np.isfinite(est), axis=1)
            angles = error_angles(np.where(m[:, None], est, 1.0), np.where(m[:, None], log.truth, 1.0))
            out[key] = {kind: _rms_deg(a, m) for kind, a in zip(("total", "heading", "inclination"), angles)}
            out[key]["samples"] = int(m.sum())
    return out


def write_replay(
    log: RecordedLog,
    q: np.ndarray,
    out_path: str | os.PathLike,
    estimator: str,
    params: Mapping[str, Any] | None = None,
    follow_param_changes: bool = True,
    tf_rate_hz: float = 50.0,
    offline_blend_s: float | None = None,
    budget_bytes: int = DEFAULT_READ_BUDGET_BYTES,
) -> Path:
    """A new log: every channel of ``log`` copied, the new estimate on /attitude (and /tf),
    the recorded /attitude moved to /attitude/original, /config naming the new estimator.

    Only the /params changes that :func:`replay` applied with the same arguments are copied,
    so replaying the new log reproduces ``q``. ``offline_blend_s``: ``q`` is the offline
    estimate of :func:`replay_offline` with that blend time (s); /config then carries
    ``estimator.offline = {"blend_time_s": …}`` and each /attitude names "<estimator>+offline",
    so it is not taken for what the causal estimator published (a causal replay of the new log
    does not reproduce it). ``budget_bytes``: the read budget the log was read with
    (``logs/budget.py``), for the second pass over its messages.
    """
    out_path = Path(out_path)
    if os.path.realpath(out_path) == os.path.realpath(log.path):  # no RuntimeError on a symlink loop
        raise ValueError("the replay must not overwrite its input")
    # an older log may hold a secret in clear: the replay records it redacted, never copied
    config = redact_config(json.loads(json.dumps(log.config))) if log.config else {}
    config["estimator"] = {"name": estimator, "params": _effective_start(log, estimator, params)}
    label = estimator if offline_blend_s is None else estimator + "+offline"
    same = estimator == log.estimator
    tf_period = int(1e9 / tf_rate_hz)
    row_of = {int(t): i for i, t in enumerate(log.t_ns.tolist())}
    est_obj = estimators.get(estimator)(**config["estimator"]["params"])
    config["estimator"]["params"] = jsonable(est_obj.get_params())
    if offline_blend_s is not None:
        config["estimator"]["offline"] = {"blend_time_s": float(offline_blend_s)}
    known, pinned = set(est_obj.param_names()), set(params or {})
    last_tf: int | None = None
    # the messages the reader read, in its order, and no further: what follows a damaged
    # chunk or a message that is not valid was neither read nor replayed
    source = MessageSource(log.path, stream_only=not log.indexed, budget_bytes=budget_bytes)
    remaining = sum(log.counts.values()) if log.damage is not None else -1
    t0 = int(log.t_ns[0]) if len(log) else 0
    # the divergence monitor's flags of the new estimate, on /log at their sample times (the
    # recorded /log keeps the live run's own)
    flag_logs = [(int(round(e.t_s * 1e9)), e) for e in divergence_events(log, q)[1]] if len(log) else []
    with McapLogFile(out_path, metadata={"replay_of": Path(log.path).name, "estimator": label}) as f:
        f.write("/config", t0, {"t_ns": t0, "reason": "replay", "config": config})
        for topic, log_time, publish_time, data in source:
            if remaining == 0:
                break
            remaining -= 1
            while flag_logs and flag_logs[0][0] <= log_time:
                t_flag, event = flag_logs.pop(0)
                f.write("/log", t_flag, log_message(t_flag, 2 if event.diverged else 6, f"replay: {event.text()}"))
            if topic in ("/config", "/tf", "/attitude/original", "/attitude/original_block") or (
                    topic == "/estimator/state" and not same):
                continue
            if topic == "/params":
                name = json.loads(data).get("name")
                if not (same and follow_param_changes and name in known and name not in pinned):
                    continue  # a change the replay did not apply
            if topic in ("/attitude", "/attitude_block"):
                f.write_encoded(_ORIGINAL[topic], log_time, data, publish_time)
                continue
            if topic == "/imu/raw_block":  # a burst in, a burst out: its rows' new estimates
                times = [int(t) for t in json.loads(data)["t_ns"]]
                f.write_encoded(topic, log_time, data, publish_time, samples=len(times))
                rows_here = [row_of[t] for t in times if t in row_of]
                if len(rows_here) != len(times):
                    continue
                q_block = q[rows_here]
                f.write("/attitude_block", log_time, attitude_block_message(times, q_block, label))
                if np.all(np.isfinite(q_block[-1])) and (last_tf is None or log_time - last_tf >= tf_period):
                    last_tf = log_time
                    q_last = q_block[-1].tolist()
                    f.write("/attitude", log_time, attitude_message(log_time, q_last, label))
                    f.write("/tf", log_time, tf_message(log_time, q_last))
                continue
            f.write_encoded(topic, log_time, data, publish_time)
            if topic == "/imu/raw":
                i = row_of.get(int(log_time))
                if i is None or not np.all(np.isfinite(q[i])):
                    continue
                qi = q[i].tolist()
                f.write("/attitude", log_time, attitude_message(log_time, qi, label))
                if last_tf is None or log_time - last_tf >= tf_period:
                    last_tf = log_time
                    f.write("/tf", log_time, tf_message(log_time, qi))
        for t_flag, event in flag_logs:  # after the last message copied
            f.write("/log", t_flag, log_message(t_flag, 2 if event.diverged else 6, f"replay: {event.text()}"))
        # citation, provenance …: kept; the source's own writer record under another name
        for name, data in source.metadata.items():
            f.add_metadata(name if name != "ahrs-service" else "source:ahrs-service", data)
    return out_path
