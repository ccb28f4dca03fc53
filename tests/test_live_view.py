"""The live view end to end: the running service's Foxglove WebSocket server, spoken to by a
real ``websockets`` client over 127.0.0.1 (Foxglove's WebSocket protocol: JSON text ops,
binary message data ``0x01 | subscription u32 | log time u64 | payload``, little endian)."""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import struct
import time

import pytest

pytest.importorskip("foxglove")
websockets = pytest.importorskip("websockets")

from ahrs_service.logs.reader import MessageSource  # noqa: E402
from ahrs_service.logs.schemas import CHANNELS, decode, validate  # noqa: E402
from tests.test_service import RunningService, service_config  # noqa: E402

pytestmark = pytest.mark.timeout(120)
# the only subprotocol the SDK's server accepts (docs/live.md); foxglove.websocket.v1 gets HTTP 400
SUBPROTOCOL = "foxglove.sdk.v1"
SUBPROTOCOLS = [SUBPROTOCOL]
UPGRADE_REQUEST = ("GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                   "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
                   "Sec-WebSocket-Protocol: {}\r\n\r\n")


async def raw_upgrade(port: int, subprotocol: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, bytes]:
    """A hand-written WebSocket upgrade offering ``subprotocol``: the reader, the writer and the
    server's HTTP response head (status line and headers)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(UPGRADE_REQUEST.format(subprotocol).encode())
    await writer.drain()
    head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10)
    return reader, writer, head


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def live_service(tmp_path, live=None, **sections):
    cfg = service_config(
        tmp_path, free_port(), estimator={"name": "madgwick"}, source={"profile": "figure8"},
        live={"enabled": True, "port": free_port(), "rate_hz": 20, **(live or {})}, **sections,
    )
    return RunningService(cfg, duration_s=60.0)


async def _ops(ws, wanted: str, seconds: float = 10.0) -> dict:
    """The next JSON op named ``wanted`` (binary frames and other ops skipped)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        frame = await asyncio.wait_for(ws.recv(), end - time.monotonic())
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg.get("op") == wanted:
                return msg
    raise AssertionError(f"no {wanted} op within {seconds} s")


async def _advertised(ws) -> dict[str, dict]:
    channels: dict[str, dict] = {}
    while not {"/attitude", "/tf", "/log", "/imu/raw"} <= channels.keys():
        for ch in (await _ops(ws, "advertise"))["channels"]:
            channels[ch["topic"]] = ch
    return channels


async def _messages(ws, by_sub: dict[int, str], count: int, seconds: float = 15.0) -> dict[str, list]:
    got: dict[str, list] = {topic: [] for topic in by_sub.values()}
    end = time.monotonic() + seconds
    while min(len(v) for v in got.values()) < count and time.monotonic() < end:
        frame = await asyncio.wait_for(ws.recv(), end - time.monotonic())
        if isinstance(frame, bytes) and frame[0] == 0x01:
            sub, log_time = struct.unpack_from("<IQ", frame, 1)
            got[by_sub[sub]].append((log_time, decode(frame[13:])))
    return got


