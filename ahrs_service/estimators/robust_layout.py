"""Parameters and state layout of the robust estimator (``robust.py``).

``RobustParams`` holds every tuning parameter with its unit and default; ``P`` names the
indices of the packed parameter vector (``p[P.tau_acc]``), ``STATE`` declares the state
array's slots after the common header of ``_kernel`` (q, flags, counters, gyro bias) and
``ST`` names their first indices (``s[ST.hi_h]``). No offset is counted by hand: the
``Layout`` computes them from the slot sizes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ahrs_service.core.layout import Layout, Slot, param_index
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
        report's timing table); carrying the output forward by that lag lowers every
        estimator's inclination error there, VQF's included (value and figures:
        docs/robust-estimator.md, "Latency compensation"). Only the output is affected, never
        the filter state.

    Inclination and bias (VQF's parameters, same meaning):
    tau_acc: time constant of the accelerometer low-pass in the gyro frame while the sensor
        tilts fast (the shortest one used), s. VQF's 3 s, chosen for handheld motion.
    tau_acc_max: the same for a sensor that does not tilt, s; between the two the time
        constant follows the tilt rate (the project's own, see ``robust._accel_time_constant``
        and the doc): τ = tau_acc_max / √(1 + |ω̄_h| / tilt_rate_ref), never below tau_acc.
        The gyro frame's inclination drifts by the residual bias plus the scale error times
        the tilt rate; where it drifts little, accelerations can be averaged for longer. 6 s:
        tau_acc·√(1 + 60/20), so that VQF's 3 s holds at the ≈ 60 °/s of handheld motion.
        On quadrotor flights (sustained accelerations, slow tilting) it is what cuts DIDO's
        inclination error by about a third against a fixed 3 s (figures:
        docs/robust-estimator.md, "Accuracy on quadrotor flights (DIDO)").
    tilt_rate_ref: tilt rate at which the gyro's scale-error drift equals its residual bias
        drift, °/s: bias 0.1 °/s (bias_sigma_motion) over a 0.5 % scale error, 20 °/s. 0
        disables the adaptation (τ = tau_acc).
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
    tau_acc_max: float = 6.0
    tilt_rate_ref: float = 20.0
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
        positive = ("tau_acc", "tau_acc_max", "tau_acc_rest", "rest_filter_tau", "bias_forgetting_time", "bias_clip", "tau_mag", "block_time")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for f in dataclasses.fields(self):
            if getattr(self, f.name) < 0:
                raise ValueError(f"{f.name} must be >= 0, got {getattr(self, f.name)}")
        if self.mag_rejection_factor < 1:
            raise ValueError(f"mag_rejection_factor must be >= 1, got {self.mag_rejection_factor}")


#: indices of the packed parameter vector, named like the fields: ``p[P.tau_acc]``
P = param_index(RobustParams)
N_PARAMS = len(P)  # length of the parameter vector

#: the state after the common header of ``_kernel`` (q, flags, counters, gyro bias). The
#: order is that of earlier releases (slots were appended, never moved), so state snapshots
#: in older logs still replay.
STATE = Layout(
    "robust state",
    [
        Slot("gq", 4, "q_g, I←S: strapdown integration of the bias-corrected gyro"),
        Slot("aq", 4, "q_a, E6←I: inclination correction"),
        Slot("delta", 1, "heading offset δ, rad (rotation about NED down)"),
        Slot("coef_dt", 1, "dt the cached low-pass coefficients were computed for, s"),
        Slot("coef_tau_acc", 1, "accelerometer time constant of the cached coefficients, s"),
        Slot("coef_tau_rest", 1, "rest_filter_tau of the cached coefficients, s"),
        Slot("ca", 3, "(b0, a1, a2) of the low-pass for tau_acc"),
        Slot("cr", 3, "(b0, a1, a2) of the low-pass for rest_filter_tau"),
        Slot("acc_lp", 6, "2 × 3 filter states: accelerometer low-pass in I"),
        Slot("rest_gyr", 6, "2 × 3 filter states: gyro low-pass for rest detection"),
        Slot("rest_acc", 6, "2 × 3 filter states: accelerometer low-pass for rest detection"),
        Slot("gyr_lp", 3, "low-passed gyro, rad/s"),
        Slot("rest_t", 1, "time the rest tests have passed, s"),
        Slot("rest", 1, "1.0 while at rest"),
        Slot("bias_p", 9, "gyro-bias covariance, (0.01 °/s)², row-major 3 × 3"),
        Slot("r_lp", 18, "2 × 9 filter states: low-pass of R(q_a ⊗ q_g)"),
        Slot("bias_lp", 4, "2 × 2 filter states: low-pass of the first two rows of R b"),
        Slot("mag_ref_norm", 1, "learned reference field norm, µT"),
        Slot("mag_ref_dip", 1, "learned reference dip, rad"),
        Slot("mag_nd", 4, "low-passed (norm, dip) of the raw and of the hard-iron-corrected field"),
        Slot("mag_undist_t", 1, "time the field has passed the tests, s"),
        Slot("mag_dist", 1, "1.0 while a disturbance is detected"),
        Slot("mag_reject_t", 1, "rejection clock, s"),
        Slot("mag_cand_norm", 1, "candidate new field: norm, µT"),
        Slot("mag_cand_dip", 1, "candidate new field: dip, rad"),
        Slot("mag_cand_t", 1, "time the candidate was seen steady while turning, s"),
        Slot("mag_n", 1, "number of field samples used so far"),
        Slot("mag_t", 1, "time since the start of the heading (for mag_init_time), s"),
        Slot("mag_dt", 1, "time since the last field sample, s"),
        Slot("mag_used", 1, "which field fed the heading: 0 none (rejected), 1 raw, 2 hard-iron corrected"),
        Slot("hi_h", 3, "hard-iron estimate, µT, body frame"),
        Slot("hi_a", 9, "information matrix Σ λ ΔR̄ᵀΔR̄"),
        Slot("hi_g", 3, "Σ λ ΔR̄ᵀ Δȳ"),
        Slot("hi_sum_m", 3, "running sum of R_g m in the current block"),
        Slot("hi_sum_r", 9, "running sum of R_g in the current block"),
        Slot("hi_n", 1, "samples in the current block"),
        Slot("hi_t", 1, "time in the current block, s"),
        Slot("hi_prev_m", 3, "mean of R_g m in the previous block"),
        Slot("hi_prev_r", 9, "mean of R_g in the previous block"),
        Slot("hi_prev_ok", 1, "1.0 once a previous block exists"),
        Slot("hi_ok", 1, "1.0 while the hard-iron estimate is trusted (observed, sane)"),
        Slot("cons", 1, "consistency statistic: low-passed block residual² / tolerance² (< 1: consistent)"),
        Slot("scratch", 36, "work space of the Kalman and least-squares algebra (see HI_SCRATCH)"),
        Slot("car", 3, "(b0, a1, a2) of the low-pass for tau_acc_rest"),
        Slot("coef_tau_acc_rest", 1, "tau_acc_rest of the cached coefficients, s"),
        Slot("mag_confirmed", 1, "1.0 once the start-up field was confirmed while turning"),
        Slot("hi_pending", 1, "1.0 from a detected offset change until the estimate is trusted again"),
        Slot("gain_dt", 1, "field-sample dt the cached heading gains were computed for, s"),
        Slot("gain_tau_mag", 1, "tau_mag of the cached gains, s"),
        Slot("gain_cur", 1, "cached gain for mag_current_tau"),
        Slot("gain_ref", 1, "cached gain for mag_ref_tau"),
        Slot("gain_mag", 1, "cached gain for tau_mag"),
        Slot("gain_tau_cur", 1, "mag_current_tau of the cached gains, s"),
        Slot("gain_tau_ref", 1, "mag_ref_tau of the cached gains, s"),
        Slot("delta_c", 1, "cos(δ/2) of q_δ, updated with δ"),
        Slot("delta_s", 1, "sin(δ/2) of q_δ, updated with δ"),
        Slot("tilt_rate", 1, "tilt rate |ω̄_h| about the horizontal axes, low-passed, rad/s"),
        # the error model's accumulators (robust.attitude_variance, docs/autopilot.md)
        Slot("u_tilt", 1, "gyro drift of the inclination not yet corrected by the accelerometer, rad"),
        Slot("u_yaw", 1, "heading drift of the residual gyro bias not yet corrected by the field, rad"),
        Slot("u_turn", 1, "heading turned by the gyro since the field last corrected it (signed, shrunk like u_yaw), rad"),
        Slot("u_field", 1, "mean square heading error of the fields that corrected the heading, rad²"),
        Slot("acc_sustained", 2, "vector mean of the unit specific force's horizontal part in E6 (error model)"),
    ],
    start=K.HEADER,
)
ST = STATE.index  # first index of each slot, constant in compiled code: ``s[ST.hi_h + 2]``
STATE_SIZE = STATE.end

#: the hard-iron update's use of the scratch space (the Kalman update uses all of it in its
#: own way, see ``robust_blocks.bias_kalman_update``; the two never run interleaved)
HI_SCRATCH = Layout(
    "hard-iron scratch",
    [
        Slot("d_r", 9, "ΔR̄: change of the block mean of R_g, row-major"),
        Slot("d_y", 3, "Δȳ: change of the block mean of R_g m, µT"),
        Slot("a_inv", 9, "A⁻¹, inverse of the information matrix"),
    ],
    start=ST.scratch,
    within=(ST.scratch, 36),
).index
