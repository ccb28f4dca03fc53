"""Reference columns from peer libraries, converted into our convention so they score alike.

Every peer takes our inputs (gyr rad/s, acc m/s² specific force, mag µT, (N, 3), sensor axes)
and returns (N, 4) q_earth←sensor [w, x, y, z] against **NED** with north = magnetic north —
the same thing ``ahrs_service.estimators.run`` returns. Each library's earth frame and
quaternion meaning were determined on BROAD recordings (trial 02, slow rotation): of the six
candidates {NED, ENU, NWU} × {q_earth←sensor, its conjugate}, exactly one gives a small error,
every other one is off by far more (figures: docs/evaluation.md, "Peers and their frames").
What was found:

==============  ============================  ============================================
peer            inputs given                  output, and how it becomes q_ned←sensor
==============  ============================  ============================================
vqf             as ours (specific force)      q_enu←sensor; q_ned = q_ned←enu ⊗ q
vqf.offline     as ours (specific force)      as vqf (the library's own offline mode)
imufusion       deg/s, g; convention NWU      q_nwu←sensor; q_ned = q_ned←nwu ⊗ q
                (library default);
                ``IMUFUSION_SETTINGS``
ahrs.madgwick   as ours                       q_nwu←sensor (Madgwick's z-up frame)
ahrs.mahony     as ours                       q_enu←sensor
ahrs.aqua       as ours                       q_sensor←nwu: q_ned = q_ned←nwu ⊗ q*
ahrs.ekf        −acc (gravity direction),     q_ned←sensor (frame="NED")
                magnetic_ref = dip
ahrs.triad      w1 = −acc, v1 = (0, 0, 1),    q_sensor←ned: conjugated
                w2 = mag, v2 = (cos δ, 0, sin δ)
ahrs.quest      −acc, magnetic_dip = δ        q_ned←sensor
==============  ============================  ============================================

The ``ahrs`` package's EKF, TRIAD and QUEST match the accelerometer against gravity (0, 0, 1)
in NED, i.e. they expect the *gravity* direction where we measure specific force, hence the
sign flip. Those three and QUEST need the field's dip δ (their default is Munich's field from a
world model); like our QUEST, they get it from the first usable accelerometer/magnetometer
sample pair, so heading is against magnetic north.

q_ned←enu is 180° about (1, 1, 0)/√2 (``Q_NED_TO_ENU``, its own inverse); q_ned←nwu is 180°
about x.
"""

from __future__ import annotations

import importlib.util
import math
import warnings
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ahrs_service.core.quaternion import Q_NED_TO_ENU, quat_conj_array, quat_mul_array

#: q_ned←nwu: 180° about the north axis (x); its own inverse.
Q_NWU_TO_NED = np.array([0.0, 1.0, 0.0, 0.0])

_G = 9.80665


@dataclass(frozen=True)
class Peer:
    """One reference implementation: ``name`` as shown in tables, ``package`` its import name."""

    name: str
    package: str
    observes_heading: bool
    func: Callable[..., np.ndarray]
    description: str
    causal: bool = True  # False: the peer is itself an offline (forward-backward) method

    def available(self) -> bool:
        return importlib.util.find_spec(self.package) is not None

    def run(self, gyr: Any, acc: Any, mag: Any, *, rate_hz: float, **params: Any) -> np.ndarray:
        """(N, 4) q_ned←sensor for (N, 3) gyr rad/s, acc m/s² (specific force), mag µT.

        ``params`` go to the library unchanged (its own names, e.g. ``gain`` for ahrs.madgwick).
        """
        if not self.available():
            raise ModuleNotFoundError(f"peer {self.name!r} needs the package {self.package!r}")
        gyr, acc, mag = (np.ascontiguousarray(v, dtype=np.float64) for v in (gyr, acc, mag))
        if not (gyr.shape == acc.shape == mag.shape and gyr.ndim == 2 and gyr.shape[1] == 3):
            raise ValueError(f"gyr, acc, mag must all be (N, 3); got {gyr.shape}, {acc.shape}, {mag.shape}")
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        with warnings.catch_warnings():
            # the ahrs package warns about its default parameters; the values are ours to choose
            warnings.simplefilter("ignore")
            q = self.func(gyr, acc, mag, float(rate_hz), **params)
        q = np.asarray(q, dtype=np.float64).reshape(len(gyr), 4)
        return q / np.linalg.norm(q, axis=1, keepdims=True)


