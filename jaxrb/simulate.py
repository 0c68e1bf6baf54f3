"""Building a step function and rolling it out.

``step = make_step(scene, integrator, dt)`` is a pure function ``step(params, state) ->
state``. ``rollout(step, params, state, num_steps)`` runs it as one compiled
``lax.scan``. Both compose with ``jax.jit``, ``jax.vmap``, ``jax.grad`` and
``jax.jacfwd``; the scene, integrator and ``dt`` are static, ``params`` and ``state``
are traced, so new values never recompile.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp

from ._branch import any_batched, branch, members_differentiated
from ._static import positive_count, static_step_length, static_switch
from .contact import ContactSettings
from .contact._penetration import penetration, thinnest_size
from .contact._solver import SAVE_NAMED
from .contact._step import contact_step, far_from_contact, free_step, impulse_shape, initial_impulses
from .integrators import Integrator
from .scene import Scene
from .state import Params, State

__all__ = ["Step", "make_step", "rollout"]


class Step(eqx.Module):
    """``step(params, state) -> state``: one time step of a scene. Built by :func:`make_step`.

    Calling it directly runs a jitted version; inside a user's ``jit``/``vmap``/``grad``
    it is inlined like any JAX function.
    """

    scene: Scene = eqx.field(static=True)
    integrator: Integrator
    dt: float = eqx.field(static=True)
    debug: bool = eqx.field(static=True, default=False)
    contact: ContactSettings = eqx.field(static=True, default=ContactSettings())
    max_penetration: float = eqx.field(static=True, default=math.inf)

    def prepare(self, state: State) -> State:
        """Put a state in the form this step carries (idempotent): the integrator's form
        (see Integrator) and, with contacts, the warm-start impulses. Impulses of another
        scene's shape (a state carried over from another scene) are replaced by zeros, and
        dropped in a scene without contacts: they are a warm start only."""
        self.scene.check_state_shapes(state)
        # The time in the positions' precision: an integer time had failed in rollout's scan
        # (its carry's type changed at the first step), a float32 one with float64 positions
        # had stayed float32 throughout.
        state = dataclasses.replace(state, time=jnp.asarray(state.time, state.position.dtype))
        state = self.integrator.prepare(state)
        if not self.scene.contact_pairs:
            return dataclasses.replace(state, contact_impulse=None)
        if state.contact_impulse is None or jnp.shape(state.contact_impulse) != impulse_shape(self.scene):
            state = dataclasses.replace(state, contact_impulse=initial_impulses(self.scene, state.position.dtype))
        return state

    def __call__(self, params: Params, state: State) -> State:
        # As rollout does: a vmap seen here, outside the jit, traces the step's derivative
        # rules in their per-member form (jax.grad of a vmapped step skips what no member
        # needs). Under a user's own scan the step is traced for one member and cannot see it.
        members = any_batched((params, state))
        with members_differentiated(members):
            return self._call(params, state, members)

    @eqx.filter_jit
    def _call(self, params: Params, state: State, members: bool) -> State:
        # ``members`` is static: each form of the derivative rules has a trace of its own.
        # Reverse mode through a user's own loop of steps recomputes each step from its
        # input state (and, with contacts, the solves' saved solutions), as rollout's loop
        # does, instead of stacking its intermediates: with contacts, the residuals of both
        # branches of its lax.cond; without, those of the integrator (a tumbling box's
        # 1000-step gradient through jax.lax.scan: 6.4 -> 4.6 ms, benchmarks/README.md,
        # "One recomputation of the rotations").
        # (For an ensemble a new function: JAX caches the checkpoint's trace by function, and
        # one traced for a single member would bring the rules of that form.)
        advance = jax.checkpoint((lambda *a: self.advance(*a)) if members else self.advance, policy=SAVE_NAMED)
        return advance(params, state, self.integrator.precompute(params))

    def advance(self, params: Params, state: State, derived) -> State:
        """One step, given ``derived = self.integrator.precompute(params)`` (see Integrator)."""
        # Shapes only, so at trace time: params from another scene, or a field changed by
        # Params.replace (which cannot validate), would otherwise broadcast silently.
        self.scene.check_inputs(params, state)
        if self.scene.contact_pairs:
            _check_impulses(self.scene, state)
            # The state in the integrator's carried form, as rollout prepares it (a no-op
            # then): the contact step's branches must agree on it, and ExplicitEuler's free
            # branch adds the rotation matrix that a state from scene.state() lacks.
            state = self.integrator.prepare(state)
            new = contact_step(self.scene, self.integrator, self.contact, self.dt, params, state, derived)
        else:
            new = self.integrator.step_using(self.scene, params, state, self.dt, derived)
        if self.debug:
            new = _checked(self, new)
        return new


def _check_impulses(scene: Scene, state: State) -> None:
    """Refuse warm-start impulses of another scene's shape (which failed inside the step's
    ``cond`` with a message about its branches' shapes)."""
    need = impulse_shape(scene)
    have = None if state.contact_impulse is None else jnp.shape(state.contact_impulse)
    if have is not None and have != need:
        raise ValueError(f"State.contact_impulse has shape {have}; this scene's contact slots need {need}: the "
                         "state comes from another scene. Pass it through step.prepare(state), which resets them "
                         "(rollout does).")