def test_client_sees_channels_messages_and_sets_a_parameter(tmp_path, capfd):
    run = live_service(tmp_path)
    port = run.service.live.port
    beta0 = run.service.estimator.get_params()["beta"]

    async def session():
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            info = await _ops(ws, "serverInfo")
            assert "parameters" in info["capabilities"]
            channels = await _advertised(ws)
            for topic in ("/attitude", "/tf", "/imu/raw", "/log", "/loop"):
                ch = channels[topic]
                assert ch["encoding"] == "json" and ch["schemaName"] == CHANNELS[topic][0]
                assert json.loads(ch["schema"]) == CHANNELS[topic][1]  # the log's schema, verbatim
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 1, "channelId": channels["/attitude"]["id"]}, {"id": 2, "channelId": channels["/tf"]["id"]}]}))
            got = await _messages(ws, {1: "/attitude", 2: "/tf"}, count=5)
            await ws.send(json.dumps({"op": "getParameters", "parameterNames": ["estimator.beta"], "id": "g"}))
            values = await _ops(ws, "parameterValues")
            await ws.send(json.dumps({"op": "setParameters", "id": "s",
                                      "parameters": [{"name": "estimator.beta", "value": beta0 * 2}]}))
            answer = await _ops(ws, "parameterValues")
            return got, values, answer

    try:
        got, values, answer = asyncio.run(session())
        assert run.service.estimator.get_params()["beta"] == pytest.approx(beta0 * 2)
    finally:
        run.stop()
    for topic in ("/attitude", "/tf"):
        assert len(got[topic]) >= 5
        for log_time, msg in got[topic]:
            assert validate(msg, CHANNELS[topic][1]) == []
    att = got["/attitude"][-1][1]
    assert att["estimator"] == "madgwick" and abs(sum(v * v for v in att["q"]) - 1) < 1e-9
    assert "initialised" in att["diagnostics"] and "reduced" in att["diagnostics"]
    tf = got["/tf"][-1][1]
    assert (tf["parent_frame_id"], tf["child_frame_id"]) == ("ned", "body")
    # decimated for viewers: 20 Hz of a 200 Hz loop, judged by the samples' own times
    times = [t for t, _ in got["/attitude"]]
    assert min(b - a for a, b in zip(times, times[1:])) >= 45_000_000
    assert {p["name"]: p["value"] for p in values["parameters"]} == {"estimator.beta": pytest.approx(beta0)}
    assert {p["name"]: p["value"] for p in answer["parameters"]}["estimator.beta"] == pytest.approx(beta0 * 2)
    # the change is in the log, with its sample index, as a MAVLink PARAM_SET would be
    (path,) = (tmp_path / "logs").glob("*.mcap")
    params = [decode(d) for topic, _, _, d in MessageSource(path) if topic == "/params"]
    assert [(p["name"], p["source"]) for p in params] == [("beta", "foxglove")]
    assert params[0]["new"] == pytest.approx(beta0 * 2) and params[0]["sample_index"] > 0
    logs = [decode(d)["message"] for topic, _, _, d in MessageSource(path) if topic == "/log"]
    assert any("parameter beta" in m and "foxglove" in m for m in logs)
    assert "Callback failed" not in capfd.readouterr().err  # the SDK found every listener callback


def test_bad_clients_do_not_disturb_the_service_or_other_clients(tmp_path):
    run = live_service(tmp_path)
    port = run.service.live.port
    beta0 = run.service.estimator.get_params()["beta"]

    async def session():
        # ten clients at once, each completing its handshake, then vanishing in the middle of a frame
        for _ in range(10):
            r, w, head = await raw_upgrade(port, SUBPROTOCOL)
            assert head.startswith(b"HTTP/1.1 101 ") and f"sec-websocket-protocol: {SUBPROTOCOL}".encode() in head.lower()
            w.write(b"\x81\xfe\x01")  # a masked text frame whose 16-bit length is cut after one byte
            await w.drain()
            w.close()
        clients = [await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS) for _ in range(10)]
        bad, good = clients[0], clients[1]
        for junk in ("not json", json.dumps({"op": "launchRocket"}), json.dumps({"op": "subscribe"}),
                     json.dumps({"op": "setParameters", "parameters": [{"name": "estimator.beta", "value": "x"}]}),
                     json.dumps({"op": "setParameters", "parameters": [{"name": "estimator.nope", "value": 1.0}]})):
            try:
                await bad.send(junk)
            except websockets.ConnectionClosed:
                break
        for c in clients[2:]:
            await c.close()
        channels = await _advertised(good)
        await good.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": channels["/attitude"]["id"]}]}))
        got = await _messages(good, {7: "/attitude"}, count=3)
        await good.close()
        await bad.close()
        return got

    try:
        samples_before = run.service.pipeline.samples
        got = asyncio.run(session())
        assert run.thread.is_alive() and run.service.pipeline.samples > samples_before
        assert run.service.estimator.get_params()["beta"] == beta0  # the junk sets changed nothing
    finally:
        run.stop()
    assert len(got["/attitude"]) >= 3


