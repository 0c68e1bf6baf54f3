"""Seed 000's impulse for one colliding contact, in its closed form."""

from __future__ import annotations

import jax
import numpy as np
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
    B's rotational term needs both ``inv_inertia_b`` and ``r_b`` (neither for a body that
    does not turn, such as the ground); a concrete ``normal`` must be unit and a concrete
    ``restitution`` in ``[0, 1]``.
    """
    if (inv_inertia_b is None) != (r_b is None):
        raise ValueError("collision_impulse: give both inv_inertia_b and r_b (B's rotational term), or neither "
                         "(B does not turn, e.g. the ground); with one of them the term was left out.")
    _check_concrete(normal, restitution)
    term_a = spatial.dot(spatial.cross(spatial.matvec(inv_inertia_a, spatial.cross(r_a, normal)), r_a), normal)
    denominator = inv_mass_a + inv_mass_b + term_a
    if inv_inertia_b is not None and r_b is not None:
        denominator = denominator + spatial.dot(
            spatial.cross(spatial.matvec(inv_inertia_b, spatial.cross(r_b, normal)), r_b), normal)
    return -(1.0 + restitution) * normal_velocity / denominator


def _check_concrete(normal, restitution) -> None:
    """Raise for a concrete normal that is not unit or a restitution outside [0, 1]
    (traced values, under ``jit``/``grad``, are the caller's to keep in range)."""
    try:
        n, e = np.asarray(normal, dtype=float), np.asarray(restitution, dtype=float)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return  # traced: nothing to check here
    if n.shape[-1:] != (3,) or not np.all(np.abs(np.linalg.norm(n, axis=-1) - 1.0) <= 1e-6):
        raise ValueError(f"collision_impulse: normal must be a unit 3-vector (from B to A), got {normal!r}; "
                         "divide it by its norm.")
    if not np.all((e >= 0.0) & (e <= 1.0)):
        raise ValueError(f"collision_impulse: restitution must be in [0, 1], got {restitution!r}.")
