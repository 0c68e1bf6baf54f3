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
after the other. The sweep count is bounded, and every loop that reverse mode crosses is a
``lax.scan``; the step's solve (:func:`solve`), whose derivative a custom rule gives, ends
its sweeps in a ``lax.while_loop`` once they stop changing the impulses.

Energy. Every update of the resting solve is chosen so that it cannot add kinetic energy:
an impulse ``dP`` changes it by ``u . dP + dP.K dP / 2``. A normal push is capped at
``2|u_n|/K_nn`` (the elastic bound; without it, friction that has already slowed the
approach would let Newton's law add energy, Kane's paradox), and a friction update is a
projected-gradient step of length ``1/k_max``, which only descends; the warm start,
applied before the sweeps, is scaled by the step so that it adds none either
(``_step._warm_start_within_energy``). (The split impulse's solve, ``normal_only=True``,
has no cap: its pseudo-velocities move only positions.) An
impact (:func:`collisions`) gives back in restitution at most the energy its compression
took, and its friction only takes energy, so no impact with ``e <= 1`` creates energy,
whatever the iteration count.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from jaxtyping import Array, Float

from .. import spatial
from .._branch import branch, member_cond, member_switch
from .._indexing import literal_array
from ._coulomb import (
    coulomb_impulse,
    energy_change,
    fraction_within,
    frictionless_impulse,
    largest_fraction,
    solve2,
)

#: The name (``jax.ad_checkpoint.checkpoint_name``) of a resting solve's impulses and
#: velocities (not the split impulse's: see :func:`_pgs_jvp`).
SOLUTION = "jaxrb_contact_solution"
#: The name of the contact pairs' signed separations at both ends of a step's free flight
#: (``_step.contact_step``): they choose the step's branch and bracket the time of impact.
SEPARATIONS = "jaxrb_contact_separations"
#: The name of the time of impact's root (the search's result, a scalar): saved as well,
#: no recomputation runs the search again. Without it, the impact step's reverse pass ran
#: its 14 iterations twice more (``python benchmarks/kernels.py --scene impact``: 251.7 ->
#: 232.4 kernels a step, with ``branch``'s checkpoints saving the names too).
TIME_OF_IMPACT = "jaxrb_contact_time_of_impact"
#: The ``jax.checkpoint`` policy that keeps these named quantities (and nothing else),
#: so a rematerialised step runs neither the sweeps nor the test that chose its branch
#: twice. Saving the solutions in the step's checkpoint was measured on a
#: 3-box stack: 1050 ms against 1150 ms for the 200-step gradient (on the bouncing ball it
#: made no difference). Saving the separations too (one ``(2, P)`` array a step): the
#: 1000-step ball's reverse pass 237.5 -> 223.5 kernels a step, its gradient 11.37 ->
#: 10.64 ms (minima of 40, side by side), the same gradient to the last bit.
SAVE_NAMED = jax.checkpoint_policies.save_only_these_names(SOLUTION, SEPARATIONS, TIME_OF_IMPACT)

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

    def padded(body):
        """The slots' body rows and the padding slot's (the padding body, ``N + 1``)."""
        if isinstance(body, (tuple, list, np.ndarray)):  # a layout's: literals (jaxrb._indexing)
            return literal_array([*np.asarray(body).reshape(-1), n_rows - 1])
        return jnp.concatenate([jnp.asarray(body, jnp.int32), jnp.array([n_rows - 1], jnp.int32)])

    body_a, body_b = padded(body_a), padded(body_b)
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
    """The slots ``idx``' relative velocities ``(..., 3)`` (m/s) in their bases ``(n, t1,
    t2)``. ``idx`` is an index array, or a Python ``slice`` where the slots are a range: a
    slice reads the frames as they are, where ``jnp.arange`` would gather each field."""
    a, b = f.body_a[idx], f.body_b[idx]
    ua = bodies.velocity[a] + spatial.cross(bodies.angular_velocity[a], f.r_a[idx])
    ub = bodies.velocity[b] + spatial.cross(bodies.angular_velocity[b], f.r_b[idx])
    return spatial.matvec(f.basis[idx], ua - ub)  # (..., 3) in (n, t1, t2)


def normal_velocities(bodies: Bodies, f: Frames) -> Array:
    """``u_n`` (m/s) of every slot, padding included: ``(C + 1,)``."""
    return relative_velocity(bodies, f, slice(None))[:, 0]


def _apply(bodies: Bodies, f: Frames, idx, local_impulse) -> Bodies:
    """Apply ``+P`` to A and ``-P`` to B of slots ``idx`` (index array or ``slice``, as in
    :func:`relative_velocity`); ``P`` given in the slot basis."""
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
    return _apply(bodies, f, slice(0, local_impulses.shape[0]), local_impulses)


class _Colour(eqx.Module):
    """The slots of the colours, gathered once per solve: leading axes ``(K, W)`` (one colour
    of ``W`` slots per row). A sweep then scans over these rows, so the loop body reads its
    slots' data as a slice instead of gathering it by index on every visit, with the
    quantities that do not change between sweeps (reciprocals of the Delassus block's
    normal entry and of its largest tangential eigenvalue) computed once.

    A slot's *pair twist* is ``(v_a, w_a, v_b, w_b)`` ``(12,)``, the twists of its two
    bodies; ``rows`` ``(K, 2W)`` lists the body rows ``a_0, b_0, a_1, b_1, ...``, so that a
    colour's pair twists are one gather (and one scatter back)."""

    rows: Array
    inv_mass_a: Array
    inv_mass_b: Array
    inv_inertia_a: Array
    inv_inertia_b: Array
    r_a: Array
    r_b: Array
    basis: Array
    inv_k_nn: Array
    k_tn: Array
    inv_k_max: Array


def _safe_reciprocal(x):
    """``1 / x`` where ``x > 0``, else 0, with a finite derivative everywhere."""
    positive = x > 0
    return jnp.where(positive, 1.0 / jnp.where(positive, x, 1.0), 0.0)


def _by_colour(bodies: Bodies, f: Frames, colours) -> _Colour:
    idx = jnp.asarray(colours)
    a, b = f.body_a[idx], f.body_b[idx]
    delassus = f.delassus[idx]
    return _Colour(jnp.stack([a, b], -1).reshape(a.shape[0], -1),
                   bodies.inv_mass[a], bodies.inv_mass[b], bodies.inv_inertia[a], bodies.inv_inertia[b],
                   f.r_a[idx], f.r_b[idx], f.basis[idx], _safe_reciprocal(delassus[..., 0, 0]),
                   delassus[..., 1:, 0], _safe_reciprocal(_largest_tangential_eigenvalue(delassus)))