def test_port_in_use_warns_once_and_the_service_runs_on(tmp_path, caplog):
    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        port = blocker.getsockname()[1]
        cfg = service_config(tmp_path, free_port(), live={"enabled": True, "port": port})
        with caplog.at_level(logging.WARNING, logger="ahrs_service"):
            run = RunningService(cfg, duration_s=30.0)
        try:
            assert run.service.live is None
            end = time.monotonic() + 10
            while run.service.pipeline.samples < 5 and time.monotonic() < end:
                time.sleep(0.05)
            assert run.service.pipeline.samples >= 5
        finally:
            run.stop()
    warnings = [r.getMessage() for r in caplog.records if "live view" in r.getMessage()]
    assert len(warnings) == 1 and str(port) in warnings[0] and "without live view" in warnings[0]


def test_run_live_flag_starts_the_view(tmp_path, caplog):
    from ahrs_service.cli import main

    port = free_port()
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[mavlink]\nendpoints = ["udpout:127.0.0.1:{free_port()}"]\n\n[live]\nport = {port}\n')
    with caplog.at_level(logging.INFO, logger="ahrs_service"):
        assert main(["run", "-c", str(cfg), "--live", "--no-log", "--duration", "0.3"]) == 0
    assert any(f"ws://127.0.0.1:{port}" in r.getMessage() for r in caplog.records)


def test_parameter_sets_outside_the_mavlink_bounds_are_refused(tmp_path):
    """Issue 14 probe (14d): a Foxglove client could set ``estimator.beta = 1e300`` (or 3e38,
    or -1; NaN is no JSON, which the SDK drops) — the bounds a MAVLink PARAM_SET has (``mavlink_bridge.estimator_param_bounds``)
    did not apply to the live view's sets. Now they do; the answer carries the value in force,
    and a set inside the bounds still works."""
    from ahrs_service import estimators
    from ahrs_service.mavlink_bridge import estimator_param_bounds

    run = live_service(tmp_path)
    port = run.service.live.port
    beta0 = run.service.estimator.get_params()["beta"]
    lo, hi = estimator_param_bounds(estimators.create("madgwick").get_params()["beta"])

    async def session():
        answers = []
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS) as ws:
            await _ops(ws, "serverInfo")
            for i, value in enumerate((1e300, 3e38, hi * 1.01, -1.0, beta0 * 3)):
                await ws.send(json.dumps({"op": "setParameters", "id": f"s{i}",
                                          "parameters": [{"name": "estimator.beta", "value": value}]}))
                answer = await _ops(ws, "parameterValues")
                answers.append({p["name"]: p["value"] for p in answer["parameters"]}["estimator.beta"])
        return answers

    try:
        answers = asyncio.run(session())
        beta = run.service.estimator.get_params()["beta"]
        refused = run.service.live.refused_sets
    finally:
        run.stop()
    assert answers[:4] == [pytest.approx(beta0)] * 4 and refused == 4
    assert answers[4] == pytest.approx(beta0 * 3) and beta == pytest.approx(beta0 * 3)
    (path,) = (tmp_path / "logs").glob("*.mcap")
    params = [decode(d) for topic, _, _, d in MessageSource(path) if topic == "/params"]
    assert [p["new"] for p in params] == [pytest.approx(beta0 * 3)]  # only the set inside the bounds


def test_only_the_sdk_subprotocol_is_accepted(tmp_path):
    """docs/live.md names the one subprotocol the server speaks: a client offering it gets the
    upgrade and then the serverInfo op; one offering only the older ``foxglove.websocket.v1``
    gets HTTP 400, and the view stays up for the next client."""
    run = live_service(tmp_path)
    port = run.service.live.port

    async def session():
        refused = await raw_upgrade(port, "foxglove.websocket.v1")
        refused[1].close()
        reader, writer, head = await raw_upgrade(port, SUBPROTOCOL)
        first = await asyncio.wait_for(reader.read(2), 10)  # an unmasked text frame: FIN|text, length
        writer.close()
        return refused[2], head, first

    try:
        refused, accepted, first = asyncio.run(session())
    finally:
        run.stop()
    assert refused.startswith(b"HTTP/1.1 400 ")
    assert accepted.startswith(b"HTTP/1.1 101 ") and f"sec-websocket-protocol: {SUBPROTOCOL}".encode() in accepted.lower()
    assert first[0] == 0x81  # the server's first message: serverInfo, a text frame
