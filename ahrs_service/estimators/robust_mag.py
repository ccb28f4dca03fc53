"""Magnetic part of the robust estimator (``robust.py``): gyro consistency, hard-iron
learning with change detection, and the gated heading-offset filter.

An undisturbed field with a body-fixed (hard-iron) offset h obeys R_g(t)(m(t) − h) = const
in the gyro frame I. Block means (``block_time``) ȳ = mean(R_g m), R̄ = mean(R_g) therefore
satisfy Δȳ = ΔR̄ h between consecutive blocks: linear in h (least squares with forgetting),
and whatever Δȳ the rotation and ĥ do not explain is a field that changed in I — the
gyro-consistency statistic. The heading offset δ follows VQF eq. 11–12 (D. Laidig, T. Seel,
Information Fusion 91, 2023), written for NED: δ turns the field's horizontal part onto north.

Credit: the heading filter, the norm/dip disturbance test, the rejection clock and new-field
acceptance (with the start-up confirmation, VQF's magNewFirstTime) in ``heading`` follow
VQF's reference implementation (github.com/dlaidig/vqf, vqf/cpp/vqf.cpp, MIT, © 2021 Daniel
Laidig; notice in THIRD_PARTY_NOTICES). The project's own: ``hard_iron_and_consistency``
(gyro consistency, hard-iron least squares, offset-change detection), the veto after an
offset change and the choice of the corrected field in ``heading``, and ``mag_rot_rate``.
"""

from __future__ import annotations

import math

from numba import njit

from ahrs_service.core.quaternion import quat_rotate
from ahrs_service.estimators import robust_blocks as B
from ahrs_service.estimators.robust_layout import DEG, ST, P
from ahrs_service.estimators.robust_layout import HI_SCRATCH as HS

_jit = njit(cache=True, inline="always")