def _local_velocity(c: _Colour, pair):
    """Relative velocity ``(W, 3)`` in each slot's ``(n, t1, t2)`` basis."""
    ua = pair[:, 0:3] + spatial.cross(pair[:, 3:6], c.r_a)
    ub = pair[:, 6:9] + spatial.cross(pair[:, 9:12], c.r_b)
    return spatial.matvec(c.basis, ua - ub)


def _local_apply(c: _Colour, pair, local_impulse):
    """``+P`` on A and ``-P`` on B, ``P`` given in the slot basis ``(W, 3)``."""
    impulse = spatial.matvec(spatial.transpose(c.basis), local_impulse)
    return pair + jnp.concatenate([
        c.inv_mass_a[:, None] * impulse, spatial.matvec(c.inv_inertia_a, spatial.cross(c.r_a, impulse)),
        -c.inv_mass_b[:, None] * impulse, -spatial.matvec(c.inv_inertia_b, spatial.cross(c.r_b, impulse))], -1)


def _friction_step(c: _Colour, u_t, old_t, radius, on):
    """Friction: a projected-gradient step on the disk ``|lambda_t| <= radius`` (Coulomb's
    cone), with the step ``1/k_max``, ``k_max`` the largest eigenvalue of the 2x2 tangential
    block. The step is along ``-u_t``, so a sliding contact's friction opposes its slip
    (maximal dissipation); a full ``K_tt^-1`` step would not, and would twist a sliding box.
    A projected-gradient step of length at most ``1/k_max`` cannot add energy.
    ``u_t`` ``(W, 2)`` is the tangential slip. Returns the change of the tangential impulse
    ``(W, 2)``."""
    wanted = old_t - u_t * c.inv_k_max[:, None]
    return jnp.where(on[:, None], _onto_disk(wanted, radius), 0.0) - old_t


def _disk_scale(wanted, radius):
    """``(scale, outside, 1/|wanted|)`` of :func:`_onto_disk` (``1/|wanted|`` where outside)."""
    # One reciprocal square root: with a norm and a quotient, each was a kernel of its own
    # in every colour's step.
    squared = wanted[:, 0] * wanted[:, 0] + wanted[:, 1] * wanted[:, 1]
    outside = squared > radius * radius
    inverse = jax.lax.rsqrt(jnp.where(outside, squared, 1.0))
    return jnp.where(outside, radius * inverse, 1.0), outside, inverse


@jax.custom_jvp
def _onto_disk(wanted, radius):
    """``wanted`` ``(W, 2)`` projected onto the disks ``|x| <= radius`` ``(W,)``, ``radius >= 0``."""
    return wanted * _disk_scale(wanted, radius)[0][:, None]


@_onto_disk.defjvp
def _onto_disk_jvp(primals, tangents):
    """The projection's derivative, written so that every factor is bounded. Outside the
    disk, ``p = r u`` with ``u = w/|w|``, and ``dp = dr u + (r/|w|)(I - u u^T) dw``, where
    ``r/|w| < 1`` and ``|u| = 1``; inside, ``dp = dw``. Differentiated by JAX, the
    reciprocal square root's ``-q^(-3/2)/2`` overflows in float32 for ``|w| < 1e-13`` and is
    multiplied by ``r = 0`` (a slot that touches without pushing: no friction): NaN, in the
    sweeps' Jacobian and so in a whole rollout's gradient (four cubes touching in a 2x2 grid,
    float32: ``benchmarks/repro/grid_gradient_nan.py``;
    ``tests/test_contact.py::test_a_slot_touching_without_pushing_has_a_finite_solve_derivative``)."""
    wanted, radius = primals
    d_wanted, d_radius = tangents
    scale, outside, inverse = _disk_scale(wanted, radius)
    unit = wanted * inverse[:, None]
    along = unit[:, 0] * d_wanted[:, 0] + unit[:, 1] * d_wanted[:, 1]
    sliding = d_radius[:, None] * unit + scale[:, None] * (d_wanted - unit * along[:, None])
    return wanted * scale[:, None], jnp.where(outside[:, None], sliding, d_wanted)


def _slip_after(c: _Colour, u, d_n):
    """The tangential slip ``(W, 2)`` after a normal impulse ``d_n`` ``(W,)``: ``u_t + K_tn d_n``.

    The Delassus block is exact for a colour (its slots share no moving body), so this is
    what applying ``d_n`` and measuring the velocities again would give, and one impulse
    (normal and friction together) is applied per update instead of two."""
    return u[:, 1:] + c.k_tn * d_n[:, None]


def _update(c: _Colour, v, lam, target, mu, on, normal_only: bool):
    """One projected Gauss-Seidel update of one colour's slots; ``lam`` is theirs ``(W, 3)``.

    ``normal_only``: normal impulses only, without the elastic bound. For the split
    impulse (its pseudo-velocities start from rest, ``u_n = 0``, where the bound would allow
    no push at all, and move only the positions, so they carry no kinetic energy to bound)."""
    u = _local_velocity(c, v)
    # Normal: reach u_n = target, keep lambda_n >= 0, and never push past the elastic bound.
    step = (target - u[:, 0]) * c.inv_k_nn
    if not normal_only:
        elastic_cap = jnp.maximum(-2.0 * u[:, 0] * c.inv_k_nn, 0.0)
        step = jnp.where(step > 0, jnp.minimum(step, elastic_cap), step)
    new_n = jnp.where(on, jnp.maximum(lam[:, 0] + step, 0.0), 0.0)
    d_n = new_n - lam[:, 0]
    if normal_only:
        zero = jnp.zeros_like(d_n)
        return _local_apply(c, v, jnp.stack([d_n, zero, zero], -1)), lam.at[:, 0].set(new_n)
    d_t = _friction_step(c, _slip_after(c, u, d_n), lam[:, 1:], mu * new_n, on)
    v = _local_apply(c, v, jnp.concatenate([d_n[:, None], d_t], -1))
    return v, jnp.concatenate([new_n[:, None], lam[:, 1:] + d_t], -1)


def _impact(k, u, e, mu):
    """One contact's impact ``(3,)`` (slot basis), Poisson's hypothesis with Coulomb friction.

    Compression brings ``u_n`` to 0 with friction (sticking, or sliding opposite the slip it
    leaves), then restitution adds ``e`` times its normal impulse, with friction again
    (:mod:`._coulomb`). It is cut where it would give back more kinetic energy than
    compression took, so no impact with ``e <= 1`` gains energy. Each phase is one
    implicit step: exact where the contact sticks at the phase's end or slides one way
    throughout it (``u_n' = -e u_n`` then, as Newton's law has it, where it also arrives
    without slip; where friction stops an arriving slip, Poisson's rebound differs)."""
    # Both phases from one program (a traced flag per phase), as in _pair_impact, so the
    # step holds one Coulomb solve here instead of two.
    def phase(carry, restitution):
        u_now, compression = carry
        impulse = coulomb_impulse(k, u_now, mu, jnp.where(restitution, e * compression[0], 0.0), ~restitution)
        return (u_now + k @ impulse, jnp.where(restitution, compression, impulse)), impulse

    _, (compression, restitution) = jax.lax.scan(phase, (u, jnp.zeros_like(u)), literal_array([False, True], bool))
    taken = jnp.maximum(-energy_change(k, u, compression), 0.0)
    u = u + k @ compression
    return compression + largest_fraction(k, u, restitution, taken) * restitution


