import math

import numpy as np
import pytest

from ahrs_service.core import quaternion as Q


def random_quats(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_scalar_and_array_products_agree():
    a, b = random_quats(50, 1), random_quats(50, 2)
    arr = Q.quat_mul_array(a, b)
    for i in range(50):
        assert np.allclose(Q.quat_mul(tuple(a[i]), tuple(b[i])), arr[i])


def test_rotation_matches_matrix_and_inverse():
    q = random_quats(20)
    v = np.random.default_rng(3).normal(size=(20, 3))
    R = Q.quat_to_matrix_array(q)
    assert np.allclose(Q.quat_rotate_array(q, v), np.einsum("nij,nj->ni", R, v))
    for i in range(20):
        back = Q.quat_rotate_inv(tuple(q[i]), Q.quat_rotate(tuple(q[i]), tuple(v[i])))
        assert np.allclose(back, v[i])


def test_euler_round_trip_and_yaw_range():
    rng = np.random.default_rng(4)
    e = np.column_stack([rng.uniform(-3, 3, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(-3, 3, 200)])
    q = Q.quat_from_euler_array(e)
    assert np.allclose(Q.euler_from_quat_array(q), e)
    for i in range(5):
        assert np.allclose(Q.quat_to_euler(Q.quat_from_euler(*e[i])), e[i])
    assert Q.quat_to_euler(Q.quat_from_euler(0.0, 0.0, math.pi))[2] == pytest.approx(math.pi)


def test_matrix_to_quaternion_all_branches():
    q = random_quats(200, 5)
    R = Q.quat_to_matrix_array(q)
    for i in range(200):
        qi = np.array(Q.quat_from_matrix(*R[i].ravel()))
        assert min(np.abs(qi - q[i]).max(), np.abs(qi + q[i]).max()) < 1e-9


def test_ned_to_enu_maps_axes():
    # north (x_N) becomes ENU y, east becomes ENU x, down becomes −z
    q_id = np.array([[1.0, 0, 0, 0]])
    q_enu = Q.ned_to_enu_array(q_id)
    v = Q.quat_rotate_array(q_enu, np.array([[1.0, 2.0, 3.0]]))
    assert np.allclose(v, [[2.0, 1.0, -3.0]])


def test_gravity_and_field_initialiser():
    # level, facing east: specific force (0, 0, -g); the field points north and down in earth,
    # so the body (x = east) sees it along -y and +z
    q = Q.quat_from_gravity_and_field(0.0, 0.0, -9.81, 0.0, -20.0, 40.0, True)
    roll, pitch, yaw = Q.quat_to_euler(q)
    assert (roll, pitch) == pytest.approx((0.0, 0.0), abs=1e-12)
    assert yaw == pytest.approx(math.pi / 2)
    # upside down, no field: roll = π
    q = Q.quat_from_gravity_and_field(0.0, 0.0, 9.81, 0.0, 0.0, 0.0, False)
    assert abs(Q.quat_to_euler(q)[0]) == pytest.approx(math.pi)


def test_rotation_vector_round_trip_shortest_way_and_nan():
    q = random_quats(200, 4)
    r = Q.quat_to_rotvec_array(q)
    assert np.linalg.norm(r, axis=1).max() <= math.pi + 1e-12  # the shortest way
    back = Q.quat_from_rotvec_array(r)
    assert np.allclose(np.abs(np.sum(back * q, axis=1)), 1.0)  # the same rotation (q or −q)
    np.testing.assert_allclose(Q.quat_to_rotvec_array(-q), r, atol=1e-12)
    tiny = Q.quat_from_rotvec_array(np.array([[1e-14, -2e-14, 3e-14]]))
    np.testing.assert_allclose(Q.quat_to_rotvec_array(tiny), [[1e-14, -2e-14, 3e-14]], rtol=1e-9)
    assert np.isnan(Q.quat_to_rotvec_array([np.nan, 0.0, 0.0, 0.0])).all()
