"""Spatial algebra: vectors, skew matrices, quaternions, rotation matrices, Euler angles.

Conventions (used throughout jaxrb):

* Quaternions are scalar first, ``q = (w, x, y, z) = (cos(phi/2), sin(phi/2) * axis)``
  (seed 000, "Rotation in 3-d"). A unit quaternion maps **body** vectors to **world**
  vectors: ``v_world = q (0, v_body) q*``.
* A rotation matrix ``A`` has the body axes, expressed in the world frame, as its columns
  (seed 000: "the columns a1, a2, a3 of A are the new axes"), so ``v_world = A @ v_body``.
* Rotation vectors ``r = phi * axis`` (radians) are the coordinates of the exponential map.

All functions broadcast over leading axes. 3x3 products are written element-wise instead
of with ``@``/``einsum``: on GPUs a matmul may silently run in TF32 (10-bit mantissa),
which would wreck the 1e-12 invariants the tests check. Element-wise multiply-and-sum is
exact in every dtype and fuses into the surrounding kernel.

Every normalisation is *safe*: finite value and finite gradient at zero (double-``where``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "safe_norm",
    "safe_normalize",
    "cross",
    "dot",
    "skew",
    "vee",
    "matvec",
    "matmul",
    "transpose",
    "inverse3",
    "quat_multiply",
    "quat_conjugate",
    "quat_rotate",
    "quat_rotate_inverse",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_from_axis_angle",
    "quat_exp",
    "quat_log",
    "quat_normalize",
    "rotation_matrix_exp",
    "rotation_angle",
    "euler_to_quat",
    "quat_to_euler",
    "euler_to_matrix",
    "matrix_to_euler",
    "gram_schmidt",
    "polar_orthonormalize",
    "identity_quat",
]

# Below this squared angle the Taylor series replaces sin(x)/x-type quotients. At
# theta^2 = 1e-6 the first dropped term (theta^6 / 322560 for sin(theta/2)/theta) is
# ~3e-24, far below float64 resolution, and the series has exact derivatives at 0.
_SMALL_ANGLE_SQ = 1e-6


# --------------------------------------------------------------------------- vectors


def _sum_last(x: Array) -> Array:
    """Sum over a short last axis as explicit element-wise adds, not a reduce op.

    XLA:CPU (jax 0.10) hands reduce ops over length-3/4 axes of large batches to
    YNNPACK kernels that are several times slower than fused element-wise code
    (benchmarks/free_body.py). Unrolling keeps the whole step one fused loop.
    """
    if x.shape[-1] > 4:
        return jnp.sum(x, axis=-1)
    first, *rest = _components(x)
    for c in rest:
        first = first + c
    return first


def _components(x: ArrayLike) -> list[Array]:
    """The ``n`` components of ``x`` along its last axis, each of shape ``(...)``.

    One ``unstack``, whose transpose in reverse mode is one ``stack``. Indexing each
    component (``x[..., i]``) transposes to one ``pad`` per component instead, and
    XLA:CPU runs each pad as its own kernel: taking components this way removed about 16
    of the bouncing ball's 274 reverse-pass kernels a step (benchmarks/README.md,
    "Components by ``unstack``").
    """
    return jnp.unstack(jnp.asarray(x), axis=-1)


def dot(a: Float[ArrayLike, "... n"], b: Float[ArrayLike, "... n"]) -> Float[Array, "..."]:
    """Element-wise dot product over the last axis (exact: no matmul unit)."""
    return _sum_last(jnp.asarray(a) * jnp.asarray(b))


def cross(a: Float[ArrayLike, "... 3"], b: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """Cross product ``a x b`` over the last axis."""
    ax, ay, az = _components(a)
    bx, by, bz = _components(b)
    return jnp.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def safe_norm(
    x: Float[ArrayLike, "... n"], axis: int = -1, keepdims: bool = False
) -> Float[Array, "..."]:
    """Euclidean norm whose gradient is 0 (not NaN) at ``x = 0``.

    ``d|x|/dx = x/|x|`` is 0/0 at the origin, and ``jnp.linalg.norm`` returns NaN there.
    The inner ``where`` keeps the square root's argument away from 0 on the masked branch,
    so that branch's (discarded) derivative is finite; the outer ``where`` selects the
    value. The mask is per element, never one ``allclose`` over a whole batch. It tests
    ``sq == 0`` (not ``sq > 0``) so that a NaN input stays NaN instead of becoming 0.
    """
    x = jnp.asarray(x)
    if axis in (-1, x.ndim - 1):
        sq = _sum_last(x * x)
        sq = sq[..., None] if keepdims else sq
    else:
        sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    zero = sq == 0
    return jnp.where(zero, 0.0, jnp.sqrt(jnp.where(zero, 1.0, sq)))


def safe_normalize(x: Float[ArrayLike, "... n"], axis: int = -1) -> Float[Array, "... n"]:
    """``x / |x|``, returning 0 (with a finite gradient) where ``x = 0``."""
    x = jnp.asarray(x)
    n = safe_norm(x, axis=axis, keepdims=True)
    zero = n == 0  # NaN stays NaN: a blow-up must not be silently reset
    return jnp.where(zero, 0.0, x / jnp.where(zero, 1.0, n))


def skew(w: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3 3"]:
    """The cross-product matrix ``w~`` with ``w~ @ x = w x x`` (seed 000).

    ``[[0, -wz, wy], [wz, 0, -wx], [-wy, wx, 0]]``.
    """
    wx, wy, wz = _components(w)
    z = jnp.zeros_like(wx)
    return jnp.stack(
        [
            jnp.stack([z, -wz, wy], axis=-1),
            jnp.stack([wz, z, -wx], axis=-1),
            jnp.stack([-wy, wx, z], axis=-1),
        ],
        axis=-2,
    )


def vee(m: Float[ArrayLike, "... 3 3"]) -> Float[Array, "... 3"]:
    """Inverse of :func:`skew` applied to the skew part ``(M - M^T)/2`` of ``M``."""
    m = jnp.asarray(m)
    return 0.5 * jnp.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        axis=-1,
    )


def matvec(m: Float[ArrayLike, "... 3 3"], v: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """``M @ v`` element-wise (exact in every dtype; see the module docstring)."""
    return _sum_last(jnp.asarray(m) * jnp.asarray(v)[..., None, :])


def matmul(a: Float[ArrayLike, "... 3 3"], b: Float[ArrayLike, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """``A @ B`` for 3x3 matrices, element-wise (exact in every dtype)."""
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    return _sum_last(a[..., :, None, :] * transpose(b)[..., None, :, :])


def transpose(m: Float[ArrayLike, "... i j"]) -> Float[Array, "... j i"]:
    """Swap the last two axes."""
    return jnp.swapaxes(jnp.asarray(m), -1, -2)


def inverse3(m: Float[ArrayLike, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """Inverse of a 3x3 matrix by the adjugate: ``adj(M) / det(M)``.

    Closed form, so it vectorises as plain element-wise arithmetic; used for inertia
    tensors, which the scene validates to be symmetric positive definite. Computed on
    ``M / max|M_ij|`` and divided by that scale after: ``det`` is cubic in ``M``, so
    unscaled it underflowed in float32 below about 1e-13 kg m^2 (a 0.1 mm grain, whose
    inverse came out inf) and overflowed above about 1e13.
    """
    m = jnp.asarray(m)
    # The scale is a constant of the algorithm (the inverse does not depend on it), so it
    # carries no derivative.
    scale = jax.lax.stop_gradient(jnp.max(jnp.abs(m), axis=(-2, -1)))
    scale = jnp.where(scale > 0, scale, jnp.ones_like(scale))[..., None, None]
    m = m / scale
    c0 = cross(m[..., 1, :], m[..., 2, :])
    c1 = cross(m[..., 2, :], m[..., 0, :])
    c2 = cross(m[..., 0, :], m[..., 1, :])
    det = dot(m[..., 0, :], c0)
    # Rows of the inverse's transpose are the cofactor rows c_i, so inv = [c0 c1 c2] / det.
    return jnp.stack([c0, c1, c2], axis=-1) / (det[..., None, None] * scale)


# ----------------------------------------------------------------------- quaternions


def identity_quat(shape: tuple[int, ...] = (), dtype=None) -> Float[Array, "... 4"]:
    """The identity rotation ``(1, 0, 0, 0)`` broadcast to ``shape + (4,)``."""
    q = jnp.zeros((*shape, 4), dtype=dtype)
    return q.at[..., 0].set(1.0)


def quat_multiply(p: Float[ArrayLike, "... 4"], q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 4"]:
    """Hamilton product ``p q`` (apply ``q`` first, then ``p``)."""
    pw, px, py, pz = _components(p)
    qw, qx, qy, qz = _components(q)
    return jnp.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conjugate(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 4"]:
    """``q* = (w, -x, -y, -z)``: the inverse of a unit quaternion."""
    w, x, y, z = _components(q)
    return jnp.stack([w, -x, -y, -z], axis=-1)


def non_unit_norms(q) -> tuple[np.ndarray, np.ndarray]:
    """The norms of concrete quaternions ``(..., 4)`` given as input, and which of them are
    not 1 to 1e-3 (NumPy, for input checks: rounded decimals such as 0.7071 pass; the
    pose is read with the unit quaternion's formula, so any other norm distorts it)."""
    norms = np.linalg.norm(np.asarray(q, dtype=float), axis=-1)
    return norms, ~(np.abs(norms - 1.0) <= 1e-3)


#: What the error for a non-unit input quaternion advises.
UNIT_QUATERNION_ADVICE = ("Pass (w, x, y, z), scalar first, with norm 1, e.g. from "
                          "rb.spatial.quat_from_axis_angle or rb.spatial.quat_normalize.")


@jax.custom_jvp
def quat_normalize(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 4"]:
    """Project onto the unit sphere. A zero quaternion becomes the identity; NaN stays NaN.

    One zero test on ``|q|^2``, not :func:`safe_norm` and a second test on ``|q|``: that
    made XLA:CPU run the norm, the guarded divisor and the quotient as three kernels in
    every integrator's step, where this runs two (``benchmarks/kernels.py``). The divisor
    stays behind a ``where``: written as ``q / sqrt(|q|^2)``, XLA rewrites it to
    ``q * rsqrt(|q|^2)``, one rounding more, which raised the round-off floor of the
    fourth-order convergence tests (RKMK4 after 12,800 steps: 1.9e-14 -> 5.5e-14 rad).
    This form gives the values of the former one to the last bit.

    Its tangent is written out (:func:`_quat_normalize_jvp`).
    """
    return _quat_normalized(jnp.asarray(q))[0]


def _quat_normalized(q: Array) -> tuple[Array, Array, Array]:
    """``(q / |q|, |q|, |q| == 0)``, the divisor 1 where ``q = 0`` (keepdims)."""
    sq = _sum_last(q * q)[..., None]
    zero = sq == 0
    # The inner where keeps sqrt's (discarded) derivative finite at q = 0.
    divisor = jnp.where(zero, 1.0, jnp.sqrt(jnp.where(zero, 1.0, sq)))
    return jnp.where(zero, identity_quat(q.shape[:-1], q.dtype), q / divisor), divisor, zero


@quat_normalize.defjvp
def _quat_normalize_jvp(primals, tangents):
    """``d(q/|q|) = (dq - u (u . dq)) / |q|`` with ``u = q/|q|``: the tangent's component
    along ``u`` removed, through the output and the divisor the value already computed (0
    at ``q = 0``, where the output is the constant identity).

    Differentiated through its arithmetic instead, the reverse pass recomputed the norm's
    square root and its derivative's quotients as kernels of their own (XLA does not
    duplicate a square root or a division into the four components' kernel): measured with
    ``benchmarks/kernels.py``, the ball's reverse pass 81.4 -> 76.4 kernels a step and the
    tumbling box's 64.9 -> 59.9; the forward is the same program. The ball's gradient is
    the same to the 16 digits printed."""
    (q,), (dq,) = primals, tangents
    q = jnp.asarray(q)
    unit, divisor, zero = _quat_normalized(q)
    along = _sum_last(unit * dq)[..., None]
    return unit, jnp.where(zero, 0.0, (dq - unit * along) / divisor)


def quat_rotate(q: Float[ArrayLike, "... 4"], v: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """Rotate ``v`` by unit quaternion ``q``: ``q (0, v) q*`` (seed 000's Rot(v)).

    Uses the expanded form ``v + 2 w (u x v) + 2 u x (u x v)`` with ``u = (x, y, z)``,
    which costs two cross products instead of two Hamilton products.
    """
    v = jnp.asarray(v)
    w, x, y, z = _components(q)
    u = jnp.stack([x, y, z], axis=-1)
    t = 2.0 * cross(u, v)
    return v + w[..., None] * t + cross(u, t)


def quat_rotate_inverse(q: Float[ArrayLike, "... 4"], v: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """Rotate ``v`` by ``q*`` (world to body for a body-to-world ``q``)."""
    return quat_rotate(quat_conjugate(q), v)


def quat_to_matrix(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 3 3"]:
    """Rotation matrix ``A`` of a unit quaternion, so that ``A v = q (0, v) q*``."""
    w, x, y, z = _components(q)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)], axis=-1),
            jnp.stack([2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)], axis=-1),
            jnp.stack([2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)], axis=-1),
        ],
        axis=-2,
    )