@_jit
def hard_iron_and_consistency(s, p, x, dt, r):
    """Block means of R_g m and R_g; their block-to-block changes feed the hard-iron least
    squares Δȳ = ΔR̄ h and the gyro-consistency statistic (the part of Δȳ not explained).

    ``r`` is R_g = R(q_g), I←S, row-major."""
    mx, my, mz = x[6], x[7], x[8]
    s[ST.hi_sum_m] += r[0] * mx + r[1] * my + r[2] * mz
    s[ST.hi_sum_m + 1] += r[3] * mx + r[4] * my + r[5] * mz
    s[ST.hi_sum_m + 2] += r[6] * mx + r[7] * my + r[8] * mz
    for k in range(9):
        s[ST.hi_sum_r + k] += r[k]
    s[ST.hi_n] += 1.0
    if s[ST.hi_t] < p[P.block_time]:
        return
    inv_n = 1.0 / s[ST.hi_n]
    # block mean; the sums are then restarted (the previous block's mean takes their slots' place)
    ok = s[ST.hi_prev_ok] != 0.0
    h0, h1, h2 = s[ST.hi_h], s[ST.hi_h + 1], s[ST.hi_h + 2]
    res2 = 0.0
    for i in range(3):
        mean = s[ST.hi_sum_m + i] * inv_n
        # Δȳ_i and residual Δȳ_i − (ΔR̄ h)_i
        dyi = mean - s[ST.hi_prev_m + i]
        drh = 0.0
        for j in range(3):
            drij = s[ST.hi_sum_r + 3 * i + j] * inv_n - s[ST.hi_prev_r + 3 * i + j]
            s[HS.d_r + 3 * i + j] = drij  # ΔR̄ kept for the update below
            drh += drij * (h0, h1, h2)[j]
        res2 += (dyi - drh) ** 2
        s[HS.d_y + i] = dyi
        s[ST.hi_prev_m + i] = mean
        s[ST.hi_sum_m + i] = 0.0
    for k in range(9):
        s[ST.hi_prev_r + k] = s[ST.hi_sum_r + k] * inv_n
        s[ST.hi_sum_r + k] = 0.0
    block_t = s[ST.hi_t]
    s[ST.hi_n] = 0.0
    s[ST.hi_t] = 0.0
    s[ST.hi_prev_ok] = 1.0
    if not ok:
        return
    # normalised: a floor for sensor noise plus a share of the field turned by the rotation,
    # since gyro scale and misalignment errors leave that much unexplained while turning
    dr2 = 0.0
    for k in range(9):
        dr2 += s[HS.d_r + k] ** 2
    y2 = s[ST.hi_prev_m] ** 2 + s[ST.hi_prev_m + 1] ** 2 + s[ST.hi_prev_m + 2] ** 2
    tol2 = p[P.consistency_th] ** 2 + p[P.consistency_rel] ** 2 * y2 * dr2
    if tol2 > 0.0:
        s[ST.cons] += B.first_order_gain(block_t, p[P.consistency_tau]) * (res2 / tol2 - s[ST.cons])
    if p[P.hard_iron_tau] <= 0.0:
        return
    # recursive least squares with exponential forgetting, information form:
    # A ← λA + ΔR̄ᵀΔR̄, g ← λg + ΔR̄ᵀΔȳ, h = A⁻¹ g; Huber weight against outlying blocks
    lam = math.exp(-block_t / p[P.hard_iron_tau])
    res = math.sqrt(res2)
    if p[P.hard_iron_reset] > 0.0 and res > p[P.hard_iron_reset]:
        # change detection: a jump no rotation explains (a magnet attached, moved or removed)
        # restarts the least squares: A and g shrink alike, so h stays until new data speak
        for k in range(9):
            s[ST.hi_a + k] *= 0.01
        for k in range(3):
            s[ST.hi_g + k] *= 0.01
        s[ST.hi_ok] = 0.0
        s[ST.hi_pending] = 1.0
        return
    wgt = 1.0 if res <= p[P.hard_iron_huber] else p[P.hard_iron_huber] / res
    for i in range(3):
        gi = 0.0
        for j in range(3):
            aij = 0.0
            for k in range(3):
                aij += s[HS.d_r + 3 * k + i] * s[HS.d_r + 3 * k + j]
            s[ST.hi_a + 3 * i + j] = lam * s[ST.hi_a + 3 * i + j] + wgt * aij
            gi += s[HS.d_r + 3 * j + i] * s[HS.d_y + j]
        s[ST.hi_g + i] = lam * s[ST.hi_g + i] + wgt * gi
    s[ST.hi_ok] = 0.0
    if not B.invert3(s, ST.hi_a, HS.a_inv):
        return
    inv = HS.a_inv
    # trusted only when every axis is observed (the diagonal of A⁻¹ is small enough)
    if max(s[inv], s[inv + 4], s[inv + 8]) * p[P.hard_iron_min_info] > 1.0:
        return
    e0 = s[inv] * s[ST.hi_g] + s[inv + 1] * s[ST.hi_g + 1] + s[inv + 2] * s[ST.hi_g + 2]
    e1 = s[inv + 3] * s[ST.hi_g] + s[inv + 4] * s[ST.hi_g + 1] + s[inv + 5] * s[ST.hi_g + 2]
    e2 = s[inv + 6] * s[ST.hi_g] + s[inv + 7] * s[ST.hi_g + 1] + s[inv + 8] * s[ST.hi_g + 2]
    if math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) > p[P.hard_iron_max]:
        return  # sanity gate: not a believable offset
    s[ST.hi_h], s[ST.hi_h + 1], s[ST.hi_h + 2] = e0, e1, e2
    s[ST.hi_ok] = 1.0
    s[ST.hi_pending] = 0.0


@_jit
def norm_dip(v):
    """Norm (µT) and dip (rad, positive downwards in NED) of an earth-frame field."""
    n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return n, math.asin(max(-1.0, min(1.0, v[2] / n)))


@_jit
def matches(s, p, norm, dip):
    ref = s[ST.mag_ref_norm]
    return abs(norm - ref) < p[P.mag_norm_th] * ref and abs(dip - s[ST.mag_ref_dip]) < p[P.mag_dip_th] * DEG


@_jit
def wrap(a):
    if a > math.pi:
        return a - 2.0 * math.pi
    if a < -math.pi:
        return a + 2.0 * math.pi
    return a


