"""Compiled building blocks of the robust estimator (``robust.py``): low-pass filters that
live inside the state array, the dt-keyed coefficient cache, the gyro-bias Kalman update, the 3×3 inverse that the
hard-iron least squares (``robust_mag``) uses, and ``load_tuple`` for the parameter vector.

Every function works on slots of the float64 state array ``s`` given by their first index,
so the estimator step never allocates. Filters follow the state-space conventions of
D. Laidig, T. Seel, "VQF: Highly accurate IMU orientation estimation with bias estimation
and magnetic disturbance rejection", Information Fusion 91, 2023 (section 3 and appendix):
a second-order Butterworth low-pass parametrised by a time constant τ, whose cut-off
frequency is f_c = √2 / (2π τ), so that its step response settles like a first-order
filter of time constant τ.

Credit: ``butter2_*`` and the bias Kalman update follow VQF's reference implementation
(github.com/dlaidig/vqf, vqf/cpp/vqf.cpp: filterCoeffs, filterInitialState, the bias update;
MIT, © 2021 Daniel Laidig; notice in THIRD_PARTY_NOTICES).
"""

from __future__ import annotations

import math

from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

_jit = njit(cache=True, inline="always")

SQRT2 = math.sqrt(2.0)


@_jit
def first_order_gain(dt, tau):
    """Gain k of y ← y + k (x − y) for time constant ``tau`` (s) over ``dt`` (s).

    τ ≤ 0 means "no filtering" (k = 1).
    """
    if tau <= 0.0:
        return 1.0
    return 1.0 - math.exp(-dt / tau)


@_jit
def cache_is_stale(s, key_slots, keys):
    """The dt-keyed coefficient cache's check: True, with the new ``keys`` stored in their
    slots ``key_slots`` (tuples of equal length: the dt and the time constants the cached
    coefficients were computed for), when any of them changed; False when the cache holds.

    Coefficients cost a tan() or an exp() each: at a steady rate they are computed once.
    """
    stale = False
    for k in range(len(keys)):
        if s[key_slots[k]] != keys[k]:
            stale = True
    if stale:
        for k in range(len(keys)):
            s[key_slots[k]] = keys[k]
    return stale


@_jit
def butter2_coefficients(s, i, dt, tau):
    """Stores (b0, a1, a2) of the 2nd-order Butterworth low-pass for ``tau``, ``dt`` at s[i:i+3].

    Bilinear transform with pre-warping, C = tan(π f_c dt):
    b = (C², 2C², C²)/D, a = (1, 2(C²−1)/D, (1 − √2 C + C²)/D), D = C² + √2 C + 1.
    The numerator is b0·(1, 2, 1), so b0 is all that has to be kept.
    """
    fc = SQRT2 / (2.0 * math.pi * tau)
    c = math.tan(math.pi * min(fc * dt, 0.45))  # clamp: a time step near Nyquist stays stable
    c2 = c * c
    d = c2 + SQRT2 * c + 1.0
    s[i] = c2 / d
    s[i + 1] = 2.0 * (c2 - 1.0) / d
    s[i + 2] = (1.0 - SQRT2 * c + c2) / d


@_jit
def butter2_step(s, coef, st, n, k, x):
    """One step of channel ``k`` of an ``n``-channel 2nd-order low-pass; returns the output.

    Transposed direct form II: the two delay states of channel k are s[st+k] and s[st+n+k].
    """
    b0, a1, a2 = s[coef], s[coef + 1], s[coef + 2]
    y = b0 * x + s[st + k]
    s[st + k] = 2.0 * b0 * x - a1 * y + s[st + n + k]
    s[st + n + k] = b0 * x - a2 * y
    return y


@_jit
def butter2_reset(s, coef, st, n, k, x):
    """Puts channel ``k`` into its steady state for a constant input ``x`` (output = x)."""
    b0, a2 = s[coef], s[coef + 2]
    s[st + n + k] = (b0 - a2) * x
    s[st + k] = (1.0 - b0) * x


