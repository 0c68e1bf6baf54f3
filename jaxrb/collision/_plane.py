"""Shapes against the static ground :class:`~jaxrb.Plane`, the half-space ``{x : n.x <= offset}``.

The plane is always shape B and has no pose; the contact normal is the plane's ``n``. The
signed distance of a point ``x`` above the plane is ``n.x - offset``, so every contact
here is "deepest point of A vs the plane", and its gap is exact.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import spatial
from .._indexing import literal_array
from ..shapes import Box, Capsule, Plane, Sphere
from . import _geometry as geo
from ._contact import Contact, contact_from_surface_point

__all__ = ["sphere_plane", "box_plane", "capsule_plane"]


def _plane_normal(plane: Plane, dtype) -> Array:
    return literal_array(plane.normal, dtype)


def sphere_plane(
    sphere: Sphere,
    position: Float[ArrayLike, "3"],
    orientation: Float[ArrayLike, "4"],
    plane: Plane,
    margin: float = 0.0,
) -> Contact:
    """Sphere (A) on the ground plane (B): ``K = 1``.

    ``gap = n.c - offset - r``; A's surface point is the sphere's lowest point ``c - r n``.
    ``orientation`` is accepted for a uniform signature and ignored.
    """
    position, orientation = geo.pose("sphere_plane", position, orientation)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position, orientation)
    (position,) = geo.as_float(dtype, position)
    n = _plane_normal(plane, dtype)
    gap = spatial.dot(n, position) - plane.offset - sphere.radius
    lowest = position - sphere.radius * n
    return contact_from_surface_point(lowest[None], n[None], gap[None], margin)


def box_plane(
    box: Box,
    position: Float[ArrayLike, "3"],
    orientation: Float[ArrayLike, "4"],
    plane: Plane,
    margin: float = 0.0,
) -> Contact:
    """Box (A) on the ground plane (B): ``K = 4``, the four deepest corners.

    Each slot is a corner ``x`` with ``gap = n.x - offset``; a corner is active when it is
    within ``margin`` of the plane. A box resting flat has its four bottom corners active
    (a face contact needs all four to hold the box still); resting on an edge, two; on a
    vertex, one. The minimum gap is the box's exact signed distance to the plane, because
    a box's lowest point is always a corner.

    The four corners are those of lowest rank in depth (ties broken by corner index), kept
    in corner order, so a slot keeps its corner while the choice is unchanged; equally
    deep corners are the same contact set whichever is taken. The ranks come from all 8x8
    comparisons, element-wise (``lax.top_k`` plus a sort was several times slower on a
    vmapped CPU batch). Gradients flow through the chosen corners; the choice itself is
    piecewise constant.
    """
    position, orientation = geo.pose("box_plane", position, orientation)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position, orientation)
    position, orientation = geo.as_float(dtype, position, orientation)
    n = _plane_normal(plane, dtype)
    corners = geo.box_corners(position, geo.body_axes(orientation), literal_array(box.half_extents, dtype))
    height = spatial.dot(corners, n[None, :]) - plane.offset  # (8,)
    index = jnp.arange(8)
    same = height[None, :] == height[:, None]
    deeper = (height[None, :] < height[:, None]) | (same & (index[None, :] < index[:, None]))  # (i, j): j before i
    chosen = jnp.sum(deeper, axis=1) < 4  # rank in depth below 4
    running = jnp.cumsum(chosen)
    deepest = jnp.argmax(running[None, :] == jnp.arange(1, 5)[:, None], axis=1)  # the chosen corners, in order
    gap = height[deepest]
    normal = jnp.broadcast_to(n, (4, 3))
    return contact_from_surface_point(corners[deepest], normal, gap, margin)


def capsule_plane(
    capsule: Capsule,
    position: Float[ArrayLike, "3"],
    orientation: Float[ArrayLike, "4"],
    plane: Plane,
    margin: float = 0.0,
) -> Contact:
    """Capsule (A) on the ground plane (B): ``K = 2``, one per end-sphere centre.

    Slot 0 is the end at ``+half_length`` along the capsule's body z axis, slot 1 the end
    at ``-half_length``. Each is a sphere-plane contact of the end sphere; a capsule lying
    flat has both active, one standing on an end has the lower one active. The capsule's
    lowest point is always on one of its end spheres, so the minimum gap is exact.

    For a tilted capsule, the upper end's slot is that end sphere's lowest point, which
    lies inside the capsule's cylinder: a (speculative) contact of the end sphere, active
    only within the margin, not a point of the capsule's surface.
    """
    position, orientation = geo.pose("capsule_plane", position, orientation)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position, orientation)
    position, orientation = geo.as_float(dtype, position, orientation)
    n = _plane_normal(plane, dtype)
    axis = spatial.quat_rotate(orientation, literal_array([0.0, 0.0, 1.0], dtype))
    ends = position[None, :] + literal_array([[1.0], [-1.0]], dtype) * (capsule.half_length * axis[None, :])
    gap = spatial.dot(ends, n[None, :]) - plane.offset - capsule.radius
    lowest = ends - capsule.radius * n[None, :]
    return contact_from_surface_point(lowest, jnp.broadcast_to(n, (2, 3)), gap, margin)