def _central_collision_update(c: _Colour, v, k, e, mu, eligible, threshold):
    """:func:`_collision_update` where the contact's normal passes through both centres of
    mass (``K_tn = 0``: ``Layout.central``): the seed's impulse ``j = -(1 + e) u_n / K_nn``,
    then friction bounded by ``mu j``: the sticking impulse ``-K_tt^-1 u_t`` where it lies in
    the cone, else one projected-gradient step (:func:`_friction_step`). Without the coupling
    a normal impulse makes no slip and friction changes no ``u_n``, so for an isotropic
    ``K_tt`` (uniform spheres) this is Poisson's law with Coulomb friction, at a small part
    of :func:`_impact`'s program. For a sphere given an anisotropic inertia it is exact
    where the contact sticks; where it slides, its friction opposes the arriving slip and
    adds no energy, but may stay inside the cone (the general path's Coulomb solve does
    not). Until stop 91 the sticking case also took the projected step, along ``-u_t`` and
    ``1/k_max`` long: such a sphere (inertia (2, 6, 4) g m^2, mu = 5) left an impact
    slipping at 0.556 m/s with its friction far inside the cone.

    ``k`` ``(W, 3, 3)``: the slots' Delassus blocks."""
    u = _local_velocity(c, v)
    hit = eligible & (u[:, 0] < -threshold)
    j = jnp.where(hit, -(1.0 + e) * u[:, 0] * c.inv_k_nn, 0.0)
    radius = mu * j
    u_t = u[:, 1:]
    stick = -jax.vmap(solve2)(k[:, 1:, 1:], jnp.zeros_like(j), u_t)
    inside = hit & (stick[:, 0] * stick[:, 0] + stick[:, 1] * stick[:, 1] <= radius * radius)
    slide = _friction_step(c, u_t, jnp.zeros((j.shape[0], 2), j.dtype), radius, hit)
    d_t = jnp.where(inside[:, None], stick, slide)
    impulse = jnp.concatenate([j[:, None], d_t], -1)
    return _local_apply(c, v, impulse), impulse


def _collision_update(c: _Colour, v, k, e, mu, eligible, threshold):
    """Binary collisions of one colour's slots that approach faster than ``threshold``:
    :func:`_impact` from the *current* relative velocity, the seed's impulse
    ``j = -(1 + e) u_n / K_nn`` where there is no friction. Impulses are new each time
    (never taken back), as in a sequence of two-body collisions. ``k`` ``(W, 3, 3)``: the
    slots' Delassus blocks."""
    u = _local_velocity(c, v)
    hit = eligible & (u[:, 0] < -threshold)
    impulse = jnp.where(hit[:, None], jax.vmap(_impact)(k, u, e, mu), 0.0)
    return _local_apply(c, v, impulse), impulse


def _colour_sweeps(bodies: Bodies, f: Frames, colours, slot_data, per_slot, update, iterations: int,
                   tolerance: float | None = None, early_exit: bool = False, recompute: bool = False,
                   idle=None):
    """At most ``iterations`` sweeps of ``update`` over the colours. ``slot_data`` are per-slot
    arrays ``(C + 1, ...)`` read by the update, ``per_slot`` ``(C + 1, 3)`` the one it rewrites.

    With a ``tolerance``, the sweeps stop after the first one that changes no value of
    ``per_slot`` by more than ``tolerance`` times the largest (0: by nothing at all): the
    later sweeps are skipped at run time by a cond inside the ``lax.scan`` (so reverse mode
    still crosses them; under ``vmap``, once every member is done: ``jaxrb._branch``).
    With ``early_exit`` as well, the sweeps are a ``lax.while_loop`` that ends there
    instead: reverse mode cannot cross it, so it serves only where the derivative is taken
    by other means (:func:`_pgs`'s rule). A settled 5-box stack runs one sweep of its 20 a
    step; each skipped one cost it a ``cond``, copies of its operands and the test, 133
    kernels a step in all (benchmarks/README.md, "The stack's sweeps"). With ``recompute``,
    reverse mode keeps each sweep's input only (``branch``'s ``recompute_in_reverse``),
    not the residuals of the sweep (zero-filled for a skipped one). ``idle`` (bool scalar,
    with a ``tolerance``): nothing to do, every sweep skipped.
    Returns the bodies, ``per_slot`` and the number of sweeps run (int32).
    """
    idx = jnp.asarray(colours)
    c = _by_colour(bodies, f, colours)
    data = jax.tree.map(lambda x: x[idx], slot_data)

    # The sweeps' state is one array: the bodies' twists (rows 0 .. N + 1) and below them the
    # slots' values, colour by colour (colour k's at rows N + 2 + kW ..., zero-padded from 3
    # to 6 columns). A colour's step is then one gather of its bodies' and slots' rows and
    # one scatter back. No two slots of a colour share a dynamic body, so each dynamic row
    # is written once; the static rows (ground, padding) may be written by several slots,
    # all with their unchanged value (zero inverse mass), and the padding slots' values
    # stay zero. Writing values, not adding differences, keeps float32 from rounding each
    # update twice (``v + ((v + dv) - v)``).
    n_rows = bodies.velocity.shape[0]
    num_colours, width = idx.shape
    value_rows = n_rows + jnp.arange(num_colours * width, dtype=jnp.int32).reshape(num_colours, width)
    rows = jnp.concatenate([c.rows, value_rows], -1)  # (K, 3W)

    def colour_step(state, inputs):
        c_k, data_k, rows_k = inputs
        gathered = state[rows_k]
        pair, mine = gathered[: 2 * width].reshape(width, 12), gathered[2 * width:, :3]
        end, mine = update(c_k, pair, mine, *data_k)
        written = jnp.concatenate([end.reshape(2 * width, 6), jnp.pad(mine, ((0, 0), (0, 3)))])
        return state.at[rows_k].set(written), None

    def run(twist, values, c, data):
        state = jnp.concatenate([twist, jnp.pad(values.reshape(-1, 3), ((0, 0), (0, 3)))])
        state, _ = jax.lax.scan(colour_step, state, (c, data, rows))
        return state[:n_rows], state[n_rows:, :3].reshape(values.shape)

    def converged(new, values):
        return jnp.max(jnp.abs(new - values)) <= tolerance * jnp.max(jnp.abs(new))

    def sweep(carry, _):
        twist, values, count, done = carry
        if tolerance is None:
            return (*run(twist, values, c, data), count + 1, done), None
        # (An ensemble skips a sweep once all its members are done: see ``_branch``.)
        twist, new = branch(done, lambda t, v, *_: (t, v), run, twist, values, c, data,
                            recompute_in_reverse=recompute)
        return (twist, new, count + jnp.where(done, 0, 1), done | converged(new, values)), None

    def next_sweep(carry):
        twist, values, count, _ = carry
        twist, new = run(twist, values, c, data)
        return twist, new, count + 1, converged(new, values)

    twist = jnp.concatenate([bodies.velocity, bodies.angular_velocity], -1)
    start = (twist, per_slot[idx], jnp.zeros((), jnp.int32), jnp.zeros((), bool) if idle is None else idle)
    if early_exit and tolerance is not None:
        twist, values, count, _ = jax.lax.while_loop(lambda x: (x[2] < iterations) & ~x[3], next_sweep, start)
    else:
        (twist, values, count, _), _ = jax.lax.scan(sweep, start, None, length=iterations)
    velocity, omega = twist[:, :3], twist[:, 3:]
    bodies = eqx.tree_at(lambda x: (x.velocity, x.angular_velocity), bodies, (velocity, omega))
    # Padding entries of ``colours`` all point at the inert slot C, whose value stays 0.
    return bodies, per_slot.at[idx].set(values), count


