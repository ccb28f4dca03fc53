"""One MAVLink link (UDP, TCP, serial) opened from a pymavlink connection string.

pymavlink's ``mavutil`` opens the link; this module adds what a long-running service needs:

* the link's parser is always a MAVLink 2 ``common`` parser (see ``dialect``), whatever
  dialect ``mavutil`` was set to globally;
* send errors are seen and counted — ``mavutil`` swallows socket errors on UDP and TCP, so the
  port object is wrapped in a tap that notes them before ``mavutil`` drops them;
* each UDP datagram is parsed on its own: bytes of a truncated message left at the end of a
  datagram are discarded (and reported), instead of being glued to the next datagram and
  spoiling the good message in it.

* a ``udpin`` link sends to its *peers*: addresses that sent a well-formed MAVLink frame (a
  datagram of garbage or a bad CRC makes nobody a peer), each forgotten ``PEER_TIMEOUT_S``
  after its last frame, at most ``MAX_PEERS`` of them. At the cap a new one replaces the
  least recently heard peer that has sent one frame only, or failing that one silent for
  ``PEER_STALE_S``; when every peer is an established one (two frames or more) heard within
  ``PEER_STALE_S``, the newcomer is not served (``refused``). So one-datagram senders cost
  nothing lasting and a flood of new addresses cannot push out a ground station that
  beats at 1 Hz. mavutil on its own sends every frame to every address that ever sent a
  datagram and never forgets one, so anyone able to reach the port could load the loop without
  limit.

* a ``udpout``/``udpbcast`` destination given by name is resolved off the loop, by
  :class:`HostResolver`'s thread, retried with back-off while it does not resolve (a companion
  that starts at boot before DNS is up keeps running and publishing on its other links);
  until then its frames are counted (``unresolved``), not sent. mavutil on its own resolves
  the name in the loop thread at the first write, and after a failure hands the name to
  ``sendto`` — a blocking DNS lookup for every frame, in the estimation loop.

Connection strings (mavutil's): ``udpout:HOST:PORT`` (send to a listener such as
QGroundControl on 14550), ``udpin:HOST:PORT`` (listen; replies go to the peers above —
nothing is sent before a peer has spoken), ``tcp:HOST:PORT``, ``tcpin:HOST:PORT``,
``/dev/ttyUSB0,921600`` (serial device, baud).
"""

from __future__ import annotations

import errno
import hashlib
import ipaddress
import socket
import threading
import time
from collections import OrderedDict
from typing import Any, Sequence

from pymavlink import mavutil

from ahrs_service.protocols.mavlink.dialect import mavlink

_STREAM_READ = 4096  # bytes per read on TCP/serial
_UDP_MAX = 65535  # bytes per datagram
PEER_TIMEOUT_S = 10.0  # a udpin peer silent this long is forgotten (ground stations beat at 1 Hz)
MAX_PEERS = 16  # udpin peers served at once
#: at the cap, an established peer (two frames or more) silent this long may be replaced by a
#: new one; a ground station beating at 1 Hz never is
PEER_STALE_S = 3.0


#: first retry of a name that did not resolve, s; each later one twice the last, at most
#: RESOLVE_RETRY_MAX_S (mavlink-router retries a TCP endpoint it could not open every 5 s)
RESOLVE_RETRY_FIRST_S = 1.0
RESOLVE_RETRY_MAX_S = 30.0


def destination_host(url: str) -> tuple[str, int] | None:
    """(HOST, PORT) of an endpoint that sends to a remote host (``udpout``, ``udpbcast``,
    ``tcp``); None for listening endpoints and serial devices."""
    scheme, sep, rest = url.partition(":")
    if not sep or scheme not in ("udpout", "udpbcast", "tcp"):
        return None
    host, _, port = rest.rpartition(":")
    return (host, int(port)) if host and port.isdigit() else None


def resolve(host: str) -> str:
    """The IPv4 address of ``host`` (mavutil's sockets are AF_INET); raises OSError
    (``socket.gaierror``) when it does not resolve. Blocks as long as the system resolver."""
    return socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_DGRAM)[0][4][0]


def is_numeric(host: str) -> bool:
    try:
        ipaddress.IPv4Address(host)
    except ValueError:
        return False
    return True


