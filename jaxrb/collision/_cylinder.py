"""Cylinder (A) against a box or a cylinder (B): ``K = 5``, well-spread slots from point contacts.

This docstring describes cylinder-box; :func:`cylinder_cylinder` builds its candidates
from both cylinders the same way (see there).

A cylinder's surface is curved, so there is no finite set of separating axes to test as
box-box does. Instead the candidates are points of one solid, each against the other:

* **the box's points**: its 8 corners, and on each of its 12 edges the point closest to the
  cylinder. A point's signed distance to a convex solid is convex along a line, so the
  golden-section search of capsule-box finds it (one Newton step gives it the implicit
  function theorem's derivative); where an end of the edge is as close (an edge flat on a
  cap or along the side), that corner;
* **the cylinder's points**: the 4 rim points per cap fixed in the body (cylinder-plane's
  square, to stand on a face), and for each box face that the cylinder's centre lies out
  of, the cylinder's side line lowest along that face's normal (its ends are the deepest
  points towards the face, one on each rim), clipped to the part over the face: its ends.

Each point is paired with its closest point on the other solid
(:func:`._sphere.ball_cylinder_contact`, :func:`._sphere.ball_box_contact` with radius 0):
its gap is the point's signed distance, its normal the other solid's there. Where it lies over a
**reference face** and at most ``0.1`` of the smallest size into it, it is held against
that face instead, as box-box holds a clipped face: a cylinder point over the box face its
centre is farthest out of (a line's ends over their own face), a box point over the cap
facing the box (when the box's centre is farther out of the caps' slab than out of the
side) or beside the side (otherwise). For a point outside the other solid this is the
same pair; for one a little inside, it keeps the face's normal where a point near an edge
of the face would have taken the nearer side face (a can resting 0.1 mm deep by a box's
edge: its rim points had the side's normal and the gap 0).

**Slot 0** is the deepest candidate. For separated or touching shapes it is the exact
signed distance: the closest pair has the box's point on an edge or a corner (an edge's
search), or inside a face, and then the cylinder's point is its lowest towards that face
and lies over the face (an unclipped end of that face's line), or the support is a whole
cap or side line, where an end, a corner or an edge point over it is as close. Below a tilt
of :data:`._plane.TILT_RAMP` from a face's normal, the "lowest" cap point slides in towards
the cap's centre (as in cylinder-plane), up to ``r TILT_RAMP / 4`` above the rim.

Where the deepest candidate is inside the other solid by more than round-off, or either
shape's centre is inside the other (two equal coaxial cylinders have every candidate on
the other's surface, however deep they overlap), the shapes overlap: slot 0 keeps that
point but takes the separating direction along which the shapes overlap least, and that
overlap as its gap, a push that frees the shapes (a point's own
depth would free that point only). The directions tried are the box's face normals, the
cylinder's axis, every candidate's normal (held and nearest), and where a box edge or
corner meets a rim, the direction across the two (perpendicular to the edge and to the rim
there; from the rim to the corner). The overlap along any direction is at least the true
penetration depth, and these hold the true push for the contacts a simulation meets (a
corner, an edge, a rim or the side a little way into a face, an edge across a rim):
measured on random poses against a support-function reference, up to 1.3e-5 m deeper than
the truth below 1 cm of overlap, up to 3.5e-4 m at 1 to 3 cm (a box edge across a rim: the
direction across the two is taken at the rim point nearest the edge's searched point, which
is not where they cross; stop 93's review, whose bound is exact: a direction that overlaps
less), and up to 1.1e-3 m in overlaps of 5 to 20 cm. Touching to within the edges' search (where a rim
meets an edge, the edge's distance has a kink at 0, and its point's normal could be any
direction), slot 0 takes that best direction too.

**Slots 1-4** are spread over the candidates within the margin: each is the one farthest
from the slots already taken (farthest-point sampling), skipping points closer to a taken
one than ``1e-3`` of the smallest size (radius, half length, half extents): one contact
twice would make a solver's matrix singular. As in cylinder-plane, a square point within
``0.9 r`` of its rim's lowest point towards the face the cylinder rests on is left out (a
rolling rim would bring it down onto the face: an impact every quarter of a turn). A
cylinder standing on a face gets its cap's lowest point and the square, one lying on a
face the two ends of its line (clipped to a narrow face), a box on a cylinder's cap its
corners (or the rim points under it), a box edge across the side one point.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .. import spatial
from .._indexing import literal_array
from ..shapes import Box, Cylinder
from . import _geometry as geo
from ._capsule import _closest_point, _newton_step
from ._contact import Contact, contact_from_surface_point
from ._plane import _SQUARE, TILT_RAMP
from ._sphere import ball_box_contact, ball_cylinder_contact

__all__ = ["cylinder_box", "cylinder_cylinder"]

#: Slots, as in cylinder-plane: a cylinder standing on a face needs its cap's deepest point
#: and a square of rim points around it.
SLOTS = 5

def _edge_centres() -> np.ndarray:
    """``(12, 3)``: edge ``k`` runs along box axis ``k // 4``, through the point with 0 on that
    axis and the signs ``(+-1, +-1)`` of its corner on the other two (in half extents)."""
    rows = []
    for axis in range(3):
        for first in (-1.0, 1.0):
            for second in (-1.0, 1.0):
                row = np.zeros(3)
                row[(axis + 1) % 3], row[(axis + 2) % 3] = first, second
                rows.append(row)
    return np.array(rows)


def cylinder_box(
    cylinder: Cylinder,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    box: Box,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
    margin: float = 0.0,
) -> Contact:
    """Cylinder (A) against box (B): ``K = 5`` (see the module docstring).

    Every slot is a point of one solid with its closest point on the other or on a
    reference face; slot 0 is the deepest, the exact signed distance of separated shapes,
    and for overlapping ones the push along the best of many directions. Degenerate cases
    (a box point on the cylinder's axis, a cylinder point at the box's centre) are those of
    sphere-cylinder and sphere-box, finite in value and gradient.
    """
    position_a, orientation_a = geo.pose("cylinder_box (cylinder)", position_a, orientation_a)
    position_b, orientation_b = geo.pose("cylinder_box (box)", position_b, orientation_b)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    pa, qa, pb, qb = geo.as_float(dtype, position_a, orientation_a, position_b, orientation_b)
    axes_a = geo.body_axes(qa)
    x_axis, y_axis, axis = axes_a
    axes_b = geo.body_axes(qb)
    half_box = geo.size_vector(box.half_extents, dtype)
    radius, half = cylinder.radius, cylinder.half_length

    scale = spatial.safe_norm(pa - pb) + radius + half + jnp.sum(half_box)
    # A point is held against a reference face only this far into it: deeper, another face
    # may be nearer by much, and its own nearest face gives the shorter way out.
    shallow = 0.1 * geo.smallest(radius, half, *box.half_extents)
    round_off = 64 * jnp.finfo(dtype).eps * scale

    def signed_distance(x):  # of a point to the cylinder (m): convex along any line
        return ball_cylinder_contact(x, 0.0, pa, axes_a, radius, half)[2]

    def on_edge(centre, direction, length):
        """The edge's point closest to the cylinder; where an end is as close (to round-off:
        an edge lying flat on a cap or along the side), that end, a corner."""
        def gap(s):
            return signed_distance(centre + s * direction)

        s = _closest_point(lambda s: jax.lax.stop_gradient(gap(s)), length, dtype)
        ends = jnp.stack([-length, length])
        end_gap = jax.lax.stop_gradient(jax.vmap(gap)(ends))
        at_end = jnp.min(end_gap) <= jax.lax.stop_gradient(gap(s)) + round_off
        return centre + jnp.where(at_end, ends[jnp.argmin(end_gap)], _newton_step(gap, s, length)) * direction

    edge_centres = pb[None, :] + spatial.dot(
        spatial.transpose(axes_b)[None], (literal_array(_edge_centres(), dtype) * half_box[None, :])[:, None, :])
    edges = jax.vmap(on_edge)(edge_centres, jnp.repeat(axes_b, 4, axis=0), jnp.repeat(half_box, 4))
    box_points = jnp.concatenate([geo.box_corners(pb, axes_b, half_box), edges])  # (20, 3)

    # The cylinder's points against the box: the square on each rim, and per box face that
    # looks towards the cylinder, its lowest side line clipped to the face.
    angles = literal_array(_SQUARE, dtype)
    square = jnp.cos(angles)[:, None] * x_axis[None, :] + jnp.sin(angles)[:, None] * y_axis[None, :]  # (4, 3)
    caps = literal_array([[1.0], [-1.0]], dtype) * (half * axis[None, :])  # (2, 3)
    rims = (pa[None, None, :] + caps[:, None, :] + radius * square[None, :, :]).reshape(8, 3)
    faces = geo.sign_nonzero(spatial.dot(axes_b, (pa - pb)[None, :]))[:, None] * axes_b  # (3, 3), out of the box
    tilt = faces - spatial.dot(faces, axis[None, :])[:, None] * axis[None, :]
    towards = tilt / jnp.maximum(spatial.safe_norm(tilt), TILT_RAMP)[:, None]  # (3, 3), unit above the ramp
    lowest = pa[None, :] - radius * towards
    local = spatial.dot(axes_b[None, :, :], (lowest - pb[None, :])[:, None, :])  # (3 faces, 3 box axes)
    # As in cylinder-plane, a square point within 0.9 r of the rim's lowest point towards
    # the face the cylinder rests on (the one its centre is farthest out of) is left out:
    # a rolling rim would bring it down onto the face, an impact every quarter of a turn.
    centre = spatial.dot(axes_b, (pa - pb)[None, :])
    resting = jnp.argmax(jnp.abs(centre) - half_box)
    square_valid = spatial.safe_norm(square + towards[resting][None, :]) >= 0.9
    enter, leave = jax.vmap(geo.slab_intervals, in_axes=(0, None, None, None))(
        local, spatial.dot(axes_b, axis[None, :]), half_box, half)
    tangential = jnp.arange(3)[None, :] != jnp.arange(3)[:, None]  # face f's own slab is along its normal
    low = jnp.maximum(-half, jnp.max(jnp.where(tangential, enter, -half), axis=1))
    high = jnp.minimum(half, jnp.min(jnp.where(tangential, leave, half), axis=1))
    # A face's line is a contact only where the cylinder lies beside that face: its centre
    # out of the face's plane (the closest point of separated shapes inside a face has the
    # cylinder's lowest point, so its centre, above it).
    over_face = (low <= high) & (jnp.abs(centre) > half_box)
    ends = jnp.stack([low, high], axis=1)  # (3, 2)
    lines = (lowest[:, None, :] + ends[:, :, None] * axis[None, None, :]).reshape(6, 3)
    cylinder_points = jnp.concatenate([rims, lines])  # (14, 3)

    # Each point against the other solid, held against a reference face where it lies over
    # it (see the module docstring): A's surface point, the normal (B to A), the gap, and the
    # nearest face's normal.
    def against_cylinder(x):
        point, outward, gap, nearest = _held_on_cylinder(x, pa, axes_a, radius, half, pb, round_off, shallow)
        return point, -outward, gap, -nearest

    def against_box(x, face, over_by_construction):
        _, normal, gap, _ = ball_box_contact(x, 0.0, pb, axes_b, half_box)
        local = spatial.dot(axes_b, (x - pb)[None, :])
        face_gap = spatial.dot(faces[face], x - pb) - half_box[face]
        over = (over_by_construction | jnp.all((jnp.abs(local) <= half_box) | (jnp.arange(3) == face))) & (
            face_gap >= -shallow)
        return x, jnp.where(over, faces[face], normal), jnp.where(over, face_gap, gap), normal

    surface_b, normal_b, gap_b, nearest_b = jax.vmap(against_cylinder)(box_points)
    held_face = jnp.concatenate([jnp.full(8, resting), jnp.repeat(jnp.arange(3), 2)])
    surface_c, normal_c, gap_c, nearest_c = jax.vmap(against_box)(cylinder_points, held_face, jnp.arange(14) >= 8)
    surface = jnp.concatenate([surface_b, surface_c])
    normal = jnp.concatenate([normal_b, normal_c])
    gap = jnp.concatenate([gap_b, gap_c])
    valid = jnp.concatenate([jnp.ones(20, bool), jnp.tile(square_valid, 2), jnp.repeat(over_face, 2)])

    chosen, found = _spread_slots(surface, gap, valid, margin, 1e-3 * geo.smallest(radius, half, *box.half_extents))
    surface, normal, gap = surface[chosen], normal[chosen], gap[chosen]

    # Overlapping: slot 0 is the best of these separating directions, a push that frees the
    # shapes (see the module docstring): the box's faces, the cylinder's axis, every
    # candidate's normals, and where an edge or a corner meets the rim, the directions
    # across the two (perpendicular to the edge and the rim; from the rim to the corner).
    rims_near = jax.vmap(lambda x: _nearest_rim_point(x, pa, axes_a, radius, half))(box_points)  # (20, 3)
    tangents = spatial.cross(axis[None, :], rims_near[8:] - pa[None, :])
    across_edges = spatial.cross(jnp.repeat(axes_b, 4, axis=0), tangents)
    directions = jnp.concatenate([axes_b, axis[None, :], normal_b, normal_c, nearest_b, nearest_c, across_edges,
                                  box_points[:8] - rims_near[:8]])
    push_normal, push_gap = _best_separating_direction(
        directions, pa - pb, lambda n: _cylinder_reach(n, axis, radius, half) + _box_reach(n, axes_b, half_box))
    centre_inside = ((signed_distance(pb) < -round_off)
                     | (ball_box_contact(pa, 0.0, pb, axes_b, half_box)[2] < -round_off))
    return _with_push(surface, normal, gap, found, push_normal, push_gap, round_off, scale, margin, centre_inside)


def _with_push(surface, normal, gap, found, push_normal, push_gap, round_off, scale, margin,
               centre_inside) -> Contact:
    """The slots, with slot 0 along the best separating direction where the shapes overlap
    (its gap the overlap along it) or touch to within the searches' resolution.

    ``centre_inside``: either shape's centre is inside the other (by more than round-off),
    so they overlap whatever the candidates say. Every candidate of two coaxial cylinders
    of one radius lies on the other's surface (its gap 0), and they had counted as touching
    however deep they overlapped (two cans stacked 0.2 m into each other, or at one centre:
    no contact at all), as had a box at a cylinder's centre."""
    # (Inside by more than round-off: touching shapes keep their exact candidate.)
    overlap = (gap[0] < -round_off) | centre_inside
    # Touching to within the searches (which place a point to ~1e-10 of an edge's length or
    # a rim's arc, so where a rim meets an edge, whose distance has a kink at 0, its point's
    # normal can be any direction), slot 0 takes the best direction too where that is as
    # good (the direction across the edge and the rim).
    touching = (gap[0] <= 1e-8 * scale) & (push_gap >= gap[0] - 1e-8 * scale)
    first = jnp.arange(SLOTS) == 0
    normal = jnp.where((first & (overlap | touching))[:, None], push_normal[None, :], normal)
    gap = jnp.where(first & overlap, push_gap, gap)
    return contact_from_surface_point(surface, normal, gap, margin, valid=found)


