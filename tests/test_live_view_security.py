"""Who may reach and steer the live view: the bind rule of ``[live]``, the token, view-only mode,
the bounds on parameter sets, the connection cap and the handshake timeout. Real Foxglove
WebSocket clients (``websockets``) over 127.0.0.1, completing their handshake."""

from __future__ import annotations

import asyncio
import collections
import json
import socket
import struct
import time

import pytest

pytest.importorskip("foxglove")
websockets = pytest.importorskip("websockets")

from ahrs_service import config as config_mod  # noqa: E402
from ahrs_service.core.settings import ConfigError  # noqa: E402
from ahrs_service.logs.reader import MessageSource  # noqa: E402
from ahrs_service.logs.schemas import decode  # noqa: E402
from tests.test_live_view import SUBPROTOCOLS, _advertised, _ops, live_service  # noqa: E402

pytestmark = pytest.mark.timeout(180)


def _connect(port: int):
    return websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=20,
                              max_size=None)


def _logged_params(tmp_path) -> list[dict]:
    (path,) = (tmp_path / "logs").glob("*.mcap")
    return [decode(d) for topic, _, _, d in MessageSource(path) if topic == "/params"]


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.168.1.20", "drone.local"])
def test_a_network_reachable_host_needs_view_only(host):
    with pytest.raises(ConfigError) as err:
        config_mod.validate({"live": {"host": host}})
    message = str(err.value)
    assert message.startswith("live.host: ") and "allow_remote_control = false" in message and "\n" not in message
    cfg = config_mod.validate({"live": {"host": host, "allow_remote_control": False}})
    assert cfg.live["host"] == host and cfg.live["allow_remote_control"] is False


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.1.1", "::1", "localhost"])
def test_loopback_hosts_keep_control_by_default(host):
    cfg = config_mod.validate({"live": {"host": host}})
    assert cfg.live["allow_remote_control"] is True


def test_view_only_refuses_every_set_and_still_shows_the_values(tmp_path):
    run = live_service(tmp_path, live={"allow_remote_control": False})
    port = run.service.live.port
    beta0 = run.service.estimator.get_params()["beta"]

    async def session():
        async with _connect(port) as ws:
            await _ops(ws, "serverInfo")
            await ws.send(json.dumps({"op": "getParameters", "parameterNames": ["estimator.beta"], "id": "g"}))
            shown = await _ops(ws, "parameterValues")
            await ws.send(json.dumps({"op": "setParameters", "id": "s",
                                      "parameters": [{"name": "estimator.beta", "value": beta0 * 2}]}))
            answer = await _ops(ws, "parameterValues")
        return shown, answer

    try:
        shown, answer = asyncio.run(session())
        beta = run.service.estimator.get_params()["beta"]
        denied = run.service.live.denied_sets
    finally:
        run.stop()
    assert {p["name"]: p["value"] for p in shown["parameters"]} == {"estimator.beta": pytest.approx(beta0)}
    assert {p["name"]: p["value"] for p in answer["parameters"]}["estimator.beta"] == pytest.approx(beta0)
    assert beta == beta0 and denied == 1
    assert _logged_params(tmp_path) == []