@_jit
def heading(s, p, x, q6):
    """Magnetic rejection features and the heading-offset filter δ (VQF eq. 11–12, NED).

    ``q6`` is q_a ⊗ q_g, the 6-D (inclination-corrected) attitude."""
    dtm = s[ST.mag_dt]
    s[ST.mag_dt] = 0.0
    m_raw = quat_rotate(q6, (x[6], x[7], x[8]))
    n_raw, d_raw = norm_dip(m_raw)
    hn = math.sqrt(s[ST.hi_h] ** 2 + s[ST.hi_h + 1] ** 2 + s[ST.hi_h + 2] ** 2)
    if hn >= p[P.hard_iron_min]:
        hi = quat_rotate(q6, (s[ST.hi_h], s[ST.hi_h + 1], s[ST.hi_h + 2]))
        m_cor = (m_raw[0] - hi[0], m_raw[1] - hi[1], m_raw[2] - hi[2])
        n_cor, d_cor = norm_dip(m_cor)
    else:
        # no offset worth correcting: the corrected field is the raw one
        m_cor, n_cor, d_cor = m_raw, n_raw, d_raw
    first = s[ST.mag_n] == 0.0
    s[ST.mag_n] += 1.0
    s[ST.mag_t] += dtm
    if B.cache_is_stale(
        s,
        (ST.gain_dt, ST.gain_tau_mag, ST.gain_tau_cur, ST.gain_tau_ref),
        (dtm, p[P.tau_mag], p[P.mag_current_tau], p[P.mag_ref_tau]),
    ):
        # exp() three times per field sample is avoidable at a steady rate: cache by dt
        s[ST.gain_cur] = B.first_order_gain(dtm, p[P.mag_current_tau])
        s[ST.gain_ref] = B.first_order_gain(dtm, p[P.mag_ref_tau])
        s[ST.gain_mag] = B.first_order_gain(dtm, p[P.tau_mag])
    kc = 1.0 if first else s[ST.gain_cur]
    s[ST.mag_nd] += kc * (n_raw - s[ST.mag_nd])
    s[ST.mag_nd + 1] += kc * (d_raw - s[ST.mag_nd + 1])
    s[ST.mag_nd + 2] += kc * (n_cor - s[ST.mag_nd + 2])
    s[ST.mag_nd + 3] += kc * (d_cor - s[ST.mag_nd + 3])

    init = s[ST.mag_t] < p[P.mag_init_time]
    if init:
        # start-up: the first field defines the reference (gain 1/n: the running mean)
        kr = 1.0 / s[ST.mag_n]
        s[ST.mag_ref_norm] += kr * (s[ST.mag_nd] - s[ST.mag_ref_norm])
        s[ST.mag_ref_dip] += kr * (s[ST.mag_nd + 1] - s[ST.mag_ref_dip])
        s[ST.mag_dist] = 0.0
        s[ST.mag_undist_t] = p[P.mag_min_undisturbed_time]
        s[ST.mag_cand_norm], s[ST.mag_cand_dip] = s[ST.mag_nd], s[ST.mag_nd + 1]
        m, nm, dm = m_raw, s[ST.mag_nd], s[ST.mag_nd + 1]
        s[ST.mag_used] = 1.0
        if p[P.mag_new_first_time] <= 0.0:
            s[ST.mag_confirmed] = 1.0
        else:
            # the start-up field is only trusted once it stayed steady while turning
            s[ST.mag_dist] = 1.0
            s[ST.mag_undist_t] = 0.0
    else:
        # choose the field: hard-iron corrected when trusted, sizeable and matching the reference
        use_cor = s[ST.hi_ok] != 0.0 and hn >= p[P.hard_iron_min] and matches(s, p, s[ST.mag_nd + 2], s[ST.mag_nd + 3])
        if use_cor:
            m, nm, dm = m_cor, s[ST.mag_nd + 2], s[ST.mag_nd + 3]
        else:
            m, nm, dm = m_raw, s[ST.mag_nd], s[ST.mag_nd + 1]
        # after an offset change neither field is believed until the offset is known again;
        # nor the raw field while a sizeable offset is known
        raw_vetoed = s[ST.hi_pending] != 0.0 or (s[ST.hi_ok] != 0.0 and hn >= p[P.hard_iron_min])
        consistent = p[P.consistency_th] <= 0.0 or s[ST.cons] < 1.0
        kref = s[ST.gain_ref]
        if matches(s, p, nm, dm) and consistent and s[ST.mag_confirmed] != 0.0 and (use_cor or not raw_vetoed):
            s[ST.mag_undist_t] += dtm
            if s[ST.mag_undist_t] >= p[P.mag_min_undisturbed_time]:
                s[ST.mag_dist] = 0.0
                s[ST.mag_ref_norm] += kref * (nm - s[ST.mag_ref_norm])
                s[ST.mag_ref_dip] += kref * (dm - s[ST.mag_ref_dip])
        else:
            s[ST.mag_undist_t] = 0.0
            s[ST.mag_dist] = 1.0
        # new-field acceptance (VQF): a steady new field seen long enough while turning
        if (
            abs(nm - s[ST.mag_cand_norm]) < p[P.mag_norm_th] * s[ST.mag_cand_norm]
            and abs(dm - s[ST.mag_cand_dip]) < p[P.mag_dip_th] * DEG
            and consistent
        ):
            g2 = s[ST.gyr_lp] ** 2 + s[ST.gyr_lp + 1] ** 2 + s[ST.gyr_lp + 2] ** 2
            if math.sqrt(g2) >= p[P.mag_new_min_gyr] * DEG:
                s[ST.mag_cand_t] += dtm
            s[ST.mag_cand_norm] += kref * (nm - s[ST.mag_cand_norm])
            s[ST.mag_cand_dip] += kref * (dm - s[ST.mag_cand_dip])
            if s[ST.mag_confirmed] == 0.0 and s[ST.mag_cand_t] >= p[P.mag_new_first_time]:
                s[ST.mag_confirmed] = 1.0
                s[ST.mag_ref_norm], s[ST.mag_ref_dip] = s[ST.mag_cand_norm], s[ST.mag_cand_dip]
            if s[ST.mag_dist] != 0.0 and s[ST.mag_cand_t] >= p[P.mag_new_time]:
                s[ST.mag_ref_norm], s[ST.mag_ref_dip] = s[ST.mag_cand_norm], s[ST.mag_cand_dip]
                s[ST.mag_dist] = 0.0
                s[ST.mag_undist_t] = p[P.mag_min_undisturbed_time]
        else:
            s[ST.mag_cand_t] = 0.0
            s[ST.mag_cand_norm], s[ST.mag_cand_dip] = nm, dm
        s[ST.mag_used] = 2.0 if use_cor else 1.0

    # heading disagreement: δ must turn the field's horizontal part onto north
    e = wrap(-math.atan2(m[1], m[0]) - s[ST.delta])
    k = s[ST.gain_mag]
    if p[P.mag_rot_rate] > 0.0:
        w = math.sqrt(s[ST.gyr_lp] ** 2 + s[ST.gyr_lp + 1] ** 2 + s[ST.gyr_lp + 2] ** 2)
        k = B.first_order_gain(dtm, p[P.tau_mag] / (1.0 + w / (p[P.mag_rot_rate] * DEG)))
    if init:
        k = max(k, 1.0 / s[ST.mag_n])
    elif s[ST.mag_dist] != 0.0:
        if s[ST.mag_reject_t] <= p[P.mag_max_rejection_time]:
            s[ST.mag_reject_t] += dtm
            k = 0.0
            s[ST.mag_used] = 0.0
        else:
            k /= p[P.mag_rejection_factor]
    else:
        s[ST.mag_reject_t] = max(s[ST.mag_reject_t] - p[P.mag_rejection_factor] * dtm, 0.0)
    if k != 0.0:  # a rejected field leaves δ, and so its cached half-angle cosine and sine
        # error model (robust.attitude_variance): the correction removes the share k of the
        # gyro drift and mixes in this field's heading error, a disturbance of relative size
        # |Δn|/n and dip change Δd turning the horizontal field by about √(Δn²/n² + Δd²) / cos d
        s[ST.u_yaw] *= 1.0 - min(k, 1.0)
        s[ST.u_turn] *= 1.0 - min(k, 1.0)
        ref = s[ST.mag_ref_norm]
        c = math.cos(s[ST.mag_ref_dip])
        if ref > 0.0 and c > 0.05:
            ef2 = (((nm - ref) / ref) ** 2 + (dm - s[ST.mag_ref_dip]) ** 2) / (c * c)
            s[ST.u_field] += min(k, 1.0) * (ef2 - s[ST.u_field])
        s[ST.delta] = wrap(s[ST.delta] + k * e)
        s[ST.delta_c], s[ST.delta_s] = math.cos(0.5 * s[ST.delta]), math.sin(0.5 * s[ST.delta])


# error_model="numpy": divisions by zero give inf/NaN instead of raising (every division
# here is guarded), which spares a branch per division on the per-sample path