def _spread_slots(points, gap, valid, margin, distinct):
    """``SLOTS`` candidate indices and whether each slot found one: the deepest valid
    candidate, then, among the valid ones within the margin, each time the one farthest from
    those already taken (more than ``distinct`` away)."""
    first = jnp.argmin(jnp.where(valid, gap, jnp.inf))
    chosen, found = [first], [jnp.ones((), bool)]
    nearest = jnp.sum((points - points[first][None, :]) ** 2, axis=-1)
    candidate = valid & (gap < margin)
    for _ in range(SLOTS - 1):
        available = candidate & (nearest > distinct**2)
        pick = jnp.argmax(jnp.where(available, nearest, -jnp.inf))
        chosen.append(pick)
        found.append(jnp.any(available))
        nearest = jnp.minimum(nearest, jnp.sum((points - points[pick][None, :]) ** 2, axis=-1))
    return jnp.stack(chosen), jnp.stack(found)


def _nearest_rim_point(x, centre, axes, radius, half):
    """The point of the cylinder's rims (``centre``, world axes ``axes`` rows, the third its
    axis) nearest to ``x``: on the rim of the cap on ``x``'s side, in ``x``'s radial
    direction (the cylinder's body x axis where ``x`` is on the axis)."""
    offset = x - centre
    along = spatial.dot(offset, axes[2])
    radial = offset - along * axes[2]
    length = spatial.safe_norm(radial)
    on_axis = length <= 64 * jnp.finfo(x.dtype).eps * (spatial.safe_norm(offset) + radius + half)
    outward = jnp.where(on_axis, axes[0], radial / jnp.where(on_axis, 1.0, length))
    return centre + geo.sign_nonzero(along) * half * axes[2] + radius * outward


