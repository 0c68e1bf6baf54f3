"""Contact impulses: the seed's impulse law, Coulomb friction and projected Gauss-Seidel.

Notation (seed 000). At a contact point with unit normal ``n`` (from B towards A) and
lever arms ``r_a = p - x_a``, ``r_b = p - x_b``, the relative velocity is
``u = (v_a + w_a x r_a) - (v_b + w_b x r_b)``; ``u_n = n . u > 0`` means separating.
An impulse ``P`` (N s, world frame) acts as ``+P`` on A and ``-P`` on B at the point:
``dv = P / M``, ``dL = r x P``. It changes ``u`` by ``K P`` with the contact's
inverse effective mass (the Delassus block)

    K = (1/M_a + 1/M_b) E - [r_a]x I_a^-1 [r_a]x - [r_b]x I_b^-1 [r_b]x,

and ``n . K n = 1/M_a + 1/M_b + [I_a^-1 (r_a x n) x r_a + I_b^-1 (r_b x n) x r_b] . n`` is
the denominator of the seed's impulse ``j = -(1 + e) u_n / (n . K n)``.

Projected Gauss-Seidel (Moreau, Jean; Catto's "sequential impulses") visits the contacts
one at a time, always with the current velocities, and keeps an *accumulated* impulse per
contact that it projects onto the friction cone: ``lambda_n >= 0`` and
``|lambda_t| <= mu lambda_n`` (the circular cone, not a pyramid). Contacts of one colour
(see ``_layout``) share no body, so a whole colour is updated at once, exactly as if one
after the other. The iteration count is fixed and the loops are ``lax.scan``: reverse
mode crosses them.

Energy. Every single update is chosen so that it cannot add kinetic energy: an impulse
``dP`` changes it by ``u . dP + dP.K dP / 2``. A normal push is capped at ``2|u_n|/K_nn``
(the elastic bound; without it, friction that has already slowed the approach would let
Newton's law add energy, Kane's paradox), and a friction update is a projected-gradient
step of length ``1/k_max``, which only descends. So an impact with ``e <= 1`` never
creates energy, whatever the iteration count.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .. import spatial

__all__ = ["Bodies", "Frames", "frames", "solve", "sweeps", "pad_slots", "tangent_basis", "apply_impulses",
           "relative_velocity", "normal_velocities", "collisions"]


class Bodies(eqx.Module):
    """The solver's view of the bodies: ``N + 2`` rows (``N``: ground, ``N + 1``: padding).

    Attributes:
        inv_mass: ``(N + 2,)`` 1/kg; zero for the two static rows.
        inv_inertia: ``(N + 2, 3, 3)`` world-frame inverse inertia, 1/(kg m^2); zero for
            the static rows.
        velocity: ``(N + 2, 3)`` m/s.
        angular_velocity: ``(N + 2, 3)`` rad/s, world frame.
    """

    inv_mass: Float[Array, " m"]
    inv_inertia: Float[Array, "m 3 3"]
    velocity: Float[Array, "m 3"]
    angular_velocity: Float[Array, "m 3"]


class Frames(eqx.Module):
    """Per-slot contact geometry, padded with one inert slot at index ``C``.

    Attributes:
        body_a, body_b: ``(C + 1,)`` int body rows.
        r_a, r_b: ``(C + 1, 3)`` m, lever arms from each centre of mass to the contact point.
        basis: ``(C + 1, 3, 3)`` rows ``(n, t1, t2)``, orthonormal, world frame.
        delassus: ``(C + 1, 3, 3)`` ``K`` in the ``(n, t1, t2)`` basis, 1/kg.
    """

    body_a: Array
    body_b: Array
    r_a: Float[Array, "c 3"]
    r_b: Float[Array, "c 3"]
    basis: Float[Array, "c 3 3"]
    delassus: Float[Array, "c 3 3"]


def tangent_basis(normal: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """Rows ``(n, t1, t2)``: ``n`` and two unit tangents, a right-handed orthonormal frame.

    ``t1`` is ``n x e`` normalised, with ``e`` the world axis least aligned with ``n`` (a
    static choice per branch, so the frame is smooth where it does not switch).
    """
    ax = jnp.abs(normal)
    use_x = (ax[..., 0] <= ax[..., 1]) & (ax[..., 0] <= ax[..., 2])
    use_y = ~use_x & (ax[..., 1] <= ax[..., 2])
    e = jnp.stack([use_x, use_y, ~use_x & ~use_y], axis=-1).astype(normal.dtype)
    t1 = spatial.safe_normalize(spatial.cross(normal, e))
    t2 = spatial.cross(normal, t1)
    return jnp.stack([normal, t1, t2], axis=-2)


def _arm_block(inv_mass, inv_inertia, r):
    """``inv_mass E - [r]x I^-1 [r]x`` (world frame, ``(..., 3, 3)``)."""
    skew = spatial.skew(r)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=r.dtype), (*r.shape[:-1], 3, 3))
    return inv_mass[..., None, None] * eye - spatial.matmul(spatial.matmul(skew, inv_inertia), skew)


def frames(bodies: Bodies, body_a, body_b, point, normal, position) -> Frames:
    """Lever arms, tangent bases and Delassus blocks for ``C`` slots (+1 inert padding).

    ``position`` is ``(N + 2, 3)``, the centres of mass (the static rows' values do not matter).
    """
    pad = lambda x, value: jnp.concatenate([x, jnp.full((1, *x.shape[1:]), value, x.dtype)])  # noqa: E731
    n_rows = bodies.inv_mass.shape[0]
    body_a = jnp.concatenate([jnp.asarray(body_a, jnp.int32), jnp.array([n_rows - 1], jnp.int32)])
    body_b = jnp.concatenate([jnp.asarray(body_b, jnp.int32), jnp.array([n_rows - 1], jnp.int32)])
    point = pad(point, 0.0)
    normal = pad(normal, 0.0).at[-1, 2].set(1.0)
    r_a = point - position[body_a]
    r_b = point - position[body_b]
    basis = tangent_basis(normal)
    k_world = (_arm_block(bodies.inv_mass[body_a], bodies.inv_inertia[body_a], r_a)
               + _arm_block(bodies.inv_mass[body_b], bodies.inv_inertia[body_b], r_b))
    delassus = spatial.matmul(spatial.matmul(basis, k_world), spatial.transpose(basis))
    return Frames(body_a, body_b, r_a, r_b, basis, delassus)


def relative_velocity(bodies: Bodies, f: Frames, idx):
    a, b = f.body_a[idx], f.body_b[idx]
    ua = bodies.velocity[a] + spatial.cross(bodies.angular_velocity[a], f.r_a[idx])
    ub = bodies.velocity[b] + spatial.cross(bodies.angular_velocity[b], f.r_b[idx])
    return spatial.matvec(f.basis[idx], ua - ub)  # (..., 3) in (n, t1, t2)


def normal_velocities(bodies: Bodies, f: Frames) -> Array:
    """``u_n`` (m/s) of every slot, padding included: ``(C + 1,)``."""
    return relative_velocity(bodies, f, jnp.arange(f.body_a.shape[0]))[:, 0]


def _apply(bodies: Bodies, f: Frames, idx, local_impulse) -> Bodies:
    """Apply ``+P`` to A and ``-P`` to B of slots ``idx``; ``P`` given in the slot basis."""
    impulse = spatial.matvec(spatial.transpose(f.basis[idx]), local_impulse)
    a, b = f.body_a[idx], f.body_b[idx]
    dva = bodies.inv_mass[a][:, None] * impulse
    dvb = bodies.inv_mass[b][:, None] * impulse
    dwa = spatial.matvec(bodies.inv_inertia[a], spatial.cross(f.r_a[idx], impulse))
    dwb = spatial.matvec(bodies.inv_inertia[b], spatial.cross(f.r_b[idx], impulse))
    velocity = bodies.velocity.at[a].add(dva).at[b].add(-dvb)
    omega = bodies.angular_velocity.at[a].add(dwa).at[b].add(-dwb)
    return eqx.tree_at(lambda x: (x.velocity, x.angular_velocity), bodies, (velocity, omega))


def apply_impulses(bodies: Bodies, f: Frames, local_impulses) -> Bodies:
    """Apply every slot's impulse ``(C, 3)`` (slot basis) at once (e.g. a warm start)."""
    c = local_impulses.shape[0]
    return _apply(bodies, f, jnp.arange(c), local_impulses)


def _update(bodies: Bodies, f: Frames, idx, lam, target, mu, active, friction: bool):
    """One projected Gauss-Seidel update of the slots ``idx`` (one colour; no shared body)."""
    u = relative_velocity(bodies, f, idx)
    k = f.delassus[idx]
    on = active[idx]
    # Normal: reach u_n = target, keep lambda_n >= 0, and never push past the elastic bound.
    k_nn = k[:, 0, 0]
    raw = (target[idx] - u[:, 0]) / k_nn
    elastic_cap = jnp.maximum(-2.0 * u[:, 0] / k_nn, 0.0)
    step = jnp.where(raw > 0, jnp.minimum(raw, elastic_cap), raw)
    new_n = jnp.where(on, jnp.maximum(lam[idx, 0] + step, 0.0), 0.0)
    d_n = new_n - lam[idx, 0]
    bodies = _apply(bodies, f, idx, jnp.stack([d_n, jnp.zeros_like(d_n), jnp.zeros_like(d_n)], -1))
    lam = lam.at[idx, 0].set(new_n)
    if not friction:
        return bodies, lam
    # Friction: a projected-gradient step on the disk |lambda_t| <= mu lambda_n (Coulomb's
    # cone), with the step 1/k_max, k_max the largest eigenvalue of the 2x2 tangential block.
    # The step is along -u_t, so a sliding contact's friction opposes its slip (maximal
    # dissipation); a full K_tt^-1 step would not, and would twist a sliding box. A projected
    # gradient step with step <= 1/k_max cannot add energy.
    u = relative_velocity(bodies, f, idx)
    k_max = _largest_tangential_eigenvalue(k)
    old_t = lam[idx, 1:]
    wanted = old_t - u[:, 1:] / k_max[:, None]
    radius = mu[idx] * new_n
    norm = spatial.safe_norm(wanted)
    scale = jnp.where(norm > radius, radius / jnp.where(norm > 0, norm, 1.0), 1.0)
    d_t = jnp.where(on[:, None], wanted * scale[:, None], 0.0) - old_t
    bodies = _apply(bodies, f, idx, jnp.concatenate([jnp.zeros_like(d_t[:, :1]), d_t], -1))
    lam = lam.at[idx, 1:].add(d_t)
    return bodies, lam


def _collision_update(bodies: Bodies, f: Frames, idx, e, mu, eligible, threshold):
    """Binary collisions of the slots ``idx`` (one colour) that approach faster than ``threshold``.

    The seed's impulse from the *current* relative velocity, ``j = -(1 + e) u_n / K_nn``,
    then friction bounded by ``mu j``. Impulses are new each time (never taken back), as in
    a sequence of two-body collisions.
    """
    u = relative_velocity(bodies, f, idx)
    k = f.delassus[idx]
    hit = eligible[idx] & (u[:, 0] < -threshold)
    j = jnp.where(hit, -(1.0 + e[idx]) * u[:, 0] / k[:, 0, 0], 0.0)
    bodies = _apply(bodies, f, idx, jnp.stack([j, jnp.zeros_like(j), jnp.zeros_like(j)], -1))
    u = relative_velocity(bodies, f, idx)
    k_max = _largest_tangential_eigenvalue(k)
    wanted = -u[:, 1:] / k_max[:, None]
    radius = mu[idx] * j
    norm = spatial.safe_norm(wanted)
    scale = jnp.where(norm > radius, radius / jnp.where(norm > 0, norm, 1.0), 1.0)
    d_t = jnp.where(hit[:, None], wanted * scale[:, None], 0.0)
    bodies = _apply(bodies, f, idx, jnp.concatenate([jnp.zeros_like(j)[:, None], d_t], -1))
    return bodies, jnp.concatenate([j[:, None], d_t], -1)


def collisions(bodies: Bodies, f: Frames, colours, e, mu, eligible, threshold, iterations: int):
    """Sequential binary collisions (the impact law), ``iterations`` sweeps; impulses ``(C, 3)``.

    Each slot approaching faster than ``threshold`` gets Newton's impulse with its ``e`` from
    its current velocity, so momentum travels along a row of touching bodies as a sequence
    of collisions (Newton's cradle) rather than being shared by a simultaneous solve. Each
    collision with ``e <= 1`` and its bounded friction cannot add energy. ``e``, ``mu`` and
    ``eligible`` are ``(C,)``.
    """
    pad1 = lambda x, v: jnp.concatenate([x, jnp.full((1, *x.shape[1:]), v, x.dtype)])  # noqa: E731
    e, mu, eligible = pad1(e, 0.0), pad1(mu, 0.0), pad1(eligible, False)
    total = jnp.zeros((e.shape[0], 3), bodies.velocity.dtype)

    def colour_step(carry, idx):
        b, total = carry
        b, impulse = _collision_update(b, f, idx, e, mu, eligible, threshold)
        return (b, total.at[idx].add(impulse)), None

    def sweep(carry, _):
        return jax.lax.scan(colour_step, carry, colours)[0], None

    (bodies, total), _ = jax.lax.scan(sweep, (bodies, total), None, length=iterations)
    return bodies, total[:-1]


def _largest_tangential_eigenvalue(k):
    k_tt = k[:, 1:, 1:]
    spread = spatial.safe_norm(jnp.stack([0.5 * (k_tt[:, 0, 0] - k_tt[:, 1, 1]), k_tt[:, 0, 1]], -1))
    return 0.5 * (k_tt[:, 0, 0] + k_tt[:, 1, 1]) + spread


def pad_slots(target, mu, active, lam0):
    """Append the inert padding slot (index ``C``) to the per-slot arrays."""
    pad1 = lambda x, v: jnp.concatenate([x, jnp.full((1, *x.shape[1:]), v, x.dtype)])  # noqa: E731
    active = pad1(active, False)
    return pad1(target, 0.0), pad1(mu, 0.0), active, pad1(lam0 * active[:-1, None], 0.0)


def sweeps(bodies: Bodies, f: Frames, colours, target, mu, active, lam, iterations: int, friction: bool = True):
    """``iterations`` projected Gauss-Seidel sweeps on padded slot arrays; ``lam`` already applied."""

    def colour_step(carry, idx):
        b, lam = carry
        return _update(b, f, idx, lam, target, mu, active, friction), None

    def sweep(carry, _):
        return jax.lax.scan(colour_step, carry, colours)[0], None

    (bodies, lam), _ = jax.lax.scan(sweep, (bodies, lam), None, length=iterations)
    return bodies, lam


def solve(
    bodies: Bodies,
    f: Frames,
    colours: Array,
    target: Float[Array, " c"],
    mu: Float[Array, " c"],
    active: Array,
    lam0: Float[Array, "c 3"],
    iterations: int,
    friction: bool = True,
) -> tuple[Bodies, Float[Array, "c 3"]]:
    """Projected Gauss-Seidel on ``C`` slots, colour by colour, ``iterations`` sweeps.

    Args:
        bodies: velocities before the contact impulses (``lam0`` is applied first: warm start).
        f: from :func:`frames`.
        colours: ``(num_colours, width)`` int slot indices, ``C`` for padding.
        target: ``(C,)`` m/s, the smallest normal velocity ``u_n`` each active slot must
            reach (``-e u_n^-`` at an impact, ``0`` at rest, ``-gap/dt`` ahead of a contact).
        mu: ``(C,)`` friction coefficients.
        active: ``(C,)`` bool; inactive slots carry no impulse.
        lam0: ``(C, 3)`` initial accumulated impulses ``(n, t1, t2)``, N s.
        iterations: static sweep count.
        friction: ``False`` solves the normal impulses only.

    Returns:
        ``(bodies, lam)``: velocities after the impulses, and the accumulated impulses.
    """
    target, mu, active, lam = pad_slots(target, mu, active, lam0)
    bodies = apply_impulses(bodies, f, lam)
    bodies, lam = sweeps(bodies, f, colours, target, mu, active, lam, iterations, friction)
    return bodies, lam[:-1]
