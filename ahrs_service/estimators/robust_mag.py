"""Magnetic part of the robust estimator (``robust.py``): gyro consistency, hard-iron
learning with change detection, and the gated heading-offset filter.

An undisturbed field with a body-fixed (hard-iron) offset h obeys R_g(t)(m(t) − h) = const
in the gyro frame I. Block means (``block_time``) ȳ = mean(R_g m), R̄ = mean(R_g) therefore
satisfy Δȳ = ΔR̄ h between consecutive blocks: linear in h (least squares with forgetting),
and whatever Δȳ the rotation and ĥ do not explain is a field that changed in I — the
gyro-consistency statistic. The heading offset δ follows VQF eq. 11–12 (D. Laidig, T. Seel,
Information Fusion 91, 2023), written for NED: δ turns the field's horizontal part onto north.
"""

from __future__ import annotations

import math

from numba import njit

from ahrs_service.estimators import robust_blocks as B
from ahrs_service.estimators.robust_layout import *  # noqa: F403 - slot and parameter indices
from ahrs_service.quaternion import quat_rotate

_jit = njit(cache=True, inline="always")

@_jit
def hard_iron_and_consistency(s, p, x, dt, r):
    """Block means of R_g m and R_g; their block-to-block changes feed the hard-iron least
    squares Δȳ = ΔR̄ h and the gyro-consistency statistic (the part of Δȳ not explained).

    ``r`` is R_g = R(q_g), I←S, row-major."""
    mx, my, mz = x[6], x[7], x[8]
    s[HI_SUM_M] += r[0] * mx + r[1] * my + r[2] * mz
    s[HI_SUM_M + 1] += r[3] * mx + r[4] * my + r[5] * mz
    s[HI_SUM_M + 2] += r[6] * mx + r[7] * my + r[8] * mz
    for k in range(9):
        s[HI_SUM_R + k] += r[k]
    s[HI_N] += 1.0
    if s[HI_T] < p[P_BLOCK]:
        return
    inv_n = 1.0 / s[HI_N]
    # block mean; the sums are then restarted (the previous block's mean takes their slots' place)
    ok = s[HI_PREV_OK] != 0.0
    h0, h1, h2 = s[HI_H], s[HI_H + 1], s[HI_H + 2]
    res2 = 0.0
    for i in range(3):
        mean = s[HI_SUM_M + i] * inv_n
        # Δȳ_i and residual Δȳ_i − (ΔR̄ h)_i
        dyi = mean - s[HI_PREV_M + i]
        drh = 0.0
        for j in range(3):
            drij = s[HI_SUM_R + 3 * i + j] * inv_n - s[HI_PREV_R + 3 * i + j]
            s[SCRATCH + 3 * i + j] = drij  # ΔR̄ kept for the update below
            drh += drij * (h0, h1, h2)[j]
        res2 += (dyi - drh) ** 2
        s[SCRATCH + 9 + i] = dyi
        s[HI_PREV_M + i] = mean
        s[HI_SUM_M + i] = 0.0
    for k in range(9):
        s[HI_PREV_R + k] = s[HI_SUM_R + k] * inv_n
        s[HI_SUM_R + k] = 0.0
    block_t = s[HI_T]
    s[HI_N] = 0.0
    s[HI_T] = 0.0
    s[HI_PREV_OK] = 1.0
    if not ok:
        return
    # normalised: a floor for sensor noise plus a share of the field turned by the rotation,
    # since gyro scale and misalignment errors leave that much unexplained while turning
    dr2 = 0.0
    for k in range(9):
        dr2 += s[SCRATCH + k] ** 2
    y2 = s[HI_PREV_M] ** 2 + s[HI_PREV_M + 1] ** 2 + s[HI_PREV_M + 2] ** 2
    tol2 = p[P_CONS_TH] ** 2 + p[P_CONS_REL] ** 2 * y2 * dr2
    if tol2 > 0.0:
        s[CONS] += B.first_order_gain(block_t, p[P_CONS_TAU]) * (res2 / tol2 - s[CONS])
    if p[P_HI_TAU] <= 0.0:
        return
    # recursive least squares with exponential forgetting, information form:
    # A ← λA + ΔR̄ᵀΔR̄, g ← λg + ΔR̄ᵀΔȳ, h = A⁻¹ g; Huber weight against outlying blocks
    lam = math.exp(-block_t / p[P_HI_TAU])
    res = math.sqrt(res2)
    if p[P_HI_RESET] > 0.0 and res > p[P_HI_RESET]:
        # change detection: a jump no rotation explains (a magnet attached, moved or removed)
        # restarts the least squares: A and g shrink alike, so h stays until new data speak
        for k in range(9):
            s[HI_A + k] *= 0.01
        for k in range(3):
            s[HI_G + k] *= 0.01
        s[HI_OK] = 0.0
        s[HI_PENDING] = 1.0
        return
    wgt = 1.0 if res <= p[P_HI_HUBER] else p[P_HI_HUBER] / res
    for i in range(3):
        gi = 0.0
        for j in range(3):
            aij = 0.0
            for k in range(3):
                aij += s[SCRATCH + 3 * k + i] * s[SCRATCH + 3 * k + j]
            s[HI_A + 3 * i + j] = lam * s[HI_A + 3 * i + j] + wgt * aij
            gi += s[SCRATCH + 3 * j + i] * s[SCRATCH + 9 + j]
        s[HI_G + i] = lam * s[HI_G + i] + wgt * gi
    s[HI_OK] = 0.0
    if not B.invert3(s, HI_A, SCRATCH + 12):
        return
    inv = SCRATCH + 12
    # trusted only when every axis is observed (the diagonal of A⁻¹ is small enough)
    if max(s[inv], s[inv + 4], s[inv + 8]) * p[P_HI_INFO] > 1.0:
        return
    e0 = s[inv] * s[HI_G] + s[inv + 1] * s[HI_G + 1] + s[inv + 2] * s[HI_G + 2]
    e1 = s[inv + 3] * s[HI_G] + s[inv + 4] * s[HI_G + 1] + s[inv + 5] * s[HI_G + 2]
    e2 = s[inv + 6] * s[HI_G] + s[inv + 7] * s[HI_G + 1] + s[inv + 8] * s[HI_G + 2]
    if math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) > p[P_HI_MAX]:
        return  # sanity gate: not a believable offset
    s[HI_H], s[HI_H + 1], s[HI_H + 2] = e0, e1, e2
    s[HI_OK] = 1.0
    s[HI_PENDING] = 0.0