#: Projected Gauss-Seidel passes over a pair's slots in its compression phase (pairs of
#: several slots). Measured without friction (e = 0.8, 3 m/s), the rebound's relative
#: error after 4 / 8 / 12 / 16 passes: a box landing flat (4 slots) 3e-4, 2e-7, 9e-12,
#: 1e-14; a capsule landing on its side (2 slots) 3e-3, 2e-6, 2e-9, 1e-12.
PAIR_PASSES = 12
#: Gauss-Seidel passes over a pair's slots with friction, in compression (after the
#: frictionless ones) and in restitution. One is exact for a pair touching at one slot.
#: A box (0.05, 0.1, 0.3) tilted 30 degrees, landing on an edge (2 slots) at 3 m/s, e = 1,
#: mu = 10 (it sticks), the edge's ends leave at, after 4 / 8 / 16 / 32 passes: 3.040 and
#: 2.953, 3.012 and 2.987, 3.0010 and 2.9990, 3.000006 and 2.999994 m/s (exact: 3.0).
FRICTION_PASSES = 16
#: A pass of :func:`_pair_impact` that moves no slot's impulse by more than this many
#: machine epsilons of the largest impulse has settled its phase: the phase's later passes
#: are skipped. (Rounding alone moves a settled impulse by a few epsilons.)
SETTLED = 64


def _slot_major(c: _Colour) -> _Colour:
    """The slots of a pair colour first: fields ``(W, K, ...)`` -> ``(K, W, ...)``."""
    return jax.tree.map(lambda x: jnp.moveaxis(x, 1, 0), c)