def _checked(step: Step, new: State) -> State:
    """``new``, with the debug mode's run-time checks attached (``equinox.error_if``)."""
    bad = ~jnp.all(jnp.isfinite(new.position)) | ~jnp.all(jnp.isfinite(new.orientation))
    bad = bad | ~jnp.all(jnp.isfinite(new.velocity)) | ~jnp.all(jnp.isfinite(new.angular_momentum))
    new = eqx.error_if(
        new,
        bad,
        "jaxrb: the state became NaN or infinite in this step. Check for a blow-up "
        "(reduce dt, or use a more stable integrator) or for invalid params.",
    )
    if step.scene.contact_pairs and math.isfinite(step.max_penetration):
        new = eqx.error_if(
            new,
            penetration(step.scene, new) > step.max_penetration,
            "jaxrb: bodies overlap deeper than max_penetration after this step (a contact blow-up "
            "or a tunnel). Reduce dt, raise ContactSettings(iterations=...), use "
            "ContactSettings(solver='exact') for heavy bodies resting on light ones, check that "
            "the bodies did not start overlapping, or raise make_step(max_penetration=...).",
        )
    return new


def make_step(
    scene: Scene,
    integrator: Integrator,
    dt: float,
    *,
    debug: bool = False,
    contact: ContactSettings | None = None,
    max_penetration: float | None = None,
) -> Step:
    """The step function of ``scene`` advanced by ``integrator`` with time step ``dt`` (s).

    If the scene declares contact pairs, each step is the contact step of
    :mod:`jaxrb.contact` (kick, contact solve, drift, kick, with the time of impact
    located inside the step), configured by ``contact`` (default
    :class:`jaxrb.ContactSettings()`); the integrator then supplies the torque-free drift
    of the attitude, and such steps are second order in ``dt`` (kick-drift-kick). A step
    in which no pair touches or closes is free flight: kick-drift-kick as well where
    gravity is the only force (exact for it), else the integrator's own step, so that
    flight keeps the integrator's order. A scene without contacts compiles no contact
    code at all.

    With ``debug=True`` the step raises (also inside ``jit``, through
    ``equinox.error_if``) as soon as the state turns NaN or infinite, instead of letting
    the NaN propagate silently, and, in a scene with contacts, as soon as two bodies
    overlap deeper than ``max_penetration`` (m; default half the smallest radius or half
    extent of the bodies in contact pairs). That check costs one more narrow-phase pass
    per step (:func:`jaxrb.contact.penetration`); without ``debug`` neither check is
    compiled.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"make_step needs an rb.Scene, got {type(scene).__name__}.")
    if isinstance(integrator, type) and issubclass(integrator, Integrator):
        raise ValueError(
            f"make_step needs an integrator instance: write {integrator.__name__}(), "
            f"not {integrator.__name__}."
        )
    if not isinstance(integrator, Integrator):
        raise ValueError(
            f"make_step needs an integrator from rb.integrators (e.g. rb.integrators.RK4()), "
            f"got {integrator!r}."
        )
    dt = static_step_length(dt, "make_step")
    debug = static_switch("debug", debug)
    if contact is not None and not scene.contact_pairs:
        raise ValueError("contact settings need a scene with contact pairs (Scene(..., contacts=...)); this "
                         "scene has none, so they would be ignored. Leave contact out.")
    if contact is None:
        contact = ContactSettings()
    if not isinstance(contact, ContactSettings):
        raise ValueError(f"contact must be an rb.ContactSettings(...), got {contact!r}.")
    return Step(scene=scene, integrator=integrator, dt=dt, debug=debug, contact=contact,
                max_penetration=_penetration_limit(scene, debug, max_penetration))


def _penetration_limit(scene: Scene, debug: bool, max_penetration) -> float:
    """The debug mode's overlap limit, m (``inf``: not checked)."""
    if max_penetration is None:
        thinnest = thinnest_size(scene)
        return 0.5 * thinnest if debug and thinnest is not None else math.inf
    if not debug:
        raise ValueError("max_penetration is checked by the debug mode only: pass debug=True as well.")
    if not scene.contact_pairs:
        raise ValueError("max_penetration needs a scene with contact pairs (Scene(..., contacts=...)).")
    try:
        limit = float(max_penetration)
    except (TypeError, ValueError):
        raise ValueError(f"max_penetration must be a positive distance in metres, got {max_penetration!r}.") from None
    if not limit > 0:  # inf is allowed: no overlap check
        raise ValueError(f"max_penetration must be a positive distance in metres, got {limit}.")
    return limit