@_jit
def norm_dip(v):
    """Norm (µT) and dip (rad, positive downwards in NED) of an earth-frame field."""
    n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return n, math.asin(max(-1.0, min(1.0, v[2] / n)))


@_jit
def matches(s, p, norm, dip):
    ref = s[MAG_REF_NORM]
    return abs(norm - ref) < p[P_MAG_NORM_TH] * ref and abs(dip - s[MAG_REF_DIP]) < p[P_MAG_DIP_TH] * DEG


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
    dtm = s[MAG_DT]
    s[MAG_DT] = 0.0
    m_raw = quat_rotate(q6, (x[6], x[7], x[8]))
    n_raw, d_raw = norm_dip(m_raw)
    hn = math.sqrt(s[HI_H] ** 2 + s[HI_H + 1] ** 2 + s[HI_H + 2] ** 2)
    if hn >= p[P_HI_MIN]:
        hi = quat_rotate(q6, (s[HI_H], s[HI_H + 1], s[HI_H + 2]))
        m_cor = (m_raw[0] - hi[0], m_raw[1] - hi[1], m_raw[2] - hi[2])
        n_cor, d_cor = norm_dip(m_cor)
    else:
        # no offset worth correcting: the corrected field is the raw one
        m_cor, n_cor, d_cor = m_raw, n_raw, d_raw
    first = s[MAG_N] == 0.0
    s[MAG_N] += 1.0
    s[MAG_T] += dtm
    if (
        s[GAIN_DT] != dtm
        or s[GAIN_TAU_MAG] != p[P_TAU_MAG]
        or s[GAIN_TAU_CUR] != p[P_MAG_CUR_TAU]
        or s[GAIN_TAU_REF] != p[P_MAG_REF_TAU]
    ):
        # exp() three times per field sample is avoidable at a steady rate: cache by dt
        s[GAIN_CUR] = B.first_order_gain(dtm, p[P_MAG_CUR_TAU])
        s[GAIN_REF] = B.first_order_gain(dtm, p[P_MAG_REF_TAU])
        s[GAIN_MAG] = B.first_order_gain(dtm, p[P_TAU_MAG])
        s[GAIN_DT], s[GAIN_TAU_MAG] = dtm, p[P_TAU_MAG]
        s[GAIN_TAU_CUR], s[GAIN_TAU_REF] = p[P_MAG_CUR_TAU], p[P_MAG_REF_TAU]
    kc = 1.0 if first else s[GAIN_CUR]
    s[MAG_ND] += kc * (n_raw - s[MAG_ND])
    s[MAG_ND + 1] += kc * (d_raw - s[MAG_ND + 1])
    s[MAG_ND + 2] += kc * (n_cor - s[MAG_ND + 2])
    s[MAG_ND + 3] += kc * (d_cor - s[MAG_ND + 3])

    init = s[MAG_T] < p[P_MAG_INIT_TIME]
    if init:
        # start-up: the first field defines the reference (gain 1/n: the running mean)
        kr = 1.0 / s[MAG_N]
        s[MAG_REF_NORM] += kr * (s[MAG_ND] - s[MAG_REF_NORM])
        s[MAG_REF_DIP] += kr * (s[MAG_ND + 1] - s[MAG_REF_DIP])
        s[MAG_DIST] = 0.0
        s[MAG_UNDIST_T] = p[P_MAG_MIN_UNDIST]
        s[MAG_CAND_NORM], s[MAG_CAND_DIP] = s[MAG_ND], s[MAG_ND + 1]
        m = m_raw
        s[MAG_USED] = 1.0
        if p[P_MAG_NEW_FIRST] <= 0.0:
            s[MAG_CONFIRMED] = 1.0
        else:
            # the start-up field is only trusted once it stayed steady while turning
            s[MAG_DIST] = 1.0
            s[MAG_UNDIST_T] = 0.0
    else:
        # choose the field: hard-iron corrected when trusted, sizeable and matching the reference
        use_cor = s[HI_OK] != 0.0 and hn >= p[P_HI_MIN] and matches(s, p, s[MAG_ND + 2], s[MAG_ND + 3])
        if use_cor:
            m, nm, dm = m_cor, s[MAG_ND + 2], s[MAG_ND + 3]
        else:
            m, nm, dm = m_raw, s[MAG_ND], s[MAG_ND + 1]
        # after an offset change neither field is believed until the offset is known again;
        # nor the raw field while a sizeable offset is known
        raw_vetoed = s[HI_PENDING] != 0.0 or (s[HI_OK] != 0.0 and hn >= p[P_HI_MIN])
        consistent = p[P_CONS_TH] <= 0.0 or s[CONS] < 1.0
        kref = s[GAIN_REF]
        if matches(s, p, nm, dm) and consistent and s[MAG_CONFIRMED] != 0.0 and (use_cor or not raw_vetoed):
            s[MAG_UNDIST_T] += dtm
            if s[MAG_UNDIST_T] >= p[P_MAG_MIN_UNDIST]:
                s[MAG_DIST] = 0.0
                s[MAG_REF_NORM] += kref * (nm - s[MAG_REF_NORM])
                s[MAG_REF_DIP] += kref * (dm - s[MAG_REF_DIP])
        else:
            s[MAG_UNDIST_T] = 0.0
            s[MAG_DIST] = 1.0
        # new-field acceptance (VQF): a steady new field seen long enough while turning
        if (
            abs(nm - s[MAG_CAND_NORM]) < p[P_MAG_NORM_TH] * s[MAG_CAND_NORM]
            and abs(dm - s[MAG_CAND_DIP]) < p[P_MAG_DIP_TH] * DEG
            and consistent
        ):
            g2 = s[GYR_LP] ** 2 + s[GYR_LP + 1] ** 2 + s[GYR_LP + 2] ** 2
            if math.sqrt(g2) >= p[P_MAG_NEW_GYR] * DEG:
                s[MAG_CAND_T] += dtm
            s[MAG_CAND_NORM] += kref * (nm - s[MAG_CAND_NORM])
            s[MAG_CAND_DIP] += kref * (dm - s[MAG_CAND_DIP])
            if s[MAG_CONFIRMED] == 0.0 and s[MAG_CAND_T] >= p[P_MAG_NEW_FIRST]:
                s[MAG_CONFIRMED] = 1.0
                s[MAG_REF_NORM], s[MAG_REF_DIP] = s[MAG_CAND_NORM], s[MAG_CAND_DIP]
            if s[MAG_DIST] != 0.0 and s[MAG_CAND_T] >= p[P_MAG_NEW_TIME]:
                s[MAG_REF_NORM], s[MAG_REF_DIP] = s[MAG_CAND_NORM], s[MAG_CAND_DIP]
                s[MAG_DIST] = 0.0
                s[MAG_UNDIST_T] = p[P_MAG_MIN_UNDIST]
        else:
            s[MAG_CAND_T] = 0.0
            s[MAG_CAND_NORM], s[MAG_CAND_DIP] = nm, dm
        s[MAG_USED] = 2.0 if use_cor else 1.0

    # heading disagreement: δ must turn the field's horizontal part onto north
    e = wrap(-math.atan2(m[1], m[0]) - s[DELTA])
    k = s[GAIN_MAG]
    if p[P_MAG_ROT] > 0.0:
        w = math.sqrt(s[GYR_LP] ** 2 + s[GYR_LP + 1] ** 2 + s[GYR_LP + 2] ** 2)
        k = B.first_order_gain(dtm, p[P_TAU_MAG] / (1.0 + w / (p[P_MAG_ROT] * DEG)))
    if init:
        k = max(k, 1.0 / s[MAG_N])
    elif s[MAG_DIST] != 0.0:
        if s[MAG_REJECT_T] <= p[P_MAG_MAX_REJ]:
            s[MAG_REJECT_T] += dtm
            k = 0.0
            s[MAG_USED] = 0.0
        else:
            k /= p[P_MAG_REJ_FACTOR]
    else:
        s[MAG_REJECT_T] = max(s[MAG_REJECT_T] - p[P_MAG_REJ_FACTOR] * dtm, 0.0)
    if k != 0.0:  # a rejected field leaves δ, and so its cached half-angle cosine and sine
        s[DELTA] = wrap(s[DELTA] + k * e)
        s[DELTA_C], s[DELTA_S] = math.cos(0.5 * s[DELTA]), math.sin(0.5 * s[DELTA])


# error_model="numpy": divisions by zero give inf/NaN instead of raising (every division
# here is guarded), which spares a branch per division on the per-sample path
