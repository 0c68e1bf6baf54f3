"""Capsule (A) against capsule (B): ``K = 2``.

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
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from .. import spatial
from ..shapes import Capsule
from . import _geometry as geo
from ._contact import Contact, contact_from_surface_point
from ._sphere import rounded_points_contact

__all__ = ["capsule_capsule"]

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
    # parallel ones any perpendicular to A (A's body x axis).
    perpendicular = spatial.safe_normalize(spatial.cross(axis_a, axis_b))
    perpendicular = jnp.where(spatial.dot(perpendicular, perpendicular) > 0.5, perpendicular, axes_a[0])
    surface_a, normal, gap = rounded_points_contact(
        core_a, capsule_a.radius, core_b, capsule_b.radius, jnp.broadcast_to(perpendicular, (2, 3))
    )
    distinct = jnp.abs(s1 - s0) > _DISTINCT_FRACTION * min(capsule_a.radius, capsule_b.radius)
    valid = jnp.stack([jnp.ones((), bool), distinct])
    return contact_from_surface_point(surface_a, normal, gap, margin, valid=valid)
