"""Shapes against the static ground :class:`~jaxrb.Plane`, the half-space ``{x : n.x <= offset}``.

The plane is always shape B and has no pose; the contact normal is the plane's ``n``. The
signed distance of a point ``x`` above the plane is ``n.x - offset``, so every contact
here is "deepest point of A vs the plane", and its gap is exact.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import spatial
from .._indexing import literal_array
from ..shapes import Box, Capsule, Cylinder, Plane, Sphere
from . import _geometry as geo
from ._contact import Contact, contact_from_surface_point

__all__ = ["sphere_plane", "box_plane", "capsule_plane", "cylinder_plane"]


def _plane_normal(plane: Plane, dtype) -> Array:
    return geo.size_vector(plane.normal, dtype)


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
    deep corners are the same contact set whichever is taken (:func:`_four_deepest`).
    Gradients flow through the chosen corners; the choice itself is piecewise constant.
    """
    position, orientation = geo.pose("box_plane", position, orientation)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position, orientation)
    position, orientation = geo.as_float(dtype, position, orientation)
    n = _plane_normal(plane, dtype)
    corners = geo.box_corners(position, geo.body_axes(orientation), geo.size_vector(box.half_extents, dtype))
    height = spatial.dot(corners, n[None, :]) - plane.offset  # (8,)
    deepest = _four_deepest(height)
    return contact_from_surface_point(corners[deepest], jnp.broadcast_to(n, (4, 3)), height[deepest], margin)


def _four_deepest(height: Float[Array, " m"]) -> Array:
    """Indices ``(4,)`` of the four lowest of ``m`` candidate heights, in candidate order.

    Ties go to the lower index, so a slot keeps its candidate while the choice is
    unchanged. The ranks come from all ``m x m`` comparisons, element-wise (``lax.top_k``
    plus a sort was several times slower on a vmapped CPU batch)."""
    index = jnp.arange(height.shape[0])
    same = height[None, :] == height[:, None]
    deeper = (height[None, :] < height[:, None]) | (same & (index[None, :] < index[:, None]))  # (i, j): j before i
    chosen = jnp.sum(deeper, axis=1) < 4  # rank in depth below 4
    running = jnp.cumsum(chosen)
    return jnp.argmax(running[None, :] == jnp.arange(1, 5)[:, None], axis=1)


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


#: Below this tilt (``sin`` of the angle between the cylinder's axis and the plane's
#: normal), :func:`cylinder_plane`'s deepest rim point slides in towards its cap's centre.
#: At a tilt ``t`` the deepest point of a rim is ``e - r w/|w|`` (``|w| = t``), whose
#: derivative in the pose grows as ``r / t``: a cylinder standing upright, tilted by
#: round-off, would carry derivatives of 1e15 through a rollout. Taken as ``e - r w /
#: max(|w|, TILT_RAMP)`` instead, it is exact above the ramp and its derivative is at most
#: ``r / TILT_RAMP``; below it, the point lies on the cap inside the rim and its height is
#: at most ``r TILT_RAMP / 4`` above the rim's lowest.
TILT_RAMP = 1e-3

#: Body angles (rad) of the four rim points per cap that hold a cylinder standing on it:
#: a square, whose edges are ``r / sqrt(2)`` from the axis. A can whose friction tips it
#: forward while it slides (moment ``mu m g h_c`` about the base's centre) is held upright
#: by them while ``mu h_c < r / sqrt(2)`` at any turn about its axis; a real can's disc holds
#: it while ``mu h_c < r``. Three points (a triangle, edges at ``r / 2``) had let a can with
#: a rim point trailing lean at half that friction.
_SQUARE = (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi)


def cylinder_plane(
    cylinder: Cylinder,
    position: Float[ArrayLike, "3"],
    orientation: Float[ArrayLike, "4"],
    plane: Plane,
    margin: float = 0.0,
) -> Contact:
    """Cylinder (A) on the ground plane (B): ``K = 5``, the five deepest of ten rim points.

    The candidates, for each cap ``e = c +- h a`` (``a`` the body z axis):

    * the rim's deepest point ``e - r u``, ``u`` the unit direction of ``w = n - (n.a) a``
      (``n`` projected onto the cap's plane): the cylinder's lowest point is always one of
      the two, so the smallest gap is the exact signed distance (below a tilt of
      :data:`TILT_RAMP`, ``u = w / TILT_RAMP``: see there);
    * four rim points fixed in the body, 90 degrees apart (:data:`_SQUARE`): a cylinder
      standing on a cap touches along its whole rim and needs points that enclose its
      centre, reaching far towards the rim, to stand and to slide upright. A fixed point is
      left out where it lies within 0.9 r of the deepest point (closer than about 54
      degrees along the rim): near the contact it would add a second contact point that a
      rolling rim brings down onto the ground, an impact every quarter of a turn.

    The five lowest candidates are the slots. Standing on a cap: the cap's deepest point
    (at its centre, within the ramp) and its four fixed points; lying on the side: the two
    rims' deepest points, the line they span; tilted onto a rim: its deepest point and the
    fixed points near the ground. All are on the cylinder's surface, so every gap is a
    point's distance to the plane. Five slots, not four: with four, a standing can would
    have to drop its deepest point (so the smallest gap would jump as it tilts past the
    ramp) or one fixed point (a triangle again).
    """
    position, orientation = geo.pose("cylinder_plane", position, orientation)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position, orientation)
    position, orientation = geo.as_float(dtype, position, orientation)
    n = _plane_normal(plane, dtype)
    x_axis, y_axis, axis = geo.body_axes(orientation)
    w = n - spatial.dot(n, axis) * axis
    u = w / jnp.maximum(spatial.safe_norm(w), TILT_RAMP)
    angles = literal_array(_SQUARE, dtype)
    fixed = jnp.cos(angles)[:, None] * x_axis[None, :] + jnp.sin(angles)[:, None] * y_axis[None, :]  # (4, 3)
    # Per cap: the deepest point, then the fixed points; valid unless near the deepest.
    rim = jnp.concatenate([-u[None, :], fixed])  # (5, 3), unit (or shorter, within the ramp)
    valid = jnp.concatenate([jnp.ones(1, bool), spatial.safe_norm(fixed + u[None, :]) >= 0.9])
    caps = literal_array([[1.0], [-1.0]], dtype) * (cylinder.half_length * axis[None, :])  # (2, 3)
    points = (position[None, None, :] + caps[:, None, :] + cylinder.radius * rim[None, :, :]).reshape(10, 3)
    height = spatial.dot(points, n[None, :]) - plane.offset
    # The five lowest by lax.top_k (stable: ties go to the lower index), in candidate
    # order, not by _four_deepest's ranks: compiled with these heights in one fusion, the
    # ranks dropped a base point of a standing cylinder for a top-cap point in 2% of
    # poses tilted by 1e-13 to 1e-3 (op by op, never), and the can stood on three points.
    # The cause inside XLA:CPU is not known. box_plane keeps the ranks: no pose of its
    # test differs, and top_k made the 5-box stack's first 200 steps 14% slower.
    masked = jnp.where(jnp.tile(valid, 2), height, jnp.inf)
    deepest = jnp.sort(jax.lax.top_k(-masked, 5)[1])
    return contact_from_surface_point(points[deepest], jnp.broadcast_to(n, (5, 3)), height[deepest], margin)
