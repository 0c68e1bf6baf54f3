"""Capsule (A) against capsule (B), a box (B) and a cylinder (B): ``K = 2`` each.

A capsule is a segment ``c + s a``, ``|s| <= half_length`` (``a`` = its body z axis),
rounded by its radius, so capsule-capsule is segment-segment distance (Ericson,
*Real-Time Collision Detection*, sec. 5.1.9) followed by a ball-ball contact between the
two closest segment points.

Two slots, because two capsules lying side by side touch along a line, and one contact
point cannot hold one still on the other:

* slot 0: the closest pair of segment points, so its gap is the exact signed distance;
* slot 1: the end, farther from slot 0, of the interval of A's segment that B's segment
  overlaps when projected onto A's axis, paired with its closest point on B.

For parallel overlapping capsules the two slots are the two ends of the overlap (both at
the same gap). For crossing capsules slot 1 lies away from the crossing, with a larger
gap, so it is active only when it is within the margin too (like a box-plane corner),
and it is switched off when it coincides with slot 0 (perpendicular or end-to-end
capsules), so one point is never reported twice. Slot 1 is the contact of A's ball at
that end of the overlap: when A is tilted towards B there, its point on A can lie inside
A's cylinder rather than on A's surface (as for capsule-plane's upper end).

Capsule-box is a ball-box contact (:func:`._sphere.ball_box_contact`) at two points of
the segment, chosen the same way:

* slot 0: the segment point closest to the box. The box's signed distance is convex along
  the segment, so a golden-section search finds its minimiser (``GOLDEN_ITERATIONS``
  steps, no derivative through it: at a smooth minimum the distance's derivative in the
  point is 0). The ends of the overlap below are preferred where they are as close, so a
  capsule lying on a face gets the ends of its contact line, not an arbitrary point of it.
* slot 1: the end, farther from slot 0, of the overlap: the part of the segment whose
  projection along slot 0's box face normal falls on that face (the segment clipped to the
  face's two slabs). It is active only within the margin and when distinct from slot 0.

A segment that crosses the box's interior (a penetration deeper than the radius) has a
kink at the minimum; the gap's derivative there is that of the face the point lies
nearest to, with the point held.

Capsule-cylinder is the same construction with a ball-cylinder contact
(:func:`._sphere.ball_cylinder_contact`): the overlap is the part of the segment over the
cap's disc, or within the caps' slab on the side (see :func:`capsule_cylinder`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import spatial
from ..shapes import Box, Capsule, Cylinder
from . import _geometry as geo
from ._contact import Contact, contact_from_surface_point
from ._sphere import ball_box_contact, ball_cylinder_contact, rounded_points_contact

__all__ = ["capsule_box", "capsule_capsule", "capsule_cylinder"]

#: Golden-section steps for the segment point closest to a box: the bracket shrinks by
#: 0.618 a step, to 1e-10 of the segment's length after 48.
GOLDEN_ITERATIONS = 48

#: Slot 1 is reported only if it is at least this fraction of the smaller radius away
#: from slot 0 along A: closer than that, the two points lie in one contact patch and add
#: no lever arm, while a duplicated point would make a contact solver's matrix singular.
_DISTINCT_FRACTION = 1e-3


def capsule_capsule(
    capsule_a: Capsule,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    capsule_b: Capsule,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
    margin: float = 0.0,
) -> Contact:
    """Two capsules: ``K = 2`` (see the module docstring for the two slots).

    Slot 0 candidates are the general closest pair and the two overlap ends; an overlap end
    is preferred unless the general pair is closer by more than round-off, so parallel
    capsules get the two ends of their overlap rather than an arbitrary middle point, and
    near-parallel ones (where the general formula loses accuracy) never get a worse point
    than an end.

    Degenerate cases: when the segments intersect, the normal is ``a_a x a_b`` normalised
    (perpendicular to both axes, the shortest way out; its sign is arbitrary), and for
    intersecting parallel segments A's body x axis; ``gap = -(r_a + r_b)`` there.
    """
    position_a, orientation_a = geo.pose("capsule_capsule (A)", position_a, orientation_a)
    position_b, orientation_b = geo.pose("capsule_capsule (B)", position_b, orientation_b)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    position_a, orientation_a, position_b, orientation_b = geo.as_float(
        dtype, position_a, orientation_a, position_b, orientation_b
    )
    axes_a = geo.body_axes(orientation_a)
    axes_b = geo.body_axes(orientation_b)
    axis_a, axis_b = axes_a[2], axes_b[2]
    half_a, half_b = capsule_a.half_length, capsule_b.half_length

    # Interval of A's segment facing B's: B's end points projected onto A's axis, clamped.
    centre_on_a = spatial.dot(axis_a, position_b - position_a)
    reach = half_b * spatial.dot(axis_a, axis_b)
    low = jnp.clip(centre_on_a - jnp.abs(reach), -half_a, half_a)
    high = jnp.clip(centre_on_a + jnp.abs(reach), -half_a, half_a)

    s_general, t_general = geo.closest_between_segments(
        position_a, axis_a, half_a, position_b, axis_b, half_b, parallel_s=low
    )
    s_ends = jnp.stack([low, high])
    t_ends, _ = geo.closest_on_segment(
        position_b[None, :], axis_b[None, :], half_b, position_a[None, :] + s_ends[:, None] * axis_a[None, :]
    )

    def segment_distance(s, t):
        return spatial.safe_norm(delta[None, :] + s[:, None] * axis_a[None, :] - t[:, None] * axis_b[None, :])

    delta = position_a - position_b
    end_distance = segment_distance(s_ends, t_ends)
    best_end = jnp.argmin(end_distance)
    # Round-off in a distance of points ~|c_a - c_b| + half lengths away from each other.
    eps = jnp.finfo(dtype).eps
    tolerance = 64 * eps * (spatial.safe_norm(delta) + half_a + half_b)
    general_distance = segment_distance(s_general[None], t_general[None])[0]
    use_general = general_distance < end_distance[best_end] - tolerance
    s0 = jnp.where(use_general, s_general, s_ends[best_end])
    t0 = jnp.where(use_general, t_general, t_ends[best_end])
    far_end = jnp.where(jnp.abs(high - s0) >= jnp.abs(low - s0), 1, 0)
    s1, t1 = s_ends[far_end], t_ends[far_end]

    s = jnp.stack([s0, s1])
    t = jnp.stack([t0, t1])
    core_a = position_a[None, :] + s[:, None] * axis_a[None, :]
    core_b = position_b[None, :] + t[:, None] * axis_b[None, :]
    # Fallback normal for intersecting segments: the common perpendicular, or for
    # parallel ones (within sqrt(eps) rad) any perpendicular to A (A's body x axis). The
    # test is on the cross product's length, not its normalised square: under jit, equal
    # axes came out apart by round-off, whose normalised cross product (any direction,
    # derivatives of 1e16) had passed it.
    across = spatial.cross(axis_a, axis_b)
    parallel = spatial.dot(across, across) <= jnp.finfo(dtype).eps
    perpendicular = jnp.where(parallel, axes_a[0], spatial.safe_normalize(jnp.where(parallel, axes_a[0], across)))
    surface_a, normal, gap = rounded_points_contact(
        core_a, capsule_a.radius, core_b, capsule_b.radius, jnp.broadcast_to(perpendicular, (2, 3))
    )
    distinct = jnp.abs(s1 - s0) > _DISTINCT_FRACTION * geo.smallest(capsule_a.radius, capsule_b.radius)
    valid = jnp.stack([jnp.ones((), bool), distinct])
    return contact_from_surface_point(surface_a, normal, gap, margin, valid=valid)


def capsule_box(
    capsule: Capsule,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    box: Box,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
    margin: float = 0.0,
) -> Contact:
    """Capsule (A) against box (B): ``K = 2`` (see the module docstring for the two slots).

    Each slot is the ball of the capsule's radius at one segment point against the box, so
    its gap is that point's signed distance to the box less the radius, and slot 0's is the
    capsule's. Degenerate cases are those of :func:`._sphere.sphere_box` (a segment point
    inside the box takes its nearest face), all finite in value and gradient.
    """
    position_a, orientation_a = geo.pose("capsule_box (capsule)", position_a, orientation_a)
    position_b, orientation_b = geo.pose("capsule_box (box)", position_b, orientation_b)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    position_a, orientation_a, position_b, orientation_b = geo.as_float(
        dtype, position_a, orientation_a, position_b, orientation_b
    )
    axis = geo.body_axes(orientation_a)[2]
    axes_b = geo.body_axes(orientation_b)
    half_box = geo.size_vector(box.half_extents, dtype)
    half = capsule.half_length

    def ball(s):
        return ball_box_contact(position_a + s * axis, capsule.radius, position_b, axes_b, half_box)

    # The search compares values only: no derivative crosses it (see _newton_step).
    def distance(s):
        return jax.lax.stop_gradient(ball(s)[2])

    s_search = _newton_step(lambda s: ball(s)[2], _closest_point(distance, half, dtype), half)
    normal_box = ball(s_search)[3]

    # The overlap: the segment clipped to the slabs of the face slot 0's normal points out of.
    centre = spatial.dot(axes_b, (position_a - position_b)[None, :])  # box frame
    direction = spatial.dot(axes_b, axis[None, :])
    tangential = jnp.arange(3) != jnp.argmax(jnp.abs(normal_box))
    enter, leave = geo.slab_intervals(centre, direction, half_box, half)
    tolerance = 64 * jnp.finfo(dtype).eps * (spatial.safe_norm(centre) + half + jnp.sum(half_box))
    s0, s1, overlaps = _overlap_slots(
        ball, distance, s_search, jnp.max(jnp.where(tangential, enter, -half)),
        jnp.min(jnp.where(tangential, leave, half)), half, tolerance)
    surface_a, normal, gap, _ = jax.vmap(ball)(jnp.stack([s0, s1]))

    # Where the segment itself meets the box, slot 0 is the separating-axis contact.
    crossing = distance(s_search) <= -capsule.radius  # (``distance`` is the capsule's gap)
    sat_surface, sat_normal, sat_gap = _segment_box_penetration(
        position_a, axis, half, s0, position_b, axes_b, half_box, tolerance)
    first = jnp.arange(2) == 0
    surface_a = jnp.where(first[:, None] & crossing, sat_surface - capsule.radius * sat_normal, surface_a)
    normal = jnp.where(first[:, None] & crossing, sat_normal, normal)
    gap = jnp.where(first & crossing, sat_gap - capsule.radius, gap)
    return _two_slots(surface_a, normal, gap, margin, s0, s1, overlaps, capsule.radius)


def capsule_box_separation(
    capsule: Capsule,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    box: Box,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
) -> Float[Array, ""]:
    """The gap (m) of the capsule's ball at its segment point closest to the box: slot 0 of
    :func:`capsule_box` without its refining Newton step, its second slot and, where the
    segment meets the box, its separating axes, for the time-of-impact search to evaluate
    many times. Zero exactly when they touch, positive when apart (the distance, to
    round-off), negative when they overlap (the depth until the segment itself meets the
    box, a smaller depth after).

    Its derivative in the poses holds the point on the segment (the search's is none): at
    a minimum over the segment the point's own derivative adds nothing to the distance's
    (the distance's slope along the segment is 0 there, or the point is at an end)."""
    half_box = box.half_extents
    return _gap_at_closest_point(capsule, position_a, orientation_a, position_b, orientation_b,
                                 lambda c, p, axes: ball_box_contact(c, capsule.radius, p, axes,
                                                                     geo.size_vector(half_box, c.dtype))[2])


def capsule_cylinder(
    capsule: Capsule,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    cylinder: Cylinder,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
    margin: float = 0.0,
) -> Contact:
    """Capsule (A) against cylinder (B): ``K = 2``, the ball of the capsule's radius at two
    segment points against the cylinder (:func:`._sphere.ball_cylinder_contact`).

    * slot 0: the segment point closest to the cylinder (the cylinder's signed distance is
      convex along the segment, so the golden-section search of capsule-box finds it, and
      one Newton step refines it), or an end of the overlap below where that is as close;
    * slot 1: the overlap's other end. The overlap is the part of the segment over the
      face slot 0 touches: over the cap's disc where slot 0's normal is nearer the axis
      than the side's (a capsule lying across the top of a can: its two ends on the cap,
      or on the rim where it overhangs), within the caps' slab otherwise (a capsule lying
      along the side). Active only within the margin and when distinct from slot 0.

    Slot 0's gap is the exact signed distance while the segment stays outside the cylinder
    (a penetration shallower than the capsule's radius). Where the segment itself enters
    the cylinder it is the signed distance of the segment's deepest point less the radius,
    along that point's nearest face: a smaller depth than the true one (which no finite set
    of separating axes gives for a curved side), pushing the deepest point out. Degenerate
    cases are those of :func:`._sphere.sphere_cylinder`, finite in value and gradient.
    """
    position_a, orientation_a = geo.pose("capsule_cylinder (capsule)", position_a, orientation_a)
    position_b, orientation_b = geo.pose("capsule_cylinder (cylinder)", position_b, orientation_b)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    position_a, orientation_a, position_b, orientation_b = geo.as_float(
        dtype, position_a, orientation_a, position_b, orientation_b
    )
    axis = geo.body_axes(orientation_a)[2]
    axes_b = geo.body_axes(orientation_b)
    half, radius_b, half_b = capsule.half_length, cylinder.radius, cylinder.half_length
    eps = jnp.finfo(dtype).eps

    def ball(s):
        return ball_cylinder_contact(position_a + s * axis, capsule.radius, position_b, axes_b, radius_b, half_b)

    def distance(s):  # the search compares values only (see _newton_step)
        return jax.lax.stop_gradient(ball(s)[2])

    s_search = _newton_step(lambda s: ball(s)[2], _closest_point(distance, half, dtype), half)
    normal_local = spatial.dot(axes_b, ball(s_search)[1][None, :])
    centre = spatial.dot(axes_b, (position_a - position_b)[None, :])  # cylinder frame
    direction = spatial.dot(axes_b, axis[None, :])

    # Over the disc: |radial(centre + s direction)| <= radius_b, a quadratic in s.
    disc_enter, disc_leave = geo.disc_interval(centre, direction, radius_b, half)
    # Within the slab |z| <= half_b.
    moving = jnp.abs(direction[2]) > eps
    step = jnp.where(moving, direction[2], 1.0)
    ends = jnp.stack([(-half_b - centre[2]) / step, (half_b - centre[2]) / step])
    in_slab = jnp.abs(centre[2]) <= half_b
    slab_enter = jnp.where(moving, jnp.min(ends), jnp.where(in_slab, -half, half))
    slab_leave = jnp.where(moving, jnp.max(ends), jnp.where(in_slab, half, -half))
    on_cap = normal_local[2] ** 2 >= 0.5
    tolerance = 64 * eps * (spatial.safe_norm(centre) + half + radius_b + half_b)
    s0, s1, overlaps = _overlap_slots(ball, distance, s_search, jnp.where(on_cap, disc_enter, slab_enter),
                                      jnp.where(on_cap, disc_leave, slab_leave), half, tolerance)
    surface_a, normal, gap = jax.vmap(ball)(jnp.stack([s0, s1]))
    return _two_slots(surface_a, normal, gap, margin, s0, s1, overlaps, capsule.radius)


def capsule_cylinder_separation(
    capsule: Capsule,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    cylinder: Cylinder,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
) -> Float[Array, ""]:
    """Slot 0's gap of :func:`capsule_cylinder` (m) without its Newton step and second slot,
    for the time-of-impact search (as :func:`capsule_box_separation` for a box): the signed
    distance, zero exactly when they touch, with the point held in its derivative."""
    return _gap_at_closest_point(capsule, position_a, orientation_a, position_b, orientation_b,
                                 lambda c, p, axes: ball_cylinder_contact(c, capsule.radius, p, axes, cylinder.radius,
                                                                          cylinder.half_length)[2])


def _gap_at_closest_point(capsule, position_a, orientation_a, position_b, orientation_b, gap_of_ball):
    """``gap_of_ball(centre, position_b, axes_b)`` at the capsule's segment point where it is
    smallest (golden-section search, no derivative through the point)."""
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    position_a, orientation_a, position_b, orientation_b = geo.as_float(
        dtype, position_a, orientation_a, position_b, orientation_b)
    axis, axes_b = geo.body_axes(orientation_a)[2], geo.body_axes(orientation_b)

    def gap(s):
        return gap_of_ball(position_a + s * axis, position_b, axes_b)

    return gap(_closest_point(lambda s: jax.lax.stop_gradient(gap(s)), capsule.half_length, dtype))


def _overlap_slots(ball, distance, s_search, enter, leave, half, tolerance):
    """The two slots' segment parameters ``(s0, s1)`` and whether the overlap is non-empty.

    ``enter`` and ``leave`` bound the part of the segment that lies over slot 0's face
    (before clipping to ``[-half, half]``); ``ball(s)[2]`` is the ball's gap at ``s`` and
    ``distance`` the same without derivative. Slot 0 is an end of the overlap unless the
    search's point is closer by more than ``tolerance`` (so a capsule lying on a face gets
    the ends of its contact line); slot 1 is the overlap's other end."""
    lo, hi = jnp.maximum(-half, enter), jnp.minimum(half, leave)
    overlaps = lo <= hi
    lo, hi = jnp.where(overlaps, lo, s_search), jnp.where(overlaps, hi, s_search)
    s_ends = jnp.stack([lo, hi])
    end_gap = jax.vmap(lambda s: ball(s)[2])(s_ends)
    best_end = jnp.argmin(end_gap)
    use_search = distance(s_search) < jax.lax.stop_gradient(end_gap[best_end]) - tolerance
    s0 = jnp.where(use_search, s_search, s_ends[best_end])
    s1 = jnp.where(jnp.abs(hi - s0) >= jnp.abs(lo - s0), hi, lo)
    return s0, s1, overlaps


def _two_slots(surface_a, normal, gap, margin, s0, s1, overlaps, radius):
    """The :class:`Contact` of slots at ``s0`` and ``s1`` (see :func:`_overlap_slots`); slot 1
    only where the overlap is non-empty and ``s1`` is distinct from ``s0``."""
    distinct = overlaps & (jnp.abs(s1 - s0) > _DISTINCT_FRACTION * radius)
    return contact_from_surface_point(surface_a, normal, gap, margin, valid=jnp.stack([jnp.ones((), bool), distinct]))


def _closest_point(distance, half, dtype):
    """The segment parameter ``s`` in ``[-half, half]`` where the convex ``distance(s)`` is
    smallest: a golden-section search of ``GOLDEN_ITERATIONS`` steps, with the two ends as
    candidates of their own (the bracket closes on an end without reaching it). Values
    only: no derivative."""
    golden = (5.0**0.5 - 1.0) / 2.0

    def shrink(bracket, _):
        low, high = bracket
        left, right = high - golden * (high - low), low + golden * (high - low)
        keep_left = distance(left) <= distance(right)  # the minimiser lies in [low, right]
        return (jnp.where(keep_left, low, left), jnp.where(keep_left, right, high)), None

    start = (jnp.asarray(-half, dtype), jnp.asarray(half, dtype))
    (low, high), _ = jax.lax.scan(shrink, start, None, length=GOLDEN_ITERATIONS)
    candidates = jnp.stack([(low + high) / 2, -start[1], start[1]])
    return jax.lax.stop_gradient(candidates[jnp.argmin(jax.vmap(distance)(candidates))])


def _newton_step(gap, s, half):
    """``s`` moved by one Newton step on ``gap'(s) = 0`` where it is an interior minimum.

    The search only compares values, so it places a smooth minimum to about ``sqrt(eps)``
    of the length and gives ``s`` no derivative; the step brings it to round-off, and its
    derivative is the implicit function theorem's, ``ds/dx = -(d gap'/dx) / gap''``, so the
    contact point moves with the poses. It is taken only where it is small (``64 sqrt(eps)``
    of the half length: 1e-6 in float64, 2e-2 in float32, whose search places the point
    only to ~1e-4 m; with 1e-6 there, float32 skipped the step and its point's derivative
    lacked the implicit term, off by up to 13 in ``tests/test_collision.py``'s skew
    capsule): at an end, or where ``gap'' = 0`` (a point above a face, whose distance is
    linear), ``s`` is kept. A curvature under ``eps / half`` counts as zero: above a face
    float32 left 3e-21 (1/m) of round-off, whose step was refused, but whose derivative
    (``-value / curvature^2``, inf) made the refused branch's zero cotangent NaN: a capsule
    lying on a box face or a cylinder's cap had NaN gradients in 14 of 64 random poses."""
    slope = jax.grad(gap)
    value, curvature = jax.jvp(slope, (s,), (jnp.ones_like(s),))
    eps = jnp.finfo(s.dtype).eps
    curved = curvature > eps / half
    step = value / jnp.where(curved, curvature, 1.0)
    small = curved & (jnp.abs(step) <= 64 * jnp.sqrt(eps) * half) & (jnp.abs(s) < half)
    return s - jnp.where(small, step, 0.0)


def _segment_box_penetration(position_a, axis, half, s_flat, position_b, axes_b, half_box, tolerance):
    """A segment ``position_a + s axis``, ``|s| <= half``, that meets a box: its deepest point
    (world, m), the normal (box to segment) and the signed distance (m, ``<= 0``).

    The segment and the box are separated along some axis unless they intersect, and the
    candidates are the facet normals of their Minkowski difference: the box's three face
    normals and the cross products of the segment with the box's three edge directions
    (Ericson, sec. 4.4, as in :func:`._box.box_box`). The largest separation over them is
    the signed distance, minus the penetration depth. A segment parallel to a face
    (``s_flat``: the overlap's end chosen for slot 0) keeps that point; an edge axis must
    beat the best face by more than ``tolerance``, so ties go to faces."""
    offset = position_a - position_b
    edges = spatial.cross(axis[None, :], axes_b)
    edge_length = spatial.safe_norm(edges)
    usable = edge_length > jnp.sqrt(jnp.finfo(offset.dtype).eps)  # not parallel to that edge
    candidates = jnp.concatenate([axes_b, edges / jnp.where(usable, edge_length, 1.0)[:, None]])
    candidates = candidates * geo.sign_nonzero(spatial.dot(candidates, offset[None, :]))[:, None]  # box to segment
    reach_box = spatial.dot(half_box[None, :], jnp.abs(spatial.dot(candidates[:, None, :], axes_b[None, :, :])))
    reach_segment = half * jnp.abs(spatial.dot(candidates, axis[None, :]))
    separation = spatial.dot(candidates, offset[None, :]) - reach_box - reach_segment
    separation = jnp.where(jnp.concatenate([jnp.ones(3, bool), usable]), separation, -jnp.inf)
    face, edge = jnp.argmax(separation[:3]), 3 + jnp.argmax(separation[3:])
    use_edge = separation[edge] > separation[face] + tolerance
    normal = jnp.where(use_edge, candidates[edge], candidates[face])
    depth = jnp.where(use_edge, separation[edge], separation[face])

    # The deepest point: for a face, the segment's end farthest along -normal (``s_flat``
    # where the segment is parallel to it); for an edge, the segment's point closest to
    # the box's edge that supports the box along the normal.
    along = spatial.dot(candidates[face], axis)
    s_face = jnp.where(jnp.abs(along) > jnp.finfo(offset.dtype).eps, -half * geo.sign_nonzero(along), s_flat)
    m = edge - 3
    towards = geo.sign_nonzero(spatial.dot(axes_b, candidates[edge][None, :]))
    others = jnp.arange(3) != m
    corner = jnp.where(others, towards * half_box, 0.0)  # box frame
    edge_centre = position_b + spatial.dot(spatial.transpose(axes_b), corner[None, :])
    s_edge, _ = geo.closest_between_segments(position_a, axis, half, edge_centre, axes_b[m], half_box[m])
    s_deep = jnp.where(use_edge, s_edge, s_face)
    return position_a + s_deep * axis, normal, depth