def matrix_to_quat(m: Float[ArrayLike, "... 3 3"]) -> Float[Array, "... 4"]:
    """Unit quaternion of a rotation matrix (Shepperd's method), with ``w >= 0``.

    Shepperd's method divides by the largest of ``4w^2, 4x^2, 4y^2, 4z^2``, so it is
    accurate for every rotation, including 180-degree turns where the trace form fails.
    All four candidates are computed and one is selected; each square root's argument is
    floored at 0.5 so the unselected candidates have finite derivatives (the selected
    one's argument is at least 1 for an orthonormal matrix). A slightly non-orthonormal
    matrix (an un-reorthonormalised explicit-Euler ``A``) gives a unit quaternion within
    an angle of the order of its deviation from its nearest rotation, not that rotation's:
    for ``A = R (I + e S)``, ``S`` symmetric (nearest rotation ``R``), 5.5e-5 rad off at
    ``e = 1e-4`` and 5.5e-7 at ``1e-6`` (first order in ``e``).
    """
    m = jnp.asarray(m)
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    trace = m00 + m11 + m22

    def half_root(arg):
        return 0.5 * jnp.sqrt(jnp.maximum(arg, 0.5))

    rw = half_root(1.0 + trace)
    rx = half_root(1.0 + m00 - m11 - m22)
    ry = half_root(1.0 - m00 + m11 - m22)
    rz = half_root(1.0 - m00 - m11 + m22)
    # Each candidate is 4 * (quaternion) * (its largest component), rescaled below.
    cand_w = jnp.stack([rw, (m21 - m12) / (4 * rw), (m02 - m20) / (4 * rw), (m10 - m01) / (4 * rw)], -1)
    cand_x = jnp.stack([(m21 - m12) / (4 * rx), rx, (m01 + m10) / (4 * rx), (m02 + m20) / (4 * rx)], -1)
    cand_y = jnp.stack([(m02 - m20) / (4 * ry), (m01 + m10) / (4 * ry), ry, (m12 + m21) / (4 * ry)], -1)
    cand_z = jnp.stack([(m10 - m01) / (4 * rz), (m02 + m20) / (4 * rz), (m12 + m21) / (4 * rz), rz], -1)
    choice = jnp.argmax(jnp.stack([trace, m00, m11, m22], axis=-1), axis=-1)[..., None]
    q = jnp.where(choice == 0, cand_w, jnp.where(choice == 1, cand_x, jnp.where(choice == 2, cand_y, cand_z)))
    q = jnp.where(q[..., :1] < 0, -q, q)
    return quat_normalize(q)


