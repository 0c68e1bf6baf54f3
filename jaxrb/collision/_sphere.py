"""Sphere (A) against sphere, box, capsule and cylinder (B): one contact each (``K = 1``).

Sphere-sphere and sphere-capsule both reduce to two "core" points, each carrying a radius:
the contact is along the line between the cores (Ericson, *Real-Time Collision Detection*,
sec. 4.3 and 5.1.2). Sphere-box and sphere-cylinder use the closest point of the solid to
the sphere centre (sec. 5.1.4 for the box), or the nearest face when the centre is inside.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import spatial
from .._indexing import literal_array
from ..shapes import Box, Capsule, Cylinder, Sphere
from . import _geometry as geo
from ._contact import Contact, contact_from_surface_point

__all__ = ["ball_box_contact", "ball_cylinder_contact", "sphere_sphere", "sphere_box", "sphere_capsule",
           "sphere_cylinder", "rounded_points_contact"]


def rounded_points_contact(
    core_a: Float[Array, "*k 3"],
    radius_a: float,
    core_b: Float[Array, "*k 3"],
    radius_b: float,
    fallback_normal: Float[Array, "*k 3"],
) -> tuple[Array, Array, Array]:
    """Contact of two balls ``(core_a, radius_a)``, ``(core_b, radius_b)``: A's surface point, normal, gap.

    ``normal = (core_a - core_b) / |core_a - core_b|`` and ``gap = |core_a - core_b| - r_a - r_b``.
    When the cores coincide every direction is a valid normal; ``fallback_normal`` (unit)
    is used. ``safe_norm`` keeps the gradient finite there (0 for the distance, whose
    derivative ``d/|d|`` is 0/0), and ``safe_normalize`` keeps the unused branch finite.
    Cores within round-off of each other (8 eps of the coordinates and radii) count as
    coincident: their difference is noise. The fallback is turned to A's side of B where
    ``d`` points against it by more than its rounding (2 eps; a common perpendicular of two
    segments has no sign of its own).

    The bound was 64 eps: in float32 at 1 km from the origin that is 7.6 mm, and cores a few
    mm apart, whose difference is good to 1%, took the fallback (two 5 mm balls side by side
    were pushed apart along z; crossing capsules 5 mm apart, into each other). Just past the
    bound ``d`` is a few ulps, which XLA may round differently where it evaluates it twice
    (under ``jit`` and ``vmap`` the norm and the quotient had given normals of length 0.05 to
    11 at 64 eps' noise): the direction is normalised a second time, from one array.
    Broadcasts over leading slot axes.
    """
    d = core_a - core_b
    distance = spatial.safe_norm(d)
    scale = jnp.maximum(jnp.max(jnp.abs(core_a), axis=-1), jnp.max(jnp.abs(core_b), axis=-1)) + radius_a + radius_b
    rounding = jnp.finfo(d.dtype).eps * scale
    coincident = distance <= 8 * rounding
    direction = spatial.safe_normalize(spatial.safe_normalize(d))
    # Turned only where d has a sign beyond its rounding: cores that coincide keep the
    # documented fallback, not one flipped by noise.
    behind = spatial.dot(fallback_normal, d) < -2 * rounding
    fallback = fallback_normal * jnp.where(behind, -1.0, 1.0).astype(d.dtype)[..., None]
    normal = jnp.where(coincident[..., None], fallback, direction)
    gap = distance - radius_a - radius_b
    return core_a - radius_a * normal, normal, gap


def sphere_sphere(
    sphere_a: Sphere,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    sphere_b: Sphere,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
    margin: float = 0.0,
) -> Contact:
    """Two spheres: ``K = 1``. Orientations are ignored.

    Coincident centres: the normal falls back to the world ``+z`` axis (A is pushed up),
    with ``gap = -(r_a + r_b)``; value and gradient stay finite.
    """
    position_a, orientation_a = geo.pose("sphere_sphere (A)", position_a, orientation_a)
    position_b, orientation_b = geo.pose("sphere_sphere (B)", position_b, orientation_b)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    position_a, position_b = geo.as_float(dtype, position_a, position_b)
    up = literal_array([0.0, 0.0, 1.0], dtype)
    surface_a, normal, gap = rounded_points_contact(position_a, sphere_a.radius, position_b, sphere_b.radius, up)
    return contact_from_surface_point(surface_a[None], normal[None], gap[None], margin)


def sphere_box(
    sphere: Sphere,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    box: Box,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
    margin: float = 0.0,
) -> Contact:
    """Sphere (A) against box (B): ``K = 1``, also with the sphere centre inside the box.

    In the box frame, with the centre at ``c`` and half extents ``e``:

    * centre outside: the closest box point is ``clip(c, -e, e)`` (Ericson sec. 5.1.4);
      the normal points from it to ``c`` and ``gap = |c - clip(c)| - r``.
    * centre inside (or on the surface, to round-off): the nearest face ``k = argmin_i (e_i - |c_i|)``
      gives the shortest way out, normal ``sign(c_k) a_k`` and
      ``gap = -(e_k - |c_k|) - r`` -- the exact signed distance, so the two branches
      agree on the surface and the gap is continuous.

    Degenerate cases, all finite in value and gradient: a centre exactly on a face takes
    the inside branch (normal = that face's); on an edge or corner, the first of the tied
    faces (x before y before z); with ``c_k = 0`` (centre of a cube) the ``+`` face.
    ``orientation_a`` is ignored.
    """
    position_a, orientation_a = geo.pose("sphere_box (sphere)", position_a, orientation_a)
    position_b, orientation_b = geo.pose("sphere_box (box)", position_b, orientation_b)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    position_a, position_b, orientation_b = geo.as_float(dtype, position_a, position_b, orientation_b)
    axes = geo.body_axes(orientation_b)  # rows: box axes, world frame
    surface_a, normal, gap, _ = ball_box_contact(position_a, sphere.radius, position_b, axes,
                                                 geo.size_vector(box.half_extents, dtype))
    return contact_from_surface_point(surface_a[None], normal[None], gap[None], margin)


def ball_box_contact(
    centre: Float[Array, "3"], radius: float, position_b: Float[Array, "3"], axes: Float[Array, "3 3"],
    half: Float[Array, "3"],
) -> tuple[Array, Array, Array, Array]:
    """A ball ``(centre, radius)`` (world frame, m) against a box at ``position_b`` whose
    world axes are the rows of ``axes``, half extents ``half``: A's surface point ``(3,)``,
    the normal ``(3,)`` (world, box to ball), the gap ``()`` and the normal in the box
    frame ``(3,)``. See :func:`sphere_box`."""
    centre = spatial.dot(axes, (centre - position_b)[None, :])  # box frame
    # Outside: the clamped point.
    closest = jnp.clip(centre, -half, half)
    offset = centre - closest
    outside_distance = spatial.safe_norm(offset)
    # A centre within round-off of the surface counts as inside, where its face gives a unit
    # normal: a compiled program can round ``offset`` differently in the two places it is
    # used, and a capsule-box slot is placed exactly on a face's plane by construction
    # (a normal of 0 was seen there under jit and vmap).
    outside = outside_distance > 64 * jnp.finfo(centre.dtype).eps * (jnp.max(jnp.abs(centre)) + jnp.sum(half))
    # Inside: the nearest face. Its sign never returns 0, so a centred sphere still gets a face.
    depth = half - jnp.abs(centre)  # distance to each pair of faces, >= 0 inside
    k = jnp.argmin(depth)
    face_sign = geo.sign_nonzero(centre[k])
    face_normal = face_sign * jnp.eye(3, dtype=centre.dtype)[k]
    inside_closest = centre.at[k].set(face_sign * half[k])
    normal_box = jnp.where(outside, spatial.safe_normalize(offset), face_normal)
    box_point = jnp.where(outside, closest, inside_closest)
    gap = jnp.where(outside, outside_distance, -depth[k]) - radius
    normal = spatial.dot(spatial.transpose(axes), normal_box[None, :])  # back to world
    surface_b = position_b + spatial.dot(spatial.transpose(axes), box_point[None, :])
    return surface_b + gap * normal, normal, gap, normal_box


def sphere_capsule(
    sphere: Sphere,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    capsule: Capsule,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
    margin: float = 0.0,
) -> Contact:
    """Sphere (A) against capsule (B): ``K = 1``.

    The capsule is the segment ``c_b + t a``, ``|t| <= half_length`` (``a`` = its body z
    axis), rounded by its radius; the contact is sphere-sphere with the segment point
    closest to the sphere centre. Centre exactly on the segment: the normal falls back to
    the capsule's body x axis, perpendicular to the segment, which is the shortest way out
    (``gap = -(r_sphere + r_capsule)``). ``orientation_a`` is ignored.
    """
    position_a, orientation_a = geo.pose("sphere_capsule (sphere)", position_a, orientation_a)
    position_b, orientation_b = geo.pose("sphere_capsule (capsule)", position_b, orientation_b)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    position_a, position_b, orientation_b = geo.as_float(dtype, position_a, position_b, orientation_b)
    axes = geo.body_axes(orientation_b)
    _, core_b = geo.closest_on_segment(position_b, axes[2], capsule.half_length, position_a)
    surface_a, normal, gap = rounded_points_contact(position_a, sphere.radius, core_b, capsule.radius, axes[0])
    return contact_from_surface_point(surface_a[None], normal[None], gap[None], margin)


def sphere_cylinder(
    sphere: Sphere,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    cylinder: Cylinder,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
    margin: float = 0.0,
) -> Contact:
    """Sphere (A) against cylinder (B): ``K = 1``, also with the sphere centre inside it.

    In the cylinder's frame (axis z), with the centre at radial offset ``rho`` and height
    ``z``:

    * centre outside: the closest point of the solid cylinder has its radial offset cut to
      the radius and its height to ``[-h, h]`` (a point of the side, a cap or the rim); the
      normal points from it to the centre and ``gap = distance - r``;
    * centre inside (or on the surface, to round-off): the nearer of the side
      (``R - |rho|`` away, radial normal) and the cap on its side (``h - |z|``), whose
      depth is the exact signed distance, so the gap is continuous across the surface.

    Degenerate cases, all finite in value and gradient: a centre on the axis takes the
    cylinder's body x axis as its radial direction; on an inside tie, the cap.
    ``orientation_a`` is ignored.
    """
    position_a, orientation_a = geo.pose("sphere_cylinder (sphere)", position_a, orientation_a)
    position_b, orientation_b = geo.pose("sphere_cylinder (cylinder)", position_b, orientation_b)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    position_a, position_b, orientation_b = geo.as_float(dtype, position_a, position_b, orientation_b)
    surface_a, normal, gap = ball_cylinder_contact(position_a, sphere.radius, position_b,
                                                   geo.body_axes(orientation_b), cylinder.radius,
                                                   cylinder.half_length)
    return contact_from_surface_point(surface_a[None], normal[None], gap[None], margin)


def ball_cylinder_contact(
    centre: Float[Array, "3"], radius: float, position_b: Float[Array, "3"], axes: Float[Array, "3 3"],
    cylinder_radius: float, half_length: float,
) -> tuple[Array, Array, Array]:
    """A ball ``(centre, radius)`` (world frame, m) against a cylinder at ``position_b``
    whose world axes are the rows of ``axes`` (its axis the third): A's surface point
    ``(3,)``, the normal ``(3,)`` (world, cylinder to ball) and the gap ``()``. See
    :func:`sphere_cylinder`."""
    local = spatial.dot(axes, (centre - position_b)[None, :])  # cylinder frame
    x_axis, z_axis = literal_array([1.0, 0.0, 0.0], local.dtype), literal_array([0.0, 0.0, 1.0], local.dtype)
    radial = local * literal_array([1.0, 1.0, 0.0], local.dtype)
    rho = spatial.safe_norm(radial)
    # Within round-off of the axis, the radial direction is body x. Its components are
    # round-off there, and XLA may round them differently where it computes them again
    # for rho (a centre 0.1 m along a turned axis: |radial / rho| = 1.15 under jit).
    round_off = 64 * jnp.finfo(local.dtype).eps * (jnp.max(jnp.abs(local)) + cylinder_radius + half_length)
    on_axis = rho <= round_off
    outward = jnp.where(on_axis, x_axis, radial / jnp.where(on_axis, 1.0, rho))
    height = local[2]
    # Outside: the closest point of the solid (side, cap or rim).
    closest = outward * jnp.minimum(rho, cylinder_radius) + z_axis * jnp.clip(height, -half_length, half_length)
    offset = local - closest
    outside_distance = spatial.safe_norm(offset)
    # Within round-off of the surface counts as inside, as in ball_box_contact.
    outside = outside_distance > round_off
    # Inside: the nearer of the side and the cap on the centre's side.
    side_depth, cap_depth = cylinder_radius - rho, half_length - jnp.abs(height)
    side = side_depth < cap_depth
    cap_sign = geo.sign_nonzero(height)
    inside_normal = jnp.where(side, outward, cap_sign * z_axis)
    inside_point = jnp.where(side, outward * cylinder_radius + z_axis * height,
                             radial + z_axis * cap_sign * half_length)
    normal_local = jnp.where(outside, spatial.safe_normalize(offset), inside_normal)
    point_local = jnp.where(outside, closest, inside_point)
    gap = jnp.where(outside, outside_distance, -jnp.minimum(side_depth, cap_depth)) - radius
    to_world = spatial.transpose(axes)
    normal = spatial.dot(to_world, normal_local[None, :])
    surface_b = position_b + spatial.dot(to_world, point_local[None, :])
    return surface_b + gap * normal, normal, gap