def _held_on_cylinder(x, centre, axes, radius, half, other_centre, round_off, shallow):
    """A point ``x`` (world, m) against a cylinder (``centre``; ``axes`` rows its world axes,
    the third its axis), held on a reference face where it lies over it (see the module
    docstring): the cap facing ``other_centre`` (the other shape's centre) where that is
    farther out of the caps' slab than out of the side, the side otherwise, while ``x`` is at
    most ``shallow`` into it. Returns the cylinder's point, the unit normal from the cylinder
    towards ``x``, the gap (m), and the nearest face's normal (as
    :func:`._sphere.ball_cylinder_contact`)."""
    dtype = x.dtype
    _, nearest, gap = ball_cylinder_contact(x, 0.0, centre, axes, radius, half)
    other = spatial.dot(axes, (other_centre - centre)[None, :])  # the cylinder's frame
    cap_sign = geo.sign_nonzero(other[2])
    on_cap = jnp.abs(other[2]) - half >= spatial.safe_norm(other[:2]) - radius
    local = spatial.dot(axes, (x - centre)[None, :])
    rho = spatial.safe_norm(local[:2])
    along = cap_sign * local[2]  # height along the axis, towards the other shape's side
    off_axis = rho > round_off
    radial = jnp.where(off_axis, local * literal_array([1.0, 1.0, 0.0], dtype) / jnp.where(off_axis, rho, 1.0),
                       literal_array([1.0, 0.0, 0.0], dtype))
    over_cap = on_cap & (rho <= radius) & (along >= -half)
    beside = ~on_cap & (jnp.abs(local[2]) <= half)
    held_gap = jnp.where(over_cap, along - half, rho - radius)
    held = (over_cap | beside) & (held_gap >= -shallow)
    held_local = jnp.where(over_cap, cap_sign * literal_array([0.0, 0.0, 1.0], dtype), radial)
    outward = jnp.where(held, spatial.dot(spatial.transpose(axes), held_local[None, :]), nearest)
    gap = jnp.where(held, held_gap, gap)
    return x - gap * outward, outward, gap, nearest


