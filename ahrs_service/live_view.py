"""Live view: the flight log's channels served to Foxglove over its WebSocket protocol.

Built on the ``foxglove-sdk`` package (extra ``live``), imported only when ``[live] enabled``.
The SDK's server runs on its own (Rust) threads: the service loop only hands it already
encoded messages, and only at IO rate. The per-sample channels (``/imu/raw``, ``/attitude``,
``/tf``, ``/attitude/truth``) are *decimated before encoding*: the latest sample is encoded and
published when it is ``1/rate_hz`` of sample time after the last one published (sample time,
not the loop's wall clock: a loop catching up after a stall still shows the viewer evenly
spaced samples), nothing is done for the others (the MCAP log keeps every sample). The slow channels (``/loop``, ``/log``, ``/params``, ``/config``) are published as
they are written to the log. Channel names and JSON schemas are the log's
(:data:`ahrs_service.logs.schemas.CHANNELS`), so one Foxglove layout serves both.

The view is one of the service's sinks (``ahrs_service.sinks``): the loop hands it every
estimated block (:meth:`LiveView.receive`), and it publishes the newest state of the pipeline
that estimated it at its own rate.

The estimator's parameters appear as Foxglove parameters ``estimator.<name>``. A client's
set request is queued by the server thread and applied by the loop at its IO ticks, at most
``APPLY_PER_TICK`` a tick, through the ``set_param`` the service gives the view (its
``set_estimator_param``) — the path of a MAVLink PARAM_SET: between two samples, logged on
``/params`` with its sample index. The request waits (at most ``SET_WAIT_S``) for the loop and
answers with the values now in force. A setParameters message is accepted whole or refused
whole: refused in a view-only view (``allow_control`` false), when it carries more than
``MAX_SETS_PER_MESSAGE`` entries, or when the view's budget of ``MAX_SETS_PER_S`` entries a
second (all clients together) is spent — so no client can make the loop apply thousands of
sets in one tick.

The SDK has no hook to authenticate a client, cap connections or time out a handshake, so
its server listens on a private loopback port and clients reach it through the view's front
(:class:`ahrs_service.live_front.LiveFront`) on the configured host and port: it caps the
connections, times out a client that sends no upgrade request, and checks the token.

Faults: a port already in use gives one warning and no live view (the service runs on);
malformed or unknown client operations are the SDK's to ignore; unknown parameter names and
non-numeric values are ignored and answered with the current values.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from ahrs_service.estimators import STATE_HEADER
from ahrs_service.live_front import FrontUnavailable, LiveFront
from ahrs_service.live_settings import (
    DEFAULT_HANDSHAKE_TIMEOUT_S,
    DEFAULT_HOST,
    DEFAULT_MAX_CONNECTIONS,
    DEFAULT_PORT,
    DEFAULT_RATE_HZ,
    is_loopback,
)
from ahrs_service.logs import schemas
from ahrs_service.pipeline import EstimatedBlock, EstimationPipeline

log = logging.getLogger("ahrs_service.live")

_H = STATE_HEADER.slices  # the state header every estimator shares
PARAM_PREFIX = "estimator."
SET_WAIT_S = 1.0  # how long a client's parameter set waits for the loop to apply it, s
#: entries one setParameters message may carry (Foxglove's panels send one at a time)
MAX_SETS_PER_MESSAGE = 64
#: entries accepted per second from all clients together (a token bucket this deep)
MAX_SETS_PER_S = 64
#: queued sets the loop applies in one IO tick (5 ms): the rest wait for the next ticks
APPLY_PER_TICK = 8
#: at most one warning this often per kind of refused set, s (the counters count every one)
REFUSAL_WARNING_PERIOD_S = 5.0
#: how long closing waits for the SDK's server to stop, s (its stop waits for every connection
#: still in its handshake; the front has closed them all by then)
STOP_WAIT_S = 2.0
# channels the live view serves: the log's, less those only a file needs
LIVE_TOPICS = ("/imu/raw", "/attitude", "/attitude/truth", "/tf", "/loop", "/log", "/params", "/config", "/mavlink",
               "/autopilot/attitude", "/monitor")  # the last two beside an autopilot (attitude monitor)


class LiveViewUnavailable(RuntimeError):
    """The live view cannot start (extra not installed, port in use …); the message says why."""


@dataclass
class _SetRequest:
    """One parameter set from a client, waiting for the loop (name without the prefix)."""

    name: str
    value: float
    done: threading.Event = field(default_factory=threading.Event)


class LiveView:
    """The Foxglove WebSocket server of a running service.

    estimates: the pipeline whose newest state is published (read at IO rate; each block
        received names the pipeline that estimated it).
    set_param: (name, value, source) → the value in force: applies an estimator parameter
        live (called on the loop thread).
    host, port: where to listen (port 0: any free port; see :attr:`port`).
    rate_hz: per-sample channels are published at most this often.
    allow_control: false makes the view view-only: every parameter set is refused.
    max_connections, handshake_timeout_s (s), token: the front's connection cap, the time a
        client has to send its upgrade request, and the ``?token=`` every client must send
        ("" none); see :class:`ahrs_service.live_front.LiveFront`.
    """

    def __init__(self, estimates: EstimationPipeline, set_param: Callable[[str, float, str], float],
                 host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                 rate_hz: float = DEFAULT_RATE_HZ, allow_control: bool = True,
                 max_connections: int = DEFAULT_MAX_CONNECTIONS,
                 handshake_timeout_s: float = DEFAULT_HANDSHAKE_TIMEOUT_S, token: str = "") -> None:
        try:
            import foxglove
            from foxglove.websocket import Capability
        except ImportError:
            raise LiveViewUnavailable("live view needs the 'live' extra: pip install 'ahrs-service[live]'") from None
        self._foxglove = foxglove
        self.estimates = estimates
        self.set_param = set_param
        self.period_ns = int(1e9 / rate_hz)
        self._published_t_ns: int | None = None  # sample time of the last sample published, ns
        self._requests: collections.deque[_SetRequest] = collections.deque()
        self._params = self._current_params()
        self.allow_control = allow_control
        self.published = 0  # messages handed to the server
        self.ignored_sets = 0  # set requests for unknown names or with non-numeric values
        self.refused_sets = 0  # set requests the estimator or the EST_* bounds refused (applied by the loop)
        self.denied_sets = 0  # entries of setParameters messages refused because the view is view-only
        self.excess_sets = 0  # entries of messages refused for size or for the per-second budget
        self._budget_lock = threading.Lock()  # the SDK may call the listener from several threads
        self._budget = float(MAX_SETS_PER_S)
        self._budget_t = time.monotonic()
        self._warned_at: dict[str, float] = {}
        self._bounds_of: dict[tuple[str, str], tuple[float, float]] = {}
        self._ctx = foxglove.Context()
        self._channels = {
            topic: foxglove.Channel(
                topic,
                schema=foxglove.Schema(
                    name=schemas.CHANNELS[topic][0], encoding=schemas.SCHEMA_ENCODING, data=schemas.schema_bytes(topic)
                ),
                message_encoding=schemas.MESSAGE_ENCODING,
                context=self._ctx,
            )
            for topic in LIVE_TOPICS
        }
        self._capabilities = [Capability.Parameters]
        self._listener = _listener(self)
        try:  # private: only the front connects to it
            self._server = foxglove.start_server(
                name="ahrs-service", host="127.0.0.1", port=0, capabilities=self._capabilities,
                server_listener=self._listener, context=self._ctx,
            )
        except Exception as exc:  # the SDK raises on bind errors (no loopback, no descriptors)
            raise LiveViewUnavailable(f"live view: cannot start the WebSocket server: {exc}") from None
        try:
            self._front = LiveFront(host, port, self._server.port, max_connections=max_connections,
                                    handshake_timeout_s=handshake_timeout_s, token=token)
        except FrontUnavailable as exc:  # port in use, an address this computer lacks
            _stop_server(self._server, STOP_WAIT_S)
            raise LiveViewUnavailable(f"live view: cannot listen on {host}:{port}: {exc}") from None
        self.port: int = self._front.port  # where clients connect

    @property
    def connections(self) -> dict[str, int]:
        """The front's connection counters: open, accepted (handed to the server), refused_cap,
        refused_token, handshake_timeouts, malformed."""
        return self._front.stats()

    # ---------------------------------------------------------------- loop thread
    def receive(self, estimated: EstimatedBlock) -> None:
        """An estimated block (once per block): published from its pipeline at the view's rate."""
        self.estimates = estimated.pipeline

    def follow(self, pipeline: EstimationPipeline) -> None:
        """Publishes ``pipeline``'s state from now on (a reload built a new one)."""
        self.estimates = pipeline

    def tick(self, now_ns: int) -> None:
        """Called by the loop at IO rate: applies queued parameter sets, then publishes the
        latest sample's /imu/raw, /attitude, /tf and truth when it is due (:meth:`_due`)."""
        applied = 0
        while self._requests and applied < APPLY_PER_TICK:
            self._apply(self._requests.popleft())
            applied += 1
        if applied:
            self._params = self._current_params()
            self._server.publish_parameter_values(self._parameters(None))
        pipeline = self.estimates
        sample = pipeline.last_sample
        if sample is None or not self._due(sample.t_ns):
            return
        est = pipeline.estimator
        t_ns = sample.t_ns
        q = est.state[_H.q].tolist()
        self.publish("/imu/raw", t_ns, schemas.raw_message(t_ns, pipeline.row.tolist(), sample.flags, sample.raw,
                                                           sample.temperature_c, pipeline.samples - 1))
        self.publish("/attitude", t_ns, schemas.attitude_message(t_ns, q, est.name, est.state[_H.bias].tolist(),
                                                                 pipeline.diagnostics()))
        if all(v == v for v in q):  # a NaN rotation would break the 3-D panel
            self.publish("/tf", t_ns, schemas.tf_message(t_ns, q))
        if sample.truth_q is not None:
            self.publish("/attitude/truth", t_ns, schemas.truth_message(t_ns, list(sample.truth_q)))

    def _due(self, t_ns: int) -> bool:
        """Whether a sample at ``t_ns`` (ns) is ``1/rate_hz`` of sample time after the last one
        published, or before it (a new timeline after a reload); marks it published if so."""
        last = self._published_t_ns
        if last is not None and 0 <= t_ns - last < self.period_ns:
            return False
        self._published_t_ns = t_ns
        return True

    def publish(self, topic: str, t_ns: int, message: Mapping[str, Any]) -> None:
        """Encodes and publishes one message (nothing when no client subscribes to ``topic``)."""
        channel = self._channels[topic]
        if not channel.has_sinks():
            return
        channel.log(schemas.encode(message), log_time=int(t_ns))
        self.published += 1

    def log_event(self, t_ns: int, severity: int, text: str) -> None:
        """A health event on /log (MAVLink severity, mapped as in the flight log)."""
        self.publish("/log", t_ns, schemas.log_message(t_ns, severity, text))

    def _apply(self, req: _SetRequest) -> None:
        try:
            lo, hi = self._bounds(req.name)
            if not lo <= req.value <= hi:  # NaN too: the bounds a MAVLink PARAM_SET has
                raise ValueError(f"outside [{lo:g}, {hi:g}]")
            self.set_param(req.name, req.value, "foxglove")
        except (KeyError, ValueError, TypeError) as exc:  # a value the estimator refuses
            self.refused_sets += 1
            self._warn("refused", "live view: parameter %s = %r refused: %s", req.name, req.value, exc)
        req.done.set()

    def _bounds(self, name: str) -> tuple[float, float]:
        """[minimum, maximum] of estimator parameter ``name``: those of its MAVLink EST_*
        parameter (``mavlink_bridge.estimator_param_bounds`` around the estimator's default),
        so a Foxglove client cannot put into the filter what a ground station may not (1e300)."""
        estimator_name = self.estimates.estimator.name
        key = (estimator_name, name)
        if key not in self._bounds_of:  # building an estimator for its defaults costs more than a tick
            from ahrs_service import estimators
            from ahrs_service.mavlink_bridge import estimator_param_bounds

            default = estimators.create(estimator_name).get_params()[name]
            self._bounds_of[key] = estimator_param_bounds(float(default))
        return self._bounds_of[key]

    def _warn(self, kind: str, message: str, *args: Any) -> None:
        """A warning of ``kind``, at most one every ``REFUSAL_WARNING_PERIOD_S`` (a client
        sending refused sets in a loop must not flood the journal; the counters keep the count)."""
        now = time.monotonic()
        if now - self._warned_at.get(kind, -REFUSAL_WARNING_PERIOD_S) >= REFUSAL_WARNING_PERIOD_S:
            self._warned_at[kind] = now
            log.warning(message, *args)

    def params_changed(self) -> None:
        """The estimator's parameters changed another way (MAVLink, reload): tells the clients."""
        self._params = self._current_params()
        self._server.publish_parameter_values(self._parameters(None))

    def close(self) -> None:
        self._front.close()
        if not _stop_server(self._server, STOP_WAIT_S):
            log.warning("live view: the WebSocket server has not stopped within %.0f s (connections stuck in "
                        "their handshake); left to end with the process", STOP_WAIT_S)
        while self._requests:  # nobody will apply these any more: let their clients go
            self._requests.popleft().done.set()

    def _current_params(self) -> dict[str, float]:
        # loop thread (and the constructor): the numeric parameters of the running estimator
        return {k: float(v) for k, v in self.estimates.estimator.get_params().items()
                if isinstance(v, (int, float)) and not isinstance(v, bool)}

    # ---------------------------------------------------------------- server threads
    def _parameters(self, names: list[str] | None) -> list[Any]:
        params = self._params  # replaced, never mutated: safe to read from the server thread
        Parameter = self._foxglove.Parameter
        wanted = params if not names else [n[len(PARAM_PREFIX):] for n in names if n.startswith(PARAM_PREFIX)]
        return [Parameter(PARAM_PREFIX + n, value=params[n]) for n in wanted if n in params]

    def _admit(self, count: int) -> bool:
        """Whether a setParameters message of ``count`` entries may be queued; counts and warns
        (rate-limited) when not. Server threads."""
        if not self.allow_control:
            self.denied_sets += count
            self._warn("denied", "live view: view-only (live.allow_remote_control = false): "
                       "a client's set of %d parameter(s) refused", count)
            return False
        if count > MAX_SETS_PER_MESSAGE:
            self.excess_sets += count
            self._warn("excess", "live view: a setParameters message of %d entries refused whole; "
                       "at most %d per message", count, MAX_SETS_PER_MESSAGE)
            return False
        with self._budget_lock:
            now = time.monotonic()
            self._budget = min(float(MAX_SETS_PER_S), self._budget + (now - self._budget_t) * MAX_SETS_PER_S)
            self._budget_t = now
            if count > self._budget:
                self.excess_sets += count
                self._warn("budget", "live view: parameter sets beyond %d a second refused "
                           "(a message of %d entries)", MAX_SETS_PER_S, count)
                return False
            self._budget -= count
        return True

    def _request_sets(self, parameters: list[Any]) -> list[Any]:
        if not parameters or not self._admit(len(parameters)):
            return self._parameters(None)
        waiting = []
        for p in parameters:
            full = str(getattr(p, "name", ""))
            name = full[len(PARAM_PREFIX):] if full.startswith(PARAM_PREFIX) else ""
            try:
                value = p.get_value()
            except Exception:  # noqa: BLE001 - an undecodable value is ignored like an unknown name
                value = None
            if name not in self._params or isinstance(value, bool) or not isinstance(value, (int, float)):
                self.ignored_sets += 1
                continue
            req = _SetRequest(name, float(value))
            self._requests.append(req)
            waiting.append(req)
        deadline = time.monotonic() + SET_WAIT_S
        for req in waiting:
            req.done.wait(max(0.0, deadline - time.monotonic()))
        return self._parameters(None)


