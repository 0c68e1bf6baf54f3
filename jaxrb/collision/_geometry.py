"""Shared geometry for the pair functions: poses, box features and segment distances.

Every function here works on ONE shape pair (no batch axes); batches come from
``jax.vmap``. 3x3 products go through :mod:`jaxrb.spatial`'s element-wise helpers, never
``@``, so they cannot silently drop to TF32 on a GPU.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .. import spatial
from .._indexing import literal_array


def pose(name: str, position: ArrayLike, orientation: ArrayLike) -> tuple[Array, Array]:
    """Check a shape pose's static shapes and return ``(position (3,), orientation (4,))``.

    The check is on shapes only, which are static, so it also runs under ``jit``/``vmap``.
    """
    if position is None or orientation is None:
        missing = "position" if position is None else "orientation"
        raise ValueError(f"{name}: no {missing} given (None); only a plane's pose may be left out. Pass a (3,) "
                         "position (m, world) and a (4,) unit quaternion (scalar first), e.g. (1, 0, 0, 0).")
    position = jnp.asarray(position)
    orientation = jnp.asarray(orientation)
    if position.shape != (3,):
        raise ValueError(
            f"{name}: position must have shape (3,) (one shape's centre, world frame, m), got "
            f"{position.shape}. Use jax.vmap for batches of poses."
        )
    if orientation.shape != (4,):
        raise ValueError(
            f"{name}: orientation must have shape (4,) (unit quaternion, scalar first, body to "
            f"world), got {orientation.shape}. Use jax.vmap for batches of poses."
        )
    check_unit_quaternion(f"{name}: orientation", orientation)
    return position, orientation


def check_unit_quaternion(label: str, orientation) -> None:
    """Refuse a concrete quaternion whose norm is not 1 (:func:`jaxrb.spatial.non_unit_norms`,
    as ``Scene.state`` does): the rotation is read from it by the unit quaternion's
    formula, which for any other norm stretches the shape (``(1, 1, 0, 0)``: by sqrt(5)
    across two axes) or gives no rotation at all (``(0.5, 0, 0, 0)``). A traced one passes
    (a simulation keeps its attitudes normalised)."""
    if orientation is None or isinstance(orientation, jax.core.Tracer) or np.shape(orientation) != (4,):
        return  # (a wrong shape is :func:`pose`'s to report)
    norm, bad = spatial.non_unit_norms(orientation)
    if bad:
        raise ValueError(f"{label} is not a unit quaternion (norm {float(norm):.6g}). "
                         + spatial.UNIT_QUATERNION_ADVICE)


def float_dtype(*arrays: Array):
    """The floating dtype of a pair computation: the inputs' common float type."""
    return jnp.result_type(*arrays, float)


def size_vector(values, dtype) -> Array:
    """A shape's sizes (a box's half extents, a plane's normal) as an array ``(n,)``:
    literals when they are static floats (see :func:`jaxrb._indexing.literal_array`), and
    the traced values as they are when differently sized shapes of one type share one
    vmapped narrow phase (:func:`jaxrb.contact._layout.build_layout`)."""
    if any(isinstance(v, jax.core.Tracer) for v in values):
        return jnp.stack([jnp.asarray(v, dtype) for v in values])
    return literal_array(values, dtype)


def smallest(*sizes):
    """The smallest of a shape pair's sizes: Python's ``min`` for static floats (a
    constant of the program), ``jnp.min`` for traced ones (see :func:`size_vector`)."""
    if any(isinstance(v, jax.core.Tracer) for v in sizes):
        return jnp.min(jnp.stack([jnp.asarray(v) for v in sizes]))
    return min(sizes)


def as_float(dtype, *arrays: ArrayLike) -> tuple[Array, ...]:
    return tuple(jnp.asarray(a, dtype=dtype) for a in arrays)


def check_margin(margin) -> None:
    """A negative margin would make separated shapes 'active': refuse it, and anything but one
    number, when it is concrete (a JAX array too; a traced one passes)."""
    if isinstance(margin, jax.core.Tracer):
        return
    try:
        value = None if isinstance(margin, (str, bytes)) else np.asarray(margin, dtype=float)
    except (TypeError, ValueError):
        value = None
    if value is None or value.shape != () or not value >= 0:
        raise ValueError(f"margin must be one distance >= 0 in metres, got {margin!r}.")


def body_axes(orientation: Float[Array, "4"]) -> Float[Array, "3 3"]:
    """Rows are the shape frame's x, y, z axes expressed in the world frame."""
    return spatial.transpose(spatial.quat_to_matrix(orientation))


def sign_nonzero(x: Array) -> Array:
    """``+1`` for ``x >= 0`` and ``-1`` otherwise: a sign that never returns 0."""
    return jnp.where(x >= 0, 1.0, -1.0).astype(x.dtype)


#: The 8 corners of the unit cube, ``(8, 3)``, in binary order (x fastest).
CUBE_CORNERS = np.array([[sx, sy, sz] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)], dtype=float)


def box_corners(center: Array, axes: Array, half_extents: Array) -> Float[Array, "8 3"]:
    """World corners ``c + sum_i s_i e_i a_i`` of a box; ``axes`` rows are its world axes."""
    local = literal_array(CUBE_CORNERS, center.dtype) * half_extents[None, :]
    return center[None, :] + spatial.matvec(spatial.transpose(axes)[None], local)


