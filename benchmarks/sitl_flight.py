"""A scripted ArduCopter SITL flight scored against the simulator's truth, and flights kept for evaluation.

    python benchmarks/sitl_flight.py [--odometry] [--wind] [--mag-motor MGAUSS_PER_A] [--out DIR]
    python benchmarks/sitl_flight.py --score DIR

ArduCopter SITL (``tests/sitl.py``: ``$AHRS_SITL_DIR`` or ``../shared/sitl``) streams
HIGHRES_IMU at 200 Hz to the service on its SERIAL2 (UDP on 127.0.0.1, ``[location]`` set to
SITL's home so that the published heading is against true north); a pymavlink ground station on
SERIAL0 flies it: wait for the EKF origin, GUIDED, arm, take off to 10 m, four yaw turns
(MAV_CMD_CONDITION_YAW), a 30 m box (SET_POSITION_TARGET_LOCAL_NED), land. The flight ends by
itself (at most ``FLIGHT_LIMIT_S`` after arming, then it lands). The ground station keeps
SIMSTATE (the true attitude) and ATTITUDE (EKF3's own) stamped with the host's monotonic clock
on receipt; the service stamps its samples in the same clock once TIMESYNC syncs.

Scoring (from arming to disarming): every estimator of the project is replayed over the
service's recorded samples (``ahrs_service.replay``, fresh start, the service's declination
added) and compared with SIMSTATE: roll, pitch and heading RMS, mean heading error (an offset)
and the heading RMS with that offset taken out; EKF3's ATTITUDE likewise. Then what the
default estimator's heading error is made of: the best time shift against the truth (the
residual latency), the drift of the error over the flight (an uncorrected gyro bias), and the
declination of SITL's simulated field as the magnetometer measured it (the raw field rotated by
the *true* attitude) against the declination the service used.

Options: ``--odometry`` has EKF3 fuse the service's ODOMETRY yaw (``VISO_TYPE 1``,
``EK3_SRC1_YAW 6``, ``rules = "ardupilot"``; without it EKF3 flies on its compass);
``--wind`` sets SITL's ``SIM_WIND_SPD/DIR/TURB``; ``--mag-motor`` sets ``SIM_MAG_MOT_X/Y/Z``
(a field proportional to the motor current, mGauss/A, in the body frame: a magnetic
disturbance in flight only). ``--out DIR`` keeps the flight: ``DIR/flight.mcap`` (the service's
log) and ``DIR/truth.npz`` (SIMSTATE, ATTITUDE, the armed interval, the declination, the
options); ``--score DIR`` re-scores kept flights (DIR, or every folder in it holding a
``truth.npz``) without SITL. Loopback only.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

#: ArduPilot's SITL home (tests/sitl.py HOME): latitude °, longitude °, altitude m
HOME_LAT, HOME_LON, HOME_ALT_M = -35.363261, 149.165230, 584.0
TAKEOFF_ALT_M = 10.0
#: absolute headings flown with MAV_CMD_CONDITION_YAW, degrees
YAW_TURNS_DEG = (90.0, 200.0, 330.0, 0.0)
YAW_RATE_DEG_S = 45.0
#: the box's corners, local NED metres from the EKF origin (10 m up)
BOX_NE_M = ((30.0, 0.0), (30.0, 30.0), (0.0, 30.0), (0.0, 0.0))
#: after arming the flight lands, whatever step it is at, once this has passed
FLIGHT_LIMIT_S = 180.0
#: the ground station gives up when SITL has not started by then, s
SITL_START_LIMIT_S = 600.0
#: the best time shift of an estimate against the truth is looked for within ± this, s
SHIFT_SEARCH_S = 0.2
WIND = {"SIM_WIND_SPD": 6.0, "SIM_WIND_DIR": 120.0, "SIM_WIND_TURB": 2.0}
#: SET_POSITION_TARGET_LOCAL_NED: position only (velocity, acceleration, yaw and yaw rate ignored)
POSITION_ONLY_MASK = 0b0000_1101_1111_1000
GUIDED, LAND = 4, 9


class GroundStation:
    """SERIAL0: asks for SIMSTATE and ATTITUDE at 50 Hz and the position at 10 Hz, keeps them
    with their host monotonic receive times, and sends the flight's commands."""

    def __init__(self, port: int) -> None:
        from pymavlink import mavutil

        self.port = port
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{self.port}", source_system=255, source_component=190)
        self.simstate: list[tuple[float, float, float, float]] = []  # (t s, roll, pitch, yaw rad)
        self.attitude: list[tuple[float, float, float, float]] = []
        self.texts: list[str] = []
        self.armed = False
        self.mode = -1
        self.ned = (math.nan, math.nan, math.nan)
        self.yaw_deg = math.nan
        self._send = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from pymavlink import mavutil

        ml = mavutil.mavlink
        wanted = ((ml.MAVLINK_MSG_ID_SIMSTATE, 20000), (ml.MAVLINK_MSG_ID_ATTITUDE, 20000),
                  (ml.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 100000))
        asked = 0.0
        while not self._stop.is_set():
            m = self.conn.recv_match(blocking=True, timeout=0.1)
            now = time.monotonic()
            # re-asked every 3 s: SITL forgets nothing, but the first requests may precede its link
            if now - asked > 3.0 and self.conn.target_system:
                for msg_id, interval_us in wanted:
                    self.command(ml.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)
                asked = now
            if m is None:
                continue
            kind = m.get_type()
            if kind == "SIMSTATE":
                self.simstate.append((now, float(m.roll), float(m.pitch), float(m.yaw)))
            elif kind == "ATTITUDE":
                self.attitude.append((now, float(m.roll), float(m.pitch), float(m.yaw)))
                self.yaw_deg = math.degrees(m.yaw)
            elif kind == "LOCAL_POSITION_NED":
                self.ned = (float(m.x), float(m.y), float(m.z))
            elif kind == "HEARTBEAT" and m.get_srcSystem() == 1 and m.get_srcComponent() == 1:
                self.armed = bool(m.base_mode & ml.MAV_MODE_FLAG_SAFETY_ARMED)
                self.mode = int(m.custom_mode)
            elif kind == "STATUSTEXT":
                self.texts.append(str(m.text))

    def command(self, command: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        with self._send:
            self.conn.mav.command_long_send(1, 1, command, 0, *p)

    def position_target(self, north_m: float, east_m: float, down_m: float) -> None:
        from pymavlink import mavutil

        with self._send:
            self.conn.mav.set_position_target_local_ned_send(
                0, 1, 1, mavutil.mavlink.MAV_FRAME_LOCAL_NED, POSITION_ONLY_MASK,
                north_m, east_m, down_m, 0, 0, 0, 0, 0, 0, 0, 0)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.conn.close()


def _heading_error_deg(a_deg: float, b_deg: float) -> float:
    return abs((a_deg - b_deg + 180.0) % 360.0 - 180.0)


def fly(gs: GroundStation, say) -> tuple[float, float]:
    """The scripted flight; returns the host monotonic times (s) of arming and disarming."""
    from pymavlink import mavutil

    from tests.sitl import wait_until

    ml = mavutil.mavlink
    # SITL starts once the service is up (its first start may compile for minutes)
    if not wait_until(lambda: gs.mode >= 0, SITL_START_LIMIT_S):
        raise RuntimeError(f"no HEARTBEAT from SITL within {SITL_START_LIMIT_S:.0f} s")
    if not wait_until(lambda: any("origin set" in t for t in gs.texts), 120.0):
        raise RuntimeError("EKF3 set no origin within 120 s (no GPS lock in SITL?)")
    say("EKF origin set; arming in GUIDED")
    armed_at = None
    end = time.monotonic() + 90.0
    while time.monotonic() < end and armed_at is None:
        gs.command(ml.MAV_CMD_DO_SET_MODE, ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED)
        gs.command(ml.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        if wait_until(lambda: gs.armed and gs.mode == GUIDED, 3.0):
            armed_at = time.monotonic()
    if armed_at is None:
        raise RuntimeError("not armed in GUIDED within 90 s: " + " | ".join(gs.texts[-5:]))
    deadline = armed_at + FLIGHT_LIMIT_S
    left = lambda: max(0.0, deadline - time.monotonic())  # noqa: E731
    gs.command(ml.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, TAKEOFF_ALT_M)
    if wait_until(lambda: -gs.ned[2] > TAKEOFF_ALT_M - 1.0, min(40.0, left())):
        say(f"at {-gs.ned[2]:.1f} m; yaw turns")
        for heading in YAW_TURNS_DEG:
            if gs.mode != GUIDED:  # a failsafe took over: it flies (lands) from here
                break
            gs.command(ml.MAV_CMD_CONDITION_YAW, heading, YAW_RATE_DEG_S, 0, 0)
            wait_until(lambda: _heading_error_deg(gs.yaw_deg, heading) < 3.0, min(15.0, left()))
            time.sleep(min(2.0, left()))  # a still moment after each turn
        say("box")
        for north, east in BOX_NE_M:
            if left() <= 0 or gs.mode != GUIDED:
                break
            gs.position_target(north, east, -TAKEOFF_ALT_M)
            wait_until(lambda: math.hypot(gs.ned[0] - north, gs.ned[1] - east) < 1.5, min(30.0, left()))
    say("landing" if gs.mode == GUIDED else f"landing (the autopilot left GUIDED for mode {gs.mode})")
    gs.command(ml.MAV_CMD_DO_SET_MODE, ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, LAND)
    if not wait_until(lambda: not gs.armed, 60.0):
        gs.command(ml.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)  # forced: the flight must end
        wait_until(lambda: not gs.armed, 5.0)
    return armed_at, time.monotonic()


def _ground_station(port: int, result: Path) -> None:
    """The ground station's process: flies, then saves what it received into ``result``."""
    say = lambda text: print(f"[{time.strftime('%H:%M:%S')}] {text}", file=sys.stderr, flush=True)  # noqa: E731
    gs = GroundStation(port)
    armed, error = (math.nan, math.nan), ""
    try:
        armed = fly(gs, say)
    except RuntimeError as exc:
        error = str(exc)
    finally:
        gs.close()
    np.savez(result, simstate=np.array(gs.simstate).reshape(-1, 4), attitude=np.array(gs.attitude).reshape(-1, 4),
             armed=np.array(armed), texts=np.array(gs.texts[-400:], dtype=str), error=np.array(error))


def record(out: Path, odometry: bool, wind: bool, mag_motor: float, say) -> None:
    """Runs SITL, the service and the flight; keeps ``out/flight.mcap`` and ``out/truth.npz``."""
    from ahrs_service.service import Service
    from tests.sitl import Sitl, service_beside, sitl_dir
    from tests.test_autopilot import free_udp_port

    if not (sitl_dir() / "arducopter").is_file():
        raise RuntimeError(f"ArduPilot SITL arducopter not found in {sitl_dir()} (set AHRS_SITL_DIR)")
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="sitl-flight-"))
    ground_port, service_port = free_udp_port(), free_udp_port()
    # the ground station flies and stamps the truth in a process of its own: in the service's
    # process its receive stamps waited for the interpreter lock, tens of milliseconds on a
    # loaded machine; forked before the service starts any thread
    ground = multiprocessing.get_context("fork").Process(
        target=_ground_station, args=(ground_port, work / "ground.npz"), daemon=True)
    ground.start()
    cfg = service_beside(service_port, free_udp_port(), work / "logs", estimator=None,
                         odometry={"rate_hz": 30.0, "rules": "ardupilot"} if odometry else None,
                         location={"latitude_deg": HOME_LAT, "longitude_deg": HOME_LON,
                                   "altitude_km": HOME_ALT_M / 1000.0})
    params: dict[str, float] = {}
    if odometry:
        params.update({"VISO_TYPE": 1, "EK3_SRC1_YAW": 6})
    if wind:
        params.update(WIND)
    if mag_motor:
        params.update({"SIM_MAG_MOT_X": mag_motor, "SIM_MAG_MOT_Y": mag_motor, "SIM_MAG_MOT_Z": mag_motor})
    service = Service(cfg, duration_s=FLIGHT_LIMIT_S + 300.0)
    service.start()
    loop = threading.Thread(target=service.run, daemon=True)
    loop.start()
    try:
        with Sitl("arducopter", work, {0: ground_port, 2: service_port}, params):
            ground.join(120.0 + 90.0 + FLIGHT_LIMIT_S + 90.0)  # SITL is up: the flight's own bounds
            declination = service.pipeline.declination_deg
            sync = service.source.autopilot_link.timesync
            odo = service.mavlink.odometry.stats if odometry else None
    finally:
        service.request_stop()
        loop.join(30)
        service.close()
        if ground.is_alive():
            ground.terminate()
    flown = np.load(work / "ground.npz") if (work / "ground.npz").is_file() else None
    if flown is None or str(flown["error"]):
        raise RuntimeError(f"the flight failed: {str(flown['error']) if flown is not None else 'no result'}")
    logs = sorted((work / "logs").glob("*.mcap"))
    if len(logs) != 1:
        raise RuntimeError(f"expected one service log in {work / 'logs'}, found {len(logs)}")
    shutil.copyfile(logs[0], out / "flight.mcap")
    meta = {"vehicle": "arducopter", "odometry": odometry, "wind": wind, "mag_motor_mgauss_per_a": mag_motor,
            "declination_deg": declination, "timesync_synced": bool(sync.synced),
            "odometry_sent": int(odo.sent) if odo else 0, "texts": [str(t) for t in flown["texts"]]}
    np.savez_compressed(out / "truth.npz", simstate=flown["simstate"], attitude=flown["attitude"],
                        armed=flown["armed"], meta=json.dumps(meta))
    shutil.rmtree(work, ignore_errors=True)