def _listener(view: LiveView) -> Any:
    """The SDK's ServerListener for ``view``: called on the server's threads, it never touches
    the estimator. Built here because the SDK is imported only when the view is enabled; the
    other callbacks (subscribe, advertise …) are the base class's, which do nothing."""
    from foxglove.websocket import ServerListener

    class Listener(ServerListener):
        def on_get_parameters(self, client: Any, param_names: list[str], request_id: str | None = None) -> list[Any]:
            return view._parameters(param_names)

        def on_set_parameters(self, client: Any, parameters: list[Any], request_id: str | None = None) -> list[Any]:
            return view._request_sets(parameters)

    return Listener()


def _stop_server(server: Any, wait_s: float) -> bool:
    """Stops an SDK server on a daemon thread (its ``stop`` blocks while any connection is in
    its handshake) and waits at most ``wait_s``; whether it has stopped."""
    stopper = threading.Thread(target=server.stop, name="live-view-stop", daemon=True)
    stopper.start()
    stopper.join(wait_s)
    return not stopper.is_alive()


def open_live_view(estimates: EstimationPipeline, set_param: Callable[[str, float, str], float],
                   settings: Mapping[str, Any]) -> LiveView | None:
    """The configured live view, or None after one warning when it cannot start."""
    allow_control = settings.get("allow_remote_control", True)
    try:
        view = LiveView(estimates, set_param, settings["host"], settings["port"], settings["rate_hz"],
                        allow_control=allow_control,
                        max_connections=settings.get("max_connections", DEFAULT_MAX_CONNECTIONS),
                        handshake_timeout_s=settings.get("handshake_timeout_s", DEFAULT_HANDSHAKE_TIMEOUT_S),
                        token=settings.get("token", ""))
    except LiveViewUnavailable as exc:
        log.warning("%s; running without live view", exc)
        return None
    access = "clients may set estimator parameters" if allow_control else "view-only"
    token = "token required" if settings.get("token") else "no token"
    log.info("live view: Foxglove WebSocket on ws://%s:%d (%s, %s)", settings["host"], view.port, access, token)
    if not is_loopback(settings["host"]):
        log.warning("live view: listening on %s, reachable from the network %s, unencrypted (%s)", settings["host"],
                    "with a token" if settings.get("token") else "without authentication", access)
    return view
