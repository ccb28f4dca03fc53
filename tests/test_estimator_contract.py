"""What every estimator promises (../shared/DESIGN.md): the same compiled step per sample and
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