class HostResolver:
    """Resolves one destination name on a thread of its own, retrying with back-off
    (``RESOLVE_RETRY_FIRST_S`` doubling to ``RESOLVE_RETRY_MAX_S``) until it resolves; the
    loop only reads :attr:`address` (None until then). ``attempts``: lookups made;
    ``last_error``: the resolver's text for the last failure. ``resolve_fn`` (tests) stands in
    for :func:`resolve`."""

    def __init__(self, host: str, resolve_fn: Any = None) -> None:
        self.host = host
        self.address: str | None = None
        self.attempts = 0
        self.last_error = ""
        self._resolve = resolve_fn or resolve
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"resolve {host}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        delay = RESOLVE_RETRY_FIRST_S
        while not self._stop.is_set():
            self.attempts += 1
            try:
                self.address = self._resolve(self.host)
                return
            except OSError as exc:
                self.last_error = getattr(exc, "strerror", None) or str(exc)
            self._stop.wait(delay)
            delay = min(RESOLVE_RETRY_MAX_S, 2.0 * delay)

    def close(self) -> None:
        self._stop.set()


class UdpPeers:
    """The addresses a ``udpin`` link sends to, most recently heard last (see module docstring).

    Time is the monotonic clock in ns, passed in (tests drive it)."""

    def __init__(self, timeout_s: float = PEER_TIMEOUT_S, max_peers: int = MAX_PEERS,
                 stale_s: float = PEER_STALE_S) -> None:
        self.timeout_ns = int(timeout_s * 1e9)
        self.stale_ns = int(stale_s * 1e9)
        self.max_peers = int(max_peers)
        self._last: OrderedDict[Any, int] = OrderedDict()  # address -> last frame, oldest first
        self._frames: dict[Any, int] = {}  # address -> frames heard (capped at 2: "established")
        self.expired = 0  # peers forgotten after their timeout
        self.evicted = 0  # peers replaced by a newer one while at the cap
        self.refused = 0  # frames from new addresses not served: every slot held by a live peer

    def heard(self, addr: Any, now_ns: int) -> None:
        """A well-formed frame came from ``addr``."""
        if addr in self._last:
            self._last.move_to_end(addr)
            self._frames[addr] = 2
            self._last[addr] = now_ns
            return
        if len(self._last) >= self.max_peers:
            self.live(now_ns)  # the expired ones first: replacing them evicts nobody
        if len(self._last) >= self.max_peers:
            victim = next((a for a, t in self._last.items()
                           if self._frames[a] < 2 or now_ns - t >= self.stale_ns), None)
            if victim is None:
                self.refused += 1
                return
            del self._last[victim], self._frames[victim]
            self.evicted += 1
        self._last[addr] = now_ns
        self._frames[addr] = 1

    def live(self, now_ns: int) -> set:
        """The peers heard within the timeout (older ones are forgotten now)."""
        while self._last:
            addr, t = next(iter(self._last.items()))
            if now_ns - t <= self.timeout_ns:
                break
            self._last.popitem(last=False)
            del self._frames[addr]
            self.expired += 1
        return set(self._last)

    def __len__(self) -> int:
        return len(self._last)


class _Parser(mavlink.MAVLink):
    """pymavlink's MAVLink 2 parser with one fix for signed links.

    pymavlink records a stream's replay timestamp before it compares the signature, so a single
    forged packet with a far-future timestamp would lock the real sender of that
    (link, system, component) stream out. Here the signature is checked first.
    """

    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:
        key = self.signing.secret_key
        if key is None or hashlib.sha256(bytes(key) + bytes(msgbuf[:-6])).digest()[:6] != bytes(msgbuf[-6:]):
            return False
        return super().check_signature(msgbuf, srcSystem, srcComponent)


class _SendErrorTap:
    """Stands in for a connection's socket or serial port and counts write errors, which
    mavutil catches and discards. Everything else passes straight through."""

    _WRITES = ("send", "sendto", "sendall", "write")

    def __init__(self, inner: Any, endpoint: "Endpoint") -> None:
        object.__setattr__(self, "_inner", inner)
        object.__setattr__(self, "_endpoint", endpoint)

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._inner, name)
        if name not in self._WRITES:
            return attr

        def counted(*args: Any, **kwargs: Any) -> Any:
            try:
                return attr(*args, **kwargs)
            except Exception as exc:
                self._endpoint.note_send_error(exc)
                raise

        object.__setattr__(self, name, counted)  # found directly from now on: one wrapper per name
        return counted

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._inner, name, value)


