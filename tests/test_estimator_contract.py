"""What every estimator promises (docs/design.md): the same compiled step per sample and
in batch, each sample's own dt, and a clear error for an unknown parameter."""

from __future__ import annotations

import numpy as np
import pytest

from ahrs_service import estimators
from ahrs_service.estimators.base import stack_rows
from analytic import constant_rotation

RATE = 200.0


@pytest.mark.parametrize("name", estimators.names())
def test_per_sample_and_batch_identical(name):
    q, gyr, acc, mag = constant_rotation([0.5, 0.2, -0.3], RATE, 3.0)
    rng = np.random.default_rng(1)
    acc = acc + rng.normal(0, 0.3, acc.shape)
    mag = mag + rng.normal(0, 1.0, mag.shape)
    mag[50:60] = np.nan  # no field for a while: the reduced form, then back
    dt = np.full(len(q), 1 / RATE) * (1 + 0.2 * np.sin(np.arange(len(q))))
    m = mag if estimators.get(name).uses_mag else None

    batch = estimators.create(name)
    out_batch = batch.run(gyr, acc, m, dt=dt)
    by_update = estimators.create(name)
    out_update = np.array(
        [by_update.update(gyr[i], acc[i], None if m is None else m[i], dt=dt[i]).copy() for i in range(len(q))]
    )
    by_row = estimators.create(name)
    out_row = np.array([by_row.update_row(r).copy() for r in stack_rows(gyr, acc, m, dt)])
    assert np.array_equal(out_batch, out_update)
    assert np.array_equal(out_batch, out_row)
    assert np.array_equal(batch.state, by_row.state)


@pytest.mark.parametrize("name", estimators.names())
def test_unknown_parameter_is_a_clear_error(name):
    with pytest.raises(ValueError, match=f"unknown parameter.*gain.*{name}"):
        estimators.create(name, gain=1.0)


@pytest.mark.parametrize("value", ["1.5", True, b"1"])
def test_a_parameter_value_that_is_not_a_number_is_refused_not_converted(value):
    """float() takes "1.5" and True; a parameter value of the wrong kind (a hand-edited log's
    /config, a script's typo) is refused with the parameter named (issue 14)."""
    est = estimators.create("madgwick")
    name = est.param_names()[0]
    with pytest.raises(ValueError, match=f"parameter '{name}' of estimator 'madgwick' must be a number, got"):
        estimators.create("madgwick", **{name: value})
    with pytest.raises(ValueError, match="must be a number"):
        est.set_params(**{name: value})
    assert estimators.create("madgwick", **{name: np.float32(0.5)}).get_params()[name] == 0.5  # NumPy numbers are numbers


@pytest.mark.parametrize("name", estimators.names())
def test_identity_until_the_first_usable_accelerometer_sample(name):
    """Every estimator starts the same way (_kernel.initialise_from_sample): nothing is
    integrated before the attitude can be set from the sensors."""
    q, gyr, acc, mag = constant_rotation([0.5, 0.2, -0.3], RATE, 1.0)
    acc = acc.copy()
    acc[:20] = np.nan  # the gyro turns, the accelerometer has nothing yet
    m = mag if estimators.get(name).uses_mag else None
    out = estimators.create(name).run(gyr, acc, m, dt=1 / RATE)
    assert np.array_equal(out[:20], np.tile([1.0, 0.0, 0.0, 0.0], (20, 1)))
    assert not np.allclose(out[20], [1.0, 0.0, 0.0, 0.0])  # started from the 21st sample


def test_changed_kernel_sources_drop_the_cached_kernels(tmp_path, monkeypatch):
    """numba checks only the defining file's time stamp; the package checks all the sources
    its kernels are compiled from (ahrs_service/estimators/_cache.py)."""
    from ahrs_service.estimators import _cache

    cache = tmp_path / "__pycache__"
    cache.mkdir()
    src = tmp_path / "inlined.py"
    src.write_text("x = 1\n")
    monkeypatch.setattr(_cache, "_SOURCES", [src])
    monkeypatch.setattr(_cache, "cache_dir", lambda: cache)
    (cache / "k.step-1.py311.nbi").write_bytes(b"index")
    (cache / "k.step-1.py311.1.nbc").write_bytes(b"code")
    assert _cache.drop_stale_kernels()  # no stamp yet: the cache cannot be trusted
    assert not list(cache.glob("*.nb?"))
    (cache / "k.step-1.py311.nbi").write_bytes(b"index")
    assert not _cache.drop_stale_kernels()  # same sources: the cache stays
    assert (cache / "k.step-1.py311.nbi").exists()
    src.write_text("x = 2\n")  # an inlined helper changed
    assert _cache.drop_stale_kernels()
    assert not (cache / "k.step-1.py311.nbi").exists()
