"""Calibration and mounting: sensor axes and errors in, body-frame truth out."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ahrs_service.core.calibration import SensorCalibration, apply_calibration, mounting_from_rpy_deg
from ahrs_service.core.samples import GYR_VALID, MAG_NEW, ImuSample
from ahrs_service.drivers.sim.clock import ManualClock
from ahrs_service.drivers.sim.imu import SimulatedImu
from ahrs_service.drivers.sim.motion import FigureEight
from ahrs_service.drivers.sim.sensor_model import SensorErrorModel
from ahrs_service.drivers.sim.source import SimulatedSource

# a sensor mounted rotated (roll 180°, yaw 90°, then a small extra tilt) with distortions that
# do not commute with the mounting, so applying them in the wrong order would not recover truth
MOUNT = mounting_from_rpy_deg(180.0, 3.0, 90.0)
GYR_BIAS = np.array([0.02, -0.015, 0.03])
ACC_BIAS = np.array([0.3, -0.2, 0.45])
ACC_DIST = np.array([[1.03, 0.01, -0.02], [0.004, 0.97, 0.015], [-0.01, 0.02, 1.01]])
MAG_HARD = np.array([15.0, -8.0, 25.0])
MAG_SOFT = np.array([[1.15, 0.06, -0.03], [0.06, 0.88, 0.04], [-0.03, 0.04, 1.02]])


def _distorted_imu(clock):
    models = {
        "gyr": SensorErrorModel(bias=GYR_BIAS),
        "acc": SensorErrorModel(
            bias=ACC_BIAS,
            scale_factor=np.diag(ACC_DIST),
            misalignment=ACC_DIST - np.diag(np.diag(ACC_DIST)),
        ),
        "mag": SensorErrorModel(hard_iron=MAG_HARD, soft_iron=MAG_SOFT),
    }
    return SimulatedImu(FigureEight(period=10.0), models, clock=clock, mounting=MOUNT)


def _hand_calibration() -> SensorCalibration:
    """The inverse of the synthetic errors, worked out here independently of the simulator."""
    # acc model (sensor_model docstring): x = (I + off)·diag(s)·a + b
    off = ACC_DIST - np.diag(np.diag(ACC_DIST))
    gain = (np.eye(3) + off) @ np.diag(np.diag(ACC_DIST))
    return SensorCalibration.from_dict(
        {
            "gyro_bias": GYR_BIAS.tolist(),
            "acc_bias": ACC_BIAS.tolist(),
            "acc_scale": np.linalg.inv(gain).tolist(),
            "mag_hard_iron": MAG_HARD.tolist(),
            "mag_soft_iron": np.linalg.inv(MAG_SOFT).tolist(),
            "mounting_rpy_deg": [180.0, 3.0, 90.0],
        }
    )


def test_mounting_and_calibration_recover_body_truth():
    clock = ManualClock()
    imu = _distorted_imu(clock)
    src = SimulatedSource(imu, rate_hz=50.0)
    cal = _hand_calibration()
    for _ in range(200):
        s = src.read()
        ph = imu.physics(s.t_ns * 1e-9)
        truth = ph["truth"]
        # the raw sample is far from the body truth …
        assert np.linalg.norm(s.acc - truth.specific_force_body) > 1.0
        body = apply_calibration(s, cal)
        # … and calibration then mounting bring it back
        np.testing.assert_allclose(body.gyr, truth.omega_body, atol=1e-12)
        np.testing.assert_allclose(body.acc, truth.specific_force_body, atol=1e-12)
        np.testing.assert_allclose(body.mag, truth.mag_body, atol=1e-11)
        clock.advance(0.02)


def test_simulator_ideal_calibration_matches_hand_inverse():
    imu = _distorted_imu(ManualClock())
    got, want = imu.ideal_calibration().to_dict(), _hand_calibration().to_dict()
    for key in want:
        np.testing.assert_allclose(got[key], want[key], atol=1e-12, err_msg=key)


def test_wrong_order_would_not_recover_truth():
    """Guards the documented order: M·A·(acc − b), not A·M·(acc − b) nor M·A·acc − b."""
    cal = _hand_calibration()
    clock = ManualClock(1.3)
    imu = _distorted_imu(clock)
    raw = imu.physics(1.3)
    truth = raw["truth"].specific_force_body
    swapped = cal.acc_scale @ cal.mounting @ (raw["acc"] - cal.acc_bias)
    late_bias = cal.mounting @ cal.acc_scale @ raw["acc"] - cal.acc_bias
    assert np.linalg.norm(swapped - truth) > 0.05
    assert np.linalg.norm(late_bias - truth) > 0.05


def test_sample_metadata_kept_and_input_untouched():
    cal = SensorCalibration(gyro_bias=[0.1, 0.0, 0.0], mounting=mounting_from_rpy_deg(0, 0, 90))
    gyr = np.array([1.1, 2.0, 3.0])
    s = ImuSample(
        t_ns=123,
        gyr=gyr,
        acc=np.array([0.0, 0.0, -9.81]),
        mag=None,
        flags=GYR_VALID | MAG_NEW,
        raw={"gyr": [1, 2, 3]},
        truth_q=np.array([1.0, 0.0, 0.0, 0.0]),
        temperature_c=31.5,
    )
    out = apply_calibration(s, cal)
    np.testing.assert_allclose(out.gyr, [-2.0, 1.0, 3.0], atol=1e-12)  # sensor x → body y
    assert out.mag is None
    assert (out.t_ns, out.flags, out.raw, out.temperature_c) == (123, GYR_VALID | MAG_NEW, {"gyr": [1, 2, 3]}, 31.5)
    assert out.truth_q is s.truth_q
    np.testing.assert_array_equal(s.gyr, [1.1, 2.0, 3.0])  # not modified in place


def test_identity_calibration_passes_sample_through():
    s = ImuSample(t_ns=1, gyr=np.ones(3), acc=np.array([0.0, 0.0, -9.81]))
    assert SensorCalibration().is_identity
    assert apply_calibration(s, SensorCalibration.from_dict({})) is s


@pytest.mark.parametrize(
    "rpy, sensor_x_in_body",
    [((0, 0, 90), (0, 1, 0)), ((180, 0, 0), (1, 0, 0)), ((0, 90, 0), (0, 0, -1)), ((0, 0, -90), (0, -1, 0))],
)
def test_mounting_from_rpy(rpy, sensor_x_in_body):
    m = mounting_from_rpy_deg(*rpy)
    np.testing.assert_allclose(m @ [1.0, 0.0, 0.0], sensor_x_in_body, atol=1e-15)
    assert np.linalg.det(m) == pytest.approx(1.0)


def test_roll_180_mounting_flips_y_and_z():
    np.testing.assert_array_equal(mounting_from_rpy_deg(180, 0, 0), np.diag([1.0, -1.0, -1.0]))


def test_dict_round_trip():
    cal = _hand_calibration()
    again = SensorCalibration.from_dict(cal.to_dict())
    for key, value in cal.to_dict().items():
        np.testing.assert_array_equal(again.to_dict()[key], value)
    assert set(cal.to_dict()) == {"gyro_bias", "acc_bias", "acc_scale", "mag_hard_iron", "mag_soft_iron", "mounting"}


@pytest.mark.parametrize(
    "config, key",
    [
        ({"gyro_bais": [0, 0, 0]}, "gyro_bais"),
        ({"gyro_bias": [0, 0]}, "gyro_bias"),
        ({"acc_bias": "0.1"}, "acc_bias"),
        ({"acc_scale": [[1, 0, 0], [0, 1, 0]]}, "acc_scale"),
        ({"mag_hard_iron": [0, math.nan, 0]}, "mag_hard_iron"),
        ({"mag_soft_iron": [[1, 0, 0], [0, 1, 0], [0, 0, 0]]}, "mag_soft_iron"),
        ({"mounting": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}, "mounting"),
        ({"mounting": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "mounting"),  # a reflection
        ({"mounting_rpy_deg": [0, 90]}, "mounting_rpy_deg"),
        ({"mounting_rpy_deg": [0, 0, 0], "mounting": np.eye(3).tolist()}, "mounting_rpy_deg"),
    ],
)
def test_bad_config_raises_naming_the_key(config, key):
    with pytest.raises(ValueError, match=key):
        SensorCalibration.from_dict(config)


def test_calibration_arrays_read_only():
    cal = SensorCalibration()
    with pytest.raises(ValueError):
        cal.gyro_bias[0] = 1.0


def test_gyro_bias_shift_removes_body_residual():
    cal = SensorCalibration(gyro_bias=[0.01, 0.0, 0.0], mounting=MOUNT)
    sensor_rate = np.array([0.05, -0.02, 0.04])
    s = ImuSample(t_ns=0, gyr=sensor_rate, acc=np.array([0.0, 0.0, -9.81]))
    residual = apply_calibration(s, cal).gyr  # what the service sees at rest
    shifted = cal.with_gyro_bias_shift(residual)
    np.testing.assert_allclose(apply_calibration(s, shifted).gyr, 0.0, atol=1e-15)
    np.testing.assert_array_equal(cal.gyro_bias, [0.01, 0.0, 0.0])  # the original is kept
    with pytest.raises(ValueError, match="residual_body"):
        cal.with_gyro_bias_shift([1.0, 2.0])
