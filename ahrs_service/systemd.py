"""systemd ``Type=notify`` support without a dependency: READY, WATCHDOG, STATUS, STOPPING,
EXTEND_TIMEOUT_USEC (while kernels compile, see ``ahrs_service.kernels``).

The protocol is one datagram per notification to the AF_UNIX socket named in
``$NOTIFY_SOCKET`` (a leading ``@`` means the abstract namespace). ``$WATCHDOG_USEC`` tells
how often systemd expects ``WATCHDOG=1``; we ping at half that interval, from the estimation
loop itself so that a stalled loop stops the pings and systemd restarts the service.
"""

from __future__ import annotations

import os
import socket


class Notifier:
    """Sends sd_notify messages; does nothing when not started by systemd."""

    def __init__(self, environ: dict[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self._address = env.get("NOTIFY_SOCKET") or None
        self._sock: socket.socket | None = None
        if self._address:
            if self._address.startswith("@"):
                self._address = "\0" + self._address[1:]
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            # never block the estimation loop on a reader that stopped reading
            self._sock.setblocking(False)
        usec = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        enabled = usec is not None and usec.isdigit() and int(usec) > 0
        if pid and pid.isdigit() and int(pid) != os.getpid():
            enabled = False
        #: interval between WATCHDOG=1 pings in ns (0 when systemd asked for none)
        self.watchdog_interval_ns = int(usec) * 1000 // 2 if enabled else 0
        self.errors = 0

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, message: str) -> None:
        if self._sock is None:
            return
        try:
            self._sock.sendto(message.encode(), self._address)
        except OSError:  # systemd gone or its queue full (EAGAIN): never stop estimating for this
            self.errors += 1

    def ready(self, status: str = "") -> None:
        self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def watchdog(self) -> None:
        self.notify("WATCHDOG=1")

    def status(self, text: str) -> None:
        self.notify(f"STATUS={text}")

    def extend_timeout(self, seconds: float) -> None:
        """Asks for ``seconds`` more before the start (reload, stop) times out, counted from
        now; to be repeated before they run out (systemd ≥ 236; older ones ignore it)."""
        self.notify(f"EXTEND_TIMEOUT_USEC={int(seconds * 1e6)}")

    def reloading(self) -> None:
        self.notify("RELOADING=1")

    def stopping(self) -> None:
        self.notify("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