def quat_from_axis_angle(
    axis: Float[ArrayLike, "... 3"], angle: Float[ArrayLike, "..."]
) -> Float[Array, "... 4"]:
    """``(cos(phi/2), sin(phi/2) * axis/|axis|)`` (seed 000). ``angle`` in radians.

    ``axis`` need not be a unit vector; its batch shape and ``angle``'s broadcast (one axis
    and many angles, or many axes and one angle). A zero axis names no rotation: given as
    a concrete array it is refused; under ``jit`` (where it cannot be refused) the result
    there is the identity ``(1, 0, 0, 0)``, a unit quaternion like every other.
    """
    axis, angle = jnp.asarray(axis), jnp.asarray(angle)
    if axis.ndim == 0 or axis.shape[-1] != 3:
        raise ValueError(f"quat_from_axis_angle: axis must have shape (..., 3); got {axis.shape}.")
    norm = safe_norm(axis, keepdims=True)
    if not isinstance(norm, jax.core.Tracer) and bool(np.any(np.asarray(norm) == 0)):
        raise ValueError("quat_from_axis_angle: an axis is zero, so it names no rotation: give a nonzero axis "
                         "(for no rotation, any axis with angle 0).")
    batch = jnp.broadcast_shapes(axis.shape[:-1], angle.shape)
    half = jnp.broadcast_to(0.5 * angle, batch)[..., None]
    axis = jnp.broadcast_to(safe_normalize(axis), (*batch, 3))
    zero = jnp.broadcast_to(norm == 0, (*batch, 1))
    return jnp.concatenate([jnp.where(zero, 1.0, jnp.cos(half)), jnp.sin(half) * axis], axis=-1)


