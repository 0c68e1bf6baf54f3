"""The time step of a scene with contacts: kick, solve, drift, kick, with the impact located inside.

One step of length ``h`` from state ``s`` (all bodies at once):

1. **Kick.** ``v <- v + h/2 F/M``, ``L <- L + h/2 tau`` (forces at the start).
2. **Solve.** Contacts are detected at the start pose (slots closer than ``margin``).
   Projected Gauss-Seidel finds impulses so that every active slot's normal velocity
   ``u_n`` after them is at least its target: ``-(gap - skin)/h`` ahead of contact
   (speculative: it may close the gap but not pass it; ``skin`` absorbs the poses'
   rounding, ``ContactSettings.skin``) and ``0`` in contact; friction inside Coulomb's
   cone. Before it, impacts faster than the restitution threshold get Newton's law,
   ``u_n^+ = -e u_n^-`` (``_solver.collisions``: pair after pair, all slots of a pair at
   once), after a plastic pass over the other touching pairs that approach: a body resting
   on another carries leapfrog's staggered velocity (below), which an impact must not see.
   A slot that the last step held is compared with the threshold without that velocity.
3. **Drift.** The scene's integrator advances the *force-free* motion by ``h`` with those
   velocities: ``x <- x + h v`` and its torque-free attitude flow under the new ``L``
   (the splitting's exact sub-rotations, RK4's stages, ... whichever was chosen). The
   penetration correction (split impulse) adds a pseudo-velocity to this drift only, so
   positions are corrected and velocities are not: no energy is added.
4. **Kick.** ``v <- v + h/2 F/M``, ``L <- L + h/2 tau`` (forces at the end).

Without contacts this is Stoermer-Verlet: exact for constant gravity, second order. A step
in which no pair touches at its start and none closes during its free flight takes exactly
this branch (``_free_step``, chosen at run time by a cond), with the same arithmetic
as the full step and none of its detection, solves or time-of-impact search; in a scene
with a force other than gravity, it is the integrator's own step instead (kick-drift-kick
would make flight second order whatever the integrator). (Without
the time-of-impact search, which is what finds the pairs that close, "touches" means
"within the margin": the speculative contacts are what keep those from passing.)
Resting on the ground, the drift velocity is exactly zero, so nothing creeps; the velocity
reported *between* steps is then ``h/2 g`` (leapfrog's staggered velocity), not zero.

**Time of impact.** If a pair that is apart at the start overlaps at the end of the step's
free flight (constant acceleration and spin; a body that the last step's solve held
moves on at its last drift velocity instead: :func:`_free_flight`), the step is split at
the first instant ``tau h`` of contact: the free motion to it, the impact (Newton's law on
the velocities *at* contact), then the rest of the step. The instant is the root of the pair's signed
separation along the free motion (the separating axes alone for box pairs, which have the
same roots as the distance and cost a fraction of the manifold), bracketed by the two
ends, found by a fixed number of Illinois (regula falsi) iterations and a last secant step;
its derivative is the implicit-function theorem's, ``d tau = -dD / D'`` (a custom JVP):
gradients account for the time of impact. The next impact in the same step is located
the same way from the first, along the same free flight, among pairs of bodies that no
impact located so far can move: neither struck nor joined to a struck body by touching
contacts (another ball landing, on the ground or on a table resting elsewhere), and so on
up to ``ContactSettings.located_impacts`` (:func:`_split_points`). Impacts after the last
located one are handled at its instant, and so is a pair of bodies that is apart at both
ends of the flight but whose bounding spheres meet in between (a fast, small body passing
another: ``_meeting_mid_step``).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from .. import spatial
from .._branch import branch
from .._implicit import implicit_root
from .._indexing import literal_array, take_rows
from .._static import static_step_length
from ..dynamics import linear_acceleration, wrench
from ..forces import Gravity
from ..scene import Scene
from ..shapes import Box, Capsule, Cylinder, Sphere
from ..state import Params, State, angular_velocity, inverse_world_inertia, world_inertia
from ._coulomb import fraction_within
from ._layout import (
    Layout,
    bodies_with_slots,
    build_layout,
    detect,
    level_of_pairs,
    pair_separations,
    slot_values,
    with_pair_slots,
)
from ._lcp import solve_exact
from ._settings import TOUCHING, ContactSettings
from ._solver import (
    SAVE_NAMED,
    SEPARATIONS,
    TIME_OF_IMPACT,
    Bodies,
    Frames,
    collisions,
    frames,
    normal_velocities,
    relative_velocity,
    solve,
)

__all__ = ["contact_step", "far_from_contact", "free_step", "layout_of", "free_scene_of", "initial_impulses",
           "resolve_impacts"]



def _touching_distance(settings: ContactSettings, margin: float) -> float:
    """m: a pair closer than this at a step's start makes it a contact step.

    With the time-of-impact search, a pair that is apart and stays apart over the step's
    free flight needs no contact work, however close it is: the search finds any pair
    that closes (its end separation is negative), and a step taken as contact step there
    would only solve speculative constraints that the free motion already satisfies.
    So the step is free unless some pair touches (:data:`TOUCHING`, or within the
    penetration slop, which a resting contact keeps) or closes. Without the search, the
    margin: its speculative constraints are then what stops a pair from passing.
    Measured on the 1000-step bouncing ball (``benchmarks/gradients.py``'s scene): the
    contact steps around each impact went from 11 (the margin, 0.02 m at 4.4 m/s) to 1
    (the step of the impact), and its gradient from 4.82 to 4.03 ms (side by side).
    """
    if not settings.time_of_impact:
        return margin
    return min(margin, max(TOUCHING, 2.0 * settings.penetration_slop))


@functools.lru_cache(maxsize=64)
@functools.lru_cache(maxsize=64)
def layout_of(scene: Scene) -> Layout:
    """The scene's contact layout, built once per scene (the colouring tries orders)."""
    return build_layout(scene)


@functools.lru_cache(maxsize=64)
def free_scene_of(scene: Scene) -> Scene:
    """The same bodies with no forces and no contacts: its step is the torque-free drift."""
    return dataclasses.replace(scene, gravity=None, forces=(), contacts=())


def impulse_shape(scene: Scene) -> tuple[int, int]:
    """The shape of ``State.contact_impulse`` in this scene: one ``(n, t1, t2)`` row per slot."""
    return (layout_of(scene).num_slots, 3)


def initial_impulses(scene: Scene, dtype) -> jax.Array:
    return jnp.zeros(impulse_shape(scene), dtype)


# ----------------------------------------------------------------------------- pieces


def _solver_bodies(params: Params, state: State, velocity, angular_momentum) -> tuple[Bodies, jax.Array]:
    """Rows for the solver (bodies, ground, padding) and the centres of mass ``(N + 2, 3)``."""
    dtype = state.position.dtype
    pad = lambda x: jnp.concatenate([x, jnp.zeros((2, *x.shape[1:]), dtype)])  # noqa: E731
    inv_inertia = inverse_world_inertia(params, state)
    omega = spatial.matvec(inv_inertia, angular_momentum)
    bodies = Bodies(pad(1.0 / params.mass), pad(inv_inertia), pad(velocity), pad(omega))
    return bodies, pad(state.position)


def _normal_velocity(bodies: Bodies, f: Frames) -> jax.Array:
    """``u_n`` of every real slot ``(C,)``, m/s."""
    return normal_velocities(bodies, f)[:-1]


def _slot_coefficients(ctx: _Ctx, params: Params):
    """Each slot's ``(e, mu)`` ``(C,)``, from its pair's (static slices: see jaxrb._indexing)."""
    # Params.replace does not validate, and a gather clamped a short array's missing pairs
    # to its last entry, silently.
    ctx.scene.check_shapes(params, ("restitution", "friction"))
    layout = ctx.layout
    return slot_values(layout, params.restitution), slot_values(layout, params.friction)


def _warm_start_within_energy(bodies: Bodies, f: Frames, lam0: jax.Array) -> jax.Array:
    """The warm start ``lam0`` ``(C, 3)`` (slot bases, N s) scaled by the largest ``theta``
    in ``[0, 1]`` whose impulses add no kinetic energy to ``bodies``.

    Impulses ``P`` (world frame, at the slots) change the kinetic energy by
    ``sum_k P_k . u_k + sum_bodies (|dp|^2 / m + dl . I^-1 dl) / 2``, with ``u_k`` the
    slots' relative velocities and ``dp``, ``dl`` each body's net impulse and angular
    impulse; every update of the sweeps is bounded so (``_solver``), but the warm start,
    applied before them, was not. A warm start larger than the step needs (the impulse
    that stopped a landing, kept for the next step) pushes the bodies apart, and sweeps
    that stop early leave part of that push: with ``iterations=1`` a box landing flat at
    0.13 m/s with e = 0 came back up at 0.018 m/s and gained 3.6e-4 J in one step. A
    resting contact's warm start (last step's impulses, which stop this step's approach)
    takes energy and is kept whole."""
    real = slice(None, -1)  # the frames' last slot is the padding one
    a, b = f.body_a[real], f.body_b[real]
    impulse = spatial.matvec(spatial.transpose(f.basis[real]), lam0)
    r_a, r_b = f.r_a[real], f.r_b[real]
    dp = jnp.zeros_like(bodies.velocity).at[a].add(impulse).at[b].add(-impulse)
    dl = jnp.zeros_like(dp).at[a].add(spatial.cross(r_a, impulse)).at[b].add(-spatial.cross(r_b, impulse))
    linear = jnp.sum(lam0 * relative_velocity(bodies, f, real))  # P . u, both in the slot bases
    quadratic = 0.5 * (jnp.sum(bodies.inv_mass[:, None] * dp * dp)
                       + jnp.sum(dl * spatial.matvec(bodies.inv_inertia, dl)))
    return fraction_within(linear, quadratic, jnp.zeros_like(linear)) * lam0


def _run_solver(settings: ContactSettings, layout: Layout, bodies, f, target, mu, active, lam0):
    colours = literal_array(layout.colours)
    if settings.warm_start:
        lam0 = _warm_start_within_energy(bodies, f, lam0 * active[:, None])
    if settings.solver == "exact":
        return solve_exact(bodies, f, colours, target, mu, active, lam0,
                           settings.iterations, settings.newton_iterations)
    return solve(bodies, f, colours, target, mu, active, lam0, settings.iterations,
                 tolerance=settings.tolerance_for(target.dtype))


def _omega_to_momentum(params, state, omega_new, omega_old, angular_momentum):
    n = state.position.shape[0]
    return angular_momentum + spatial.matvec(world_inertia(params, state), omega_new[:n] - omega_old[:n])


def _closing_kick(scene: Scene, params: Params, state: State, half: float) -> State:
    force, torque = wrench(scene, params, state)
    if any(not isinstance(m, Gravity) for m in scene.force_models):
        # Velocity-dependent forces: evaluate at the predicted end velocity (see kick_drift_kick).
        predicted = dataclasses.replace(
            state, velocity=state.velocity + half * linear_acceleration(params, force),
            angular_momentum=state.angular_momentum + half * torque)
        force, torque = wrench(scene, params, predicted)
    return dataclasses.replace(
        state, velocity=state.velocity + half * linear_acceleration(params, force),
        angular_momentum=state.angular_momentum + half * torque)


# ------------------------------------------------------------------------------ steps


@dataclasses.dataclass(frozen=True)
class _Ctx:
    scene: Scene
    layout: Layout
    integrator: object
    settings: ContactSettings
    dt: float

    @property
    def margin(self) -> float:
        return self.settings.margin_for(self.dt)


def _regular(ctx: _Ctx, params: Params, state: State, h, lam0, derived, held, bounce=True, ahead=None) -> State:
    """Kick, solve, drift, kick over ``h`` (a traced length when the step is split).

    ``held`` ``(C,)``: the slots that the last full step's resting solve pushed on
    (:func:`_held_slots`). Their approach at the start is leapfrog's staggered velocity,
    which the restitution threshold must not see. ``ahead`` ``(P,)`` (or ``None``): pairs
    apart at the start whose impact is located at this sub-step's end (or later), which the
    sub-step leaves alone: the next one starts with their impact. As speculative contacts
    they would be pushed apart early wherever the solve's straight-line prediction of the
    gap, ``gap + h u_n``, falls below the true one: two balls meeting obliquely (the
    distance of their centres is convex in time) lost 0.27% of the normal velocity they
    exchange, plastically, before their located impact."""
    scene, layout, settings = ctx.scene, ctx.layout, ctx.settings
    # The motion takes the part's own length, however short; only the divisions by it take a
    # floor, so that a zero-length remainder divides by no zero. (Until stop 92 the length itself
    # was raised to 1e-6 dt: an impact within that of a step's end made the step run up to
    # 1e-6 dt past dt, and the step-by-step loop's time and motion left rollout's.)
    h_div = jnp.maximum(h, 1e-6 * ctx.dt)
    half = 0.5 * h
    contact = detect(scene, layout, state, ctx.margin)
    if ahead is not None:
        contact = dataclasses.replace(contact, active=contact.active & ~slot_values(layout, ahead))
    force, torque = wrench(scene, params, state)
    kick_v = half * linear_acceleration(params, force)
    kick_l = half * torque

    start, position = _solver_bodies(params, state, state.velocity, state.angular_momentum)
    f = frames(start, layout.body_a, layout.body_b, contact.point, contact.normal, position)
    e, mu = _slot_coefficients(ctx, params)
    gap = contact.gap
    colours, pair_colours = literal_array(layout.colours), literal_array(layout.pair_colours)
    # Impacts first, at the start of the step, on the velocities there: slots that touch or
    # would close during the step (at the kicked velocity) collide by Newton's law if they
    # approach faster than the threshold. (Not in the part of a split step before its
    # located impact: ``bounce`` is False there.)
    u_start = _normal_velocity(start, f)
    u_kicked = _normal_velocity(_solver_bodies(params, state, state.velocity + kick_v,
                                               state.angular_momentum + kick_l)[0], f)
    closing = contact.active & ((gap <= TOUCHING) | (gap + h * u_kicked < 0)) & bounce
    # A slot that the last step held reports, at rest, the approach of the last closing half
    # kick, dt/2 of the forces (leapfrog's stagger: see the module docstring), which is not
    # a motion: the threshold sees its approach without it. Seen with the stagger, below a
    # threshold of |g| dt / 2 a table resting on the ground bounced on it when a box hit the
    # table, and the box rebounded 5.4% above the two-body closed form (0.01 m/s, dt = 10 ms).
    # Slots that were not held (a corner landing, a body arriving) are compared as they are.
    stagger = (u_kicked - u_start) * (ctx.dt / h_div)
    approach = jnp.where(held, u_start - stagger, u_start)
    fast = closing & (approach < -settings.restitution_threshold)

    def impacts(b):
        # The other touching pairs that approach, slower than the threshold, first collide
        # plastically (e = 0): a body resting on another carries leapfrog's staggered
        # velocity -h g / 2 (see the module docstring), which is not a motion, and an impact
        # on it must not see it. Without this (with _free_flight's fix alone), a 0.5 kg box
        # dropped on a 1000 kg table resting on the ground rebounded to 0.597 h0 instead of
        # ((M e - m) / (M + m))^2 h0 = 0.639 h0 at dt = 10 ms (e = 0.8). Both passes are
        # one scan over the phases, so the step holds one copy of the impact law.
        resting = closing & ~with_pair_slots(layout, fast)
        phases = (jnp.stack([resting, closing]), jnp.stack([jnp.zeros_like(e), e]),
                  jnp.stack([jnp.zeros((), e.dtype), jnp.asarray(settings.restitution_threshold, e.dtype)]))

        def phase(b, inputs):
            on, e_phase, threshold = inputs
            return collisions(b, f, colours, pair_colours, e_phase, mu, on, threshold, settings.impact_iterations,
                              layout.central)[0], None

        return jax.lax.scan(phase, b, phases)[0]

    # Skipped at run time when nothing approaches that fast (resting stacks; in an ensemble,
    # when no member has such a slot: ``_branch``).
    hit = branch(jnp.any(fast), jax.checkpoint(impacts), lambda b: b, start)
    velocity = hit.velocity[: scene.num_bodies] + kick_v
    momentum = _omega_to_momentum(params, state, hit.angular_velocity, start.angular_velocity,
                                  state.angular_momentum) + kick_l
    bodies, _ = _solver_bodies(params, state, velocity, momentum)
    unsolved_omega = bodies.angular_velocity
    # Then resting contact: u_n >= 0 in contact, u_n >= -(gap - skin)/h ahead of it
    # (speculative). Within the skin, a slot is held: a resting slot's gap then moves its
    # target by nothing, not by its rounding over h (ContactSettings.skin).
    target = -jnp.maximum(gap - settings.skin_for(gap.dtype), 0.0) / h_div
    lam0 = lam0 if settings.warm_start else jnp.zeros_like(lam0)
    solved, lam = _run_solver(settings, layout, bodies, f, target, mu, contact.active, lam0)
    velocity = solved.velocity[: scene.num_bodies]
    momentum = _omega_to_momentum(params, state, solved.angular_velocity, unsolved_omega, momentum)

    # Split impulse: pseudo-velocities that remove penetration, used by the drift only.
    # Its derivative goes through the (at most position_iterations) sweeps run, not the
    # frozen Jacobian: the 1000-step ball's gradient compiled in 26.0-26.4 s instead of
    # 28.4-29.4 s (alternating processes), with the same gradient to the last digit, and a
    # 3-box stack's 100-step gradient (the correction active) within noise in compile and
    # run time, with the same gradient to the last digit. Its solution is not saved by
    # name (see _solver._pgs_jvp): reverse mode runs these few sweeps again.
    #
    # Pairs of several slots (all but the sphere pairs) are levelled as well (see
    # _layout._Group.levelled) where they touch at every active slot: below the slop, a
    # slot's overlap beyond the shallowest of its pair's slots is removed. A resting box
    # tilted on its face (by the unconverged sweeps of a stack's first steps) overlaps more
    # at some corners than at others, all under the slop, and nothing else restores it:
    # its face normal leans, and, frictionless, a 100 kg box on a 1 kg one pushed the light
    # box 0.16 m sideways in 2 s on a tilt of 1.4e-4 rad (levelled: 2.1 mm, from the first
    # steps' transient; benchmarks/README.md, stops 77 and 78). Differences under the level
    # tolerance are left, so that a settled stack's rounding does not run the correction
    # every step.
    depth = jnp.maximum(-gap - settings.correction_slop, 0.0)
    level = level_of_pairs(layout, gap, contact.active)
    if level is not None:
        uneven = -gap - jnp.minimum(settings.correction_slop, level)  # at least depth
        depth = jnp.maximum(depth, jnp.where(uneven > settings.level_tolerance_for(gap.dtype), uneven, 0.0))
    push = contact.active & (depth > 0)
    still = dataclasses.replace(bodies, velocity=jnp.zeros_like(bodies.velocity),
                                angular_velocity=jnp.zeros_like(bodies.angular_velocity))

    def correct(still):
        return solve(still, f, literal_array(layout.colours),
                     settings.position_correction * depth / h_div, jnp.zeros_like(mu), push,
                     jnp.zeros_like(lam0), settings.position_iterations, normal_only=True,
                     tolerance=settings.tolerance_for(depth.dtype), frozen_derivative=False)[0]

    # Skipped where nothing is deeper than the slop or uneven beyond the level tolerance (an
    # impact from flight, most resting contacts): with no slot to push, the solve returns
    # the bodies at rest, exactly.
    pseudo = branch(jnp.any(push), correct, lambda b: b, still, recompute_in_reverse=True, saved=SAVE_NAMED)
    end = _drift_kick(ctx, params, state, velocity, momentum, velocity + pseudo.velocity[: scene.num_bodies], h,
                      derived, turn=h * pseudo.angular_velocity[: scene.num_bodies])
    return dataclasses.replace(end, contact_impulse=lam.astype(state.position.dtype))


def _drift_kick(ctx: _Ctx, params: Params, state: State, velocity, momentum, drift_velocity, h, derived,
                turn=None) -> State:
    """Steps 3 and 4: the force-free drift over ``h`` (translation at ``drift_velocity``: the
    solved velocities plus the split impulse's pseudo-velocities; attitude under the solved
    angular momentum), then the split impulse's turn, then the closing half kick from the
    solved velocities.

    ``turn``: ``(N, 3)`` rad, world frame, the split impulse's rotation vectors (pseudo
    angular velocities times ``h``), or ``None``. The body turns by it after the drift, and
    its world angular momentum turns with it, so that the body-frame momentum, and with it
    the kinetic energy, is the drift's. (Until 2026-12-04 the pseudo angular velocity was
    added to the drift's angular momentum, which was then reset to the solved one in the
    turned attitude: the spin changed, and a spinning capsule at dt = 10 ms, e = 1,
    frictionless, gained 1.5e-4 of its kinetic energy in its impact step, a box landing at
    20 m/s 0.64%.)"""
    moving = dataclasses.replace(state, velocity=drift_velocity, angular_momentum=momentum, contact_impulse=None)
    free = free_scene_of(ctx.scene)
    drifted = ctx.integrator.step_using(free, params, moving, h, derived)
    if turn is not None:
        rotation = spatial.quat_exp(turn)
        drifted = dataclasses.replace(drifted, orientation=spatial.quat_multiply(rotation, drifted.orientation))
        momentum = spatial.quat_rotate(rotation, momentum)
    drifted = dataclasses.replace(drifted, velocity=velocity, angular_momentum=momentum)
    return _closing_kick(ctx.scene, params, drifted, 0.5 * h)


def _free_step(ctx: _Ctx, params: Params, state: State, derived, h=None) -> State:
    """:func:`_regular` where no pair touches at the start and none closes during the
    step: kick, drift, kick (Stoermer-Verlet), with the same arithmetic and no contact work.
    In a scene with a force other than gravity, the integrator's own step instead, so that
    flight keeps its order. ``h``: the length, s (default ``dt``; a traced one for a split
    step's first part)."""
    h = jnp.asarray(ctx.dt if h is None else h, state.position.dtype)
    if not _constant_forces(ctx.scene):
        # Kick-drift-kick samples the forces at the ends of the step: exact for constant
        # gravity, but second order for any other force, whatever the integrator (RK4 in
        # flight under a time-dependent force: errors 1.0e-4 .. 1.6e-6 at dt = 1/50 .. 1/400
        # with a ground plane, 1.7e-9 .. 4.2e-13 without one).
        bare = dataclasses.replace(state, contact_impulse=None)
        end = ctx.integrator.step_using(ctx.scene, params, bare, h, derived)
        return dataclasses.replace(end, contact_impulse=jnp.zeros_like(state.contact_impulse))
    force, torque = wrench(ctx.scene, params, state)
    velocity = state.velocity + 0.5 * h * linear_acceleration(params, force)
    momentum = state.angular_momentum + 0.5 * h * torque
    end = _drift_kick(ctx, params, state, velocity, momentum, velocity, h, derived)
    return dataclasses.replace(end, contact_impulse=jnp.zeros_like(state.contact_impulse))


def _constant_forces(scene: Scene) -> bool:
    """Whether gravity is the scene's only force (kick-drift-kick is then exact in flight)."""
    return all(isinstance(m, Gravity) for m in scene.force_models)


def _rematerialised(ctx: _Ctx, params: Params, state: State, h, lam0, derived, held, bounce=True,
                    ahead=None) -> State:
    """:func:`_regular` under ``jax.checkpoint``: reverse mode recomputes the sub-step
    instead of storing its intermediates (every solver sweep's). Measured on the 1000-step
    bouncing ball (``benchmarks/gradients.py``'s scene): the gradient ran in 292 ms instead
    of 643 and compiled in 29 s instead of 47, with the same value to the last digit. The
    solvers' solutions (named ``SOLUTION``) are kept, so the recomputation does not run
    their sweeps again."""
    return jax.checkpoint(lambda s: _regular(ctx, params, s, h, lam0, derived, held, bounce, ahead),
                          policy=SAVE_NAMED)(state)


def resolve_impacts(scene: Scene, params: Params, state: State, settings: ContactSettings | None = None,
                    dt: float = 1e-3) -> State:
    """Newton's impact law at an instant: the velocity jump of every touching, approaching slot.

    Positions are unchanged. Slots within ``1e-4`` m that approach faster than the
    restitution threshold collide, pair after pair (see ``collisions``): a pair touching at
    one slot with the impulse of seed 000, ``j = -(1 + e) u_n / (n . K n)``, and friction
    bounded by ``mu j``; one touching at several (a box landing flat) on all of them at
    once, so that it rebounds at ``-e`` times its approach without turning. Slots
    that still approach after that (slower than the threshold) get the plastic impulse
    (``e = 0``) that :class:`ContactSettings` documents for slow impacts, so every touching
    slot ends separating or at rest. ``dt`` (s) only sets the default detection margin.
    """
    if not scene.contact_pairs:
        raise ValueError("resolve_impacts needs a scene with contact pairs (Scene(..., contacts=...)).")
    settings = ContactSettings() if settings is None else settings
    if not isinstance(settings, ContactSettings):
        raise ValueError(f"settings must be an rb.ContactSettings(...), got {settings!r}.")
    dt = static_step_length(dt, "resolve_impacts")
    scene.check_inputs(params, state)
    return impact_law(_Ctx(scene, layout_of(scene), None, settings, dt), params, state)


def impact_law(ctx: _Ctx, params: Params, state: State, touching=TOUCHING) -> State:
    """:func:`_impact` (Newton's law for slots faster than the threshold), then a second pass
    with threshold 0 and ``e = 0``: the plastic impulse for every touching slot that still
    approaches. (In a step the resting-contact solve stops those; at an instant nothing else
    would, and the bodies would pass through.) ``touching``: m, the gap under which a slot
    takes part."""
    plastic = dataclasses.replace(ctx, settings=dataclasses.replace(ctx.settings, restitution_threshold=0.0))
    return _impact(plastic, params.replace(restitution=jnp.zeros_like(params.restitution)),
                   _impact(ctx, params, state, touching), touching)


def _impact(ctx: _Ctx, params: Params, state: State, touching) -> State:
    scene, layout, settings = ctx.scene, ctx.layout, ctx.settings
    contact = detect(scene, layout, state, ctx.margin)
    bodies, position = _solver_bodies(params, state, state.velocity, state.angular_momentum)
    f = frames(bodies, layout.body_a, layout.body_b, contact.point, contact.normal, position)
    e, mu = _slot_coefficients(ctx, params)
    touching = contact.active & (contact.gap <= touching)
    solved, _ = collisions(bodies, f, literal_array(layout.colours), literal_array(layout.pair_colours), e, mu,
                           touching, settings.restitution_threshold, settings.impact_iterations, layout.central)
    momentum = _omega_to_momentum(params, state, solved.angular_velocity, bodies.angular_velocity,
                                  state.angular_momentum)
    return dataclasses.replace(state, velocity=solved.velocity[: scene.num_bodies], angular_momentum=momentum)


def _pair_gaps(ctx: _Ctx, state: State) -> jax.Array:
    """Signed separation of each contact pair ``(P,)``, m (see :func:`pair_separations`)."""
    return pair_separations(ctx.scene, ctx.layout, state, ctx.margin)


def _free_pose(state: State, flight, t) -> State:
    """Pose after ``t`` seconds of the motion :func:`_free_flight` predicts: constant
    acceleration from its initial velocity, constant spin."""
    velocity, acceleration, omega = flight
    position = state.position + t * velocity + 0.5 * t * t * acceleration
    orientation = spatial.quat_normalize(spatial.quat_multiply(spatial.quat_exp(t * omega), state.orientation))
    return dataclasses.replace(state, position=position, orientation=orientation, rotation=None)


def _held_slots(state: State) -> jax.Array:
    """The slots ``(C,)`` that the last step's resting solve pushed on: a positive normal
    impulse in ``state.contact_impulse``."""
    return state.contact_impulse[:, 0] > 0


def _free_flight(ctx: _Ctx, params: Params, state: State):
    """The motion over a step that the time-of-impact search assumes: each body's initial
    velocity, constant acceleration and spin ``(N, 3)`` each.

    Free flight under the start's forces, except for a body that the last step's resting
    solve held (a positive normal impulse on one of its slots): that one moves on at its
    last drift velocity (the reported one without the closing half kick, ``v - dt/2 a``:
    zero for a body at rest, whose reported velocity is leapfrog's ``-dt g / 2``), without
    acceleration, since its supports hold it. Searched in free fall, a 1000 kg table resting
    on the ground fell away from the box dropped on it, which met it late, and the step's
    first part (to that instant) then held the box above the table that had not fallen: a
    plastic loss of 0.086 m/s in a 2.43 m/s impact at dt = 10 ms. With the impact's plastic
    pass alone (see :func:`_regular`) the box rebounded to 0.595 h0 instead of 0.639 h0, and
    a centred drop (mu = 0.5) slid sideways at up to 0.26 m/s (0.45 at dt = 1 ms).
    """
    force, _ = wrench(ctx.scene, params, state)
    acceleration = linear_acceleration(params, force)
    held = bodies_with_slots(ctx.layout, _held_slots(state))[:, None]
    velocity = jnp.where(held, state.velocity - 0.5 * ctx.dt * acceleration, state.velocity)
    return velocity, jnp.where(held, 0.0, acceleration), angular_velocity(params, state)


def _time_of_impact(ctx: _Ctx, state: State, flight, end_sep, lower, choose, known_gaps, known):
    """Fraction ``tau`` in ``[lower, 1]`` of the step at which the first of the chosen pairs
    touches, and those pairs ``(P,)`` (``tau = 1`` where none is chosen).

    ``flight`` is :func:`_free_flight` at ``state``; ``end_sep`` ``(P,)`` the separations at
    ``tau = 1`` (m). The search opens with the separations at ``lower``: ``known_gaps``
    ``(P,)`` where ``known`` (a boolean scalar) is true, else evaluated there. From them
    ``choose(gaps)`` picks the pairs to search ``(P,)``, which must be apart at ``lower``
    and overlap at ``tau = 1``: their smallest separations at both ends bracket the root.
    Its value comes from a fixed number of Illinois steps and a last secant step through
    the bracket's true values, without tangents; its derivative is the implicit function
    theorem's (:func:`jaxrb._implicit.implicit_root`).

    The opening is the loop's first iteration, not an evaluation of its own: the compiled
    step holds one copy of the separations for every search (see :func:`_split_points`).
    """
    dtype = state.position.dtype
    big = float(jnp.finfo(dtype).max / 4)  # a Python float: ``distance`` must capture no tracer

    def gaps_at(tau, state, flight):
        return _pair_gaps(ctx, _free_pose(state, flight, tau * ctx.dt))

    def distance(tau, theta):
        state, flight, pairs = theta
        return jnp.min(jnp.where(pairs, gaps_at(tau, state, flight), big))

    frozen = jax.lax.stop_gradient((state, flight))
    zero, one = jnp.zeros((), dtype), jnp.ones((), dtype)
    lower = jax.lax.stop_gradient(jnp.asarray(lower, dtype))
    end_sep = jax.lax.stop_gradient(end_sep)
    opening_gaps = jax.lax.stop_gradient(known_gaps)
    known = jnp.asarray(known, bool)

    def illinois(carry, i):
        # (a, b): the bracket; (fa, fb): the values the next secant uses (Illinois halves
        # the stale one); (ta, tb): the true values at a and b.
        (a, fa, ta, b, fb, tb, side), pairs = carry
        opening = i == 0
        c = jnp.clip((a * fb - b * fa) / jnp.where(fb != fa, fb - fa, 1.0), a, b)
        # The separations at the opening (unless known) and at each secant point while a
        # pair is searched; skipped at run time otherwise.
        needed = jnp.where(opening, ~known, jnp.any(pairs))
        gaps = branch(needed, lambda x: gaps_at(x, *frozen), lambda x: opening_gaps, jnp.where(opening, lower, c))
        # The opening: the pairs (chosen there alone: a later search's test follows
        # touching bodies through the scene, a loop of its own) and the bracket's ends.
        chosen = branch(opening, choose, lambda g: pairs, gaps)
        low, high = (jnp.min(jnp.where(chosen, x, bound)) for x, bound in ((gaps, ctx.margin), (end_sep, 0.0)))
        opened = (lower, low, low, one, high, high, jnp.zeros((), jnp.int32))
        # An Illinois step.
        fc = jnp.min(jnp.where(pairs, gaps, big))
        left = fc * fa > 0  # root in [c, b]
        a2, fa2, ta2 = jnp.where(left, c, a), jnp.where(left, fc, fa), jnp.where(left, fc, ta)
        b2, fb2, tb2 = jnp.where(left, b, c), jnp.where(left, fb, fc), jnp.where(left, tb, fc)
        # Illinois: halve the stale end's value when the same side moves twice.
        fb2 = jnp.where(left & (side > 0), 0.5 * fb2, fb2)
        fa2 = jnp.where(~left & (side < 0), 0.5 * fa2, fa2)
        stepped = (a2, fa2, ta2, b2, fb2, tb2, jnp.where(left, 1, -1).astype(jnp.int32))
        bracket = jax.tree.map(lambda o, s: jnp.where(opening, o, s), opened, stepped)
        return (bracket, chosen), None

    start = ((zero, one, one, one, -one, -one, jnp.zeros((), jnp.int32)), jnp.zeros(end_sep.shape, bool))
    ((a, _, ta, b, _, tb, _), pairs), _ = jax.lax.scan(
        illinois, start, jnp.arange(ctx.settings.toi_iterations + 1))
    # A last secant step through the true values at the bracket's ends (the bracket is tight
    # by now; no more evaluations of the separations).
    root = jnp.clip((a * tb - b * ta) / jnp.where(tb != ta, tb - ta, 1.0), a, b)
    # Named, as is the root: reverse mode through a checkpointed step reads them back
    # instead of running the search again.
    root, pairs = checkpoint_name(jax.lax.stop_gradient((root, pairs)), TIME_OF_IMPACT)
    # The derivative by the implicit function theorem, as a rule of its own (not a Newton
    # step ``root - distance / slope`` traced into the step, as until 2026-11-27): a program
    # that takes no derivative traces the separations once, in the root search, and a
    # derivative program does not differentiate the slope again. Measured in alternating
    # processes (float32 stack, float64 ball): the 5-box stack's 200-step rollout 16,386 ->
    # 14,663 lines of StableHLO and 11.1-11.9 -> 9.5-10.6 s to trace and compile; the
    # 1000-step ball's gradient 29.4-29.6 -> 27.9-28.2 s; the same values to the last digit
    # printed. The pair closes at the root (slope < 0).
    tau = jnp.clip(implicit_root(distance, root, (state, flight, pairs), -1), 0.0, 1.0)
    return jnp.where(jnp.any(pairs), tau, one), pairs


def _branch_test(ctx: _Ctx, params: Params, state: State):
    """Which branch a step from ``state`` takes: ``(far, start_sep, end_sep, candidate)``.

    ``far``: no pair touching at the start (:func:`_touching_distance`) and none closing
    during the step's free flight (then the step is :func:`_free_step`). The separations (cheap: no box-box
    manifold) at both ends of the free flight bracket the time of impact of the
    ``candidate`` pairs (``end_sep`` and ``candidate`` are ``None`` without the search).
    Only their values are used (to choose a branch, and as the bracket), so they are
    computed without tangents; and named (:data:`SEPARATIONS`, one array), so that reverse
    mode through a checkpointed step reads them back instead of computing them again.
    With the search, both ends are free poses (:func:`_free_pose` after 0 and after ``dt``;
    the first is the state's with its attitude renormalised) evaluated as one batch: the
    settled 5-box stack's step ran 664 -> 641 kernels (float32), and the compiled step
    holds one copy of the separations instead of two.
    """
    settings, dt = ctx.settings, ctx.dt
    frozen_params, frozen_state = jax.lax.stop_gradient((params, state))
    dtype = state.position.dtype
    end_sep = candidate = None
    if settings.time_of_impact:
        flight = _free_flight(ctx, frozen_params, frozen_state)
        ends = jnp.stack([jnp.zeros((), dtype), jnp.asarray(dt, dtype)])
        both = jax.vmap(lambda t: _pair_gaps(ctx, _free_pose(frozen_state, flight, t)))(ends)
        start_sep, end_sep = checkpoint_name(both, SEPARATIONS)
        candidate = (start_sep > settings.penetration_slop) & (end_sep < 0)
    else:
        start_sep = checkpoint_name(_pair_gaps(ctx, frozen_state), SEPARATIONS)
    far = jnp.all(start_sep >= _touching_distance(settings, ctx.margin))
    if candidate is not None:
        far = far & ~jnp.any(candidate)
        meeting = _meeting_mid_step(ctx, frozen_state, flight, end_sep)
        if meeting is not None:
            far = far & ~jnp.any(meeting)
    return far, start_sep, end_sep, candidate


def _bounding_radius(scene: Scene, name: str) -> float:
    """m: the radius of a sphere about the body's centre of mass that holds its shape."""
    body = scene.bodies[scene.index(name)]
    shape = body.shape
    if isinstance(shape, Sphere):
        reach = shape.radius
    elif isinstance(shape, Box):
        reach = math.hypot(*shape.half_extents)
    elif isinstance(shape, Capsule):
        reach = shape.radius + shape.half_length
    elif isinstance(shape, Cylinder):
        reach = math.hypot(shape.radius, shape.half_length)
    else:  # not reached: contact pairs hold the shapes above (and the ground) only
        raise ValueError(f"No bounding radius for {type(shape).__name__}.")
    return reach + math.hypot(*body.shape_offset)


def _meeting_mid_step(ctx: _Ctx, state: State, flight, end_sep):
    """Body pairs apart at the end of the step's free flight whose bounding spheres meet
    during it ``(P,)`` (``None`` if the scene has no body-body pair).

    The search brackets an impact between the step's two ends, so a pair that passes
    through another within the step (apart at both ends: a fast, small body) was missed,
    and went through. Such a pair makes the step a contact step, whose impact pass
    treats it as closing (Newton's law at the step's start, as without the search). The
    test: the closest approach of the centres of mass over ``[0, dt]`` along their
    relative straight-line motion, less what their relative acceleration can bend it
    (``|da| dt^2 / 2``), against the sum of the bounding radii. Rotation moves no point of
    a body out of its sphere. Pairs with the ground are left out: the gap of a body that
    translates with gravity pointing into the ground is concave in time, so it is lowest
    at an end of the step (a corner of a body spinning through the ground within one step
    is not covered).
    """
    scene = ctx.scene
    pairs = [(i, scene.index(a), scene.index(b), _bounding_radius(scene, a) + _bounding_radius(scene, b))
             for i, (a, b) in enumerate(scene.contact_pairs) if not scene.is_plane(b)]
    if not pairs:
        return None
    index, body_a, body_b, reach = (np.asarray(x) for x in zip(*pairs, strict=True))
    dtype = state.position.dtype
    dx = take_rows(state.position, body_a) - take_rows(state.position, body_b)
    velocity, acceleration, _ = flight
    dv = take_rows(velocity, body_a) - take_rows(velocity, body_b)
    da = take_rows(acceleration, body_a) - take_rows(acceleration, body_b)
    speed2 = jnp.sum(dv * dv, -1)
    moving = speed2 > 0
    t = jnp.clip(-jnp.sum(dx * dv, -1) / jnp.where(moving, speed2, 1.0), 0.0, ctx.dt)
    closest = jnp.linalg.norm(dx + t[:, None] * dv, axis=-1) - 0.5 * ctx.dt**2 * jnp.linalg.norm(da, axis=-1)
    meets = jnp.concatenate([moving & (closest < literal_array(reach, dtype)), jnp.zeros(1, bool)])
    # In pair order, ground pairs reading the appended False (static slices: jaxrb._indexing).
    row = np.full(ctx.scene.num_contact_pairs, len(index))
    row[index] = np.arange(len(index))
    return take_rows(meets, row) & (end_sep >= 0)


def far_from_contact(scene: Scene, settings: ContactSettings, dt: float, params: Params, state: State) -> jax.Array:
    """Whether :func:`contact_step` from ``state`` takes its free branch (bool scalar, no
    tangent): exactly the test it makes."""
    ctx = _Ctx(scene, layout_of(scene), None, settings, dt)
    return _branch_test(ctx, params, state)[0]


def free_step(scene: Scene, integrator, settings: ContactSettings, dt: float, params: Params, state: State,
              derived) -> State:
    """The free branch of :func:`contact_step` (:func:`_free_step`), for a state where
    :func:`far_from_contact` holds."""
    return _free_step(_Ctx(scene, layout_of(scene), integrator, settings, dt), params, state, derived)


def contact_step(scene: Scene, integrator, settings: ContactSettings, dt: float,
                 params: Params, state: State, derived) -> State:
    """One step of a scene with contacts (see the module docstring).

    Far from everything (no pair touching at the start, none closing during the step's
    free flight: :func:`_touching_distance`) it is the free step (:func:`_free_step`), with
    no contact work. Both branches are checkpointed: a
    ``lax.cond``'s linearisation outputs the residuals of both branches (zero-filled for the
    one not taken) and reverse mode would stack them at every step of a rollout; a
    checkpoint's residuals are its inputs. The cond itself is a :func:`branch` with
    ``recompute_in_reverse``, for the same reason one level up. The whole step is
    checkpointed by its callers (``rollout`` and ``Step.__call__``, with
    :data:`SAVE_NAMED`), once. A second
    checkpoint here, nested in theirs, gave the same gradients to the last bit and the
    same run times, and only slowed compilation: ``jax.jacrev`` of a 10-step two-ball
    rollout traced in 23.5 s with it and 17.1 s without (one run each); the 1000-step
    ball's gradient took 50 and 57 s to trace and compile with it, 50 and 46 s without
    (two alternating runs). Run times: see the README's gradients section.
    """
    ctx = _Ctx(scene, layout_of(scene), integrator, settings, dt)
    if state.contact_impulse is None:
        state = dataclasses.replace(state, contact_impulse=initial_impulses(scene, state.position.dtype))
    far, start_sep, end_sep, candidate = _branch_test(ctx, params, state)
    free = jax.checkpoint(lambda p, s: _free_step(ctx, p, s, derived))
    contact = jax.checkpoint(lambda p, s: _contact_step(ctx, p, s, derived, start_sep, end_sep, candidate),
                             policy=SAVE_NAMED)
    # recompute_in_reverse: the backward pass of a free step then reads the step's inputs
    # only, not zeros copied into the contact branch's 42 residual slots. On the 1000-step
    # bouncing ball (benchmarks/gradients.py), the gradient ran ~10% faster side by side
    # (10.6 against 11.5 ms, minima of 40 rounds), with the same value to the last bit;
    # a 3-box stack's 100-step gradient, all contact steps, ~4% slower (391 against 376 ms).
    return branch(far, free, contact, params, state, recompute_in_reverse=True, saved=SAVE_NAMED)


def _contact_step(ctx: _Ctx, params: Params, state: State, derived, start_sep, end_sep, candidate) -> State:
    """The step near contacts: the time-of-impact split (where ``candidate`` pairs close;
    ``None`` without the search), and the sub-steps. ``start_sep``, ``end_sep``: the pairs'
    separations at both ends of the step's free flight ``(P,)``, m."""
    dt = ctx.dt
    lam0 = state.contact_impulse
    # Held by the step's start (the impulses of the step before), not by a split step's first
    # part: that part's speculative contact may push on the pair that is about to collide.
    held = _held_slots(state)
    if candidate is None:
        return _rematerialised(ctx, params, state, jnp.asarray(dt, state.position.dtype), lam0, derived, held)

    # Split the step at the impacts: [0, tau_1 h], [tau_1 h, tau_2 h], ..., [tau_M h, h], each
    # part after the first starting with its impact (the sub-step's impact pass: the pair
    # touches there and approaches). One scan over the parts keeps one copy of the sub-step
    # in the compiled program; a part of zero length is skipped (at run time; in an
    # ensemble, when every member's is). At tau = 1 the impact is the next step's, at its
    # start. Impacts after the last located one are handled at its instant (speculatively).
    any_hit = jnp.any(candidate)
    taus, ahead = _split_points(ctx, params, state, start_sep, end_sep, candidate)
    lengths = (taus[1:] - taus[:-1]) * dt

    # The part before the impact is free flight where no pair touches at the step's start:
    # a pair apart there that does not close over the step (end separation >= 0) is one
    # the free step would leave alone too, and the candidates close only at tau. Its
    # speculative solve had nothing to do (the ball's gradient is the same to the last bit),
    # and cost the impact step a solve and its derivative (``python benchmarks/kernels.py
    # --scene impact``: 78.3 -> 73.0 kernels a step forward, 280.6 -> 251.7 in reverse).
    clear = jnp.all(start_sep >= _touching_distance(ctx.settings, ctx.margin))

    def part(carry, inputs):
        state, lam = carry
        index, h, ahead_here = inputs
        bounce = (index > 0) | ~any_hit

        def sub_step(s):
            # Both branches are checkpoints already. With ``recompute_in_reverse`` (each
            # linearisation then held both branches) the ball's gradient was 69,068 lines of
            # StableHLO instead of 45,715 (38,365 before this branch), for the same kernels.
            return branch(
                (index == 0) & any_hit & clear,
                jax.checkpoint(lambda s: _free_step(ctx, params, s, derived, h)),
                lambda s: _rematerialised(ctx, params, s, h, lam, derived, held, bounce, ahead_here),
                s)

        state = branch(
            h > 0,
            sub_step,
            lambda s: dataclasses.replace(s, contact_impulse=lam),
            state)
        return (state, state.contact_impulse), None

    parts = jnp.arange(lengths.shape[0])
    (state, _), _ = jax.lax.scan(part, (state, lam0), (parts, lengths, ahead))
    return state


def _pair_bodies(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Each contact pair's two body indices ``(P,)`` each, the ground (a plane) as ``N``."""
    index = [(scene.index(a), scene.num_bodies if scene.is_plane(b) else scene.index(b))
             for a, b in scene.contact_pairs]
    return tuple(np.asarray(x, np.int32) for x in zip(*index, strict=True))


def _pairs_of_bodies(ctx: _Ctx, bodies: jax.Array) -> jax.Array:
    """``(P,)`` bool: the pairs that have a moving body in ``bodies`` ``(N,)``.

    By static slices (``take_rows``): an index table or a scatter would capture array
    constants (see :mod:`jaxrb._indexing`)."""
    bodies = jnp.concatenate([bodies, jnp.zeros(1, bool)])  # the ground (index N) does not move
    pair_a, pair_b = _pair_bodies(ctx.scene)
    return take_rows(bodies, pair_a) | take_rows(bodies, pair_b)


def _bodies_of_pairs(ctx: _Ctx, pairs: jax.Array) -> jax.Array:
    """``(N,)`` bool: the moving bodies of the pairs in ``pairs`` ``(P,)``."""
    return bodies_with_slots(ctx.layout, slot_values(ctx.layout, pairs))


def _moved_by_impacts(ctx: _Ctx, touching: jax.Array, struck: jax.Array) -> jax.Array:
    """``(P,)`` bool: the pairs with a body that the impacts of the ``struck`` pairs can move.

    Those are the struck pairs' bodies that touch there (``touching`` ``(P,)``: pairs in
    contact) and every body joined to one of them by a chain of touching pairs, which the
    impact pass (pair after pair) and the solve pass the impulse on to. The ground joins
    nothing. A body outside that set moves on as :func:`_free_flight` predicts: in free
    flight, or at its drift velocity where the last step's solve held it (a table resting
    on the ground)."""
    def spread(carry):
        bodies, _ = carry
        more = bodies | _bodies_of_pairs(ctx, touching & _pairs_of_bodies(ctx, bodies))
        return more, jnp.any(more != bodies)

    # Until no body joins: a loop of at most N - 1 passes, most often one or two.
    bodies, _ = jax.lax.while_loop(lambda c: c[1], spread, (_bodies_of_pairs(ctx, struck & touching), True))
    return _pairs_of_bodies(ctx, bodies)


def _located_impacts(ctx: _Ctx) -> int:
    """``settings.located_impacts``, or 1 where no two contact pairs have their moving bodies
    apart (a ball and the ground, or walls): a pair located after another then always has a
    body that the other's impact moved, and is never searched (see :func:`_split_points`)."""
    bodies = [{i for i in pair if i < ctx.scene.num_bodies} for pair in zip(*_pair_bodies(ctx.scene), strict=True)]
    apart = any(not a & b for k, a in enumerate(bodies) for b in bodies[k + 1:])
    return ctx.settings.located_impacts if apart else 1


def _split_points(ctx: _Ctx, params: Params, state: State, start_sep, end_sep, candidate):
    """The instants that split a step: ``taus`` ``(M + 2,)`` (fractions of the step, from 0
    to 1, non-decreasing; ``M`` = :func:`_located_impacts`), and for each of the ``M + 1``
    parts the pairs ``(M + 1, P)`` apart at its start whose impact is located at its end,
    which it leaves alone (see :func:`_regular`).

    The first impact is the earliest root among the ``candidate`` pairs (apart at the start,
    overlapping at the end of the free flight). Each next one is searched from the last,
    along the same free flight, among the pairs apart at that instant and overlapping at
    the end whose bodies the impacts located so far cannot move
    (:func:`_moved_by_impacts`: the bodies they strike and all that touch those, through
    chains of contacts), since the flight does not know those impacts. A second ball
    landing elsewhere is found, and so is one landing on a table resting on the ground
    elsewhere; a body's second impact after its first is not, nor an impact onto a body
    touching one struck before it in the step: those are handled as before, at the start
    of the part after the last located impact.

    The searches run along :func:`_free_flight` from ``state`` (under ``params``). Where
    several impacts can be located and no pair closes (every step of a resting stack), the
    searches' loop and that flight are skipped by a ``branch``: each search would be skipped
    and return tau = 1, so the result is its constants.
    """
    dtype = state.position.dtype
    slop = ctx.settings.penetration_slop
    one = jnp.ones((), dtype)
    no_pairs = jnp.zeros_like(candidate)
    located = _located_impacts(ctx)

    def search(params, state):
        flight = _free_flight(ctx, params, state)

        def choose(k, struck):
            def pairs(gaps):
                if isinstance(k, int):  # the first search alone (no loop)
                    return candidate
                later = (gaps > slop) & (end_sep < 0) & ~_moved_by_impacts(ctx, gaps <= slop, struck)
                return jnp.where(k == 0, candidate, later)
            return pairs

        def locate(begin, struck, k):
            # The first search's pairs and the separations it opens with are the branch
            # test's; the later ones' are computed at the instant they start from.
            # Checkpointed (here and for the impacts): a cond's linearisation zero-fills the
            # residuals of the branch not taken, copied at every step; a checkpoint's are its
            # inputs.
            return jax.checkpoint(
                lambda: _time_of_impact(ctx, state, flight, end_sep, begin, choose(k, struck), start_sep, k == 0),
                policy=SAVE_NAMED)()

        def split(carry, k):
            # One search in the compiled step, however many impacts are located. The first
            # searches where a candidate closes; a later one opens where the last ended
            # inside the step. ``struck``: the pairs located so far.
            begin, struck = carry
            # (``k`` is captured, not an operand: a Python 0 where no loop runs, so that the
            # program then holds the first search's choice alone.)
            tau, pairs = branch(jnp.where(k == 0, jnp.any(candidate), begin < 1),
                                lambda b, s: locate(b, s, k), lambda *_: (one, no_pairs), begin, struck)
            tau = jnp.maximum(tau, begin)
            found = pairs & (tau < 1)
            return (tau, struck | found), (tau, found)

        zero = jnp.zeros((), dtype)
        if located == 1:  # no loop, and no search after the first in the program
            _, (tau, ahead) = split((zero, no_pairs), 0)
            return tau[None], ahead[None]
        _, (taus, ahead) = jax.lax.scan(split, (zero, no_pairs), jnp.arange(located))
        return taus, ahead

    if located == 1:
        taus, ahead = search(params, state)
    else:
        # Not where one impact is located: there is no loop to skip, and the branch made
        # XLA:CPU hand a sliding box's steps to its thread pool 5 times a step (0.01 before;
        # benchmarks/README.md, stop 82).
        taus, ahead = branch(jnp.any(candidate), search,
                             lambda *_: (jnp.ones((located,), dtype), jnp.zeros((located, *no_pairs.shape), bool)),
                             params, state)
    return (jnp.concatenate([jnp.zeros((1,), dtype), taus, one[None]]),
            jnp.concatenate([ahead, no_pairs[None]]))
