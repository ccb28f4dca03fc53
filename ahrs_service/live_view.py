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
set request is queued by the server thread and applied by the loop at its next IO tick
through the ``set_param`` the service gives the view (its ``set_estimator_param``) — the
path of a MAVLink PARAM_SET: between two samples, logged on ``/params`` with its sample index. The request
waits (at most ``SET_WAIT_S``) for the loop and answers with the value now in force.

Faults: a port already in use gives one warning and no live view (the service runs on);
malformed or unknown client operations are the SDK's to ignore; unknown parameter names and
non-numeric values are ignored and answered with the current values.
"""

from __future__ import annotations

import collections
import logging
import threading
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from ahrs_service.estimators import STATE_HEADER
from ahrs_service.live_settings import DEFAULT_HOST, DEFAULT_PORT, DEFAULT_RATE_HZ
from ahrs_service.logs import schemas
from ahrs_service.pipeline import EstimatedBlock, EstimationPipeline

log = logging.getLogger("ahrs_service.live")

_H = STATE_HEADER.slices  # the state header every estimator shares
PARAM_PREFIX = "estimator."
SET_WAIT_S = 1.0  # how long a client's parameter set waits for the loop to apply it, s
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
    """

    def __init__(self, estimates: EstimationPipeline, set_param: Callable[[str, float, str], float],
                 host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                 rate_hz: float = DEFAULT_RATE_HZ) -> None:
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
        self.published = 0  # messages handed to the server
        self.ignored_sets = 0  # set requests for unknown names or with non-numeric values
        self.refused_sets = 0  # set requests the estimator or the EST_* bounds refused (applied by the loop)
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
        try:
            self._server = foxglove.start_server(
                name="ahrs-service",
                host=host,
                port=port,
                capabilities=[Capability.Parameters],
                server_listener=_listener(self),
                context=self._ctx,
            )
        except Exception as exc:  # the SDK raises on bind errors (port in use, bad address)
            raise LiveViewUnavailable(f"live view: cannot listen on {host}:{port}: {exc}") from None
        self.port = self._server.port

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
        while self._requests:
            self._apply(self._requests.popleft())
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
            log.warning("live view: parameter %s = %r refused: %s", req.name, req.value, exc)
        self._params = self._current_params()
        req.done.set()
        self._server.publish_parameter_values(self._parameters(None))

    def _bounds(self, name: str) -> tuple[float, float]:
        """[minimum, maximum] of estimator parameter ``name``: those of its MAVLink EST_*
        parameter (``mavlink_bridge.estimator_param_bounds`` around the estimator's default),
        so a Foxglove client cannot put into the filter what a ground station may not (1e300)."""
        from ahrs_service import estimators
        from ahrs_service.mavlink_bridge import estimator_param_bounds

        default = estimators.create(self.estimates.estimator.name).get_params()[name]
        return estimator_param_bounds(float(default))

    def params_changed(self) -> None:
        """The estimator's parameters changed another way (MAVLink, reload): tells the clients."""
        self._params = self._current_params()
        self._server.publish_parameter_values(self._parameters(None))

    def close(self) -> None:
        self._server.stop()
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

    def _request_sets(self, parameters: list[Any]) -> list[Any]:
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
        for req in waiting:
            req.done.wait(SET_WAIT_S)
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


def open_live_view(estimates: EstimationPipeline, set_param: Callable[[str, float, str], float],
                   settings: Mapping[str, Any]) -> LiveView | None:
    """The configured live view, or None after one warning when it cannot start."""
    try:
        view = LiveView(estimates, set_param, settings["host"], settings["port"], settings["rate_hz"])
    except LiveViewUnavailable as exc:
        log.warning("%s; running without live view", exc)
        return None
    log.info("live view: Foxglove WebSocket on ws://%s:%d", settings["host"], view.port)
    return view