def field_dip_deg(acc: np.ndarray, mag: np.ndarray) -> float:
    """Dip of the field below the horizontal (deg, positive down) from the first usable sample pair."""
    ok = np.isfinite(acc).all(1) & np.isfinite(mag).all(1)
    ok &= (np.linalg.norm(acc, axis=1) > 1e-6) & (np.linalg.norm(mag, axis=1) > 1e-6)
    if not ok.any():
        raise ValueError("no usable accelerometer/magnetometer sample pair to take the field's dip from")
    i = int(np.argmax(ok))
    down = -acc[i] / np.linalg.norm(acc[i])
    m = mag[i] / np.linalg.norm(mag[i])
    return math.degrees(math.asin(float(np.clip(down @ m, -1.0, 1.0))))


# ------------------------------------------------------------------------------------ adapters


def _vqf(gyr, acc, mag, rate_hz, **params):
    from vqf import VQF

    est = VQF(1.0 / rate_hz, **params)
    if np.isnan(mag).all():
        # no magnetometer recorded (DIDO): VQF's 6D output, gyro and accelerometer only
        q_enu = est.updateBatch(gyr, acc)["quat6D"]
    else:
        q_enu = est.updateBatch(gyr, acc, mag)["quat9D"]
    return quat_mul_array(Q_NED_TO_ENU, q_enu)


def _vqf_offline(gyr, acc, mag, rate_hz, **params):
    # VQF's non-causal mode: forward and backward passes inside the library (bias, rest and
    # magnetic disturbance detection from both sides), the reference for our generic offline mode
    from vqf import offlineVQF

    q_enu = offlineVQF(gyr, acc, mag, 1.0 / rate_hz, **params)["quat9D"]
    return quat_mul_array(Q_NED_TO_ENU, q_enu)


#: Fusion's settings as its own README example uses them: gain 0.5, 2000 °/s gyro range,
#: 10° acceleration and magnetic rejection, 5 s recovery (in samples). The bare constructor
#: defaults switch rejection off, which leaves Fusion several times worse on our recordings,
#: worst on fast translation — not a fair reference (figures: docs/evaluation.md, "Peers and
#: their frames").
IMUFUSION_SETTINGS = {
    "gain": 0.5,
    "gyroscope_range": 2000.0,
    "acceleration_rejection": 10.0,
    "magnetic_rejection": 10.0,
    "rejection_timeout_s": 5.0,
}


def _imufusion(gyr, acc, mag, rate_hz, **params):
    import imufusion

    opts = {**IMUFUSION_SETTINGS, **params}
    opts["rejection_timeout"] = int(round(opts.pop("rejection_timeout_s") * rate_hz))
    settings = imufusion.AhrsSettings(sample_rate=rate_hz, **opts)
    ahrs = imufusion.Ahrs()
    ahrs.set_settings(settings)
    gyr_dps = np.degrees(gyr)
    acc_g = acc / _G
    out = np.empty((len(gyr), 4))
    for i in range(len(gyr)):
        ahrs.update(gyr_dps[i], acc_g[i], mag[i])
        out[i] = ahrs.get_quaternion()
    return quat_mul_array(Q_NWU_TO_NED, out)


def _ahrs_madgwick(gyr, acc, mag, rate_hz, **params):
    from ahrs.filters import Madgwick

    q_nwu = Madgwick(gyr=gyr, acc=acc, mag=mag, frequency=rate_hz, **params).Q
    return quat_mul_array(Q_NWU_TO_NED, q_nwu)


def _ahrs_mahony(gyr, acc, mag, rate_hz, **params):
    from ahrs.filters import Mahony

    q_enu = Mahony(gyr=gyr, acc=acc, mag=mag, frequency=rate_hz, **params).Q
    return quat_mul_array(Q_NED_TO_ENU, q_enu)


def _ahrs_aqua(gyr, acc, mag, rate_hz, **params):
    from ahrs.filters import AQUA

    q_sensor_nwu = AQUA(gyr=gyr, acc=acc, mag=mag, frequency=rate_hz, **params).Q
    return quat_mul_array(Q_NWU_TO_NED, quat_conj_array(q_sensor_nwu))


