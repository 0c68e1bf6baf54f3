"""The narrow phase's output: a fixed-size, masked set of contact points for one shape pair.

Conventions (shared by every pair function, and by the contact solvers built on them):

* ``normal`` is a unit vector in the world frame that points **from shape B towards
  shape A**: the direction in which A must move to separate (Baraff's convention). For a
  body against the ground :class:`~jaxrb.Plane` (always B) it is the plane's normal.
* ``gap`` is the signed distance along ``normal`` between the two surfaces, in metres:
  ``> 0`` separated, ``< 0`` penetrating. The surface points are
  ``point + gap/2 * normal`` on A and ``point - gap/2 * normal`` on B.
* ``point`` is the midpoint between those two surface points, world frame, metres.
* ``active`` marks the slots that hold a real contact, ``gap < margin``. The number of
  slots ``K`` is static per pair type (:func:`jaxrb.collision.max_contacts`); inactive
  slots still hold finite numbers, so masked arithmetic (``jnp.where(active, f, 0)``)
  never meets a NaN, in the values or in their gradients.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

__all__ = ["Contact", "concatenate_contacts", "contact_from_surface_point"]


class Contact(eqx.Module):
    """Up to ``K`` contact points between one shape A and one shape B.

    Attributes:
        point: ``(K, 3)`` m, world frame: midpoint between the two surfaces along ``normal``.
        normal: ``(K, 3)`` unit, world frame, from B towards A.
        gap: ``(K,)`` m, signed distance along ``normal`` (``< 0``: penetration depth).
        active: ``(K,)`` bool, the slots holding a contact with ``gap < margin``.

    Under ``jax.vmap`` every field gains the batch axes in front: ``(..., K, 3)``.
    """

    point: Float[Array, "*batch k 3"]
    normal: Float[Array, "*batch k 3"]
    gap: Float[Array, "*batch k"]
    active: Bool[Array, "*batch k"]

    @property
    def num_slots(self) -> int:
        """``K``, the static number of slots (active or not)."""
        return self.gap.shape[-1]

    def flip(self) -> Contact:
        """The same contacts seen with A and B swapped: normals negated.

        ``point`` (the midpoint) and ``gap`` (a distance) do not depend on the order.
        """
        return Contact(self.point, -self.normal, self.gap, self.active)


def concatenate_contacts(contacts: Sequence[Contact]) -> Contact:
    """Join several :class:`Contact` along the slot axis: ``K = sum(K_i)``.

    All must share the same leading batch shape. Useful to gather the contacts of one body
    pair made of several shapes, or to stack a scene's pair groups into one array.
    """
    contacts = list(contacts)
    if not contacts:
        raise ValueError("concatenate_contacts needs at least one Contact.")
    return Contact(
        point=jnp.concatenate([c.point for c in contacts], axis=-2),
        normal=jnp.concatenate([c.normal for c in contacts], axis=-2),
        gap=jnp.concatenate([c.gap for c in contacts], axis=-1),
        active=jnp.concatenate([c.active for c in contacts], axis=-1),
    )


def contact_from_surface_point(
    surface_point_a: Float[ArrayLike, "k 3"],
    normal: Float[ArrayLike, "k 3"],
    gap: Float[ArrayLike, " k"],
    margin: float | Float[ArrayLike, ""],
    valid: Bool[ArrayLike, " k"] | None = None,
) -> Contact:
    """Build a :class:`Contact` from A's surface point, the unit normal (B to A) and the gap.

    ``point = surface_point_a - gap/2 * normal`` (B's surface point is
    ``surface_point_a - gap * normal``). A slot is active when ``gap < margin`` and, if
    given, ``valid`` (e.g. a clipped-away manifold slot is not valid).
    """
    surface_point_a = jnp.asarray(surface_point_a)
    gap = jnp.asarray(gap)
    normal = jnp.asarray(normal)
    active = gap < margin
    if valid is not None:
        active = active & valid
    return Contact(
        point=surface_point_a - 0.5 * gap[..., None] * normal,
        normal=normal,
        gap=gap,
        active=active,
    )