# ---------------------------------------------------------------------------------- scoring
def _euler(q: np.ndarray) -> np.ndarray:
    """(N, 3) ZYX roll, pitch, yaw (rad) of (N, 4) [w, x, y, z]."""
    w, x, y, z = q.T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1, 1))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=1)


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def _at(t_src: np.ndarray, angles: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``angles`` (N, 3 rad) sampled at ``t``: linear, heading unwrapped first; NaN outside."""
    out = np.full((t.shape[0], 3), np.nan)
    good = np.all(np.isfinite(angles), axis=1)
    ts, a = t_src[good], angles[good].copy()
    if ts.size < 2:
        return out
    a[:, 2] = np.unwrap(a[:, 2])
    inside = (t >= ts[0]) & (t <= ts[-1])
    for k in range(3):
        out[inside, k] = np.interp(t[inside], ts, a[:, k])
    return out


def _errors_deg(t_est: np.ndarray, est: np.ndarray, truth: np.ndarray, window: tuple[float, float],
                shift_s: float = 0.0) -> np.ndarray:
    """(M, 4) truth time (s) and roll, pitch, heading errors (°) at the truth's times inside
    ``window`` (s), the estimate taken ``shift_s`` later than the truth's stamp."""
    t = truth[:, 0]
    inside = (t >= window[0]) & (t <= window[1])
    e = np.degrees(_at(t_est, est, t[inside] + shift_s) - truth[inside, 1:4])
    e[:, 2] = _wrap_deg(e[:, 2])
    keep = np.all(np.isfinite(e), axis=1)
    return np.column_stack([t[inside][keep], e[keep]])


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a * a))) if a.size else math.nan