def _check_udp_port_free(url: str) -> None:
    """For a listening UDP endpoint (``udpin:``, ``udp:``): raises OSError(EADDRINUSE) when
    another socket holds its port. mavutil binds with SO_REUSEADDR, with which a second service
    started on the same port (or any program) binds it too and silently takes the datagrams
    meant for the first; a bind without it fails while the port is taken."""
    scheme, _, rest = url.partition(":")
    if scheme not in ("udpin", "udp"):
        return
    host, _, port = rest.rpartition(":")
    if not port.isdigit():
        return  # mavutil reports it
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((host, int(port)))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise OSError(errno.EADDRINUSE, f"UDP port {port} is in use by another program "
                              f"(another ahrs-service?)") from None
            # anything else (an address that is not ours …) is mavutil's to report


def check_can_open(urls: Sequence[str], system_id: int, component_id: int) -> None:
    """Opens each of ``urls`` and closes it again: raises the OSError of :class:`Endpoint`
    (``cannot open MAVLink endpoint 'URL': why``) for the first that cannot be opened (an
    address this computer does not have, a port another process holds, a device that is no
    serial port, a refused TCP connection). A reload checks the endpoints it adds before it
    closes the running ones, so that one it cannot open leaves the running links as they are."""
    for url in urls:
        Endpoint(url, system_id, component_id).close()


