"""Box (A) against box (B): separating axes and a clipped contact manifold, ``K = 4``.

The algorithm (Ericson, *Real-Time Collision Detection*, sec. 4.4.1 for the 15 separating
axes; Gottschalk's OBB test; the face clipping of Catto's Box2D and of ODE's ``dBoxBox``):

1. **Separating axes.** For each of the 15 candidate axes ``L`` (3 face normals of A,
   3 of B, 9 cross products of an edge of A with an edge of B) the separation is
   ``|L.(c_a - c_b)| - h_a(L) - h_b(L)`` with the box projection radius
   ``h(L) = sum_i e_i |L.a_i|``. Every unit ``L`` gives a lower bound on the signed
   distance; the largest over the 15 is exact whenever the boxes overlap or touch
   (they are the face normals of the Minkowski difference).
2. **Face contact** (the best axis is a face normal): that box is the *reference*, the
   other the *incident* box. Its face most anti-parallel to the reference normal is
   clipped against the four side planes of the reference face (Sutherland-Hodgman,
   Ericson sec. 8.3.4), which leaves a convex polygon of at most 8 points, each with its
   depth below the reference face. Points within the margin are reduced to 4: the
   deepest (of points equally deep to round-off, a corner of the polygon), the one
   farthest from it, and the two that span the largest area on either side of that pair.
   The slots then hold them in order of their angle about their centre in A's frame, so
   that a resting face keeps each corner in its slot from step to step (the solve's warm
   start is per slot).
3. **Edge contact** (the best axis is an edge-edge cross product): one point, the midpoint
   of the closest points of the two supporting edges.
4. **Separated boxes** (the best axis separates): the separating axes only bound the
   distance from below (two corners facing each other are closer along their diagonal
   than along any of the 15 axes) and the clipped polygon can then be empty. The exact
   distance is the smallest over the corner-box pairs and the best edge axis's edge pair;
   when it differs from the first slot's gap, that closest pair replaces the first slot.

Ties are broken towards faces, and towards A before B: an edge axis must beat the best
face axis by more than round-off and :data:`EDGE_PREFERENCE` (1e-3) of the smaller box's
least half-extent. Otherwise a box resting flat on another, whose edge axes coincide with
its face normal or (edges over edges, slightly tilted) beat it by a hair, could get a
one-point edge contact. An overlap's depth may then be overstated by that much. Everything is
computed for every branch and selected with ``jnp.where``: fixed shapes, no Python
control flow on traced values, finite values and gradients in every branch.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import spatial
from ..shapes import Box
from . import _geometry as geo
from ._contact import Contact, contact_from_surface_point

__all__ = ["box_box", "box_box_separation"]

#: Clipping holds, in the derivative, the crossing point of an edge that lies within this
#: slope of a side plane (its ends' distances to the plane differ by at most this fraction
#: of its length). Such a point slides along the edge at 1/slope times the rate the bodies
#: move: where two float64 cubes touch along a shared edge, tilted against each other by
#: 1e-11 rad, it slid at 1e11 m per m, and a resting float64 2x2 grid's largest gradient
#: entry through 100 steps fell from 10 to 4.2 with it (the rest is the contacts' kink:
#: benchmarks/README.md, stop 95). The value is unchanged; the derivative then leaves out
#: the slide, which is at most the edge's length.
PARALLEL_SLOPE = 1e-3
_MAX_POLYGON = 8  # a quad clipped by 4 half-planes gains at most one vertex per plane

#: An edge axis must beat the best face axis by this fraction of the smaller box's least
#: half-extent (and by round-off) to give the one-point edge contact. Where two equal boxes
#: rest one on the other, their edges lie over each other, and under a small relative tilt
#: the axes of crossing edges beat the face normal in exact arithmetic: a cube tilted by
#: 3e-3 rad with its lowest corner 10 um into an equal one, by up to 0.057 of that depth.
#: With a round-off tolerance alone, a 5-box stack tilted by ~1e-6 rad after its first
#: step had three of its four box-box pairs reduced to one point, and jolted to 0.023 m/s
#: in its first five steps. While the boxes overlap every axis's separation is negative,
#: so an edge axis beats a face by less than the depth: overlaps shallower than this are
#: always face contacts, and a face manifold kept over an edge axis overstates the depth
#: by this much at most (0.1 mm for cubes of half-extent 0.1 m). The smallest margin by
#: which an edge axis won among 256 random poses of a box and a crate (the sampler of
#: tests/test_collision.py, seeds 0 to 3, 64 each) was 1.9e-3 of the box's least
#: half-extent, 0.2 m.
EDGE_PREFERENCE = 1e-3


def _projection_radius(axes: Array, half_extents: Array, directions: Array) -> Array:
    """``h(L) = sum_i e_i |L.a_i|`` for each direction ``L`` (rows of ``directions``, ``(m, 3)``)."""
    return spatial.dot(half_extents[None, :], jnp.abs(spatial.dot(directions[:, None, :], axes[None, :, :])))


def _clip(polygon: Array, count: Array, normal: Array, offset: Array, scale: Array) -> tuple[Array, Array]:
    """Sutherland-Hodgman: keep the part of a convex polygon with ``normal.x <= offset``.

    ``polygon`` is ``(8, 3)`` with its ``count`` vertices first, in order. Each edge
    ``a -> b`` emits its crossing point (if it crosses) and then ``b`` (if inside); the
    emitted points are packed to the front with a cumulative count and a gather (a
    fixed-size compaction). A vertex on the plane counts as
    inside, so no duplicate is created for it. The crossing parameter divides by
    ``d_a - d_b``, which is nonzero exactly when the edge crosses; other edges divide by
    1 (double ``where``). ``scale`` (m) is the size of the coordinates that the polygon and
    ``offset`` were computed from (the boxes' centres and half-extents): it sets the
    round-off of the distances ``d``.
    """
    index = jnp.arange(_MAX_POLYGON)
    wraps = (index + 1 >= count)[:, None]
    b = jnp.where(wraps, polygon[:1], jnp.roll(polygon, -1, axis=0))
    along_a, along_b = spatial.dot(polygon, normal[None, :]), spatial.dot(b, normal[None, :])
    d_a = offset - along_a
    d_b = offset - along_b
    edge = index < count
    in_a = d_a >= 0
    in_b = d_b >= 0
    crossing = edge & (in_a != in_b)
    t = d_a / jnp.where(crossing, d_a - d_b, 1.0)
    # An edge lying in the plane to rounding crosses it anywhere: where two faces have the
    # same footprint, float32 gives its ends distances of noise with opposite signs. Its
    # crossing point then moves with the edge, not along it at 1/(d_a - d_b) (1e8 per m:
    # a 3-cube tower's float32 gradient grew to 5e10 over 200 steps, and overflowed on a
    # cube bridging two). The value is the same. The round-off is that of the coordinates
    # the distances were computed from, not of the distances themselves: near the origin
    # they cancel to 1e-9 and below (a float32 2x2 grid of cubes turned 30 degrees, whose
    # diagonal neighbours share the vertical edge on the z axis: slot 0 moved at 2e8 m per
    # m, and the grid's gradient grew to 3e7 over 100 steps).
    size = scale + jnp.abs(offset) + jnp.abs(along_a) + jnp.abs(along_b)
    rounding = 8 * jnp.finfo(d_a.dtype).eps * size
    # So is the crossing of an edge within PARALLEL_SLOPE of the plane (see there).
    length = jnp.sqrt(spatial.dot(b - polygon, b - polygon))
    held = jnp.abs(d_a - d_b) <= jnp.maximum(rounding, PARALLEL_SLOPE * length)
    t = jnp.where(held, jax.lax.stop_gradient(t), t)
    crossing_point = polygon + t[:, None] * (b - polygon)
    emitted = jnp.stack([crossing, edge & in_b], axis=1).reshape(-1)  # (16,)
    points = jnp.stack([crossing_point, b], axis=1).reshape(-1, 3)
    # Output slot j takes the (j+1)-th emitted point. Round-off on a near-degenerate
    # polygon could emit more than 8 points; the extras drop. Unused slots repeat point 0.
    running = jnp.cumsum(emitted)
    source = jnp.argmax(running[None, :] == index[:, None] + 1, axis=1)
    return points[source], jnp.minimum(running[-1], _MAX_POLYGON)


def _pick(score: Array, available: Array) -> tuple[Array, Array]:
    """Index of the best available candidate, and whether there was one."""
    index = jnp.argmax(jnp.where(available, score, -jnp.inf))
    return index, jnp.any(available)


def _centre(points: Array, mask: Array) -> Array:
    """The mean ``(3,)`` of the rows of ``points`` where ``mask`` holds (0 where none does)."""
    weight = mask.astype(points.dtype)
    return jnp.sum(weight[:, None] * points, axis=0) / jnp.maximum(jnp.sum(weight), 1.0)


def _reduce_manifold(points: Array, gaps: Array, candidate: Array, normal: Array, tie: Array):
    """Choose at most 4 of the (up to 8) clipped points: deepest first, then a wide spread.

    Slot 0 is the deepest point (its gap is the penetration depth), slot 1 the point
    farthest from it, slots 2 and 3 the points that make the largest triangle with that
    pair on either side (signed area about ``normal``). Points within ``tie`` (round-off,
    m) of the deepest count as equally deep, and of those the one farthest from the
    candidates' centre is taken: a corner of the polygon. Where a face rests flat on an
    equal one, their edges lie on each other's side planes, and clipping leaves points
    anywhere along those edges, as deep as the corners to round-off; taken as slot 0, such
    a point wandered along its edge from step to step (by up to 25 mm on a settled 5-box
    stack), and a corner was left out. Slot 0's gap is then within ``tie`` of the depth.
    Returns indices ``(4,)`` and a mask ``(4,)`` of the slots that found a point.
    """
    index = jnp.arange(points.shape[0])
    deepest = jnp.min(jnp.where(candidate, gaps, jnp.inf))
    level = candidate & (gaps <= deepest + tie)
    from_centre = points - _centre(points, candidate)[None, :]
    i0, ok0 = _pick(spatial.dot(from_centre, from_centre), level)
    available = candidate & (index != i0)
    first = points[i0]
    from_first = points - first[None, :]
    i1, ok1 = _pick(spatial.dot(from_first, from_first), available)
    available = available & (index != i1)
    area = spatial.dot(normal[None, :], spatial.cross((points[i1] - first)[None, :], from_first))
    i2, ok2 = _pick(area, available)
    available = available & (index != i2)
    i3, ok3 = _pick(-area, available)
    return jnp.stack([i0, i1, i2, i3]), jnp.stack([ok0, ok1, ok2, ok3])


def _face_contact(ref_is_a, axis_index, normal_ba, pa, axes_a, ea, pb, axes_b, eb, margin, tie):
    """Clipped manifold for a face axis. Returns A's surface points, gaps (along ``normal_ba``) and a mask."""
    # Reference/incident roles are traced (they depend on which face won): select by where.
    c_ref = jnp.where(ref_is_a, pa, pb)
    axes_ref = jnp.where(ref_is_a, axes_a, axes_b)
    e_ref = jnp.where(ref_is_a, ea, eb)
    c_inc = jnp.where(ref_is_a, pb, pa)
    axes_inc = jnp.where(ref_is_a, axes_b, axes_a)
    e_inc = jnp.where(ref_is_a, eb, ea)
    normal_ref = jnp.where(ref_is_a, -normal_ba, normal_ba)  # from the reference to the incident box
    face_height = spatial.dot(normal_ref, c_ref) + e_ref[axis_index]

    # Incident face: the face of the incident box most anti-parallel to the reference normal.
    # |a_m . n| >= 1/sqrt(3) for the best m, so its sign is well defined.
    alignment = spatial.dot(axes_inc, normal_ref[None, :])
    m = jnp.argmax(jnp.abs(alignment))
    face_normal_inc = -geo.sign_nonzero(alignment[m]) * axes_inc[m]
    face_centre = c_inc + e_inc[m] * face_normal_inc
    scaled = e_inc[:, None] * axes_inc
    du, dv = scaled[(m + 1) % 3], scaled[(m + 2) % 3]
    quad = jnp.stack([face_centre + du + dv, face_centre - du + dv, face_centre - du - dv, face_centre + du - dv])
    polygon = jnp.concatenate([quad, jnp.zeros((_MAX_POLYGON - 4, 3), quad.dtype)])
    count = jnp.asarray(4)

    # Side planes of the reference face: |a_j . (x - c_ref)| <= e_j for its two tangent axes.
    # One lax.scan over the four planes, so the clipping code is compiled once.
    tangent_index = jnp.stack([(axis_index + 1) % 3, (axis_index + 2) % 3])
    tangents = axes_ref[tangent_index]
    reach = e_ref[tangent_index]
    centre = spatial.dot(tangents, c_ref[None, :])
    plane_normals = jnp.concatenate([tangents, -tangents])
    plane_offsets = jnp.concatenate([centre + reach, reach - centre])

    scale = jnp.max(jnp.abs(c_ref)) + jnp.max(jnp.abs(c_inc)) + jnp.sum(e_ref) + jnp.sum(e_inc)

    def clip_step(carry, plane):
        return _clip(*carry, *plane, scale), None

    (polygon, count), _ = jax.lax.scan(clip_step, (polygon, count), (plane_normals, plane_offsets))

    depth_gap = spatial.dot(polygon, normal_ref[None, :]) - face_height  # (8,) distance above the reference face
    candidate = (jnp.arange(_MAX_POLYGON) < count) & (depth_gap < margin)
    chosen, found = _reduce_manifold(polygon, depth_gap, candidate, normal_ref, tie)
    incident_points = polygon[chosen]
    gaps = depth_gap[chosen]
    # A's surface point: the incident point itself if A is incident, else its projection
    # onto A's (reference) face.
    surface_a = jnp.where(ref_is_a, incident_points - gaps[:, None] * normal_ref[None, :], incident_points)
    return surface_a, gaps, found


def _edge_contact(i, j, normal_ba, pa, axes_a, ea, pb, axes_b, eb):
    """One contact between A's edge along ``a_i`` and B's edge along ``b_j`` that support the axis.

    A's supporting edge is the one farthest along ``-normal_ba`` (towards B), B's the one
    farthest along ``+normal_ba``. Returns A's closest edge point and B's.
    """
    toward_b = -geo.sign_nonzero(spatial.dot(axes_a, normal_ba[None, :]))
    toward_a = geo.sign_nonzero(spatial.dot(axes_b, normal_ba[None, :]))
    not_i = jnp.arange(3) != i
    not_j = jnp.arange(3) != j
    centre_a = pa + spatial.dot(jnp.where(not_i, toward_b * ea, 0.0)[None, :], spatial.transpose(axes_a))
    centre_b = pb + spatial.dot(jnp.where(not_j, toward_a * eb, 0.0)[None, :], spatial.transpose(axes_b))
    dir_a, dir_b = axes_a[i], axes_b[j]
    s, t = geo.closest_between_segments(centre_a, dir_a, ea[i], centre_b, dir_b, eb[j])
    return centre_a + s * dir_a, centre_b + t * dir_b


def _closest_pair(pa, axes_a, ea, pb, axes_b, eb, edge_a, edge_b):
    """Exact closest points of two disjoint boxes: the best of 16 corner-box pairs and one edge pair.

    For disjoint convex polyhedra the closest pair is a corner of one box against the other
    box (vertex-face, and the vertex-edge, vertex-vertex, edge-face and face-face variants,
    whose closest set always contains a corner of one box), or two non-parallel edges
    interior to both. In the last case the separation vector is perpendicular to both
    edges, so its direction is one of the 9 edge-edge axes, where the separation equals the
    distance: it is the best edge axis of the SAT, and ``edge_a``, ``edge_b`` (the closest
    points of that axis's two supporting edges) are that pair. Every candidate is a true
    pair of surface points, so the smallest is never below the distance; it is the exact
    distance unless the best edge axis ties with others (an edge parallel to a face), where
    the edge pair handed in may not be the closest: the caller keeps a face manifold's own
    pair then. Returns ``(point on A, point on B)``; meaningless, but finite,
    for overlapping boxes.
    """

    def onto_box(points, centre, axes, half):
        local = spatial.dot((points - centre[None, :])[:, None, :], axes[None, :, :])
        local = jnp.clip(local, -half[None, :], half[None, :])
        return centre[None, :] + spatial.dot(local[:, None, :], spatial.transpose(axes)[None, :, :])

    corners_a = geo.box_corners(pa, axes_a, ea)
    corners_b = geo.box_corners(pb, axes_b, eb)
    on_a = jnp.concatenate([corners_a, onto_box(corners_b, pa, axes_a, ea), edge_a[None, :]])
    on_b = jnp.concatenate([onto_box(corners_a, pb, axes_b, eb), corners_b, edge_b[None, :]])
    difference = on_a - on_b
    best = jnp.argmin(spatial.dot(difference, difference))
    return on_a[best], on_b[best]


def _axis_separations(pa, axes_a, ea, pb, axes_b, eb):
    """Step 1: the separations ``|L.(c_a - c_b)| - h_a(L) - h_b(L)`` along the 3 + 3 face
    normals (``(6,)``, normals ``(6, 3)`` oriented from B to A) and the 9 edge cross
    products (``(9,)``, ``(9, 3)``, and which of them have a direction, ``(9,)``). Cross
    products of (nearly) parallel edges have none: below ``|a x b|^2 = eps`` they are
    masked (and their normalisation divides by 1 instead)."""
    delta = pa - pb

    def separation(directions):
        along = spatial.dot(directions, delta[None, :])
        sep = jnp.abs(along) - _projection_radius(axes_a, ea, directions) - _projection_radius(axes_b, eb, directions)
        return sep, geo.sign_nonzero(along)[:, None] * directions  # oriented from B to A

    face_sep, face_normals = separation(jnp.concatenate([axes_a, axes_b]))
    edge_axes = spatial.cross(axes_a[:, None, :], axes_b[None, :, :]).reshape(9, 3)
    edge_sq = spatial.dot(edge_axes, edge_axes)
    edge_ok = edge_sq > jnp.finfo(pa.dtype).eps
    edge_axes = edge_axes / jnp.sqrt(jnp.where(edge_ok, edge_sq, 1.0))[:, None]
    edge_sep, edge_normals = separation(edge_axes)
    return face_sep, face_normals, edge_sep, edge_normals, edge_ok


def box_box_separation(
    box_a: Box,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    box_b: Box,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
) -> Float[Array, ""]:
    """The largest separation over the 15 axes (m), without the manifold.

    Negative (the depth) when the boxes overlap, zero exactly when they touch, positive when
    they are apart, where it bounds the distance from below (it equals the minimum gap of
    :func:`box_box` except for separated boxes). Its roots are the instants of touching, so
    the time-of-impact search uses it: it costs a fraction of the clipped manifold.
    """
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    pa, qa, pb, qb = geo.as_float(dtype, position_a, orientation_a, position_b, orientation_b)
    ea, eb = geo.size_vector(box_a.half_extents, dtype), geo.size_vector(box_b.half_extents, dtype)
    face_sep, _, edge_sep, _, edge_ok = _axis_separations(pa, geo.body_axes(qa), ea, pb, geo.body_axes(qb), eb)
    return jnp.maximum(jnp.max(face_sep), jnp.max(jnp.where(edge_ok, edge_sep, -jnp.inf)))


def box_box(
    box_a: Box,
    position_a: Float[ArrayLike, "3"],
    orientation_a: Float[ArrayLike, "4"],
    box_b: Box,
    position_b: Float[ArrayLike, "3"],
    orientation_b: Float[ArrayLike, "4"],
    margin: float = 0.0,
) -> Contact:
    """Two boxes: ``K = 4`` (see the module docstring for the algorithm).

    Face contacts fill up to 4 slots, all with the reference face's normal, each gap being
    that point's depth below (or height above) the reference face; edge-edge contacts fill
    slot 0 only. The minimum active gap is the exact signed distance: the separating-axis
    depth for overlapping boxes (overstated by at most :data:`EDGE_PREFERENCE` times the
    smaller box's least half-extent, where a face contact is kept over a barely better
    edge axis), the closest-pair distance for separated ones.
    """
    position_a, orientation_a = geo.pose("box_box (A)", position_a, orientation_a)
    position_b, orientation_b = geo.pose("box_box (B)", position_b, orientation_b)
    geo.check_margin(margin)
    dtype = geo.float_dtype(position_a, orientation_a, position_b, orientation_b)
    pa, qa, pb, qb = geo.as_float(dtype, position_a, orientation_a, position_b, orientation_b)
    ea = geo.size_vector(box_a.half_extents, dtype)
    eb = geo.size_vector(box_b.half_extents, dtype)
    axes_a = geo.body_axes(qa)
    axes_b = geo.body_axes(qb)
    delta = pa - pb
    eps = jnp.finfo(dtype).eps
    # Round-off of a separation computed from coordinates of this size.
    tie = 64 * eps * (spatial.safe_norm(delta) + sum(box_a.half_extents) + sum(box_b.half_extents))

    # 1. Separating axes.
    face_sep, face_normals, edge_sep, edge_normals, edge_ok = _axis_separations(pa, axes_a, ea, pb, axes_b, eb)
    k_face = jnp.argmax(face_sep)  # ties: A's faces first
    k_edge = jnp.argmax(jnp.where(edge_ok, edge_sep, -jnp.inf))
    best_face = face_sep[k_face]
    edge_gap = edge_sep[k_edge]
    best_edge = jnp.where(edge_ok[k_edge], edge_gap, best_face)
    separated = jnp.maximum(best_face, best_edge) > 0

    # 2. Face manifold.
    normal_face = face_normals[k_face]
    face_surface_a, face_gap, face_found = _face_contact(
        k_face < 3, k_face % 3, normal_face, pa, axes_a, ea, pb, axes_b, eb, margin, tie
    )
    # The edge contact is used when its axis wins by more than round-off and the preference
    # for faces, and as a fallback should clipping leave no point within the margin (never
    # seen in tests; cheap insurance against a near-tie between a face and an edge axis).
    prefer_faces = EDGE_PREFERENCE * geo.smallest(*box_a.half_extents, *box_b.half_extents)
    use_edge = (best_edge > best_face + tie + prefer_faces) | ~face_found[0]
    # 3. Edge-edge contact (slot 0 only).
    normal_edge = edge_normals[k_edge]
    edge_a, edge_b = _edge_contact(k_edge // 3, k_edge % 3, normal_edge, pa, axes_a, ea, pb, axes_b, eb)
    edge_surface = jnp.concatenate([edge_a[None], jnp.zeros((3, 3), dtype)])
    normal = jnp.where(use_edge, normal_edge, normal_face)
    surface_a = jnp.where(use_edge, edge_surface, face_surface_a)
    gap = jnp.where(use_edge, jnp.concatenate([edge_gap[None], jnp.zeros(3, dtype)]), face_gap)
    found = jnp.where(use_edge, jnp.arange(4) == 0, face_found)
    normals = jnp.broadcast_to(normal, (4, 3))

    # 4. Separated: the exact closest pair replaces slot 0 when their gaps differ by more
    # than round-off (when they agree, slot 0 already is a closest pair, and keeping it
    # keeps a resting face contact's four points from jumping as the gap crosses 0).
    closest_a, closest_b = _closest_pair(pa, axes_a, ea, pb, axes_b, eb, edge_a, edge_b)
    distance = spatial.safe_norm(closest_a - closest_b)
    exact_normal = spatial.safe_normalize(closest_a - closest_b)
    # A face manifold's slot is itself a true pair of surface points, so only a strictly
    # closer pair replaces it: where an edge lies parallel to a face, edge axes tie with
    # the face axis, and the edge pair ``_closest_pair`` is handed may not be the closest
    # (a plank across a block, spun 20 degrees: slot 0 went from the exact 0.01 m with
    # normal +z to 0.30 m with a normal 70 degrees off). An edge contact's gap is a
    # separation along its axis, a lower bound of the distance: replaced when it differs.
    differs = jnp.where(use_edge, jnp.abs(distance - gap[0]) > tie, distance < gap[0] - tie)
    replace = separated & (~found[0] | differs) & (distance > 0)
    first = jnp.arange(4) == 0
    surface_a = jnp.where((first & replace)[:, None], closest_a[None, :], surface_a)
    normals = jnp.where((first & replace)[:, None], exact_normal[None, :], normals)
    gap = jnp.where(first & replace, distance, gap)
    found = found | (first & replace)
    order = _pose_stable_order(surface_a, normal, axes_a, found)
    return contact_from_surface_point(surface_a[order], normals[order], gap[order], margin, valid=found[order])


def _pose_stable_order(points: Array, normal: Array, axes_a: Array, found: Array) -> Array:
    """The slots ``(4,)`` in order of their points' angle about the found points' centre,
    measured in A's frame, the found slots first.

    The manifold is chosen deepest point first, and which of a resting face's four equally
    deep corners that is, and which box is the reference, changes with round-off from one
    step to the next. A solve's warm start (the last step's impulse of each slot) then
    landed on other corners. Ordered by where they lie on A, the same corners keep their
    slots while the pose moves a little. (An order by angle has one cut, where a point lies
    straight behind the centre along A's ``-u``; a pose with a point there may still swap
    two slots.) With this order and :func:`_reduce_manifold`'s corners, the 5-box stack of
    ``benchmarks/contacts.py`` (float32) kept every slot on its corner over its first 400
    steps (before: a slot moved by more than 1 mm in 195 of them), and started from 24
    poses 2 um apart it ran 1.1-1.3 PGS sweeps a step on average over its second second,
    against 3.1-3.9 (two samples of 8 and 16 starts; some starts settled into a slow
    rocking that needed 3-11 sweeps a step). The order is piecewise constant: no
    derivative."""
    m = jnp.argmax(jnp.abs(spatial.dot(axes_a, normal[None, :])))
    u, v = axes_a[(m + 1) % 3], axes_a[(m + 2) % 3]
    offset = jax.lax.stop_gradient(points - _centre(points, found)[None, :])
    angle = jnp.arctan2(spatial.dot(offset, v[None, :]), spatial.dot(offset, u[None, :]))
    key = jnp.where(found, angle, 4.0)  # above every angle: the empty slots last
    index = jnp.arange(points.shape[0])
    before = (key[None, :] < key[:, None]) | ((key[None, :] == key[:, None]) & (index[None, :] < index[:, None]))
    rank = jnp.sum(before, axis=1)  # the place of slot i
    return jnp.argmax(rank[None, :] == index[:, None], axis=1)  # the slot at each place
