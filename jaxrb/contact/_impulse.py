"""Seed 000's impulse for one colliding contact, in its closed form."""

from __future__ import annotations

from jaxtyping import Array, ArrayLike, Float

from .. import spatial

__all__ = ["collision_impulse"]


def collision_impulse(
    normal_velocity: Float[ArrayLike, ""],
    normal: Float[ArrayLike, "3"],
    restitution: Float[ArrayLike, ""],
    inv_mass_a: Float[ArrayLike, ""],
    inv_inertia_a: Float[ArrayLike, "3 3"],
    r_a: Float[ArrayLike, "3"],
    inv_mass_b: Float[ArrayLike, ""] = 0.0,
    inv_inertia_b: Float[ArrayLike, "3 3"] | None = None,
    r_b: Float[ArrayLike, "3"] | None = None,
) -> Float[Array, ""]:
    """The seed's frictionless impulse magnitude ``j`` (N s) on A along ``n``:

        j = -(1 + e) v_rel / (1/M_a + 1/M_b + [I_a^-1 (r_a x n) x r_a + I_b^-1 (r_b x n) x r_b] . n)

    Args:
        normal_velocity: ``v_rel = n . (u_a - u_b)`` before the impact, m/s (< 0: approaching).
        normal: unit normal from B to A, world frame.
        restitution: ``e`` in ``[0, 1]``.
        inv_mass_a, inv_mass_b: 1/kg (0 for a static body such as the ground).
        inv_inertia_a, inv_inertia_b: world-frame inverse inertia, 1/(kg m^2).
        r_a, r_b: m, from each centre of mass to the contact point, world frame.

    Apply it as ``dv_a = j n / M_a``, ``dL_a = r_a x j n`` (and the opposite on B).
    """
    term_a = spatial.dot(spatial.cross(spatial.matvec(inv_inertia_a, spatial.cross(r_a, normal)), r_a), normal)
    denominator = inv_mass_a + inv_mass_b + term_a
    if inv_inertia_b is not None and r_b is not None:
        denominator = denominator + spatial.dot(
            spatial.cross(spatial.matvec(inv_inertia_b, spatial.cross(r_b, normal)), r_b), normal)
    return -(1.0 + restitution) * normal_velocity / denominator