def _pair_impact(c: _Colour, k_slot, pair, e, mu, on):
    """One impact of ``W`` pairs of ``K`` slots each, all slots of a pair at once, by Poisson's
    hypothesis with Coulomb friction in both phases. Gauss-Seidel passes over the slots, in
    order; each update solves one slot's whole impulse of its phase exactly, with the other
    slots' held (:func:`._coulomb.coulomb_impulse`):

    1. Compression without friction: ``PAIR_PASSES`` passes to ``u_n = 0`` (``u_n >= 0``:
       impulses stay >= 0). For a box landing flat with no slip this is already the whole
       compression, symmetric; with friction from the first pass, slot by slot, such a box
       turned (3e-5 kg m^2/s at 4.4 m/s) and landed tilted.
    2. Compression with friction: ``FRICTION_PASSES`` passes to ``u_n = 0``, each slot
       sticking or sliding opposite the slip it leaves.
    3. Restitution: ``e`` times each slot's compression impulse along its normal, with its
       friction; then ``FRICTION_PASSES`` passes solving each slot's restitution friction
       again. The whole restitution is then scaled down where it would give back more
       kinetic energy than the pair's compression took (cutting each slot's push on its
       own bound too early: a box landing on an edge, sticking at e = 1, left at 2.995 m/s
       instead of 3.0 after 16 passes).

    For a pair touching at one slot one pass of 2 and 3 is exact: a contact that sticks
    throughout (arriving without slip), or slides one way, leaves at ``u_n' = -e u_n`` (a
    rod landing on its end,
    ``test_friction_keeps_the_rebound_of_an_off_centre_impact``). Until 2026-11-29 friction
    came after restitution, from the frictionless normal impulses, and changed ``u_n``
    through ``K_tn``: that rod left at 0.845 m/s instead of 3.0 (e = 1, mu = 10), keeping
    39% of its energy. Restitution gives back at most what compression took, so no
    impact with ``e <= 1`` gains energy. All phases share one program (a traced phase per
    pass). A phase's later passes are skipped once a pass moves no impulse by more than
    ``SETTLED`` epsilons, the frictionless passes skip the Coulomb search, and the search
    skips its root where every contact sticks: the dropped box (``benchmarks/ab.py``'s
    ``drop``) then ran its forward in 0.32x the time and its gradient in 0.34x, against
    all 45 passes each running the search (benchmarks/README.md, "The impact passes stop
    once settled"), for 86,228 lines of StableHLO against 83,549.

    ``k_slot`` ``(W, K, 3, 3)``: the slots' Delassus blocks; ``pair`` ``(W, 12)``: the
    pairs' twists; ``e``, ``mu``, ``on`` ``(W, K)``. Returns the twists and the impulses
    ``(W, K, 3)`` (slot bases).
    """
    width, depth = on.shape
    zero = jnp.zeros((width,), pair.dtype)
    # Slot-major views ``(K, W, ...)``: each pass below is a scan over the slots, in order
    # (Gauss-Seidel), so the program holds one slot's update instead of ``K`` (four for box
    # pairs), and so does its derivative. Unrolled over the slots (until 2026-11-29), the
    # dropped box's 1000-step gradient (``benchmarks/ab.py``'s ``drop``) was 106,072 lines
    # of StableHLO, now 72,523; the 5-box stack's 200-step forward 19,980, now 17,438. The
    # same values (the gradient to 1.2e-15), the same run times within noise
    # (benchmarks/README.md, "What a contact derivative program is made of").
    slots = _slot_major(c)
    k, e, mu, on = (jnp.moveaxis(x, 1, 0) for x in (k_slot, e, mu, on))

    each = lambda f, *args: jax.vmap(f)(*args)  # noqa: E731  (over a colour's pairs)

    # Passes of one program (a traced ``phase`` per pass): -1, compression without
    # friction; 0, compression with friction, each slot's impulse brought to u_n = 0 with the
    # others held; 1, restitution, e times each slot's compression impulse with its
    # friction; 2, each slot's restitution friction solved again with the others held.
    # ``taken`` counts the kinetic energy compression takes, less what restitution gives back.
    def slot_update(carry, inputs):
        pair, taken, phase = carry
        s, lam_k, rest_k, on_k, k_k, e_k, mu_k = inputs
        compressing = phase <= 0
        own = jnp.where(compressing, lam_k, rest_k)
        u = _local_velocity(s, pair)
        value = jnp.where(compressing, 0.0, jnp.where(phase == 1, e_k * lam_k[:, 0], rest_k[:, 0]))
        # The frictionless passes need no Coulomb search (the same values as with mu = 0).
        # Recomputed in reverse mode, so that a frictionless pass does not fill the Coulomb
        # solve's residuals with zeros (130 copies a slot in the table scene's step).
        new = branch(phase < 0, lambda k, u, *_: each(frictionless_impulse, k, u, jnp.zeros_like(u[:, 0])),
                     lambda *a: each(coulomb_impulse, *a), k_k, u - spatial.matvec(k_k, own), mu_k, value,
                     jnp.broadcast_to(compressing, value.shape), recompute_in_reverse=True)
        change = jnp.where(on_k[:, None], new, 0.0) - own
        taken = taken - each(energy_change, k_k, u, change)
        lam_k, rest_k = jnp.where(compressing, lam_k + change, lam_k), jnp.where(compressing, rest_k, rest_k + change)
        return (_local_apply(s, pair, change), taken, phase), (lam_k, rest_k)

    def run_pass(pair, lam, rest, taken, phase):
        # Each slot's update recomputed in reverse mode: the scan then keeps its carry a slot,
        # not the update's residuals (the Coulomb search's among them), each of which was a
        # dynamic-update-slice and a dynamic-slice a slot. One impact step of two balls and a
        # table (``python benchmarks/kernels.py --scene table``): reverse 472k -> 281k kernels.
        (pair, taken, _), (new_lam, new_rest) = jax.lax.scan(jax.checkpoint(slot_update, prevent_cse=False),
                                                             (pair, taken, phase), (slots, lam, rest, on, k, e, mu))
        moved = jnp.maximum(jnp.max(jnp.abs(new_lam - lam)), jnp.max(jnp.abs(new_rest - rest)))
        size = jnp.maximum(jnp.max(jnp.abs(new_lam)), jnp.max(jnp.abs(new_rest)))
        return pair, new_lam, new_rest, taken, moved <= SETTLED * jnp.finfo(pair.dtype).eps * size

    def one_pass(carry, phase):
        pair, lam, rest, taken, compressed, (last, settled) = carry
        # The pair as compression left it, and the energy it took (kept at the first
        # restitution pass).
        compressed = jax.tree.map(lambda new, old: jnp.where(phase == 1, new, old), (pair, taken), compressed)
        # Once a pass moves no impulse beyond rounding, the phase's later passes would
        # repeat it: they are skipped (a pair touching at one slot needs one pass a phase,
        # then one to see it settled). Recomputed in reverse mode: each pass's reverse then
        # reads its operands alone. Without it (until 2026-12-03) the reverse cost grew
        # with every pass of the scan, settled or not (45 -> 13 passes: 70 -> 40 ms), and
        # one impact step of two balls and a table (every pair on the four-slot path) took
        # 80 ms to differentiate against 37 ms now (forward 1.1-1.5 ms). The dropped box
        # (``benchmarks/ab.py /work/main <this> --programs drop,ball --rounds 10``): its
        # gradient 110 -> 89 ms by minima, 62,563 -> 60,629 lines of StableHLO, trace and
        # XLA 24.9 + 38.7 -> 18.0 + 29.7 s, the gradient within 4.3e-15 (round-off); the
        # ball unchanged (no multi-slot pair). (On 2026-11-29 it had made the program 72%
        # larger, probably because ``branch`` then traced both branches into each
        # linearisation.)
        pair, lam, rest, taken, settled = branch(
            settled & (phase == last), lambda *a: (*a[:4], jnp.ones((), bool)), run_pass,
            pair, lam, rest, taken, phase, recompute_in_reverse=True)
        return (pair, lam, rest, taken, compressed, (phase, settled)), None

    phases = literal_array([-1] * PAIR_PASSES + [0] * FRICTION_PASSES + [1] + [2] * FRICTION_PASSES)
    lam = jnp.zeros((depth, width, 3), pair.dtype)
    start = (pair, lam, lam, zero, (pair, zero), (jnp.zeros((), phases.dtype), jnp.zeros((), bool)))
    (pair, lam, rest, taken, (compressed, budget), _), _ = jax.lax.scan(one_pass, start, phases)
    # Restitution gives back at most what compression took: its change of kinetic energy is
    # theta a + theta^2 c for theta times its impulses (a linear in them, c >= 0), so the
    # largest theta <= 1 within the budget is a root. It binds only where Poisson's law
    # would gain energy (and, by a rounding, at e = 1). The twists are linear in the
    # impulses, so theta scales their change.
    linear = jnp.sum(jax.vmap(lambda s_k, r_k: jnp.sum(_local_velocity(s_k, compressed) * r_k, -1))(slots, rest), 0)
    theta = fraction_within(linear, (budget - taken) - linear, jnp.maximum(budget, 0.0))
    pair = compressed + theta[:, None] * (pair - compressed)
    rest = theta[None, :, None] * rest
    return pair, jnp.moveaxis(lam + rest, 0, 1)