def _best_shift(t_est: np.ndarray, est: np.ndarray, truth: np.ndarray, window: tuple[float, float],
                columns: slice = slice(1, 3)) -> float:
    """The time shift (s) of the estimate that fits the truth best (roll and pitch unless
    ``columns`` says otherwise): its latency against the truth's stamps."""
    shifts = np.arange(-SHIFT_SEARCH_S, SHIFT_SEARCH_S + 1e-9, 0.005)
    cost = [_rms(_errors_deg(t_est, est, truth, window, s)[:, columns]) for s in shifts]
    return float(shifts[int(np.nanargmin(cost))])


def _measured_declination_deg(log, truth: np.ndarray, window: tuple[float, float]) -> float:
    """Median declination (°) of the field the magnetometer measured, turned into NED by the
    true attitude: what the field's heading reference is, free of any estimator."""
    t = log.t_ns.astype(np.float64) / 1e9
    mag = log.rows[:, 6:9]
    inside = (t >= window[0]) & (t <= window[1]) & np.all(np.isfinite(mag), axis=1)
    r, p, y = _at(truth[:, 0], truth[:, 1:4], t[inside]).T
    m = mag[inside]
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    # body FRD → NED by the ZYX rotation; only north and east are needed
    north = (cy * cp) * m[:, 0] + (cy * sp * sr - sy * cr) * m[:, 1] + (cy * sp * cr + sy * sr) * m[:, 2]
    east = (sy * cp) * m[:, 0] + (sy * sp * sr + cy * cr) * m[:, 1] + (sy * sp * cr - cy * sr) * m[:, 2]
    d = np.degrees(np.arctan2(east, north))
    d = d[np.isfinite(d)]
    return float(np.median(d)) if d.size else math.nan