def _cylinder_reach(unit, axis, radius, half):
    """A cylinder's projection radius ``h |n.a| + r |n x a|`` along unit directions ``(m, 3)``."""
    return half * jnp.abs(spatial.dot(unit, axis[None, :])) + radius * spatial.safe_norm(
        spatial.cross(unit, axis[None, :]))


def _box_reach(unit, axes, half_extents):
    """A box's projection radius ``sum_i e_i |n.b_i|`` along unit directions ``(m, 3)``."""
    return spatial.dot(half_extents[None, :], jnp.abs(spatial.dot(unit[:, None, :], axes[None, :, :])))


def _best_separating_direction(directions, delta, reach):
    """The direction (unit, B to A) among ``directions`` ``(m, 3)`` along which A (centre
    ``delta`` from B's) is farthest out of B, and that separation ``|n.delta| - reach(n)``
    (m; ``reach``: the two projection radii summed; negative: the overlap along ``n``, a push
    that frees the shapes). The separation along any direction is at most the signed
    distance, with equality along the true contact normal. Directions shorter than
    ``sqrt(eps)`` are skipped."""
    length = spatial.safe_norm(directions)
    usable = length > jnp.sqrt(jnp.finfo(delta.dtype).eps)
    unit = directions / jnp.where(usable, length, 1.0)[:, None]
    along = spatial.dot(unit, delta[None, :])
    unit = unit * geo.sign_nonzero(along)[:, None]
    separation = jnp.where(usable, jnp.abs(along) - reach(unit), -jnp.inf)
    best = jnp.argmax(separation)
    return unit[best], separation[best]