def _ahrs_ekf(gyr, acc, mag, rate_hz, **params):
    from ahrs.filters import EKF

    params.setdefault("magnetic_ref", field_dip_deg(acc, mag))
    return EKF(gyr=gyr, acc=-acc, mag=mag, frequency=rate_hz, frame="NED", **params).Q


def _ahrs_triad(gyr, acc, mag, rate_hz, **params):
    from ahrs.filters import TRIAD

    dip = math.radians(field_dip_deg(acc, mag))
    v2 = np.array([math.cos(dip), 0.0, math.sin(dip)])
    q = TRIAD(w1=-acc, w2=mag, v1=np.array([0.0, 0.0, 1.0]), v2=v2, representation="quaternion", frame="NED").A
    return quat_conj_array(q)


def _ahrs_quest(gyr, acc, mag, rate_hz, **params):
    from ahrs.filters import QUEST

    params.setdefault("magnetic_dip", field_dip_deg(acc, mag))
    return QUEST(acc=-acc, mag=mag, **params).Q


PEERS: dict[str, Peer] = {
    p.name: p
    for p in (
        Peer("vqf", "vqf", True, _vqf, "VQF (Laidig & Seel 2023), defaults, 9D output (6D without magnetometer), updateBatch"),
        Peer("vqf.offline", "vqf", True, _vqf_offline, "VQF's own offline (non-causal) mode, offlineVQF, defaults", False),
        Peer("imufusion", "imufusion", True, _imufusion, "Fusion AHRS (x-io), its README's example settings, per-sample"),
        Peer("ahrs.madgwick", "ahrs", True, _ahrs_madgwick, "ahrs package: Madgwick, MARG"),
        Peer("ahrs.mahony", "ahrs", True, _ahrs_mahony, "ahrs package: Mahony, MARG"),
        Peer("ahrs.ekf", "ahrs", True, _ahrs_ekf, "ahrs package: quaternion EKF, NED"),
        Peer("ahrs.aqua", "ahrs", True, _ahrs_aqua, "ahrs package: AQUA (Valenti et al.)"),
        Peer("ahrs.triad", "ahrs", True, _ahrs_triad, "ahrs package: TRIAD"),
        Peer("ahrs.quest", "ahrs", True, _ahrs_quest, "ahrs package: QUEST"),
    )
}

#: Selection names of the command line (``--peers``) → peers.
PACKAGES = {"vqf": ["vqf"], "imufusion": ["imufusion"], "ahrs": [n for n in PEERS if n.startswith("ahrs.")]}


def names() -> list[str]:
    """All peer names, installed or not."""
    return list(PEERS)


def select(spec: str | None) -> list[str]:
    """Peers for a ``--peers`` value: "all", "none", or comma-separated package or peer names.

    "all" keeps only installed packages; naming a package that is not installed raises.
    """
    spec = (spec or "none").strip()
    if spec == "none" or not spec:
        return []
    if spec == "all":
        return [n for n in PEERS if PEERS[n].available()]
    chosen: list[str] = []
    for part in (s.strip() for s in spec.split(",")):
        if not part:
            continue
        if part in PACKAGES:
            members = PACKAGES[part]
        elif part in PEERS:
            members = [part]
        else:
            raise ValueError(f"unknown peer {part!r}; choose from {', '.join([*PACKAGES, *PEERS])}, all or none")
        for m in members:
            if not PEERS[m].available():
                raise ModuleNotFoundError(f"peer {m!r} needs the package {PEERS[m].package!r}, which is not installed")
            if m not in chosen:
                chosen.append(m)
    return chosen


def run(name: str, gyr: Any, acc: Any, mag: Any, *, rate_hz: float, **params: Any) -> np.ndarray:
    """Runs peer ``name`` and returns (N, 4) q_ned←sensor [w, x, y, z] (see the module notes)."""
    try:
        peer = PEERS[name]
    except KeyError:
        raise ValueError(f"unknown peer {name!r}; available: {', '.join(PEERS)}") from None
    return peer.run(gyr, acc, mag, rate_hz=rate_hz, **params)