class Endpoint:
    """A pymavlink connection with a MAVLink 2 common parser/packer and error counters."""

    def __init__(self, url: str, system_id: int, component_id: int) -> None:
        self.url = url
        try:
            _check_udp_port_free(url)
            # one connection attempt, no sleeping between retries: the service loop must not stall
            conn = mavutil.mavlink_connection(url, source_system=system_id, source_component=component_id,
                                              autoreconnect=True, retries=0, reconnect_delay=0)
        except Exception as exc:
            raise OSError(f"cannot open MAVLink endpoint {url!r}: {exc}") from exc
        self.conn = conn
        # a parser/packer of our own dialect and version, independent of mavutil's global one
        conn.mav = _Parser(conn, srcSystem=system_id, srcComponent=component_id)
        conn.mav.robust_parsing = True  # bad bytes become BAD_DATA messages instead of exceptions
        conn.WIRE_PROTOCOL_VERSION = "2.0"
        conn.first_byte = False  # no auto-switching of the protocol version on the first byte
        self.datagram = isinstance(conn, (mavutil.mavudp, mavutil.mavmcast))
        # udpin: this class reads the socket and keeps the peers; mavutil only sends to them
        self.peers: UdpPeers | None = UdpPeers() if getattr(conn, "udp_server", False) else None
        self._from: Any = None  # address of the datagram being parsed (udpin)
        if self.peers is not None:
            conn.timeout = 0  # mavutil's own expiry off: conn.clients is set from self.peers
            conn.clients = set()
        # udpout/udpbcast to a name: resolved by a thread; until then frames are not sent
        self.resolver: HostResolver | None = None
        self.unresolved = 0  # messages not sent: the destination's name did not resolve yet
        self._resolution_reported = False  # "does not resolve" said once; "resolved" once after
        dest = destination_host(url)
        if dest is not None and isinstance(conn, mavutil.mavudp) and not is_numeric(dest[0]):
            self.resolver = HostResolver(dest[0])
        self.send_errors = 0
        self.receive_errors = 0
        self.truncated = 0
        self.last_send_error = ""
        self._errors_before = 0

    @property
    def mav(self) -> "mavlink.MAVLink":
        return self.conn.mav

    # ------------------------------------------------------------------ sending
    def note_send_error(self, exc: BaseException) -> None:
        self.send_errors += 1
        self.last_send_error = f"{type(exc).__name__}: {exc}"

    def _tap_port(self) -> None:
        # TCP reconnects replace the port object, so check before every write
        port = getattr(self.conn, "port", None)
        if port is not None and not isinstance(port, _SendErrorTap):
            self.conn.port = _SendErrorTap(port, self)

    def send_many(self, msgs: Sequence[Any]) -> bool:
        """Packs ``msgs`` (each its own sequence number) and writes them back to back in one
        write — on UDP one datagram, which MAVLink parsers (pymavlink, QGroundControl,
        autopilots) split like a stream; False on any error — never raises. ``send_errors``
        counts the messages lost, every message of a failed write."""
        before = self.send_errors
        if self.peers is not None:
            self.conn.clients = self.peers.live(time.monotonic_ns())
        if self.resolver is not None and not self._destination_known():
            self.unresolved += len(msgs)
            return True  # not an error of the link: counted apart, reported by resolution_news
        try:
            self._tap_port()
            mav = self.conn.mav
            packed = []
            for msg in msgs:
                packed.append(msg.pack(mav))
                mav.seq = (mav.seq + 1) % 256
            result = self.conn.write(packed[0] if len(packed) == 1 else b"".join(packed))
        except Exception as exc:
            if self.send_errors == before:
                self.note_send_error(exc)
            result = -1
        if result == -1 and self.send_errors == before:  # mavserial's way of saying "failed"
            self.note_send_error(OSError("write failed"))
        if self.send_errors == before:
            return True
        self.send_errors = before + len(msgs)
        return False

    def _destination_known(self) -> bool:
        """Whether the resolver has an address; the first time, hands it to mavutil as the
        destination (so that mavutil never resolves the name itself)."""
        address = self.resolver.address  # type: ignore[union-attr]
        if address is None:
            return False
        if self.conn.destination_addr[0] != address:
            self.conn.destination_addr = (address, self.conn.destination_addr[1])
            self.conn.resolved_destination_addr = address  # mavutil's "already resolved"
        return True

    def resolution_news(self) -> str | None:
        """One line when there is news of the destination's name (None otherwise): once when
        its first lookups failed, once when it resolves after that. Called by the component
        from its poll, which reports it (journal, STATUSTEXT on the other links)."""
        r = self.resolver
        if r is None:
            return None
        if r.address is None:
            if self._resolution_reported or not r.last_error:
                return None
            self._resolution_reported = True
            return (f"MAVLink endpoint {self.url!r}: host {r.host!r} does not resolve ({r.last_error}); "
                    f"retrying, its messages are not sent meanwhile")
        if self._resolution_reported:
            self._resolution_reported = False
            return (f"MAVLink endpoint {self.url!r}: host {r.host!r} resolved to {r.address} after "
                    f"{r.attempts} attempts; {self.unresolved} messages were not sent before")
        return None

    # ------------------------------------------------------------------ receiving
    def read(self) -> bytes:
        """Bytes available now (one datagram on UDP); b"" when none. Never raises."""
        try:
            self._tap_port()
            if self.peers is not None:
                data = self._recv_udpin()
            else:
                data = self.conn.recv() if self.datagram else self.conn.recv(_STREAM_READ)
        except Exception:
            self.receive_errors += 1
            return b""
        if not data:
            return b""
        return bytes(data) if not isinstance(data, str) else data.encode("latin-1")

    def _recv_udpin(self) -> bytes:
        # mavutil's recv would add every sender to its clients for good: read the socket here
        try:
            data, self._from = self.conn.port.recvfrom(_UDP_MAX)
        except (BlockingIOError, InterruptedError, ConnectionRefusedError):
            return b""
        return data

    def parse(self, data: bytes) -> Any:
        """Feeds ``data`` to the parser and returns the first complete message (or None);
        call again with b"" for the rest. On udpin, a well-formed message makes its sender a
        peer."""
        msg = self.conn.mav.parse_char(data)
        if self.peers is not None and msg is not None and self._from is not None and msg.get_type() != "BAD_DATA":
            self.peers.heard(self._from, time.monotonic_ns())
        return msg

    def reset_parser(self) -> None:
        """Forgets any partly received message."""
        mav = self.conn.mav
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2

    def end_of_datagram(self) -> int:
        """Drops the unparsed tail of a datagram; returns how many bytes were dropped."""
        left = self.conn.mav.buf_len()
        if left:
            self.reset_parser()
            self.truncated += 1
        return left

    def close(self) -> None:
        if self.resolver is not None:
            self.resolver.close()
        try:
            self.conn.close()
        except Exception:
            pass
