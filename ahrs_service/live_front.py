"""The live view's front door: a TCP listener in front of the Foxglove SDK's WebSocket server.

The SDK's server accepts every TCP connection, waits for its upgrade request for ever and
gives the service no look at a client's URL or headers. So the SDK listens on a private
loopback port and this front listens where the configuration says. For each connection it:

1. closes it at once when ``max_connections`` are open already;
2. reads the HTTP upgrade request's head, closing a client that has not sent a complete one
   within ``handshake_timeout_s``;
3. when a token is configured, requires it as the query parameter ``token`` of the request
   path (``ws://host:8765/?token=…``), compared in constant time; a missing or wrong token is
   answered ``401 Unauthorized`` and closed;
4. connects to the SDK's port, forwards the head (the token taken out of the path) and pipes
   the bytes both ways until either side closes.

The front runs an asyncio loop on one daemon thread; it never touches the estimator.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import threading
import time
from typing import Any
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

log = logging.getLogger("ahrs_service.live")

#: the longest request head the front reads, bytes (a browser's upgrade request is under 2 KiB)
MAX_HEAD_BYTES = 16384
#: bytes read at a time while piping
CHUNK_BYTES = 65536
#: at most one warning this often per kind of refused connection, s (the counters count every one)
WARNING_PERIOD_S = 5.0
#: how long starting and stopping the front's thread may take, s
THREAD_WAIT_S = 5.0
UNAUTHORIZED = (b"HTTP/1.1 401 Unauthorized\r\nContent-Length: 0\r\nConnection: close\r\n"
                b"WWW-Authenticate: Bearer realm=\"ahrs-service live view\"\r\n\r\n")
BAD_REQUEST = b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"


class FrontUnavailable(OSError):
    """The front cannot listen (address in use, unknown host …); the message says why."""


def token_in(request_head: bytes, token: str) -> tuple[bool, bytes]:
    """Whether the request path of ``request_head`` carries exactly one ``token`` query
    parameter equal to ``token`` (constant-time comparison), and the head with every ``token``
    parameter taken out of the path. A head whose request line cannot be parsed: (False, head)."""
    line_end = request_head.find(b"\r\n")
    parts = request_head[:line_end].split(b" ")
    if line_end < 0 or len(parts) != 3:
        return False, request_head
    method, target, version = parts
    try:
        url = urlsplit(target.decode("ascii"))
    except UnicodeDecodeError:
        return False, request_head
    query = parse_qsl(url.query, keep_blank_values=True)
    given = [value for name, value in query if name == "token"]
    ok = len(given) == 1 and hmac.compare_digest(given[0].encode("utf-8"), token.encode("utf-8"))
    kept = urlunsplit(url._replace(query=urlencode([(n, v) for n, v in query if n != "token"])))
    return ok, b" ".join((method, (kept or "/").encode("ascii"), version)) + request_head[line_end:]


class LiveFront:
    """Listens on ``host:port`` and hands the admitted connections to ``127.0.0.1:upstream_port``.

    max_connections: connections open at once (waiting for their request head or piped);
        one more is closed as soon as it is accepted.
    handshake_timeout_s: how long a client has to send its complete request head, s.
    token: the query parameter ``token`` every client must send; "" admits every client.

    Counters (read from any thread): ``accepted`` (handed to the server), ``refused_cap``,
    ``refused_token``, ``handshake_timeouts`` and ``malformed`` (no parsable request head).
    """

    def __init__(self, host: str, port: int, upstream_port: int, max_connections: int = 16,
                 handshake_timeout_s: float = 5.0, token: str = "") -> None:
        self.host = host
        self.upstream_port = upstream_port
        self.max_connections = max_connections
        self.handshake_timeout_s = handshake_timeout_s
        self._token = token
        self.accepted = 0
        self.refused_cap = 0
        self.refused_token = 0
        self.handshake_timeouts = 0
        self.malformed = 0
        self.open = 0  # connections open now
        self._warned_at: dict[str, float] = {}
        self._transports: set[asyncio.BaseTransport] = set()
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.AbstractServer | None = None
        self._started = threading.Event()
        self._start_error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(port,), name="live-view-front", daemon=True)
        self._thread.start()
        if not self._started.wait(THREAD_WAIT_S):
            raise FrontUnavailable(f"not listening after {THREAD_WAIT_S:.0f} s")
        if self._start_error is not None:
            raise FrontUnavailable(str(self._start_error)) from None
        assert self._server is not None
        self.port: int = self._server.sockets[0].getsockname()[1]

    def stats(self) -> dict[str, int]:
        """The connection counters (see the class)."""
        return {"open": self.open, "accepted": self.accepted, "refused_cap": self.refused_cap,
                "refused_token": self.refused_token, "handshake_timeouts": self.handshake_timeouts,
                "malformed": self.malformed}

    def close(self) -> None:
        """Stops listening and closes every connection (theirs to the server too)."""
        if self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(THREAD_WAIT_S)

    # ---------------------------------------------------------------- front thread
    def _run(self, port: int) -> None:
        asyncio.set_event_loop(self._loop)
        self._loop.set_exception_handler(self._loop_fault)
        try:
            self._server = self._loop.run_until_complete(
                asyncio.start_server(self._serve, self.host, port, limit=MAX_HEAD_BYTES))
        except (OSError, ValueError) as exc:
            self._start_error = exc
            self._started.set()
            self._loop.close()
            return
        self._started.set()
        try:
            self._loop.run_forever()
        finally:
            self._server.close()
            for transport in list(self._transports):
                transport.abort()
            tasks = asyncio.all_tasks(self._loop)
            for task in tasks:
                task.cancel()
            self._loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
            self._loop.close()

    def _loop_fault(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """asyncio's report of a fault it survived (``accept`` out of descriptors, a connection's
        unexpected error): one line, rate-limited, instead of asyncio's traceback."""
        exc = context.get("exception")
        self._warn("fault", "live view: front: %s%s", context.get("message", "fault"), f": {exc}" if exc else "")

    def _warn(self, kind: str, message: str, *args: Any) -> None:
        now = time.monotonic()
        if now - self._warned_at.get(kind, -WARNING_PERIOD_S) >= WARNING_PERIOD_S:
            self._warned_at[kind] = now
            log.warning(message, *args)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        if self.open >= self.max_connections:
            self.refused_cap += 1
            writer.close()
            self._warn("cap", "live view: connection from %s refused: %d connections open "
                       "(live.max_connections)", peer, self.open)
            return
        self.open += 1
        self._transports.add(writer.transport)
        upstream: asyncio.StreamWriter | None = None
        try:
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), self.handshake_timeout_s)
            except asyncio.TimeoutError:
                self.handshake_timeouts += 1
                self._warn("timeout", "live view: connection from %s closed: no request within %.1f s "
                           "(live.handshake_timeout_s)", peer, self.handshake_timeout_s)
                return
            except asyncio.LimitOverrunError:
                self.malformed += 1
                writer.write(BAD_REQUEST)
                return
            except (asyncio.IncompleteReadError, ConnectionError):
                return  # the client left before its request was complete
            if self._token:
                ok, head = token_in(head, self._token)
                if not ok:
                    self.refused_token += 1
                    writer.write(UNAUTHORIZED)
                    self._warn("token", "live view: connection from %s refused: missing or wrong token "
                               "(live.token)", peer)
                    return
            try:
                up_reader, upstream = await asyncio.wait_for(
                    asyncio.open_connection("127.0.0.1", self.upstream_port), self.handshake_timeout_s)
            except (OSError, asyncio.TimeoutError) as exc:
                self._warn("upstream", "live view: cannot reach the WebSocket server on 127.0.0.1:%d: %s",
                           self.upstream_port, exc)
                return
            self._transports.add(upstream.transport)
            self.accepted += 1
            upstream.write(head)
            await asyncio.gather(_pipe(reader, upstream), _pipe(up_reader, writer))
        finally:
            self.open -= 1
            for w in (writer, upstream):
                if w is not None:
                    self._transports.discard(w.transport)
                    w.close()


async def _pipe(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
    """Copies ``source`` to ``sink`` until ``source`` ends, then closes ``sink`` (which ends the
    other direction too: its peer sees the close)."""
    try:
        while chunk := await source.read(CHUNK_BYTES):
            sink.write(chunk)
            await sink.drain()
    except (ConnectionError, OSError):
        pass
    finally:
        sink.close()
