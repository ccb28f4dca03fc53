"""Secrets are never written down: the MAVLink signing key (and any ``token``, ``password`` …)
stays out of a flight log's /config, a replayed log, STATUSTEXT and the journal.

The service runs in a background thread with a signing key, a real MCAP log and a pymavlink
ground station on 127.0.0.1; a reload to a file whose key is mistyped is refused on MAVLink
and in the journal without quoting it. An older log holding a key in clear is replayed
without copying it.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path

import pytest
from mcap.writer import CompressionType, Writer

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from ahrs_service import config as config_mod  # noqa: E402
from ahrs_service.cli import main  # noqa: E402
from ahrs_service.logs.reader import MessageSource, read_log  # noqa: E402
from ahrs_service.logs.redaction import REDACTED, redact_config, redact_text  # noqa: E402
from ahrs_service.logs.schemas import CHANNELS, schema_bytes  # noqa: E402
from ahrs_service.service import Service  # noqa: E402

pytestmark = pytest.mark.timeout(180)

KEY_HEX = "5e" * 32
MISTYPED = "zz" + "5e" * 31  # not hexadecimal: the checker's error would quote it


def _texts_of(path: Path) -> list[bytes]:
    """Every message of the log at ``path``, decompressed (what anyone reading it can see)."""
    return [data for _, _, _, data in MessageSource(path)]


def test_redaction_covers_the_signing_key_and_any_token_at_any_depth():
    cfg = {"mavlink": {"signing_key": KEY_HEX, "endpoints": ["udpout:127.0.0.1:14550"]},
           "live": {"token": "open-sesame", "host": "127.0.0.1"}, "other": [{"api_token": "t0k3n"}],
           "off": {"signing_key": ""}}
    out = redact_config(cfg)
    assert out["mavlink"] == {"signing_key": REDACTED, "endpoints": ["udpout:127.0.0.1:14550"]}
    assert out["live"]["token"] == REDACTED and out["other"] == [{"api_token": REDACTED}]
    assert out["off"]["signing_key"] == ""  # no key: "signing off" stays readable
    assert cfg["mavlink"]["signing_key"] == KEY_HEX  # the caller's own is not changed
    assert redact_text(f"got {KEY_HEX!r}", [KEY_HEX]) == f"got {REDACTED!r}"


def test_the_signing_key_is_in_no_log_statustext_or_journal_line(tmp_path, caplog):
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255, source_component=190)
    gcs.mav = mavlink2.MAVLink(gcs, srcSystem=255, srcComponent=190)
    gcs.mav.robust_parsing = True
    port = gcs.port.getsockname()[1]
    cfg_file = tmp_path / "ahrs.toml"
    text = (f'[source]\ntype = "simulated_i2c"\nsensor_errors = false\n\n[estimator]\nname = "madgwick"\n\n'
            f'[mavlink]\nendpoints = ["udpout:127.0.0.1:{port}"]\nsigning_key = "{{key}}"\n\n'
            f'[log]\ndirectory = "{tmp_path / "logs"}"\n')
    cfg_file.write_text(text.format(key=KEY_HEX))
    caplog.set_level(logging.INFO)
    svc = Service(config_mod.load(cfg_file), duration_s=120.0)
    svc.start()
    thread = threading.Thread(target=svc.run, daemon=True)
    thread.start()
    statustexts: list[str] = []
    try:
        deadline = time.monotonic() + 60
        seen_attitude = False
        while time.monotonic() < deadline and not seen_attitude:
            m = gcs.recv_match(blocking=True, timeout=0.1)
            seen_attitude = m is not None and m.get_type() == "ATTITUDE"
        assert seen_attitude
        cfg_file.write_text(text.format(key=MISTYPED))
        svc.request_reload()
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not any("reload refused" in t for t in statustexts):
            m = gcs.recv_match(blocking=True, timeout=0.1)
            if m is not None and m.get_type() == "STATUSTEXT":
                statustexts.append(m.text)
        refused = [t for t in statustexts if "reload refused" in t]
        assert refused and "signing_key" in refused[0] and MISTYPED not in refused[0], refused
    finally:
        svc.request_stop()
        thread.join(10)
        svc.close()
        gcs.close()
    journal = "\n".join(r.getMessage() for r in caplog.records)
    assert "reload refused: mavlink.signing_key" in journal and REDACTED in journal
    assert KEY_HEX not in journal and MISTYPED not in journal and "5e5e5e5e" not in journal
    (log_path,) = sorted((tmp_path / "logs").glob("*.mcap"))
    log = read_log(log_path)
    assert log.configs and all(c["config"]["mavlink"]["signing_key"] == REDACTED for c in log.configs)
    assert not [d for d in _texts_of(log_path) if b"5e5e5e5e" in d]  # /config, /log, anything


def test_the_live_token_is_redacted_in_the_flight_logs_config(tmp_path):
    token = "f00dfeedc0ffee11deadbeef22cafe33"
    cfg_file = tmp_path / "ahrs.toml"
    cfg_file.write_text(f'[source]\ntype = "simulated_i2c"\n\n[estimator]\nname = "madgwick"\n\n'
                        f'[mavlink]\nendpoints = ["udpout:127.0.0.1:9"]\n\n[live]\ntoken = "{token}"\n\n'
                        f'[log]\ndirectory = "{tmp_path / "logs"}"\n')
    svc = Service(config_mod.load(cfg_file), duration_s=0.5)
    svc.start()
    try:
        svc.run()
    finally:
        svc.close()
    (log_path,) = sorted((tmp_path / "logs").glob("*.mcap"))
    log = read_log(log_path)
    assert log.configs and all(c["config"]["live"]["token"] == REDACTED for c in log.configs)
    assert not [d for d in _texts_of(log_path) if token.encode() in d]


def _old_log(path: Path, key: str) -> Path:
    """A log as an earlier version wrote it: the signing key in clear in /config."""
    config = {"estimator": {"name": "madgwick", "params": {"beta": 0.1}},
              "mavlink": {"signing_key": key, "endpoints": ["udpout:127.0.0.1:14550"]}}
    raw = {"dt": 0.005, "gyr": [0.0, 0.0, 0.0], "acc": [0.0, 0.0, -9.81], "mag": [20.0, 0.0, 40.0], "flags": 7}
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        ch = {t: w.register_channel(t, "json", w.register_schema(CHANNELS[t][0], "jsonschema", schema_bytes(t)))
              for t in ("/config", "/imu/raw")}
        w.add_message(ch["/config"], 0, json.dumps({"t_ns": 0, "config": config, "reason": "start"}).encode(), 0)
        for i in range(50):
            t = (i + 1) * 5_000_000
            w.add_message(ch["/imu/raw"], t, json.dumps({**raw, "t_ns": t, "index": i}).encode(), t)
        w.finish()
    return path


def test_a_replay_of_an_old_log_with_a_clear_key_does_not_copy_it(tmp_path, capsys):
    old = _old_log(tmp_path / "old.mcap", KEY_HEX)
    assert read_log(old).config["mavlink"]["signing_key"] == KEY_HEX  # what the old writer left
    rc = main(["replay", str(old), "--out", str(tmp_path / "new.mcap"), "--json"])
    out = capsys.readouterr()
    assert rc == 0 and KEY_HEX not in out.out + out.err
    new = read_log(tmp_path / "new.mcap")
    assert len(new) == 50 and new.config["mavlink"]["signing_key"] == REDACTED
    assert not [d for d in _texts_of(tmp_path / "new.mcap") if KEY_HEX.encode() in d]