def test_a_huge_set_message_is_refused_and_the_loop_keeps_publishing(tmp_path, caplog):
    """2 000 entries in one setParameters: refused whole (counted, one warning), and /attitude
    keeps reaching the client while the server handles it — the loop is never held."""
    run = live_service(tmp_path)
    port = run.service.live.port
    beta0 = run.service.estimator.get_params()["beta"]
    huge = {"op": "setParameters", "id": "huge",
            "parameters": [{"name": "estimator.beta", "value": beta0 * (1 + (i % 50) / 100)} for i in range(2000)]}

    async def session():
        async with _connect(port) as ws:
            channels = await _advertised(ws)
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 1, "channelId": channels["/attitude"]["id"]}]}))
            arrivals: list[float] = []
            answer = None
            sent_at = None
            end = time.monotonic() + 30
            # wait for the stream, send the huge message, then watch 4 s of stream and the answer
            while time.monotonic() < end and (sent_at is None or time.monotonic() < sent_at + 4 or answer is None):
                frame = await asyncio.wait_for(ws.recv(), end - time.monotonic())
                now = time.monotonic()
                if isinstance(frame, bytes) and frame[0] == 0x01 and struct.unpack_from("<I", frame, 1)[0] == 1:
                    arrivals.append(now)
                    if sent_at is None and len(arrivals) >= 3:
                        sent_at = now
                        await ws.send(json.dumps(huge))
                elif isinstance(frame, str) and json.loads(frame).get("op") == "parameterValues":
                    answer = json.loads(frame)
            return arrivals, sent_at, answer

    try:
        with caplog.at_level("WARNING", logger="ahrs_service"):
            arrivals, sent_at, answer = asyncio.run(session())
        beta = run.service.estimator.get_params()["beta"]
        excess = run.service.live.excess_sets
    finally:
        run.stop()
    assert sent_at is not None and answer is not None
    after = [t for t in arrivals if t >= sent_at]
    gaps = [b - a for a, b in zip(after, after[1:])]
    # 20 Hz (50 ms apart): applying the 2 000 sets in one tick held the loop 0.5-9 s, machine to machine
    assert len(after) >= 20 and max(gaps) < 1.0, (len(after), max(gaps, default=None))
    assert excess == 2000 and beta == beta0
    assert {p["name"]: p["value"] for p in answer["parameters"]}["estimator.beta"] == pytest.approx(beta0)
    warnings = [r.getMessage() for r in caplog.records if "setParameters message of 2000 entries" in r.getMessage()]
    assert len(warnings) == 1 and "at most 64" in warnings[0]
    assert _logged_params(tmp_path) == []


def test_parameter_sets_beyond_the_budget_a_second_are_refused(tmp_path):
    """Messages of 64 sets back to back: the first is applied, a few sets a tick, those beyond
    the 64-a-second budget are refused whole and counted; after a second of quiet a set is
    applied again."""
    from ahrs_service.live_view import APPLY_PER_TICK, MAX_SETS_PER_MESSAGE

    run = live_service(tmp_path)
    port = run.service.live.port
    beta0 = run.service.estimator.get_params()["beta"]
    full = [{"name": "estimator.beta", "value": beta0 * 1.5}] * MAX_SETS_PER_MESSAGE

    async def session():
        async with _connect(port) as ws:
            await _ops(ws, "serverInfo")
            end = time.monotonic() + 30
            while run.service.pipeline.samples < 20 and time.monotonic() < end:  # the loop is estimating
                await asyncio.sleep(0.05)
            for i in range(4):
                await ws.send(json.dumps({"op": "setParameters", "id": f"b{i}", "parameters": full}))
                await _ops(ws, "parameterValues")
            refused_burst = run.service.live.excess_sets
            await asyncio.sleep(1.2)  # the budget refills at 64 a second
            await ws.send(json.dumps({"op": "setParameters", "id": "late",
                                      "parameters": [{"name": "estimator.beta", "value": beta0 * 2}]}))
            late = await _ops(ws, "parameterValues")
        return refused_burst, late

    try:
        refused_burst, late = asyncio.run(session())
        beta = run.service.estimator.get_params()["beta"]
    finally:
        run.stop()
    # a message is applied in ~8 ticks (40 ms): the bucket refills by a few sets, never 64
    assert refused_burst == 3 * MAX_SETS_PER_MESSAGE
    assert {p["name"]: p["value"] for p in late["parameters"]}["estimator.beta"] == pytest.approx(beta0 * 2)
    assert beta == pytest.approx(beta0 * 2)
    params = _logged_params(tmp_path)
    assert len(params) == MAX_SETS_PER_MESSAGE + 1 and params[-1]["new"] == pytest.approx(beta0 * 2)
    # spread over the loop's ticks, not applied at one sample (a tick without a new sample may
    # apply a second share at the same index)
    per_sample = collections.Counter(p["sample_index"] for p in params[:MAX_SETS_PER_MESSAGE])
    assert max(per_sample.values()) <= 3 * APPLY_PER_TICK < MAX_SETS_PER_MESSAGE