def collisions(bodies: Bodies, f: Frames, colours, pair_colours, e, mu, eligible, threshold, iterations: int,
               central: bool = False):
    """The impact law, pair after pair, ``iterations`` sweeps; impulses ``(C, 3)``.

    A pair (two bodies) with a touching slot approaching faster than ``threshold``
    collides, with new impulses each time. Pairs collide one after another, so momentum
    travels along a row of touching bodies as a sequence of collisions (Newton's cradle)
    rather than being shared by a simultaneous solve. Each collision follows Poisson's
    hypothesis with Coulomb friction: compression to ``u_n = 0``, then ``e`` times its
    normal impulse, friction acting in both phases (:func:`_impact`). Without friction, or
    where the contact sticks throughout (arriving without slip) or slides one way, the
    contact leaves at ``u_n' = -e u_n`` (Newton's law; where friction stops an arriving
    slip, Poisson's rebound differs), with the seed's impulse ``j = -(1 + e) u_n / (n . K n)`` where there is
    no friction. A pair of several slots collides on all its touching slots at once
    (:func:`_pair_impact`): colliding them one by one, a box landing flat on four corners
    at 3 m/s (e = 0.8) rebounded at 2.10 m/s instead of 2.40, spinning, and one dropped flat
    with friction slid 0.52 m in 1.2 s. Each collision with ``e <= 1`` adds no energy.

    ``colours``: the slot colours (used where every pair has one slot); ``pair_colours``:
    ``(num_pair_colours, W, K)`` slot indices (:attr:`Layout.pair_colours`); ``e``, ``mu``,
    ``eligible`` (touching): ``(C,)``; ``central``: :attr:`Layout.central` (static).
    """
    idx = jnp.asarray(pair_colours)
    if idx.shape[-1] == 1:
        return _slot_collisions(bodies, f, colours, e, mu, eligible, threshold, iterations, central)
    pad1 = lambda x, v: jnp.concatenate([x, jnp.full((1, *x.shape[1:]), v, x.dtype)])  # noqa: E731
    e, mu, eligible = pad1(e, 0.0), pad1(mu, 0.0), pad1(eligible, False)
    _, width, _ = idx.shape
    c = _by_colour(bodies, f, idx)
    c = eqx.tree_at(lambda x: x.rows, c, idx)  # (sliced with the rest; the pair rows are below)
    first = idx[:, :, 0]
    rows = jnp.stack([f.body_a[first], f.body_b[first]], -1).reshape(first.shape[0], 2 * width)
    data = (f.delassus[idx], e[idx], mu[idx], eligible[idx])

    def pair_colour(twist, inputs):
        c_p, rows_p, (k_p, e_p, mu_p, on_p) = inputs
        pair = twist[rows_p].reshape(width, 12)
        u_n = jax.vmap(lambda s: _local_velocity(s, pair)[:, 0], out_axes=-1)(_slot_major(c_p))  # (W, K)
        on_p = on_p & jnp.any(on_p & (u_n < -threshold), axis=-1, keepdims=True)
        # A colour with no pair that collides is left as it is, which is what its impact
        # would give, exactly (every change zero): most colours of a sweep, and all of the
        # sweep that ends the impact. Its 45 passes, most skipped, still cost the scan's
        # copies and tests, and in reverse mode their transposes.
        pair, lam = branch(jnp.any(on_p), _pair_impact, lambda c, k, pair, *_: (pair, jnp.zeros((*on_p.shape, 3),
                           pair.dtype)), c_p, k_p, pair, e_p, mu_p, on_p)
        return twist.at[rows_p].set(pair.reshape(2 * width, 6)), lam

    def run(twist, total):
        twist, impulses = jax.lax.scan(pair_colour, twist, (c, rows, data))
        return twist, total + impulses

    def sweep(carry, _):
        twist, total, done = carry
        # A sweep with no collision changes nothing, so every later one would be the same:
        # they are skipped, and recomputed in reverse mode (see _slot_collisions).
        new_twist, new_total = branch(done, lambda t, v: (t, v), run, twist, total, recompute_in_reverse=True)
        return (new_twist, new_total, done | jnp.all(new_total == total)), None

    twist = jnp.concatenate([bodies.velocity, bodies.angular_velocity], -1)
    total = jnp.zeros((*idx.shape, 3), twist.dtype)
    # No eligible slot (the plastic pass of an impact on bodies that rest on nothing): no sweep.
    (twist, total, _), _ = jax.lax.scan(sweep, (twist, total, ~jnp.any(eligible)), None, length=iterations)
    bodies = eqx.tree_at(lambda x: (x.velocity, x.angular_velocity), bodies, (twist[:, :3], twist[:, 3:]))
    # Back to slot order; the padding entries (all C) carry zeros.
    per_slot = jnp.zeros((e.shape[0], 3), twist.dtype).at[idx.reshape(-1)].add(total.reshape(-1, 3))
    return bodies, per_slot[:-1]


def _slot_collisions(bodies: Bodies, f: Frames, colours, e, mu, eligible, threshold, iterations: int,
                     central: bool):
    """:func:`collisions` where every pair has one slot: slot colours, ``iterations`` sweeps.

    Each slot approaching faster than ``threshold`` collides (:func:`_collision_update`, or
    :func:`_central_collision_update` where ``central``) from its current velocity, so
    momentum travels along a row of touching bodies as a sequence of collisions (Newton's
    cradle) rather than being shared by a simultaneous solve. No collision with ``e <= 1``
    adds energy. ``e``, ``mu`` and ``eligible`` are ``(C,)``.
    """
    pad1 = lambda x, v: jnp.concatenate([x, jnp.full((1, *x.shape[1:]), v, x.dtype)])  # noqa: E731
    e, mu, eligible = pad1(e, 0.0), pad1(mu, 0.0), pad1(eligible, False)
    total = jnp.zeros((e.shape[0], 3), bodies.velocity.dtype)

    def update(c, v, total, k, e, mu, eligible):
        if central:
            v, impulse = _central_collision_update(c, v, k, e, mu, eligible, threshold)
        else:
            v, impulse = _collision_update(c, v, k, e, mu, eligible, threshold)
        return v, total + impulse

    # A sweep with no collision changes nothing, so every later sweep would be the same:
    # they are skipped (tolerance 0), exactly. Recomputed in reverse mode: an impact
    # usually needs one sweep of its eight, and stacking every sweep's residuals (59 arrays
    # a sweep for the ball) was a third of the impact step's reverse pass. Measured with
    # ``python benchmarks/kernels.py --scene impact``: its reverse pass 358.4 -> 300.1
    # kernels a step. (The solver's sweeps gain nothing from it: a settled stack's
    # derivative does not cross them, and the 3-box stack's reverse pass ran 2.6% more
    # kernels with it.)
    bodies, total, _ = _colour_sweeps(bodies, f, colours, (f.delassus, e, mu, eligible), total, update, iterations, 0.0,
                                      recompute=True, idle=~jnp.any(eligible))
    return bodies, total[:-1]


def _largest_tangential_eigenvalue(k):
    k_tt = k[..., 1:, 1:]
    spread = spatial.safe_norm(jnp.stack([0.5 * (k_tt[..., 0, 0] - k_tt[..., 1, 1]), k_tt[..., 0, 1]], -1))
    return 0.5 * (k_tt[..., 0, 0] + k_tt[..., 1, 1]) + spread