def _sin_half_over(theta_sq):
    """``sin(theta/2) / theta`` as a function of ``theta^2``, smooth at 0."""
    small = theta_sq < _SMALL_ANGLE_SQ
    safe_sq = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(safe_sq)
    series = 0.5 - theta_sq / 48.0 + theta_sq * theta_sq / 3840.0
    return jnp.where(small, series, jnp.sin(0.5 * theta) / theta)


def quat_exp(rotation_vector: Float[ArrayLike, "... 3"]) -> Float[Array, "... 4"]:
    """Exponential map: the unit quaternion of a rotation by ``|r|`` about ``r/|r|``.

    ``exp(r) = (cos(|r|/2), sin(|r|/2) r/|r|)``. Exact for any angle, smooth at ``r = 0``
    (Taylor series there), so value and gradient are finite for a body at rest.
    Seed 001 ("rotate by theta = |omega| dt about omega") is ``quat_exp(omega * dt)``.
    """
    r = jnp.asarray(rotation_vector)
    theta_sq = _sum_last(r * r)[..., None]
    small = theta_sq < _SMALL_ANGLE_SQ
    cos_half = jnp.where(
        small,
        1.0 - theta_sq / 8.0 + theta_sq * theta_sq / 384.0,
        jnp.cos(0.5 * jnp.sqrt(jnp.where(small, 1.0, theta_sq))),
    )
    return jnp.concatenate([cos_half, _sin_half_over(theta_sq) * r], axis=-1)