def score(folder: Path) -> str:
    """The markdown table of one kept flight."""
    from ahrs_service import estimators
    from ahrs_service.estimators import offline
    from ahrs_service.logs.reader import read_log
    from ahrs_service.replay import replay

    kept = np.load(folder / "truth.npz")
    meta = json.loads(str(kept["meta"]))
    simstate, attitude = kept["simstate"], kept["attitude"]
    window = tuple(float(v) for v in kept["armed"])
    log = read_log(folder / "flight.mcap")
    t_log = log.t_ns.astype(np.float64) / 1e9
    decl = float(meta["declination_deg"])
    rows: list[tuple[str, np.ndarray, np.ndarray, bool]] = []
    for name in estimators.names():
        eul = _euler(replay(log, name, use_recorded_state=False))
        eul[:, 2] += math.radians(decl)
        rows.append((name, t_log, eul, offline.heading_observed(name, log.rows)))
    rows.append(("EKF3 (ATTITUDE)", attitude[:, 0], attitude[:, 1:4], True))
    lines = [
        f"flight: {folder} — {meta['vehicle']}, EKF3 yaw from {'our ODOMETRY' if meta['odometry'] else 'its compass'}"
        f"{', wind' if meta['wind'] else ''}"
        f"{', motor field %.0f mGauss/A' % meta['mag_motor_mgauss_per_a'] if meta['mag_motor_mgauss_per_a'] else ''}; "
        f"armed {window[1] - window[0]:.0f} s, {len(log)} samples, declination {decl:.3f}°",
    ]
    # a failsafe changes the flight (LAND mode ignores the box): say so beside its figures
    failsafes = [t for t in meta.get("texts", []) if "failsafe" in t.lower()]
    if failsafes:
        lines.append("autopilot: " + "; ".join(dict.fromkeys(failsafes)) + " — the script's flight was cut short")
    lines += [
        "",
        "| estimator | roll RMS (°) | pitch RMS (°) | heading RMS (°) | mean heading error (°) "
        "| heading RMS, offset removed (°) | best shift (ms) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, t, eul, has_heading in rows:
        e = _errors_deg(t, eul, simstate, window)[:, 1:]
        shift = _best_shift(t, eul, simstate, window)
        if has_heading:
            h = f"{_rms(e[:, 2]):.2f} | {np.mean(e[:, 2]):+.2f} | {_rms(e[:, 2] - np.mean(e[:, 2])):.2f}"
        else:
            h = "— | — | —"
        lines.append(f"| `{name}` | {_rms(e[:, 0]):.2f} | {_rms(e[:, 1]):.2f} | {h} | {1000 * shift:+.0f} |")
    # what the default estimator's heading error is made of
    robust = next(r for r in rows if r[0] == "robust")
    shift = _best_shift(robust[1], robust[2], simstate, window, slice(3, 4))
    e0 = _errors_deg(robust[1], robust[2], simstate, window)
    es = _errors_deg(robust[1], robust[2], simstate, window, shift)[:, 1:]
    drift = np.polyfit(e0[:, 0] - window[0], e0[:, 3], 1)[0] * 60.0 if e0.shape[0] > 10 else math.nan
    e0 = e0[:, 1:]
    ground = (simstate[0, 0], window[0] - 1.0)
    lines += [
        "",
        f"`robust`: heading RMS {_rms(e0[:, 2]):.2f}° at the recorded stamps, {_rms(es[:, 2]):.2f}° shifted by its "
        f"best heading fit {1000 * shift:+.0f} ms; heading error trend {drift:+.2f}°/min over the flight.",
        f"Field declination as measured through the true attitude: {_measured_declination_deg(log, simstate, ground):.3f}° "
        f"on the ground, {_measured_declination_deg(log, simstate, window):.3f}° armed; the service used {decl:.3f}°.",
    ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--odometry", action="store_true",
                    help="EKF3 fuses the service's ODOMETRY yaw (VISO_TYPE 1, EK3_SRC1_YAW 6)")
    ap.add_argument("--wind", action="store_true", help="SITL wind: %s" % ", ".join(f"{k} {v:g}" for k, v in WIND.items()))
    ap.add_argument("--mag-motor", type=float, default=0.0, metavar="MGAUSS_PER_A",
                    help="SITL's SIM_MAG_MOT_X/Y/Z: a body-frame field per ampere of motor current (default 0)")
    ap.add_argument("--out", type=Path, help="keep the flight in this folder (flight.mcap, truth.npz)")
    ap.add_argument("--score", type=Path, metavar="DIR", help="re-score kept flights in DIR without SITL")
    args = ap.parse_args()
    say = lambda text: print(f"[{time.strftime('%H:%M:%S')}] {text}", file=sys.stderr, flush=True)  # noqa: E731
    try:
        if args.score:
            folders = [args.score] if (args.score / "truth.npz").is_file() else sorted(
                p.parent for p in args.score.glob("*/truth.npz"))
            if not folders:
                raise SystemExit(f"error: {args.score}: no kept flight (truth.npz) in it or its folders")
            print("\n\n".join(score(f) for f in folders))
            return
        out = args.out or Path(tempfile.mkdtemp(prefix="sitl-flight-out-"))
        record(out, args.odometry, args.wind, args.mag_motor, say)
        say(f"flight kept in {out}")
        print(score(out))
    except (RuntimeError, OSError, ValueError) as exc:
        raise SystemExit(f"error: {exc}") from None
    except KeyError as exc:
        raise SystemExit(f"error: a kept flight's truth.npz lacks {exc}") from None


if __name__ == "__main__":
    main()