@eqx.filter_jit
def _rollout(step, params, state, num_steps: int, save_every: int, checkpoint: bool, members: bool = False):
    """:func:`rollout`'s loop, for one member (``members``: whether it is one of an
    ensemble's; static, so that each form of the derivative rules has a trace of its own:
    see :func:`rollout`)."""
    del members
    chunk = 1
    if isinstance(step, Step) and save_every == 1 and not checkpoint:
        chunk = _chunk_length(state, num_steps)
    return _scan_steps(step, params, state, num_steps, save_every, checkpoint, chunk)


def _scan_steps(step, params, state, num_steps: int, save_every: int, checkpoint: bool, chunk: int):
    """The loop of :func:`rollout`; with ``chunk > 1`` (``save_every == 1`` only), the
    recorded states are stacked ``chunk`` steps at a time."""
    dt = step.dt if isinstance(step, Step) else None
    # (Until 2026-12-05 a custom_jvp here tied the initial state's zero tangent to the
    # params', so that differentiating the scan found the carries with a tangent in one
    # pass: it had cut the ball's gradient tracing from 15-17 s to 10.3-10.5 s. Measured
    # again before removing it, two alternating runs of jit(grad(loss)).lower() of the
    # 1000-step ball with respect to its params: 19.4 and 18.9 s with it, 17.4 and 19.0 s
    # without. It no longer helped, and under jax.grad of a loss summed over a jax.vmap with
    # batched params its rule was batched with tangents where its primals were not: the
    # rollout failed to trace, a broadcast_in_dim TypeError.)
    t0 = state.time
    # Groups of steps tried as free flight first (see _speculative): the chunks of a
    # recording rollout, or segments of save_every steps (in parts of attempt_length).
    attempt_length = _attempt_length(save_every) if save_every > 1 and _speculates(step) else None
    speculative = attempt_length is not None or (chunk > 1 and _speculates(step))
    if isinstance(step, Step):
        # Params-only quantities (e.g. principal axes), once per rollout instead of per step.
        derived = step.integrator.precompute(params)
        # Where groups are tried as free flight, the contact steps read the params and
        # ``derived`` from one flat array. Reverse mode through the group's ``cond``
        # copies every value its contact branch's derivative reads out of the cond (JAX's
        # cond partial evaluation does not forward operands), and the loop then stacks
        # those copies at every chunk, and adds up their cotangents: one array instead of
        # nine. Measured (benchmarks/README.md, "Packed parameters"): the 1000-step
        # bouncing ball's gradient runs 2.7-2.9% fewer kernels and is 2-8% faster, its
        # forward unchanged; a sliding box's forward is 22-25% faster (its profile then
        # shows every kernel on one thread instead of alternating between two; why is not
        # known). The free steps keep the params as they are: unpacked there, the split
        # was one more kernel a step in the forward, and a long segment's steps (not tried
        # as free flight) ran 18% slower from it (benchmarks/README.md, "Long segments").
        constants, unpack = _packed((params, derived)) if speculative else ((params, derived), None)

        def one_step(c, s):
            p, d = c if unpack is None else unpack(c)
            return step.advance(p, s, d)

        # Reverse mode recomputes each step from its input state instead of stacking the
        # step's intermediates (44 arrays a step for a tumbling box under the splitting,
        # each its own dynamic-update-slice kernel). The contact solves' solutions and the
        # separations that chose the step's branch are still saved (SAVE_NAMED), so no PGS
        # sweep runs twice. Measured (benchmarks/README.md, "Checkpointed steps"): a
        # tumbling box's reverse pass 129 -> 108 kernels a step and its gradient 11.9 ->
        # 7.8 ms (medians), forward unchanged; the bouncing ball, a 1024-box float32
        # ensemble and a 3-box stack within noise.
        one_step = jax.checkpoint(one_step, policy=SAVE_NAMED)
    else:
        one_step, constants = step, params

    def advance(carry, _):
        s, k = carry
        s = one_step(constants, s)
        k = k + 1
        if dt is not None:
            s = _timed(s, t0, k, dt)
        return (s, k), None

    def segment(carry, _):
        if save_every == 1:  # no inner scan of length 1: its residuals would be stacked twice
            carry, _ = advance(carry, None)
        else:
            carry, _ = jax.lax.scan(advance, carry, None, length=save_every)
        return carry, carry[0]

    start = (state, jnp.zeros((), jnp.int32))
    if chunk > 1:
        if _speculates(step):
            chunk_of_steps = _speculative(step, params, derived,
                                          lambda c: jax.lax.scan(segment, c, None, length=chunk), chunk, t0,
                                          record=True)
        else:
            def chunk_of_steps(carry, _):
                return jax.lax.scan(segment, carry, None, length=chunk)

        (final, _), trajectory = jax.lax.scan(chunk_of_steps, start, None, length=num_steps // chunk)
        return final, jax.tree.map(lambda x: x.reshape((num_steps, *x.shape[2:])), trajectory)
    if attempt_length is not None:
        # Each segment of save_every steps, which records its last state only, is tried as
        # free flight first in the same way (then inside the checkpoint, if any), in parts
        # of attempt_length steps where it is longer than a chunk.
        def contact_steps(carry):
            return jax.lax.scan(advance, carry, None, length=attempt_length)[0]

        attempt = _speculative(step, params, derived, contact_steps, attempt_length, t0, record=False)

        if attempt_length == save_every:  # no loop of length 1 (its residuals would be stacked twice)
            segment = attempt
        else:
            def segment(carry, _):
                carry = jax.lax.scan(lambda c, _: (attempt(c, None)[0], None), carry, None,
                                     length=save_every // attempt_length)[0]
                return carry, carry[0]
    if checkpoint:
        # Rematerialise each segment in the backward pass: memory O(num_steps / save_every
        # + save_every) states instead of O(num_steps).
        segment = jax.checkpoint(segment)
    (final, _), trajectory = jax.lax.scan(segment, start, None, length=num_steps // save_every)
    return final, trajectory


def _packed(tree):
    """``(flat, unpack)``: the leaves of ``tree`` as one 1-D array, and the function that
    rebuilds ``tree`` from it; ``(tree, None)`` where the leaves do not share one floating
    dtype (one array would have to convert some of them)."""
    leaves = jax.tree.leaves(tree)
    dtypes = {jnp.result_type(x) for x in leaves}
    if not leaves or len(dtypes) != 1 or not jnp.issubdtype(dtypes.pop(), jnp.inexact):
        return tree, None
    return jax.flatten_util.ravel_pytree(tree)


def _timed(state: State, t0, k, dt: float) -> State:
    """``state`` at time ``t0 + k dt``. Accumulating ``t <- t + dt`` loses ~eps(t) per step:
    in float32 that is 43 ms after 1e5 steps of 1 ms. So t comes from an integer step count."""
    return dataclasses.replace(state, time=t0 + k.astype(t0.dtype) * dt)


def _speculates(step) -> bool:
    """Whether a rollout of ``step`` tries each chunk (``save_every == 1``) or segment
    (``save_every > 1``) as free flight first (see :func:`_speculative`)."""
    return isinstance(step, Step) and bool(step.scene.contact_pairs) and not step.debug


def _speculative(step: Step, params: Params, derived, contact_steps, length: int, t0, record: bool):
    """The body of a loop over groups of ``length`` steps of a scene with contacts: each
    group tried as free flight first, verified, and run again as contact steps
    (``contact_steps(carry) -> (carry, states)``, or ``-> carry`` when ``record`` is
    False) where it was not free. With ``record`` the group is a chunk of a rollout that
    records every state (the states of its steps are stacked); without, a segment of
    ``save_every`` steps, which records its last state only.

    A contact step far from everything (no pair touching at its start, no pair
    closing during its free flight) takes a free-step branch: kick, drift, kick, with
    nothing of the contact stage. Stepped one by one, every step still goes through that
    branch's ``cond``, whose boundary XLA does not fuse across, and whose derivative
    recomputes and transposes the step inside a ``cond`` of its own. Here a group whose
    first state is far from everything runs ``length`` plain free steps instead (one fused
    loop, no ``cond``), testing at each step's start the same condition the contact step
    tests. If every step passed, those are exactly the states the contact steps would
    have produced: the same test chose the same branch, whose arithmetic is the same.
    Otherwise (or when the group starts near a contact) the group runs as contact steps
    from its first state, and the free attempt is discarded. Measured side by side
    (benchmarks/README.md, "Free chunks" and "Free segments"): the 1000-step bouncing
    ball's gradient 26% faster recording every state (5.7 against 7.7 ms), 30% faster
    recording every 10th (5.2 against 7.4 ms); where every group is in contact (a sliding
    box) the forward pays the test, about 6% slower, the gradient 1.5-3%.
    """
    scene, settings, dt = step.scene, step.contact, step.dt

    def far(s):
        return far_from_contact(scene, settings, dt, params, s)

    # Checkpointed: the derivative keeps each step's state, not the free step's
    # intermediates, so the chunk's stacked residuals stay small (see _chunk_length). Inside
    # a scan the recomputation cannot be merged with the forward sweep's, so the barrier
    # that prevent_cse adds does nothing but keep XLA from simplifying across it (the
    # ball's gradient: 88.3 -> 86.4 kernels a step).
    @functools.partial(jax.checkpoint, prevent_cse=False)
    def free_advance(s, k):
        passed = far(s)
        # The free step zeroes the contact impulses (the next contact step's warm start).
        # attempt zeroes them once, before the loop, and the loop carries them through:
        # written at every step, the zeros were a kernel a step (and one in the reverse
        # pass's recomputation), as XLA does not hoist a loop-carried constant.
        s = dataclasses.replace(free_step(scene, step.integrator, settings, dt, params, s, derived),
                                contact_impulse=s.contact_impulse)
        s = _timed(s, t0, k, dt)
        return s, ((dataclasses.replace(s, contact_impulse=None), passed) if record else passed)

    def attempt(carry):
        s, k = carry
        impulse = jnp.zeros_like(s.contact_impulse)
        # The steps' counts are scanned over, not carried: a carried count was an add and a
        # copy a step (XLA copies a loop-carried scalar that is read after its update).
        end, out = jax.lax.scan(free_advance, dataclasses.replace(s, contact_impulse=impulse),
                                k + jnp.arange(1, length + 1, dtype=k.dtype))
        end = (end, k + length)
        if record:
            states, passed = out
            states = dataclasses.replace(states, contact_impulse=jnp.broadcast_to(impulse, (length, *impulse.shape)))
            return jnp.all(passed), (end, states)
        return jnp.all(out), end

    def skip(carry):
        # attempt's output has the carry's types (a scan's carry keeps them), and the
        # recorded states those of the state with a leading axis of ``length``.
        end = jax.tree.map(jnp.zeros_like, carry)
        if record:
            return jnp.zeros((), bool), (end, jax.tree.map(lambda x: jnp.zeros((length, *x.shape), x.dtype), carry[0]))
        return jnp.zeros((), bool), end

    def speculative_steps(carry, _):
        free, flight = branch(far(carry[0]), attempt, skip, carry)
        out = branch(free, lambda c: flight, contact_steps, carry)
        return out if record else (out, out[0])

    return speculative_steps


#: Bytes. XLA:CPU runs the kernels of a loop body one after another, in the calling
#: thread, when no buffer they touch is larger than this (or when they form a chain, each
#: needing the one before, or number at most 8); otherwise through its concurrent
#: executor. The chunked recording this sizes was measured faster (see
#: :func:`_chunk_length`), but the executor's cost alone was not reproduced: a loop of 4
#: or 30 tiny kernels ran in the same time with a 2,400-byte buffer or a 240-byte one
#: (benchmarks/README.md, "One recomputation of the rotations"). A loop or ``cond``
#: counts the buffers of the bodies it holds, even a branch not taken.
#: (``execute_sequential_buffer_threshold`` of XLA's CPU ``ThunkExecutor``: 512 in jaxlib
#: 0.10.2, not settable. A wrong value here costs speed only, never a result.)
SEQUENTIAL_BUFFER_BYTES = 512
#: The most steps one chunk of a recorded rollout stacks (see :func:`_chunk_length`).
MAX_CHUNK = 16
#: The fewest steps a part of a longer segment is tried as free flight in (see
#: :func:`_attempt_length`).
MIN_ATTEMPT = 8


def _attempt_length(save_every: int) -> int | None:
    """Steps tried as free flight at once in a segment of ``save_every`` steps (see
    :func:`_speculative`), or ``None``: not tried, the segment's steps run as contact
    steps, each taking its own free branch where it is far from contact.

    An attempt that fails is discarded whole, so a long one wastes up to its length in free
    steps: a 2,554-step segment with three bounces ran at 0.71 million steps/s tried whole
    and 1.70 million not tried (float32, benchmarks/README.md, "Long segments"). A segment
    of at most :data:`MAX_CHUNK` steps is tried whole; a longer one in parts, the largest
    divisor of ``save_every`` from :data:`MIN_ATTEMPT` to :data:`MAX_CHUNK` (smaller parts
    pay a ``cond`` and a test for too few steps); none where there is no such divisor.
    """
    if save_every <= MAX_CHUNK:
        return save_every
    return _largest_divisor(save_every, MAX_CHUNK, MIN_ATTEMPT)


def _largest_divisor(n: int, most: int, least: int) -> int | None:
    """The largest divisor of ``n`` from ``least`` to ``most``, or ``None``."""
    return next((d for d in range(most, least - 1, -1) if n % d == 0), None)


def _chunk_length(state: State, num_steps: int) -> int:
    """Steps per chunk of a rollout that records every state.

    A loop that stacks each step's state into the whole trajectory touches a buffer of
    the trajectory's size at every step, so XLA:CPU runs every step through its concurrent
    executor (see :data:`SEQUENTIAL_BUFFER_BYTES`). An inner loop over a chunk stacks into
    buffers of ``chunk`` states, which run sequentially when they fit, and the outer loop
    writes each chunk into the trajectory once. The 1000-step bouncing ball's forward
    rollout (float64) ran 25% faster, a sliding box's 22% (benchmarks/README.md,
    "Chunked recording"). Returns the largest divisor of ``num_steps``, at most
    :data:`MAX_CHUNK`, whose stack of each state field fits the threshold; 1 (no chunks)
    where none above 1 does, e.g. a 5-box stack's 60 contact impulses, or a prime
    ``num_steps``. Under ``vmap`` the shapes here are a member's and the batched buffers
    are larger: there chunking was measured neutral (1024 balls, 4096 free bodies).
    """
    largest = max((x.size * x.dtype.itemsize for x in jax.tree.leaves(state)), default=1)
    longest = min(MAX_CHUNK, num_steps, SEQUENTIAL_BUFFER_BYTES // max(largest, 1))
    return _largest_divisor(num_steps, longest, 2) or 1


def _form(tree) -> tuple:
    """A pytree's structure with each leaf's shape and dtype: what a loop's carry must keep."""
    return jax.tree.structure(tree), [(jnp.shape(x), jnp.result_type(x)) for x in jax.tree.leaves(tree)]


def _check_carried_form(step, params, state) -> None:
    """Raise unless ``step(params, state)`` returns a state of the same structure and types
    as ``state`` (what a loop carries). A step of :func:`make_step` wrapped in a function
    or ``jax.jit`` hides its ``prepare``: from an unprepared state it adds fields (the
    rotation matrix of ExplicitEuler, a contact scene's warm-start impulses), and the
    loop failed with JAX's "carry input and carry output must have the same pytree
    structure"."""
    out = jax.eval_shape(step, params, state)
    if _form(state) != _form(out):
        changed = [f.name for f in dataclasses.fields(State)
                   if _form(getattr(state, f.name)) != _form(getattr(out, f.name))]
        raise ValueError(f"step(params, state) returns a state whose {changed} differ from the state's (structure, "
                         f"shape or dtype), so a loop cannot carry it. A step of rb.make_step wrapped in a function "
                         f"or jax.jit needs its state prepared first: state = step.prepare(state), with the step "
                         f"make_step returned (or pass that step to rollout itself).")


def rollout(
    step: Callable[[Params, State], State],
    params: Params,
    state: State,
    num_steps: int,
    *,
    save_every: int = 1,
    checkpoint: bool = False,
    include_initial: bool = False,
) -> tuple[State, State]:
    """Run ``num_steps`` steps as one ``lax.scan``; return ``(final, trajectory)``.

    Args:
        step: ``step(params, state) -> state``, e.g. from :func:`make_step`.
        params, state: the starting point (pytrees of arrays).
        num_steps: number of steps (static).
        save_every: record every k-th state; ``num_steps`` must be a multiple of it.
        checkpoint: rematerialise in the backward pass instead of storing every step
            (for gradients of long rollouts). With ``save_every = k``, reverse mode stores
            one state per k steps plus k inside the segment it recomputes; pick
            ``k ~ sqrt(num_steps)``.
        include_initial: also record the initial state, first.

    With ``save_every=1`` (and ``checkpoint=False``: a checkpointed rollout that records
    every step runs step by step) and a scene of a few bodies, the states are stacked in
    chunks of up to 16 steps by a nested loop, which XLA:CPU runs faster (the 1000-step bouncing
    ball's forward by 25%), with the values of the step-by-step loop. With contacts, a
    chunk (or, with ``save_every > 1``, a segment of ``save_every`` steps, or each part of
    8 to 16 steps of a longer one) that starts far from every contact is first run as
    plain free steps, and kept if none of them came near one (else run again as contact
    steps): the same states, and a gradient a quarter faster for the ball, twice as fast in
    flight. Chunks need a divisor of ``num_steps`` from 2 to 16 (``save_every=1``), parts a
    divisor of ``save_every`` from 8 to 16: a prime ``num_steps`` (997, not 1000) runs each
    step as a contact step (which still skips its contact work far from contact), with the
    same states and without that speed-up.

    Returns:
        ``final``: the state after ``num_steps`` steps. ``trajectory``: the states after
        steps ``k, 2k, ..., num_steps`` stacked along a new leading axis, shape
        ``(num_steps // k, N, ...)`` per field; with ``include_initial`` the initial state
        comes first and the leading axis is one longer. Quantities derived from a
        trajectory come from ``jax.vmap``, e.g.
        ``jax.vmap(rb.kinetic_energy, in_axes=(None, 0))(params, trajectory)``.

    Under ``jax.vmap`` (an ensemble), derivatives skip what no member needs, as the
    forward does (a step's contact work where every member flies, a converged solve's
    sweeps; see ``jaxrb/_branch.py``). That holds for ``jax.grad`` of a vmapped loss, not
    for ``jax.vmap`` of a gradient compiled on its own (``jax.vmap(jax.jit(jax.grad(f)))``),
    which gives the same values more slowly.
    """
    # Any integer type (np.int64 from a config array too), as a Python int: they are static.
    num_steps, save_every = positive_count("num_steps", num_steps), positive_count("save_every", save_every)
    checkpoint = static_switch("checkpoint", checkpoint)
    include_initial = static_switch("include_initial", include_initial)
    if num_steps % save_every:
        raise ValueError(
            f"num_steps ({num_steps}) must be a multiple of save_every ({save_every}); "
            f"e.g. num_steps={num_steps - num_steps % save_every or save_every}."
        )
    if isinstance(step, Step):
        state = step.prepare(state)
        # Before anything reads them: a contact scene's free attempt (far_from_contact) read
        # them first, and batched params without a vmap failed in the narrow phase ("position
        # must have shape (3,)"), a float32 state with float64 params on the loop's carry type.
        step.scene.check_inputs(params, state)
    else:
        _check_carried_form(step, params, state)
    # The vmap, if any, is seen here, outside the jit: inside it the loop is traced for one
    # member, and the derivative rules with it (see _branch.members_differentiated).
    members = any_batched((params, state))
    with members_differentiated(members):
        final, trajectory = _rollout(step, params, state, num_steps, save_every, checkpoint, members)
    if include_initial:
        trajectory = jax.tree.map(lambda x0, xs: jnp.concatenate([x0[None], xs]), state, trajectory)
    return final, trajectory
