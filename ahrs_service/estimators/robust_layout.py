"""Parameters and state layout of the robust estimator (``robust.py``).

``RobustParams`` holds every tuning parameter with its unit and default; the ``P_*``
constants index the packed parameter vector and the upper-case slot names index the state
array after the common header of ``_kernel`` (q, flags, counters, gyro bias at 8..10).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ahrs_service.estimators import _kernel as K

DEG = math.pi / 180.0


@dataclass
class RobustParams:
    """Tuning of :class:`RobustEstimator`; one common set, fixed before scoring (see the doc).

    output_lead: latency compensation, s: the published attitude is the estimate carried
        forward by this time with the current bias-corrected rate, q ⊗ exp(ω̂ t_lead / 2),
        to make up for the delay of the sensor's own filters against the true motion. Off (0)
        by default: it is a property of the sensor, to be set to that IMU's filter delay.
        BROAD's IMU samples are about a sample late against its reference (the evaluate
        report's timing table); 2.04 ms lowers every estimator's inclination error there, VQF's
        included (see the doc). Only the output is affected, never the filter state.

    Inclination and bias (VQF's parameters, same meaning):
    tau_acc: time constant of the accelerometer low-pass in the gyro frame, s.
    tau_acc_rest: the same while rest is detected, s; equal to tau_acc by default (a
        shorter one did not change BROAD's figures).
    rest_min_t: time the sensor must be still before rest is declared, s.
    rest_filter_tau: time constant of the rest-detection low-passes, s.
    rest_th_gyr: rest threshold on the gyro deviation from its low-pass, °/s.
    rest_th_acc: rest threshold on the accelerometer deviation from its low-pass, m/s².
    bias_sigma_init: initial gyro-bias standard deviation, °/s.
    bias_forgetting_time: time in which the bias variance grows by (0.1 °/s)², s.
    bias_clip: largest gyro bias accepted, °/s.
    bias_sigma_motion: measurement std of the motion bias update, °/s (0 disables it).
    bias_sigma_rest: measurement std of the rest bias update, °/s (0 disables it).

    Heading:
    tau_mag: time constant of the heading correction, s. 15 s, longer than VQF's 9 s: with
        the bias estimated the gyro can be trusted longer (BROAD: better on every group).
    mag_rot_rate: off by default (0). Otherwise the turning rate at which the heading
        correction is twice as fast, °/s: 1/τ = (1 + |ω̄|/mag_rot_rate)/tau_mag with ω̄ the
        low-passed gyro (gyro scale errors turn heading in proportion to the rate). It made
        the stationary-magnet trial of BROAD worse, hence off.
    mag_current_tau: low-pass of the field norm and dip before they are tested, s.
    mag_ref_tau: time constant with which the reference norm and dip follow, s.
    mag_norm_th: relative norm deviation that counts as disturbed (0.1 = 10 %).
    mag_dip_th: dip deviation that counts as disturbed, °.
    mag_min_undisturbed_time: time the field must pass the tests before it is used again, s.
    mag_max_rejection_time: longest time a disturbed field is fully rejected, s; after it
        the field is used with gain / mag_rejection_factor. 120 s (VQF: 60 s): the 1 cm
        magnet of BROAD stays on for 60 s and the gyro holds heading that long.
    mag_rejection_factor: gain divisor after the rejection timeout, and how much faster
        the rejection clock runs down while undisturbed.
    mag_new_time: time a new, steady field must be seen while turning before it replaces
        the reference, s.
    mag_new_min_gyr: turning rate needed for the new-field clock to run, °/s.
    mag_new_first_time: the field seen at start-up is used for the initial heading, but
        corrects it afterwards only once it stayed steady this long while turning, s (as
        VQF's magNewFirstTime; 0 trusts it at once).
    mag_init_time: at start-up the reference and heading follow the field with gain 1/n
        for this long, s.

    Gyro consistency and hard iron:
    block_time: length of the blocks whose means of R_g m and R_g are compared, s.
    consistency_tau: time constant of the consistency statistic, s.
    consistency_th: rms block-to-block change of the field in the gyro frame, not explained
        by rotation, above which the field is rejected while not turning, µT (0 disables).
    consistency_rel: added tolerance while turning, as a fraction of the field turned
        between blocks (|ȳ|·‖ΔR̄‖): room for gyro scale and misalignment errors.
    hard_iron_tau: forgetting time of the hard-iron least squares, s (0 disables learning).
    hard_iron_min_info: information (Σ ΔR̄², dimensionless) each axis needs before the
        estimate is trusted.
    hard_iron_min: smallest offset worth correcting, µT.
    hard_iron_max: sanity gate: larger offsets are not believed, µT.
    hard_iron_huber: block residual beyond which a block is down-weighted (Huber), µT.
    hard_iron_reset: block residual that signals a changed offset and restarts the least
        squares (its information shrinks a hundredfold), µT (0 disables).
    """

    output_lead: float = 0.0
    tau_acc: float = 3.0
    tau_acc_rest: float = 3.0
    rest_min_t: float = 1.5
    rest_filter_tau: float = 0.5
    rest_th_gyr: float = 2.0
    rest_th_acc: float = 0.5
    bias_sigma_init: float = 0.5
    bias_forgetting_time: float = 100.0
    bias_clip: float = 2.0
    bias_sigma_motion: float = 0.1
    bias_sigma_rest: float = 0.03
    tau_mag: float = 15.0
    mag_rot_rate: float = 0.0
    mag_current_tau: float = 0.05
    mag_ref_tau: float = 20.0
    mag_norm_th: float = 0.1
    mag_dip_th: float = 10.0
    mag_min_undisturbed_time: float = 0.5
    mag_max_rejection_time: float = 120.0
    mag_rejection_factor: float = 2.0
    mag_new_time: float = 20.0
    mag_new_min_gyr: float = 20.0
    mag_new_first_time: float = 5.0
    mag_init_time: float = 2.0
    block_time: float = 0.1
    consistency_tau: float = 1.0
    consistency_th: float = 2.0
    consistency_rel: float = 0.1
    hard_iron_tau: float = 10.0
    hard_iron_min_info: float = 0.5
    hard_iron_min: float = 5.0
    hard_iron_max: float = 150.0
    hard_iron_huber: float = 3.0
    hard_iron_reset: float = 30.0

    def __post_init__(self) -> None:
        positive = ("tau_acc", "tau_acc_rest", "rest_filter_tau", "bias_forgetting_time", "bias_clip", "tau_mag", "block_time")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for f in dataclasses.fields(self):
            if getattr(self, f.name) < 0:
                raise ValueError(f"{f.name} must be >= 0, got {getattr(self, f.name)}")
        if self.mag_rejection_factor < 1:
            raise ValueError(f"mag_rejection_factor must be >= 1, got {self.mag_rejection_factor}")


# parameter vector indices (the order of the dataclass fields)
_P = {f.name: i for i, f in enumerate(dataclasses.fields(RobustParams))}
P_TAU_ACC, P_REST_MIN_T, P_REST_TAU = _P["tau_acc"], _P["rest_min_t"], _P["rest_filter_tau"]
P_TAU_ACC_REST, P_MAG_ROT, P_LEAD = _P["tau_acc_rest"], _P["mag_rot_rate"], _P["output_lead"]
P_REST_TH_GYR, P_REST_TH_ACC = _P["rest_th_gyr"], _P["rest_th_acc"]
P_BIAS_INIT, P_BIAS_FORGET, P_BIAS_CLIP = _P["bias_sigma_init"], _P["bias_forgetting_time"], _P["bias_clip"]
P_BIAS_MOTION, P_BIAS_REST = _P["bias_sigma_motion"], _P["bias_sigma_rest"]
P_TAU_MAG, P_MAG_CUR_TAU, P_MAG_REF_TAU = _P["tau_mag"], _P["mag_current_tau"], _P["mag_ref_tau"]
P_MAG_NORM_TH, P_MAG_DIP_TH, P_MAG_MIN_UNDIST = _P["mag_norm_th"], _P["mag_dip_th"], _P["mag_min_undisturbed_time"]
P_MAG_MAX_REJ, P_MAG_REJ_FACTOR = _P["mag_max_rejection_time"], _P["mag_rejection_factor"]
P_MAG_NEW_TIME, P_MAG_NEW_GYR, P_MAG_INIT_TIME = _P["mag_new_time"], _P["mag_new_min_gyr"], _P["mag_init_time"]
P_MAG_NEW_FIRST = _P["mag_new_first_time"]
P_BLOCK, P_CONS_TAU, P_CONS_TH = _P["block_time"], _P["consistency_tau"], _P["consistency_th"]
P_CONS_REL = _P["consistency_rel"]
P_HI_TAU, P_HI_INFO, P_HI_MIN, P_HI_MAX, P_HI_HUBER = (
    _P["hard_iron_tau"], _P["hard_iron_min_info"], _P["hard_iron_min"], _P["hard_iron_max"], _P["hard_iron_huber"],
)  # fmt: skip
P_HI_RESET = _P["hard_iron_reset"]
N_PARAMS = len(_P)  # length of the parameter vector

# ------------------------------------------------------------------ state layout (after the header)
GQ = K.HEADER  # 11..14 q_g, I←S
AQ = GQ + 4  # 15..18 q_a, E6←I
DELTA = AQ + 4  # 19 heading offset δ, rad (rotation about NED down)
COEF_DT, COEF_TAU_ACC, COEF_TAU_REST = DELTA + 1, DELTA + 2, DELTA + 3  # keys of the cached coefficients
CA = DELTA + 4  # (b0, a1, a2) for τ_acc
CR = CA + 3  # (b0, a1, a2) for rest_filter_tau
ACC_LP = CR + 3  # 2 × 3 filter states of the accelerometer in I
REST_GYR = ACC_LP + 6  # 2 × 3 states, gyro low-pass for rest detection
REST_ACC = REST_GYR + 6  # 2 × 3 states, accelerometer low-pass for rest detection
GYR_LP = REST_ACC + 6  # 3: low-passed gyro, rad/s
REST_T = GYR_LP + 3  # time the rest tests have passed, s
REST = REST_T + 1  # 1.0 while at rest
BIAS_P = REST + 1  # 9: bias covariance, (0.01 °/s)²
R_LP = BIAS_P + 9  # 2 × 9 states: low-pass of R(q_a ⊗ q_g)
BIAS_LP = R_LP + 18  # 2 × 2 states: low-pass of the first two rows of R b
MAG_REF_NORM, MAG_REF_DIP = BIAS_LP + 4, BIAS_LP + 5  # learned reference, µT and rad
MAG_ND = BIAS_LP + 6  # 4: low-passed (norm, dip) of the raw and of the hard-iron-corrected field
MAG_UNDIST_T = MAG_ND + 4  # time the field has passed the tests, s
MAG_DIST = MAG_UNDIST_T + 1  # 1.0 while a disturbance is detected
MAG_REJECT_T = MAG_DIST + 1  # rejection clock, s
MAG_CAND_NORM, MAG_CAND_DIP, MAG_CAND_T = MAG_REJECT_T + 1, MAG_REJECT_T + 2, MAG_REJECT_T + 3
MAG_N = MAG_CAND_T + 1  # number of field samples used so far
MAG_T = MAG_N + 1  # time since start of the heading (for mag_init_time), s
MAG_DT = MAG_T + 1  # time since the last field sample, s
MAG_USED = MAG_DT + 1  # which field fed the heading: 0 none (rejected), 1 raw, 2 hard-iron corrected
HI_H = MAG_USED + 1  # 3: hard-iron estimate, µT, body frame
HI_A = HI_H + 3  # 9: information matrix Σ λ ΔR̄ᵀΔR̄
HI_G = HI_A + 9  # 3: Σ λ ΔR̄ᵀ Δȳ
HI_SUM_M = HI_G + 3  # 3: running sum of R_g m in the current block
HI_SUM_R = HI_SUM_M + 3  # 9: running sum of R_g in the current block
HI_N, HI_T = HI_SUM_R + 9, HI_SUM_R + 10  # samples and time in the current block
HI_PREV_M = HI_T + 1  # 3: mean of R_g m in the previous block
HI_PREV_R = HI_PREV_M + 3  # 9: mean of R_g in the previous block
HI_PREV_OK = HI_PREV_R + 9  # 1.0 once a previous block exists
HI_OK = HI_PREV_OK + 1  # 1.0 while the hard-iron estimate is trusted (observed, sane)
CONS = HI_OK + 1  # consistency statistic: low-passed block residual² / tolerance² (< 1: consistent)
SCRATCH = CONS + 1  # 36 slots for the Kalman and least-squares algebra
CAR = SCRATCH + 36  # (b0, a1, a2) for tau_acc_rest
COEF_TAU_ACC_REST = CAR + 3
MAG_CONFIRMED = CAR + 4  # 1.0 once the start-up field was confirmed while turning
HI_PENDING = CAR + 5  # 1.0 from a detected offset change until the estimate is trusted again
GAIN_DT, GAIN_TAU_MAG, GAIN_CUR, GAIN_REF, GAIN_MAG = CAR + 6, CAR + 7, CAR + 8, CAR + 9, CAR + 10  # cached gains
GAIN_TAU_CUR, GAIN_TAU_REF = CAR + 11, CAR + 12
DELTA_C, DELTA_S = CAR + 13, CAR + 14  # cos(δ/2), sin(δ/2): q_δ, updated with δ
STATE_SIZE = CAR + 15

#: what ``from robust_layout import *`` brings: the parameters, DEG, and every index constant
__all__ = ["RobustParams", "DEG"] + [n for n in dir() if n.isupper() and n not in ("DEG", "K") and not n.startswith("_")]