TOKEN = "b6f1c0de5a7e4d2c9f3a8b17e0d4c6a2"


def _wait_for(condition, seconds: float = 30.0) -> bool:
    """Whether ``condition()`` became true within ``seconds`` (polled every 20 ms)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def _closed_by_server(sock: socket.socket, seconds: float, since: float | None = None) -> float:
    """Seconds from ``since`` (monotonic, s; by default now) until the server closes ``sock``
    (a read returns b""); fails when it is still open after ``seconds``."""
    started = time.monotonic() if since is None else since
    sock.settimeout(seconds)
    try:
        data = sock.recv(1024)
    except socket.timeout:
        raise AssertionError(f"still open after {seconds} s") from None
    except ConnectionResetError:
        data = b""
    assert data == b"", data
    return time.monotonic() - started


def test_a_network_reachable_host_with_a_token_passes_and_a_weak_token_is_refused_unquoted():
    cfg = config_mod.validate({"live": {"host": "0.0.0.0", "token": TOKEN}})
    assert cfg.live["token"] == TOKEN and cfg.live["allow_remote_control"] is True
    assert cfg.live["max_connections"] == 16 and cfg.live["handshake_timeout_s"] == 5.0
    for weak in ("short1", "with spaces in the token!", "percent%20encoded-token-value"):
        with pytest.raises(ConfigError) as err:
            config_mod.validate({"live": {"host": "0.0.0.0", "token": weak}})
        message = str(err.value)
        assert message.startswith("live.token: ") and weak not in message and "\n" not in message


def test_without_the_token_a_client_gets_401_and_with_it_the_handshake_completes(tmp_path):
    run = live_service(tmp_path, live={"token": TOKEN})
    port = run.service.live.port

    async def refused(query: str) -> int:
        with pytest.raises(websockets.exceptions.InvalidStatus) as err:
            async with websockets.connect(f"ws://127.0.0.1:{port}/{query}", subprotocols=SUBPROTOCOLS,
                                          open_timeout=20):
                pass
        return err.value.response.status_code

    async def session():
        codes = [await refused(""), await refused("?token=" + TOKEN[:-1] + "0"), await refused("?token=")]
        async with websockets.connect(f"ws://127.0.0.1:{port}/?token={TOKEN}", subprotocols=SUBPROTOCOLS,
                                      open_timeout=20) as ws:
            first = json.loads(await asyncio.wait_for(ws.recv(), 10))
            return codes, ws.subprotocol, first

    try:
        codes, subprotocol, first = asyncio.run(session())
        counts = run.service.live.connections
    finally:
        run.stop()
    assert codes == [401, 401, 401]
    assert subprotocol == SUBPROTOCOLS[0] and first["op"] == "serverInfo" and "parameters" in first["capabilities"]
    assert counts["refused_token"] == 3 and counts["accepted"] == 1
    (path,) = (tmp_path / "logs").glob("*.mcap")
    assert not [d for _, _, _, d in MessageSource(path) if TOKEN.encode() in d]  # /config holds "<redacted>"


def test_the_token_is_taken_out_of_the_path_the_server_sees():
    from ahrs_service.live_front import token_in

    head = b"GET /x?a=1&token=" + TOKEN.encode() + b"&b=2 HTTP/1.1\r\nHost: h\r\n\r\n"
    assert token_in(head, TOKEN) == (True, b"GET /x?a=1&b=2 HTTP/1.1\r\nHost: h\r\n\r\n")
    assert token_in(b"GET /?token=" + TOKEN.encode() + b" HTTP/1.1\r\n\r\n", TOKEN) == (True, b"GET / HTTP/1.1\r\n\r\n")
    twice = b"GET /?token=" + TOKEN.encode() + b"&token=" + TOKEN.encode() + b" HTTP/1.1\r\n\r\n"
    assert token_in(twice, TOKEN)[0] is False
    assert token_in(b"garbage\r\n\r\n", TOKEN)[0] is False


def test_connections_beyond_the_cap_are_closed_at_once(tmp_path):
    """max_connections = 4: four idle sockets hold the four places, a fifth is closed as soon
    as it is accepted; once the idle ones close, a real client completes its handshake."""
    run = live_service(tmp_path, live={"max_connections": 4, "handshake_timeout_s": 60.0})
    port = run.service.live.port
    view = run.service.live
    idle: list[socket.socket] = []
    try:
        idle = [socket.create_connection(("127.0.0.1", port), timeout=10) for _ in range(4)]
        assert _wait_for(lambda: view.connections["open"] == 4), view.connections
        with socket.create_connection(("127.0.0.1", port), timeout=10) as fifth:
            closed_after_s = _closed_by_server(fifth, 10.0)
        for s in idle:
            s.close()
        assert _wait_for(lambda: view.connections["open"] == 0), view.connections

        async def session():
            async with _connect(port) as ws:
                return await _ops(ws, "serverInfo")

        info = asyncio.run(session())
        counts = view.connections
    finally:
        for s in idle:
            s.close()
        run.stop()
    assert closed_after_s < 5.0  # at once; well under the 60 s handshake timeout
    assert "parameters" in info["capabilities"]
    assert counts["refused_cap"] == 1 and counts["accepted"] == 1 and counts["handshake_timeouts"] == 0


def test_a_client_that_sends_no_request_is_closed_after_the_handshake_timeout(tmp_path):
    run = live_service(tmp_path, live={"handshake_timeout_s": 0.5})
    port = run.service.live.port
    try:
        connected_at = time.monotonic()  # the server accepts after this: its timeout cannot end sooner
        with socket.create_connection(("127.0.0.1", port), timeout=10) as silent, \
                socket.create_connection(("127.0.0.1", port), timeout=10) as halfway:
            halfway.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n")  # a head never finished
            silent_s = _closed_by_server(silent, 15.0, since=connected_at)
            halfway_s = _closed_by_server(halfway, 15.0, since=connected_at)
        counts = run.service.live.connections
    finally:
        run.stop()
    assert 0.5 <= silent_s < 10.0 and 0.5 <= halfway_s < 10.0
    assert counts["handshake_timeouts"] == 2 and counts["open"] == 0


def test_a_crowd_of_idle_sockets_leaves_room_for_a_real_client(tmp_path):
    """200 TCP connections that never start a handshake: those beyond the cap are closed at
    once, the others after the handshake timeout, and a real client then completes its
    handshake; the service stops promptly."""
    run = live_service(tmp_path, live={"handshake_timeout_s": 1.0})
    port = run.service.live.port
    idle: list[socket.socket] = []
    try:
        try:
            for _ in range(200):
                idle.append(socket.create_connection(("127.0.0.1", port), timeout=10))
            view = run.service.live
            assert _wait_for(lambda: view.connections["refused_cap"] + view.connections["handshake_timeouts"] == 200,
                             60.0), view.connections

            async def session():
                async with _connect(port) as ws:
                    return ws.subprotocol, await _ops(ws, "serverInfo")

            subprotocol, info = asyncio.run(session())
            assert run.thread.is_alive()
            counts = view.connections
        finally:
            stop_started = time.monotonic()
            run.stop()
            stop_s = time.monotonic() - stop_started
    finally:
        for s in idle:
            s.close()
    assert subprotocol == SUBPROTOCOLS[0] and "parameters" in info["capabilities"]
    # 16 places, freed 1 s after each idle socket took one: how many were taken depends on how
    # fast the 200 connected; the cap refused the rest
    assert counts["handshake_timeouts"] >= 16 and counts["refused_cap"] > 0 and counts["accepted"] == 1
    assert counts["handshake_timeouts"] + counts["refused_cap"] == 200
    assert stop_s < 10.0