def pad_slots(target, mu, active, lam0):
    """Append the inert padding slot (index ``C``) to the per-slot arrays."""
    pad1 = lambda x, v: jnp.concatenate([x, jnp.full((1, *x.shape[1:]), v, x.dtype)])  # noqa: E731
    active = pad1(active, False)
    return pad1(target, 0.0), pad1(mu, 0.0), active, pad1(lam0 * active[:-1, None], 0.0)


def sweeps(bodies: Bodies, f: Frames, colours, target, mu, active, lam, iterations: int, normal_only: bool = False,
           tolerance: float | None = None, early_exit: bool = False):
    """At most ``iterations`` projected Gauss-Seidel sweeps on padded slot arrays (``lam``
    already applied); see :func:`_colour_sweeps` for ``tolerance`` and ``early_exit``.
    Returns the bodies, the impulses and the number of sweeps run."""

    def update(c, v, lam, target, mu, on):
        return _update(c, v, lam, target, mu, on, normal_only)

    return _colour_sweeps(bodies, f, colours, (target, mu, active), lam, update, iterations, tolerance, early_exit)


def solve(
    bodies: Bodies,
    f: Frames,
    colours: Array,
    target: Float[Array, " c"],
    mu: Float[Array, " c"],
    active: Array,
    lam0: Float[Array, "c 3"],
    iterations: int,
    normal_only: bool = False,
    tolerance: float | None = None,
    frozen_derivative: bool = True,
) -> tuple[Bodies, Float[Array, "c 3"]]:
    """Projected Gauss-Seidel on ``C`` slots, colour by colour, at most ``iterations`` sweeps.

    Args:
        bodies: velocities before the contact impulses (``lam0`` is applied first: warm start).
        f: from :func:`frames`.
        colours: ``(num_colours, width)`` int slot indices, ``C`` for padding.
        target: ``(C,)`` m/s, the smallest normal velocity ``u_n`` each active slot must
            reach (``-e u_n^-`` at an impact, ``0`` at rest, ``-gap/dt`` ahead of a contact).
        mu: ``(C,)`` friction coefficients.
        active: ``(C,)`` bool; inactive slots carry no impulse.
        lam0: ``(C, 3)`` initial accumulated impulses ``(n, t1, t2)``, N s.
        iterations: static sweep count (the most, with a ``tolerance``).
        normal_only: the split impulse's solve (penetration correction): normal impulses only,
            on pseudo-velocities from rest, with no elastic bound (:func:`_update`).
        tolerance: static; stop after the first sweep that changes no impulse by more than
            this times the largest. ``None``: run all ``iterations``.
        frozen_derivative: static; ``True``: the derivative of converged sweeps is taken
            with their Jacobian frozen at the solution (see :func:`_pgs_jvp`); ``False``:
            always through every sweep run (for a few sweeps, where that is cheap).

    Returns:
        ``(bodies, lam)``: velocities after the impulses, and the accumulated impulses.
    """
    target, mu, active, lam = pad_slots(target, mu, active, lam0)
    velocity, omega, lam, _ = _pgs(iterations, normal_only, tolerance, frozen_derivative, bodies, f, colours, target,
                                   mu, active, lam)
    bodies = eqx.tree_at(lambda x: (x.velocity, x.angular_velocity), bodies, (velocity, omega))
    return bodies, lam[:-1]


def _pgs_sweeps(iterations: int, normal_only: bool, tolerance, early_exit: bool, bodies: Bodies, f: Frames, colours,
                target, mu, active, lam):
    """The sweeps of :func:`solve` on padded slots, from ``lam`` (not yet applied to ``bodies``):
    the velocities and spins after them, the accumulated impulses ``(C + 1, 3)`` and the
    number of sweeps run (a float scalar, so that it has a tangent, zero, like the rest).
    ``early_exit``: see :func:`_colour_sweeps` (not where this is differentiated)."""

    def run(_):
        start = apply_impulses(bodies, f, lam)
        end, impulses, count = sweeps(start, f, colours, target, mu, active, lam, iterations, normal_only, tolerance,
                                      early_exit)
        return end.velocity, end.angular_velocity, impulses, count.astype(lam.dtype)

    def idle(_):
        return bodies.velocity, bodies.angular_velocity, jnp.zeros_like(lam), jnp.zeros((), lam.dtype)

    # Nothing to solve (a body in flight): skipped at run time (in an ensemble, when no
    # member has anything to solve).
    return branch(jnp.any(active), run, idle, None)


#: The largest entry of ``A^(2^m)`` (``2^m >= iterations``, ``A`` the sweep's Jacobian at the
#: solution) at which the frozen derivative is taken: what is left of a warm start's
#: tangent after that many sweeps (a mode of ``|eigenvalue| <= 0.87`` at 20 iterations).
FORGOTTEN = 1e-2


def _pgs(iterations: int, normal_only: bool, tolerance, frozen_derivative: bool, *args):
    """:func:`_pgs_sweeps`, ending at the tolerance; differentiated by :func:`_pgs_jvp`."""
    return _pgs_sweeps(iterations, normal_only, tolerance, True, *args)


_pgs = jax.custom_jvp(_pgs, nondiff_argnums=(0, 1, 2, 3))