def quat_log(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 3"]:
    """Logarithm map: the rotation vector ``phi * axis`` of a unit quaternion, ``|phi| <= pi``.

    ``q`` and ``-q`` are the same rotation; the sign with ``w >= 0`` is used so the angle
    is the short way round. Smooth at the identity (series for ``atan2(s, w)/s``).
    """
    q = jnp.asarray(q)
    q = jnp.where(q[..., :1] < 0, -q, q)
    w = q[..., :1]
    v = q[..., 1:]
    s_sq = _sum_last(v * v)[..., None]
    small = s_sq < _SMALL_ANGLE_SQ
    s = jnp.sqrt(jnp.where(small, 1.0, s_sq))
    # atan2(s, w)/s = atan(t)/(w t) with t = s/w -> 1/w as s -> 0 (w -> 1 there).
    w_safe = jnp.where(small, w, 1.0)
    ratio_sq = s_sq / (w_safe * w_safe)
    # Series of atan(t)/t to t^4: the first dropped term, t^6/7, is < 2e-19 here.
    series = (1.0 / w_safe) * (1.0 - ratio_sq / 3.0 + ratio_sq * ratio_sq / 5.0)
    scale = jnp.where(small, series, jnp.arctan2(s, w) / s)
    return 2.0 * scale * v


def rotation_matrix_exp(rotation_vector: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3 3"]:
    """Rodrigues' formula ``exp(r~)``, via the quaternion exponential."""
    return quat_to_matrix(quat_exp(rotation_vector))


def rotation_angle(
    r_a: Float[ArrayLike, "... 3 3"], r_b: Float[ArrayLike, "... 3 3"]
) -> Float[Array, "..."]:
    """Angle (radians) of the relative rotation ``M = R_a^T R_b``.

    Uses ``atan2(|vee(M - M^T)|/2 ... , (tr M - 1)/2)``, i.e. ``atan2(sin phi, cos phi)``.
    The ``arccos((tr M - 1)/2)`` form loses all accuracy for small angles (it floors
    at ~2e-8 rad in float64); this one is accurate down to round-off.
    """
    m = matmul(transpose(r_a), r_b)
    sin_phi = safe_norm(vee(m))
    cos_phi = 0.5 * (m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2] - 1.0)
    return jnp.arctan2(sin_phi, cos_phi)


# ----------------------------------------------------------------------- Euler angles


def euler_to_quat(
    roll: Float[ArrayLike, "..."], pitch: Float[ArrayLike, "..."], yaw: Float[ArrayLike, "..."]
) -> Float[Array, "... 4"]:
    """Quaternion of roll/pitch/yaw (aircraft, seed 000's "roll, pitch, heading").

    Convention: ``R = Rz(yaw) Ry(pitch) Rx(roll)``, i.e. rotate about the body x axis by
    roll, then about the *new* y axis by pitch, then the new z axis by yaw (intrinsic
    z-y'-x'' read right to left). As seed 000 warns, Euler angles "depend on the order of
    application": the same three numbers in another order give another rotation, and at
    ``pitch = +-pi/2`` roll and yaw become indistinguishable (gimbal lock). jaxrb stores
    quaternions; Euler angles are for input and display only.
    """
    dtype = jnp.result_type(roll, pitch, yaw, float)
    ex = jnp.asarray([1.0, 0.0, 0.0], dtype=dtype)
    ey = jnp.asarray([0.0, 1.0, 0.0], dtype=dtype)
    ez = jnp.asarray([0.0, 0.0, 1.0], dtype=dtype)
    qx = quat_from_axis_angle(ex, roll)
    qy = quat_from_axis_angle(ey, pitch)
    qz = quat_from_axis_angle(ez, yaw)
    return quat_multiply(qz, quat_multiply(qy, qx))


def euler_to_matrix(
    roll: Float[ArrayLike, "..."], pitch: Float[ArrayLike, "..."], yaw: Float[ArrayLike, "..."]
) -> Float[Array, "... 3 3"]:
    """``Rz(yaw) Ry(pitch) Rx(roll)``; see :func:`euler_to_quat` for the convention."""
    return quat_to_matrix(euler_to_quat(roll, pitch, yaw))


def matrix_to_euler(m: Float[ArrayLike, "... 3 3"]) -> Float[Array, "... 3"]:
    """``(roll, pitch, yaw)`` of ``R = Rz(yaw) Ry(pitch) Rx(roll)``, pitch in [-pi/2, pi/2].

    At gimbal lock (``|pitch| = pi/2``) only ``yaw -/+ roll`` is defined; the split
    returned there is arbitrary but the rotation it encodes is right, in float32 as well.
    """
    m = jnp.asarray(m)
    # Roll first, then yaw from the entries that the roll's rotation turns into (sin, cos)
    # of the yaw: ``s m02 - c m01 = sin(yaw)``, ``c m11 - s m12 = cos(yaw)`` for any pitch.
    # So the yaw matches whatever roll round-off gives near the lock, and no threshold
    # decides when the lock starts. (A fixed threshold of 1e-9 on cos(pitch) let float32's
    # round-off, ~1e-7, through: the angles then encoded a rotation up to 2 off in its
    # entries.)
    roll = jnp.arctan2(m[..., 2, 1], m[..., 2, 2])
    pitch = jnp.arctan2(-m[..., 2, 0], safe_norm(jnp.stack([m[..., 0, 0], m[..., 1, 0]], -1)))
    s, c = jnp.sin(roll), jnp.cos(roll)
    yaw = jnp.arctan2(s * m[..., 0, 2] - c * m[..., 0, 1], c * m[..., 1, 1] - s * m[..., 1, 2])
    return jnp.stack([roll, pitch, yaw], axis=-1)


def quat_to_euler(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 3"]:
    """``(roll, pitch, yaw)`` of a unit quaternion; inverse of :func:`euler_to_quat`."""
    return matrix_to_euler(quat_to_matrix(q))


# ---------------------------------------------------------------- reorthonormalisation


def gram_schmidt(a: Float[ArrayLike, "... 3 3"], cross_third: bool = True) -> Float[Array, "... 3 3"]:
    """Reorthonormalise the columns of ``A`` exactly as seed 000 does.

    ``b1 = a1/|a1|``; ``b2 = a2 - (b1.a2) b1``, ``b2 = b2/|b2|``; then, by default, the
    seed's "better" ``b3 = b1 x b2``, which also guarantees a right-handed result
    (``det = +1``). ``cross_third=False`` uses the seed's first version,
    ``b3 = a3 - (b1.a3) b1 - (b2.a3) b2``, normalised.

    The result is biased towards the first column (``b1`` keeps ``a1``'s direction);
    :func:`polar_orthonormalize` is the unbiased nearest rotation.
    """
    a = jnp.asarray(a)
    a1, a2, a3 = a[..., :, 0], a[..., :, 1], a[..., :, 2]
    b1 = safe_normalize(a1)
    b2 = safe_normalize(a2 - dot(b1, a2)[..., None] * b1)
    if cross_third:
        b3 = cross(b1, b2)
    else:
        b3 = safe_normalize(a3 - dot(b1, a3)[..., None] * b1 - dot(b2, a3)[..., None] * b2)
    return jnp.stack([b1, b2, b3], axis=-1)


def polar_orthonormalize(a: Float[ArrayLike, "... 3 3"], iterations: int = 8) -> Float[Array, "... 3 3"]:
    """Nearest rotation to ``A`` in the Frobenius norm: the polar factor ``U V^T`` of the SVD.

    Computed by the scaled Newton iteration ``X <- (g X + X^{-T}/g) / 2`` with Higham's
    scaling ``g = (|X^{-1}|_F / |X|_F)^(1/2)``, which converges quadratically to the
    orthogonal polar factor. Unlike ``jnp.linalg.svd`` it has well-defined derivatives
    when singular values coincide, which they always do near a rotation (all equal 1).
    Eight iterations reach round-off for any ``A`` with condition number below ~1e6.
    Assumes ``det A > 0`` (a perturbed rotation); a reflection stays a reflection.
    """
    x = jnp.asarray(a)
    for _ in range(iterations):
        x_inv_t = transpose(inverse3(x))
        g = jnp.sqrt(safe_norm(x_inv_t.reshape(*x.shape[:-2], 9)) / safe_norm(x.reshape(*x.shape[:-2], 9)))
        x = 0.5 * (g[..., None, None] * x + x_inv_t / g[..., None, None])
    return x