def closest_on_segment(
    center: Array, direction: Array, half_length: Array | float, point: Array
) -> tuple[Array, Array]:
    """Parameter ``t`` in ``[-half_length, half_length]`` and point of the segment closest to ``point``.

    The segment is ``center + t * direction`` with a unit ``direction``. Broadcasts.
    """
    t = jnp.clip(spatial.dot(point - center, direction), -half_length, half_length)
    return t, center + t[..., None] * direction


def closest_between_segments(
    center_a: Array,
    direction_a: Array,
    half_a: Array | float,
    center_b: Array,
    direction_b: Array,
    half_b: Array | float,
    parallel_s: Array | None = None,
) -> tuple[Array, Array]:
    """Parameters ``(s, t)`` of the closest points of two segments ``c + s u``, ``|s| <= half``.

    Ericson, *Real-Time Collision Detection* (2005), sec. 5.1.9: solve the 2x2 normal
    equations of the two infinite lines for ``s``, clamp it, take the ``t`` closest to that
    point, and if ``t`` had to be clamped, take the ``s`` closest to the clamped ``t``.
    With unit directions the determinant of the normal equations is ``|u_a x u_b|^2``,
    computed from the cross product (accurate) instead of ``1 - (u_a.u_b)^2`` (which
    cancels catastrophically for near-parallel segments).

    Parallel guard: below ``eps`` the determinant is replaced (double ``where``) and ``s``
    set to ``parallel_s`` (default 0, the centre) -- any point of a parallel segment is
    valid, and the clamp steps then find the matching closest pair. Keeping the
    determinant above ``eps`` also keeps ``1/det^2`` finite in reverse mode. Broadcasts.
    """
    r = center_a - center_b
    b = spatial.dot(direction_a, direction_b)
    c = spatial.dot(direction_a, r)
    f = spatial.dot(direction_b, r)
    cross_ab = spatial.cross(direction_a, direction_b)
    det = spatial.dot(cross_ab, cross_ab)
    eps = jnp.finfo(det.dtype).eps
    general = det > eps
    s = jnp.clip((b * f - c) / jnp.where(general, det, 1.0), -half_a, half_a)
    fallback = jnp.zeros_like(s) if parallel_s is None else parallel_s
    s = jnp.where(general, s, fallback)
    t = b * s + f
    t_clamped = jnp.clip(t, -half_b, half_b)
    s = jnp.where(t_clamped != t, jnp.clip(b * t_clamped - c, -half_a, half_a), s)
    return s, t_clamped


def slab_intervals(
    centre: Float[Array, "3"], direction: Float[Array, "3"], half_extents: Float[Array, "3"], half_length
) -> tuple[Array, Array]:
    """Where a segment ``centre + s direction``, ``|s| <= half_length``, lies inside each of a
    box's three slabs ``|x_i| <= e_i`` (all in the box frame): ``(enter, leave)``, each
    ``(3,)``, the bounds of ``s`` per slab before clipping to ``[-half_length, half_length]``.
    A segment parallel to a slab (to ``eps``) is in it entirely or not at all: ``(-half,
    half)`` or the empty ``(half, -half)``. Intersect the slabs you need and the segment's
    own range; the interval is empty where its lower bound exceeds its upper."""
    moving = jnp.abs(direction) > jnp.finfo(centre.dtype).eps
    step = jnp.where(moving, direction, 1.0)
    ends = jnp.stack([(-half_extents - centre) / step, (half_extents - centre) / step])
    inside = jnp.abs(centre) <= half_extents
    enter = jnp.where(moving, jnp.min(ends, 0), jnp.where(inside, -half_length, half_length))
    leave = jnp.where(moving, jnp.max(ends, 0), jnp.where(inside, half_length, -half_length))
    return enter, leave


def disc_interval(
    centre: Float[Array, "3"], direction: Float[Array, "3"], radius, half_length
) -> tuple[Array, Array]:
    """Where a segment ``centre + s direction``, ``|s| <= half_length``, lies over a disc of
    ``radius`` about the z axis (``x^2 + y^2 <= radius^2``; a cylinder's frame): the bounds
    ``(enter, leave)`` of ``s`` before clipping to the segment, the roots of a quadratic. A
    segment along the axis (to ``eps``) is over it entirely or not at all; one that misses
    the disc gets the empty ``(half, -half)``."""
    eps = jnp.finfo(centre.dtype).eps
    a = direction[0] ** 2 + direction[1] ** 2
    b = centre[0] * direction[0] + centre[1] * direction[1]
    c = centre[0] ** 2 + centre[1] ** 2 - radius**2
    discriminant = b * b - a * c
    tilted = a > eps  # not parallel to the axis
    crosses = discriminant > 0
    root = jnp.where(crosses, jnp.sqrt(jnp.where(crosses, discriminant, 1.0)), 0.0)
    a_safe = jnp.where(tilted, a, 1.0)
    over = c <= 0  # a segment parallel to the axis: all of it or none
    enter = jnp.where(tilted, jnp.where(crosses, (-b - root) / a_safe, half_length),
                      jnp.where(over, -half_length, half_length))
    leave = jnp.where(tilted, jnp.where(crosses, (-b + root) / a_safe, -half_length),
                      jnp.where(over, half_length, -half_length))
    return enter, leave