#: Rim angles sampled before the search for a rim's point closest to the other cylinder:
#: its distance along the rim is not convex, so the search starts from the best sample and
#: refines within one sample's spacing either side.
RIM_SAMPLES = 16


def cylinder_cylinder(
    cylinder_a: Cylinder,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    cylinder_b: Cylinder,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
    margin: float = 0.0,
) -> Contact:
    """Two cylinders: ``K = 5``, built as cylinder-box (see the module docstring), with the
    candidates of each cylinder against the other:

    * the 4 rim points per cap fixed in the body (a square);
    * per rim, the point closest to the other cylinder: the best of :data:`RIM_SAMPLES`
      angles, refined by a golden-section search within a sample's spacing and one Newton
      step (the distance along a rim is not convex);
    * the side point facing the other's axis, at the closest points of the two axes;
    * where its centre lies out of the other's caps' slab, its side line lowest towards the
      other's facing cap, clipped to the part over that cap's disc: its two ends.

    The closest pair of separated cylinders has a point on a rim (a rim's search), inside
    both sides (the side points), or inside a cap, whose partner is then on the other's rim
    or its side line or cap (a search, a line's end, a square point over it), so slot 0 is
    the exact distance while the rim searches find their minima. Overlapping, slot 0 pushes
    along the best of both axes, their cross product, every candidate's normals and the
    directions from one rim's searched point to the other's nearest rim point.
    """
    position_a, orientation_a = geo.pose("cylinder_cylinder (A)", position_a, orientation_a)
    position_b, orientation_b = geo.pose("cylinder_cylinder (B)", position_b, orientation_b)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    pa, qa, pb, qb = geo.as_float(dtype, position_a, orientation_a, position_b, orientation_b)
    axes_a, axes_b = geo.body_axes(qa), geo.body_axes(qb)
    sizes = (cylinder_a.radius, cylinder_a.half_length, cylinder_b.radius, cylinder_b.half_length)
    scale = spatial.safe_norm(pa - pb) + sum(sizes)
    round_off = 64 * jnp.finfo(dtype).eps * scale
    shallow = 0.1 * geo.smallest(*sizes)
    a = (pa, axes_a, cylinder_a.radius, cylinder_a.half_length)
    b = (pb, axes_b, cylinder_b.radius, cylinder_b.half_length)

    points_a, valid_a = _cylinder_points(a, b, dtype, round_off)
    points_b, valid_b = _cylinder_points(b, a, dtype, round_off)

    def of_a(x):  # a point of A against B: A's surface point, the normal (B to A), the gap, the nearest's
        _, outward, gap, nearest = _held_on_cylinder(x, *b[:4], pa, round_off, shallow)
        return x, outward, gap, nearest

    def of_b(x):  # a point of B against A
        point, outward, gap, nearest = _held_on_cylinder(x, *a[:4], pb, round_off, shallow)
        return point, -outward, gap, -nearest

    surface_a, normal_a, gap_a, nearest_a = jax.vmap(of_a)(points_a)
    surface_b, normal_b, gap_b, nearest_b = jax.vmap(of_b)(points_b)
    surface = jnp.concatenate([surface_a, surface_b])
    normal = jnp.concatenate([normal_a, normal_b])
    gap = jnp.concatenate([gap_a, gap_b])
    valid = jnp.concatenate([valid_a, valid_b])
    chosen, found = _spread_slots(surface, gap, valid, margin, 1e-3 * geo.smallest(*sizes))

    # From each rim's searched point (rows 8, 9) to the other's nearest rim point (two rims
    # that touch), and perpendicular to both rims there (two rims that cross).
    def across(x, this, other):
        rim = _nearest_rim_point(x, *other)
        return jnp.stack([x - rim, spatial.cross(spatial.cross(this[1][2], x - this[0]),
                                                 spatial.cross(other[1][2], rim - other[0]))])

    rims_across = jnp.concatenate([jax.vmap(lambda x: across(x, a, b))(points_a[8:10]).reshape(4, 3),
                                   jax.vmap(lambda x: across(x, b, a))(points_b[8:10]).reshape(4, 3)])
    directions = jnp.concatenate([axes_a[2:], axes_b[2:], spatial.cross(axes_a[2], axes_b[2])[None, :], normal,
                                  nearest_a, nearest_b, rims_across])
    push_normal, push_gap = _best_separating_direction(
        directions, pa - pb, lambda n: _cylinder_reach(n, axes_a[2], *a[2:]) + _cylinder_reach(n, axes_b[2], *b[2:]))
    centre_inside = ((ball_cylinder_contact(pa, 0.0, *b)[2] < -round_off)
                     | (ball_cylinder_contact(pb, 0.0, *a)[2] < -round_off))
    return _with_push(surface[chosen], normal[chosen], gap[chosen], found, push_normal, push_gap, round_off, scale,
                      margin, centre_inside)


