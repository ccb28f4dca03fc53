"""What ArduPilot's EKF3 does with a step in the heading the service publishes.

    python benchmarks/sitl_heading_step.py [--step 10] [--viso-yaw-m-nse 0.05] [--after 45]

ArduCopter SITL (``tests/sitl.py``: ``$AHRS_SITL_DIR`` or ``../shared/sitl``) on the ground,
fusing the service's ODOMETRY yaw (``VISO_TYPE 1``, ``EK3_SRC1_YAW 6``, ``rules =
"ardupilot"``, docs/autopilot.md). Once EKF3 says "yaw aligned" and 20 s have passed, the
service's declination goes up by ``--step`` degrees — what a new declination or a re-accepted
magnetometer does to the published heading — and the autopilot's heading (ATTITUDE, 20 Hz) is
followed for ``--after`` seconds. Prints the autopilot's heading change at fixed times after the
step, its peak beyond the step (the overshoot), when it last was more than 0.5° from the step,
and the service's own heading change over the same time (the estimate's slow drift, for
reference). Loopback only; the run ends by itself.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from ahrs_service.core.quaternion import quat_to_euler  # noqa: E402
from tests.sitl import GroundStation, Sitl, binary, service_beside, wait_until  # noqa: E402
from tests.test_autopilot import free_udp_port  # noqa: E402

REPORT_AT_S = (1, 2, 3, 5, 8, 12, 17, 25, 35, 44)


def _wrap(a: np.ndarray | float) -> np.ndarray | float:
    return (a + 180.0) % 360.0 - 180.0


def run(step_deg: float, yaw_noise_rad: float, after_s: float, workdir: Path) -> dict:
    from ahrs_service.service import Service

    binary("arducopter")
    ground = GroundStation({"ATTITUDE": 20.0})  # EKF3's attitude
    service_port = free_udp_port()
    cfg = service_beside(service_port, free_udp_port(), workdir / "logs", estimator=None,
                         odometry={"rate_hz": 30.0, "rules": "ardupilot"})
    service = Service(cfg, duration_s=after_s + 240.0)
    service.start()
    loop = threading.Thread(target=service.run, daemon=True)
    loop.start()
    ours: list[tuple[float, float]] = []

    def follow(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            ours.append((time.monotonic(), math.degrees(quat_to_euler(service.mavlink.latest().q)[2])))
            time.sleep(0.05)

    params = {"VISO_TYPE": 1, "EK3_SRC1_YAW": 6, "VISO_YAW_M_NSE": yaw_noise_rad}
    try:
        with Sitl("arducopter", workdir, {0: ground.port, 2: service_port}, params):
            if not wait_until(lambda: any("yaw aligned" in t for t in ground.texts), 120.0):
                raise SystemExit("EKF3 never aligned its yaw on the service's ODOMETRY")
            follow(20.0)
            t_step = time.monotonic()
            service.pipeline.set_declination(service.pipeline.declination_deg + step_deg)
            follow(after_s)
            resets = service.mavlink.odometry.stats.resets
    finally:
        service.request_stop()
        loop.join(30)
        service.close()
        ground.close()
    ap = np.array([(t, math.degrees(m.yaw)) for t, m in ground.received["ATTITUDE"]])
    own = np.array(ours)
    before = lambda a: np.median(a[(a[:, 0] > t_step - 10) & (a[:, 0] < t_step), 1])  # noqa: E731
    post = ap[ap[:, 0] >= t_step]
    change = _wrap(post[:, 1] - before(ap))
    off = np.nonzero(np.abs(change - step_deg) > 0.5)[0]
    own_after = own[own[:, 0] >= t_step + after_s - 1.0, 1]
    return {
        "at": {s: float(change[np.searchsorted(post[:, 0], t_step + s)]) for s in REPORT_AT_S
               if np.searchsorted(post[:, 0], t_step + s) < len(post)},
        "overshoot": float((change - step_deg).max() if step_deg > 0 else (step_deg - change).max()),
        "settled_s": float(post[off[-1], 0] - t_step) if len(off) else 0.0,
        "own_drift": float(_wrap(np.median(own_after) - before(own)) - step_deg),
        "resets": resets,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step", type=float, default=10.0, help="heading step, degrees (default 10)")
    ap.add_argument("--viso-yaw-m-nse", type=float, default=0.05, help="ArduPilot's VISO_YAW_M_NSE, rad (default 0.05)")
    ap.add_argument("--after", type=float, default=45.0, help="seconds followed after the step (default 45)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="sitl-step-") as tmp:
        r = run(args.step, args.viso_yaw_m_nse, args.after, Path(tmp))
    print(f"heading step {args.step:+.1f}° (VISO_YAW_M_NSE {args.viso_yaw_m_nse} rad); ODOMETRY reset_counter +{r['resets']}")
    print("| t after step (s) | " + " | ".join(str(s) for s in r["at"]) + " |")
    print("|---|" + "---:|" * len(r["at"]))
    print("| autopilot heading change (°) | " + " | ".join(f"{v:+.2f}" for v in r["at"].values()) + " |")
    print(f"overshoot {r['overshoot']:+.2f}°; last beyond ±0.5° of the step at {r['settled_s']:.1f} s; "
          f"the service's own heading moved {r['own_drift']:+.2f}° beyond the step meanwhile")


if __name__ == "__main__":
    main()
