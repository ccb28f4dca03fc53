"""A MAVLink destination given by a name that does not resolve (issue 14 re-probe).

`config --check` passed `udpout:` to an unresolvable host while `run` silently handed the name
to pymavlink, which then looked it up in the estimation loop for every frame. Now: `config
--check` warns in one line naming the key and exits 0; `run` keeps running, publishes on its
other links, resolves the name off the loop with back-off, says so once in the journal and by
STATUSTEXT on the links that work, counts what it could not send, and sends to the name once
it resolves. Real UDP sockets on 127.0.0.1 and pymavlink peers throughout; the resolver is
replaced only in the in-process test that makes a name resolve later.
"""

from __future__ import annotations

import socket
import subprocess
import time

import pytest

from ahrs_service.protocols.mavlink import endpoints
from ahrs_service.protocols.mavlink.component import MavlinkComponent
from tests.test_daemon import ahrs_service_command
from tests.test_service import collect, make_gcs

pytestmark = pytest.mark.timeout(180)

NOWHERE = "no-such-host.invalid"  # RFC 6761: never resolves


def _statustexts(gcs, seconds: float, until, chunks: dict[int, list[str]] | None = None) -> list[str]:
    """Reassembled STATUSTEXTs until ``until(texts)`` holds (at most ``seconds``); ``chunks``
    carries the parts of a chunked text over from one call to the next."""
    texts: list[str] = []
    chunks = {} if chunks is None else chunks
    end = time.monotonic() + seconds
    while time.monotonic() < end and not until(texts):
        m = gcs.recv_match(type="STATUSTEXT", blocking=True, timeout=0.05)
        if m is None:
            continue
        if m.id == 0:
            texts.append(m.text)
            continue
        chunks.setdefault(m.id, []).append(m.text)
        if len(m.text) < 50:
            texts.append("".join(chunks.pop(m.id)))
    return texts


def test_a_destination_that_resolves_later_gets_the_messages_from_then_on(monkeypatch):
    """The name fails three lookups, then resolves (to a real pymavlink peer): one warning, one
    'resolved' line, the unsent messages counted, HEARTBEAT reaching the peer afterwards, and
    the other link served all along."""
    late, late_port = make_gcs()
    other, other_port = make_gcs()
    calls = []

    def resolver(host: str) -> str:
        calls.append(host)
        if len(calls) <= 3:
            raise socket.gaierror(socket.EAI_AGAIN, "Temporary failure in name resolution")
        return "127.0.0.1"

    monkeypatch.setattr(endpoints, "resolve", resolver)
    monkeypatch.setattr(endpoints, "RESOLVE_RETRY_FIRST_S", 0.05)
    url = f"udpout:gcs.example:{late_port}"
    comp = MavlinkComponent([url, f"udpout:127.0.0.1:{other_port}"], rates={"HEARTBEAT": 50.0})
    try:
        texts: list[str] = []
        chunks: dict[int, list[str]] = {}
        got_late = []
        end = time.monotonic() + 30.0  # a bound for a hang
        while time.monotonic() < end and not got_late:
            comp.publish(time.monotonic_ns(), None)
            comp.poll(10)
            texts += _statustexts(other, 0.02, lambda t: False, chunks)
            m = late.recv_match(type="HEARTBEAT", blocking=False)
            if m is not None:
                got_late.append(m)
        texts += _statustexts(other, 5.0, lambda t: any("resolved" in x for x in t), chunks)
    finally:
        comp.close()
        late.close()
        other.close()
    assert got_late, "the late name never got a HEARTBEAT"
    assert calls == ["gcs.example"] * 4  # looked up by the resolver only, never again
    warned = [t for t in texts if "does not resolve" in t]
    resolved = [t for t in texts if "resolved to 127.0.0.1" in t]
    assert len(warned) == 1 and url in warned[0] and "Temporary failure in name resolution" in warned[0]
    assert len(resolved) == 1 and "after 4 attempts" in resolved[0]
    unsent = comp.stats.unresolved[url]
    assert unsent > 0 and f"{unsent} messages were not sent before" in resolved[0]
    assert comp.stats.send_errors[url] == 0  # not a failing link: a destination not known yet