def _cylinder_points(this, other, dtype, round_off):
    """The candidate points of cylinder ``this`` against cylinder ``other`` (each
    ``(centre, axes, radius, half)``): ``(13, 3)`` (the two rims' squares, the two rims'
    searched points, the side point facing the other's axis, the two ends of the line over
    the other's cap) and which are valid ``(13,)``."""
    centre, axes, radius, half = this
    other_centre, other_axes, other_radius, other_half = other
    x_axis, y_axis, axis = axes
    caps = literal_array([[1.0], [-1.0]], dtype) * (half * axis[None, :])  # (2, 3)
    angles = literal_array(_SQUARE, dtype)
    square = jnp.cos(angles)[:, None] * x_axis[None, :] + jnp.sin(angles)[:, None] * y_axis[None, :]
    rims = (centre[None, None, :] + caps[:, None, :] + radius * square[None, :, :]).reshape(8, 3)

    def distance(x):  # to the other cylinder (m)
        return ball_cylinder_contact(x, 0.0, other_centre, other_axes, other_radius, other_half)[2]

    def rim_point(cap, theta):
        return centre + cap + radius * (jnp.cos(theta) * x_axis + jnp.sin(theta) * y_axis)

    spacing = 2 * np.pi / RIM_SAMPLES

    def search(cap):
        samples = spacing * jnp.arange(RIM_SAMPLES, dtype=dtype)
        start = samples[jnp.argmin(jax.lax.stop_gradient(jax.vmap(lambda t: distance(rim_point(cap, t)))(samples)))]

        def gap(phi):
            return distance(rim_point(cap, start + phi))

        phi = _closest_point(lambda p: jax.lax.stop_gradient(gap(p)), spacing, dtype)
        return rim_point(cap, start + _newton_step(gap, phi, spacing))

    searched = jax.vmap(search)(caps)  # (2, 3)

    # The side point facing the other's axis, at the axes' closest points.
    s, t = geo.closest_between_segments(centre, axis, half, other_centre, other_axes[2], other_half)
    core = centre + s * axis
    towards = other_centre + t * other_axes[2] - core
    towards = towards - spatial.dot(towards, axis) * axis
    length = spatial.safe_norm(towards)
    facing = core + radius * jnp.where(length > round_off, towards / jnp.where(length > round_off, length, 1.0),
                                       x_axis)

    # The side line lowest towards the other's facing cap, over that cap's disc.
    local_centre = spatial.dot(other_axes, (centre - other_centre)[None, :])
    cap_normal = geo.sign_nonzero(local_centre[2]) * other_axes[2]
    tilt = cap_normal - spatial.dot(cap_normal, axis) * axis
    lowest = centre - radius * tilt / jnp.maximum(spatial.safe_norm(tilt), TILT_RAMP)
    enter, leave = geo.disc_interval(spatial.dot(other_axes, (lowest - other_centre)[None, :]),
                                     spatial.dot(other_axes, axis[None, :]), other_radius, half)
    low, high = jnp.maximum(-half, enter), jnp.minimum(half, leave)
    line_valid = (low <= high) & (jnp.abs(local_centre[2]) > other_half)
    ends = lowest[None, :] + jnp.stack([low, high])[:, None] * axis[None, :]

    # As in cylinder-box, a square point near its rim's lowest point towards the other (its
    # facing cap, or its axis where this lies beside it) is left out.
    beside = spatial.safe_norm(local_centre[:2]) - other_radius > jnp.abs(local_centre[2]) - other_half
    rest = jnp.where(beside, -towards, tilt)  # from this cylinder's centre away from the other
    rest = rest - spatial.dot(rest, axis) * axis
    square_valid = spatial.safe_norm(square + (rest / jnp.maximum(spatial.safe_norm(rest), TILT_RAMP))[None, :]) >= 0.9
    points = jnp.concatenate([rims, searched, facing[None, :], ends])
    valid = jnp.concatenate([jnp.tile(square_valid, 2), jnp.ones(3, bool), jnp.stack([line_valid, line_valid])])
    return points, valid