@_pgs.defjvp
def _pgs_jvp(iterations, normal_only, tolerance, frozen_derivative, primals, tangents):
    """The derivative of the sweeps: with their Jacobian frozen where they have converged,
    through every sweep where they have not.

    One sweep is a map ``lam -> G(lam, theta)`` (``theta``: velocities, masses, frames,
    targets, ``mu``), and the ``k`` sweeps run unroll to ``d lam_j = A d lam_(j-1) + B d
    theta`` with ``A = dG/d lam`` and ``B = dG/d theta`` taken at each iterate. Where the
    iterates have reached the solution and its contact states (the sweeps stopped early at
    their tolerance, or the last one left the impulses unchanged: ``|G(lam*) - lam*| <=
    sqrt(eps) |lam*|``), both are taken there: the same recursion with a constant ``A`` (a
    dense ``3(C+1)`` square, from one batched sweep) and one ``B d theta`` (one tangent
    sweep), ``iterations`` times, not only the forward's ``k``: the solution's derivative
    does not depend on how near the warm start was, but the recursion cut at ``k`` did (from
    a warm start at the solution, ``k = 1``, it was up to 36% off finite differences:
    ``tests/test_contact.py::test_the_solve_has_the_same_derivative_from_any_warm_start``).
    Reverse mode then crosses one sweep and ``iterations`` small matrix products instead
    of every sweep's intermediates (the ball's gradient: ``benchmarks/gradients.py``).
    Otherwise (a stack whose sweeps have not converged, where freezing ``A`` was measured
    0.2-0.5% off finite differences) the sweeps are differentiated one by one, and so are
    converged ones whose ``A`` does not contract (:data:`FORGOTTEN`). The warm
    start's tangent ``d lam_0`` is carried in both (``A^iterations d lam_0`` when frozen).
    With ``frozen_derivative=False`` (the split impulse's few sweeps) always the latter, and
    the derivative program holds neither the frozen branch nor the convergence test.
    """
    bodies, f, colours, target, mu, active, _ = primals
    # Named, so that a rematerialising step (``_step._rematerialised``) keeps the solution
    # instead of running the sweeps again in reverse mode. Packed into one (B + B + C + 2, 3)
    # array (the last row holds the sweep count): a rollout stacks each saved array every
    # step (one kernel each, and a cond zero-fills them every step its other branch is taken).
    # Only the resting solve's: the split impulse's few sweeps (``frozen_derivative=False``)
    # run again instead. Its saved solution was one more array that every chunk of a
    # recorded rollout stacked, zero-filled where the chunk flies, and sliced again in the
    # reverse pass, where too many slices ready at once make XLA:CPU hand work to another
    # thread (benchmarks/README.md, "Thread-pool handoffs"): the 1000-step bouncing ball's
    # gradient 5% faster (3.197 -> 3.037 ms by minima), a rolling ball, a sliding box and
    # a 3-box stack's gradients unchanged, all to the last bit.
    velocity, omega, lam, count = _pgs(iterations, normal_only, tolerance, frozen_derivative, *primals)
    rows = np.cumsum([velocity.shape[0], omega.shape[0], lam.shape[0]])
    count_row = jnp.zeros((1, 3), lam.dtype).at[0, 0].set(count)
    packed = jnp.concatenate([velocity, omega, lam, count_row])
    if frozen_derivative:
        packed = checkpoint_name(packed, SOLUTION)
    velocity, omega, lam, count_row = jnp.split(packed, rows)
    count = count_row[0, 0]

    def sweep(lam_in, bodies, f, target, mu):
        start = apply_impulses(bodies, f, lam_in)
        return sweeps(start, f, colours, target, mu, active, lam_in, 1, normal_only)[1]

    def frozen_recursion(a_mat, t):
        d_bodies, d_f, _, d_target, d_mu, _, d_lam0 = t
        _, b_vec = jax.jvp(lambda *theta: sweep(lam, *theta), (bodies, f, target, mu),
                           (d_bodies, d_f, d_target, d_mu))
        d_lam, b_vec = d_lam0.reshape(-1), b_vec.reshape(-1)
        for _ in range(iterations):
            d_lam = a_mat @ d_lam + b_vec
        d_lam = d_lam.reshape(lam.shape)
        _, d_end = jax.jvp(apply_impulses, (bodies, f, lam), (d_bodies, d_f, d_lam))
        return d_end.velocity, d_end.angular_velocity, d_lam

    # The branches take the tangents as an operand, not from this scope: in an ensemble's
    # derivative each then sees those of the members that take it (``member_switch``).
    def unrolled(t):
        return jax.jvp(lambda *p: _pgs_sweeps(iterations, normal_only, tolerance, False, *p)[:3], primals, t)[1]

    def contraction(_):
        # The sweep's Jacobian at the solution, and whether it forgets: where A keeps a
        # direction (|eigenvalue| near 1: the redundant normal impulses of four corners on a
        # face, their friction sliding different ways as the box spins), the warm start's
        # tangent along it never decays, and the sweeps apply their own iterates' Jacobians to
        # it, not the solution's: the frozen recursion drifts from the derivative of what the
        # sweeps computed (5e-5 of it a step; a spinning, sliding box's mass derivative 1.6e-3
        # off differences after 200 steps). It is not the tangent sweep's b piling up along
        # the mode: P b was 1e-13 (benchmarks/README.md, "The frozen derivative on a face").
        # There, the sweeps' own derivative. The test: A^(2^m), 2^m >= iterations, by
        # squaring, on the active slots (the sweeps leave the padding slot as it is: an
        # identity block).
        a_mat = jax.jacfwd(lambda x: sweep(x.reshape(lam.shape), bodies, f, target, mu).reshape(-1))(lam.reshape(-1))
        kept = jnp.repeat(active, 3).astype(a_mat.dtype)
        power = a_mat * kept[:, None] * kept[None, :]
        for _ in range(max(1, int(np.ceil(np.log2(iterations))))):
            power = power @ power
        # A Jacobian with a NaN must not be frozen. The max alone let one through: XLA:CPU's
        # max reduction skips NaN (an all-NaN matrix's max came out -inf, and passed).
        return a_mat, (jnp.max(jnp.abs(power)) <= FORGOTTEN) & jnp.all(jnp.isfinite(power))

    def no_contraction(_):
        return jnp.zeros((lam.size, lam.size), lam.dtype), jnp.zeros((), bool)

    def idle(t):
        return t[0].velocity, t[0].angular_velocity, jnp.zeros_like(lam)

    def converged(_):
        tol = jnp.sqrt(jnp.finfo(lam.dtype).eps) * jnp.max(jnp.abs(lam))
        return jnp.max(jnp.abs(sweep(lam, bodies, f, target, mu) - lam)) <= tol

    if not frozen_derivative:
        return (velocity, omega, lam, count), (*jax.checkpoint(unrolled)(tangents), jnp.zeros_like(count))
    # (The convergence test costs a sweep: not run in flight, nor when the sweeps stopped early.)
    any_active = jnp.any(active)
    settled = any_active & member_cond(any_active & (count >= iterations), converged, lambda _: True, None)
    # The Jacobian and its test outside the switch, so that the sweeps' own derivative is
    # one branch of it, not also the fallback of a frozen branch: the 1000-step bouncing
    # ball's gradient program held two copies of it (44,522 lines of StableHLO, compiled
    # in 17.2 s; see benchmarks/README.md, "One copy of the sweeps' derivative").
    a_mat, forgets = member_cond(settled, contraction, no_contraction, None)
    branch = jnp.where(any_active, jnp.where(settled & forgets, 1, 2), 0)
    # The branches under ``jax.checkpoint``: a switch's linearisation zero-fills the residuals
    # of the branches not taken, copied at every step; a checkpoint's are just its inputs.
    # member_switch: under a vmap (an ensemble's gradient) a plain switch ran all three for
    # every member, the sweep-by-sweep derivative above all (see member_switch).
    tangent = member_switch(branch, [lambda _, t: idle(t), jax.checkpoint(frozen_recursion),
                                     jax.checkpoint(lambda _, t: unrolled(t))], a_mat, tangents, tangents_from=1)
    return (velocity, omega, lam, count), (*tangent, jnp.zeros_like(count))