@_jit
def bias_kalman_update(s, ip, ib, iw, h, e, w, m):
    """Kalman update of the gyro bias b (s[ib:ib+3], rad/s) with covariance P (s[ip:ip+9]).

    Measurement model e = H Δb + noise, with the first ``m`` (2 or 3) rows of the 3×3 matrix
    ``h`` (row-major 9-tuple), innovations ``e`` (rad/s, 3-tuple) and noise variances ``w``
    (3-tuple, units of P). K = P Hᵀ (W + H P Hᵀ)⁻¹; b ← b + K e; P ← P − K H P.
    s[iw:iw+36] is scratch space (P Hᵀ, S, S⁻¹, K), so nothing is allocated.
    """
    pht, sm, inv, kg = iw, iw + 9, iw + 18, iw + 27
    for r in range(3):  # P Hᵀ (3 × m)
        for c in range(m):
            acc = 0.0
            for j in range(3):
                acc += s[ip + 3 * r + j] * h[3 * c + j]
            s[pht + 3 * r + c] = acc
    for r in range(3):  # S = H P Hᵀ + W (m × m, padded with the identity to 3 × 3)
        for c in range(3):
            if r < m and c < m:
                acc = 0.0
                for j in range(3):
                    acc += h[3 * r + j] * s[pht + 3 * j + c]
                s[sm + 3 * r + c] = acc + (w[r] if r == c else 0.0)
            else:
                s[sm + 3 * r + c] = 1.0 if r == c else 0.0
    if not invert3(s, sm, inv):
        return
    for r in range(3):  # K = P Hᵀ S⁻¹ (3 × m)
        for c in range(m):
            acc = 0.0
            for j in range(m):
                acc += s[pht + 3 * r + j] * s[inv + 3 * j + c]
            s[kg + 3 * r + c] = acc
    for r in range(3):
        acc = 0.0
        for c in range(m):
            acc += s[kg + 3 * r + c] * e[c]
        s[ib + r] += acc
    # P ← P − K (H P), H P = (P Hᵀ)ᵀ as P is symmetric; S's slots are reused for the result
    for r in range(3):
        for c in range(3):
            acc = 0.0
            for j in range(m):
                acc += s[kg + 3 * r + j] * s[pht + 3 * c + j]
            s[sm + 3 * r + c] = s[ip + 3 * r + c] - acc
    for r in range(3):
        for c in range(3):
            # symmetrise: rounding must not let P drift away from a covariance
            s[ip + 3 * r + c] = 0.5 * (s[sm + 3 * r + c] + s[sm + 3 * c + r])


@_jit
def invert3(s, i, o):
    """Inverse of the 3×3 row-major matrix s[i:i+9] into s[o:o+9] (adjugate); False if singular."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = s[i], s[i + 1], s[i + 2], s[i + 3], s[i + 4], s[i + 5], s[i + 6], s[i + 7], s[i + 8]
    c00 = a4 * a8 - a5 * a7
    c01 = a5 * a6 - a3 * a8
    c02 = a3 * a7 - a4 * a6
    det = a0 * c00 + a1 * c01 + a2 * c02
    if not abs(det) > 1e-300:
        return False
    inv = 1.0 / det
    s[o] = c00 * inv
    s[o + 1] = (a2 * a7 - a1 * a8) * inv
    s[o + 2] = (a1 * a5 - a2 * a4) * inv
    s[o + 3] = c01 * inv
    s[o + 4] = (a0 * a8 - a2 * a6) * inv
    s[o + 5] = (a2 * a3 - a0 * a5) * inv
    s[o + 6] = c02 * inv
    s[o + 7] = (a1 * a6 - a0 * a7) * inv
    s[o + 8] = (a0 * a4 - a1 * a3) * inv
    return True


@_jit
def quat_to_matrix(q):
    """Row-major R(q) (body → earth) of a unit quaternion [w, x, y, z], as a 9-tuple."""
    w, x, y, z = q
    return (
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )  # fmt: skip


@intrinsic
def load_tuple(typingctx, array, length):
    """The first ``length`` (a constant) entries of a 1-D array as a tuple, loaded one by one.

    Helpers that take the tuple instead of the array cost no reference counting: numba
    increfs an array on every inlined call and prunes the pair only in simple control flow
    (see the note before ``robust._first_sample``). numba's own ``to_fixed_tuple`` rebuilds
    the tuple on the stack for every entry, quadratic in ``length``. No bounds check:
    ``length`` must not exceed the array's size.
    """
    if not isinstance(length, types.IntegerLiteral) or not isinstance(array, types.Array) or array.ndim != 1:
        return None
    n = length.literal_value
    sig = types.UniTuple(array.dtype, n)(array, length)

    def codegen(context, builder, sig, args):
        arr = context.make_array(sig.args[0])(context, builder, args[0])
        stride = cgutils.unpack_tuple(builder, arr.strides, 1)[0]
        values = [
            context.unpack_value(builder, array.dtype, cgutils.get_item_pointer2(
                context, builder, arr.data, [arr.nitems], [stride], array.layout, [context.get_constant(types.intp, i)]
            ))
            for i in range(n)
        ]
        return context.make_tuple(builder, sig.return_type, values)

    return sig, codegen