def test_config_check_warns_and_run_keeps_publishing_on_the_other_link(tmp_path):
    gcs, port = make_gcs()
    cfg = tmp_path / "config.toml"
    cfg.write_text(f'[mavlink]\nendpoints = ["udpout:{NOWHERE}:14550", "udpout:127.0.0.1:{port}"]\n'
                   f'[log]\nenabled = false\n')
    check = subprocess.run(ahrs_service_command() + ["config", "--check", str(cfg)], capture_output=True, text=True,
                           timeout=120)
    assert check.returncode == 0, check.stderr
    err = check.stderr.strip()
    assert "\n" not in err and err.startswith("ahrs-service: warning: mavlink.endpoints[0]: ")
    assert f"host '{NOWHERE}' does not resolve now" in err and "run starts anyway" in err

    proc = subprocess.Popen(ahrs_service_command() + ["run", "--config", str(cfg), "--duration", "4"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    try:
        texts = _statustexts(gcs, 120.0, lambda t: any("does not resolve" in x for x in t))
        attitudes = collect(gcs, 30.0, until=lambda m: m.get_type() == "ATTITUDE")
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        gcs.close()
    assert proc.returncode == 0 and "Traceback" not in out, out
    assert any(f"'udpout:{NOWHERE}:14550': host '{NOWHERE}' does not resolve" in t for t in texts), texts
    assert attitudes and attitudes[-1].get_type() == "ATTITUDE"  # the other link publishes
    assert out.count("does not resolve") == 1, out  # one journal line, not one per frame or retry


def test_config_check_looks_at_the_autopilot_link_too():
    from ahrs_service import config as config_mod

    cfg = config_mod.validate({"source": {"type": "mavlink", "mavlink_connection": f"udpout:{NOWHERE}:14540"},
                               "mavlink": {"endpoints": ["udpout:127.0.0.1:14550"]}})
    (warning,) = config_mod.check_endpoint_hosts(cfg)
    assert warning.startswith(f"source.mavlink_connection: 'udpout:{NOWHERE}:14540': host '{NOWHERE}' does not resolve now")
    cfg = config_mod.validate({"source": {"type": "simulated_i2c", "mavlink_connection": f"udpout:{NOWHERE}:14540"}})
    assert config_mod.check_endpoint_hosts(cfg) == []  # not the source: not looked up


@pytest.mark.parametrize("url", [f"udpin:{NOWHERE}:14560", f"tcpin:{NOWHERE}:5760"])
def test_a_listening_address_that_does_not_resolve_is_refused_by_check_and_run(tmp_path, url):
    cfg = tmp_path / "config.toml"
    cfg.write_text(f'[mavlink]\nendpoints = ["{url}"]\n[log]\nenabled = false\n')
    check = subprocess.run(ahrs_service_command() + ["config", "--check", str(cfg)], capture_output=True, text=True,
                           timeout=120)
    run = subprocess.run(ahrs_service_command() + ["run", "--config", str(cfg), "--duration", "1"],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert check.returncode == 2 and run.returncode != 0, (check.stderr, run.stderr)
    assert check.stderr.strip() == (f"ahrs-service: configuration error: mavlink.endpoints[0]: {url!r}: host "
                                    f"'{NOWHERE}' does not resolve (Name or service not known); accepted: a local "
                                    f"address to listen on (0.0.0.0, 127.0.0.1, this computer's name)")
    assert "Traceback" not in run.stderr and run.stderr.strip().endswith("Name or service not known"), run.stderr


@pytest.mark.parametrize("url, warning", [
    (f"tcp:{NOWHERE}:5760", f"host '{NOWHERE}' does not resolve now (Name or service not known); run connects once at start"),
    ("/dev/ahrs-no-such-tty,57600", "serial device /dev/ahrs-no-such-tty does not exist now; run opens it once at start"),
])
def test_an_endpoint_run_opens_once_at_start_is_a_warning_of_check_and_an_error_of_run(tmp_path, url, warning):
    """`tcp:` connects and a serial device is opened once at start: check warns (the file is
    valid, the network or udev may not be ready yet), run refuses in one line (exit 1;
    systemd's Restart=on-failure starts it again)."""
    cfg = tmp_path / "config.toml"
    cfg.write_text(f'[mavlink]\nendpoints = ["{url}"]\n[log]\nenabled = false\n')
    check = subprocess.run(ahrs_service_command() + ["config", "--check", str(cfg)], capture_output=True, text=True,
                           timeout=120)
    run = subprocess.run(ahrs_service_command() + ["run", "--config", str(cfg), "--duration", "1"],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path)
    err = check.stderr.strip()
    assert check.returncode == 0 and "\n" not in err, check.stderr
    assert err.startswith(f"ahrs-service: warning: mavlink.endpoints[0]: {url!r}: {warning}"), err
    assert run.returncode == 1 and "Traceback" not in run.stderr, run.stderr
    assert run.stderr.strip().startswith(f"ahrs-service: cannot start: cannot open MAVLink endpoint {url!r}: ")
