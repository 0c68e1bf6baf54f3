"""A ``lax.cond`` that still skips its branch under ``jax.vmap`` when no member needs it.

``jax.vmap`` turns a ``lax.cond`` whose predicate is batched into a ``select``: every member
of an ensemble then runs *both* branches, every step. For the contact step that is all its
skipped work at once: all solver sweeps after convergence, the impact pass, the time-of-
impact search, the second part of a split step. :func:`branch` has the same value as
``lax.cond`` but its own batching rule: with a batched predicate it runs the first branch
when some member takes it, the second when some member takes that, and selects per
member (both run only when the members disagree). An ensemble of similar environments
mostly agrees, and then costs what one environment does in kernels.

Derivatives are those of ``lax.cond`` (a ``jax.custom_jvp`` whose rule differentiates
the branch taken), so ``grad`` and ``jvp`` are unchanged. A derivative *of* a ``vmap``
(``grad`` of an ensemble's loss) batches that rule, and a plain ``lax.cond`` in it became a
``select``: every member ran both branches' JVPs (until 2026-12-03; the 8-ball ensemble
of ``benchmarks/ab.py``: 300 steps' gradient in ~400 ms against ~3 ms forward). The rule
takes a per-member form instead (:func:`member_switch`: each branch's JVP under a
``lax.cond`` on whether any member takes it, then a select per member) when it can tell
that it is batched:

* traced under the ``vmap`` itself: a ``vmap`` written around the code (the contact
  solver's over a colour's pairs), ``jax.grad`` of it, ``jax.vmap(jax.grad(f))`` traced in
  one go;
* within :func:`members_differentiated`, which ``rollout`` and ``Step.__call__`` enter
  when a ``vmap`` batches their params or state. A ``vmap`` over a program already
  traced (a ``jit`` or a ``scan`` inside it: ``rollout`` is both) batches the rules
  *after* tracing them unbatched, so they cannot see it themselves.

Not covered: a ``vmap`` of a derivative traced on its own first
(``jax.vmap(jax.jit(jax.grad(f)))``), and a user's own ``lax.scan`` of ``Step`` calls under
``vmap``. Those run both branches' derivatives, with the same values. Unbatched, the
per-member form is exact but costs more, so it is not the only form (see
:func:`members_differentiated`). With ``recompute_in_reverse`` each branch's JVP is
checkpointed: the same values and derivatives, and fewer residuals in reverse mode.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex_core

__all__ = ["branch", "member_cond", "member_switch", "members_differentiated"]

#: Whether the derivative rules traced now belong to an ensemble (see
#: :func:`members_differentiated`).
_MEMBERS = contextvars.ContextVar("jaxrb_members_differentiated", default=False)


@contextlib.contextmanager
def members_differentiated(on: bool = True):
    """Within the ``with``, derivative rules traced (:func:`branch`'s, :func:`member_switch`'s)
    take the per-member form, as if their predicate were batched.

    For code that a ``vmap`` batches as a whole program (a ``jit`` or ``scan`` inside it):
    there JAX traces each rule unbatched and batches the traced rule afterwards, so a rule
    cannot see the batching, and a plain ``lax.cond`` in it becomes a ``select`` (every
    member runs both branches' derivatives). The caller that sees the ``vmap``
    (``rollout``, which knows whether its params or state are batched) says so here. The
    per-member form is exact either way; unbatched it costs a second ``cond`` and a select
    per output (the ball's gradient: 76.8 -> 83.4 kernels a step), which is why it is not
    the only form.
    """
    token = _MEMBERS.set(bool(on))
    try:
        yield
    finally:
        _MEMBERS.reset(token)


def any_batched(tree) -> bool:
    """Whether a ``vmap`` batches any array leaf of ``tree`` here (at trace time). (The probe
    sees each leaf's value, without its tangent: a ``custom_vmap`` has no reverse mode.)"""
    return any(_is_batched(jax.lax.stop_gradient(x)) for x in jax.tree.leaves(tree) if isinstance(x, jax.Array))


def branch(pred, true_fn: Callable, false_fn: Callable, *operands, recompute_in_reverse: bool = False,
           saved=None):
    """``lax.cond(pred, true_fn, false_fn, *operands)``, which ``jax.vmap`` keeps a branch.

    Args:
        pred: scalar bool.
        true_fn, false_fn: functions of ``*operands`` with the same output structure.
        operands: pytrees of arrays (``None`` leaves allowed).
        recompute_in_reverse: differentiate each branch inside a ``jax.checkpoint`` of its
            own. Reverse mode then keeps only the operands between the forward and the
            backward pass, instead of every residual of either branch (see ``_jvp``).
        saved: with ``recompute_in_reverse``, the ``jax.checkpoint`` policy of those
            checkpoints (``None``: save nothing). The contact step passes its named
            quantities (solutions, separations, time of impact), so that no recomputation
            runs a solve or a search again.

    Returns:
        The taken branch's output. Under ``jax.vmap`` with a batched ``pred``: the
        same values as ``lax.cond`` (per member), computed by one branch when all members
        agree.
    """

    # Each branch is traced once here, to a jaxpr of its own: the custom rules below then
    # close over no tracer (custom_vmap refuses functions that do; whatever the branches
    # captured becomes explicit consts), and the batching rule, which knows which branch
    # each of its conds runs, binds that branch alone. (One jaxpr of the whole cond,
    # evaluated with a constant predicate, carried both branches into each: a 64-member
    # stack's rollout lowered to 28,524 lines of StableHLO, 14,176 now.)
    # In the per-member mode each function is traced afresh (a new wrapper): a function
    # traced before for the same shapes (JAX caches by function) would bring the rules of
    # the branches nested in it, traced and memoised in the other mode.
    fresh = _MEMBERS.get()
    (true_jaxpr, true_shape), (false_jaxpr, false_shape) = (
        jax.make_jaxpr((lambda *a, fn=fn: fn(*a)) if fresh else fn, return_shape=True)(*operands)
        for fn in (true_fn, false_fn))
    out_tree = jax.tree.structure(true_shape)
    if jax.tree.structure(false_shape) != out_tree:
        raise TypeError(f"branch: true_fn and false_fn must return the same structure, got {out_tree} "
                        f"and {jax.tree.structure(false_shape)}.")
    out_shape = jax.tree.unflatten(out_tree, [_joined(a, b) for a, b in zip(
        jax.tree.leaves(true_shape), jax.tree.leaves(false_shape), strict=True)])

    def run_branch(take: bool, ops, consts):
        """The branch ``take`` names, alone (no cond)."""
        closed, branch_consts = (true_jaxpr, consts[0]) if take else (false_jaxpr, consts[1])
        out = jex_core.jaxpr_as_fun(jex_core.ClosedJaxpr(closed.jaxpr, branch_consts))(*jax.tree.leaves(ops))
        return jax.tree.unflatten(out_tree, [_as(x, s) for x, s in zip(out, jax.tree.leaves(out_shape), strict=True)])

    def evaluate(p, ops, consts):
        return jax.lax.cond(p, lambda o, c: run_branch(True, o, c), lambda o, c: run_branch(False, o, c), ops, consts)

    @jax.custom_batching.custom_vmap
    def batched(p, ops, consts):
        return evaluate(p, ops, consts)

    @batched.def_vmap
    def _rule(axis_size, in_batched, p, ops, consts):
        p_batched, ops_batched, consts_batched = in_batched
        ops = jax.tree.map(lambda x, b: x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))), ops, ops_batched)
        const_axes = jax.tree.map(lambda b: 0 if b else None, consts_batched)
        # axis_size: with no array operand (None) and unbatched consts, vmap had no axis to read.
        yes = jax.vmap(lambda o, c: run_branch(True, o, c), in_axes=(0, const_axes), axis_size=axis_size)
        no = jax.vmap(lambda o, c: run_branch(False, o, c), in_axes=(0, const_axes), axis_size=axis_size)
        if not p_batched:
            out = jax.lax.cond(p, yes, no, ops, consts)
        else:
            # Each branch once (in a cond of its own, skipped when no member takes it), then
            # a select per member: nesting these does not multiply the compiled code, as
            # three cases (all, none, mixed) would.
            idle = lambda o, c: jax.tree.map(  # noqa: E731
                lambda x: jnp.zeros((axis_size, *x.shape), x.dtype), out_shape)
            a = jax.lax.cond(jnp.any(p), yes, idle, ops, consts)
            b = jax.lax.cond(jnp.all(p), idle, no, ops, consts)
            out = jax.tree.map(lambda x, y: jnp.where(p.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), a, b)
        return out, jax.tree.map(lambda _: True, out)

    differentiable = jax.custom_jvp(batched)

    def branch_jvp(take: bool):
        """The JVP of the branch ``take`` names, alone: ``(o, c, o_dot, c_dot) -> (out, out_dot)``."""
        # (Until 2026-12-02, a cond of both with a constant predicate, which had measured
        # 6-9% faster on the ball's gradient on 2026-11-25. Each linearisation then traced
        # both branches: four branch JVPs a nested level instead of two. Side by side
        # (benchmarks/ab.py, 5 rounds): the same values to the last bit, run times within
        # noise (the ball's gradient 3.555 against 3.512 ms by minima, 3.857 against 3.931 by
        # medians; the dropped box's 132.5 against 128.3, 134.8 against 133.3), and the
        # gradients' programs smaller and faster to trace: the ball's 49,228 -> 40,904 lines
        # of StableHLO (10.8 -> 9.6 s), the box's 86,853 -> 62,314 (30.6 -> 22.5 s), one
        # resolve_impacts of a box landing on a corner 46,597 -> 26,898 (21.1 -> 13.9 s).)
        return lambda o, c, o_dot, c_dot: jax.jvp(lambda o, c: run_branch(take, o, c), (o, c), (o_dot, c_dot))

    @differentiable.defjvp
    def _jvp(primals, tangents):
        p, ops, consts = primals
        _, ops_dot, consts_dot = tangents
        if not recompute_in_reverse:
            return member_cond(p, branch_jvp(True), branch_jvp(False), ops, consts, ops_dot, consts_dot,
                               tangents_from=2)
        # Reverse mode splits a cond into a forward cond that returns the residuals of
        # both branches (the branch not taken returns zeros in the other's slots) and a
        # backward cond that reads them. A branch checkpointed inside the cond still adds
        # its saved intermediates and the integer values it needs to that list: in the
        # bouncing ball's step, 42 slots, which the free branch filled with 35 copies at
        # every step of the backward pass. Here the whole linearisation of each branch is
        # checkpointed, so its residuals are its operands and nothing else (and what
        # ``saved`` names).
        def linearised(take):
            return jax.checkpoint(branch_jvp(take), policy=saved)

        # The cond itself inside a checkpoint as well: its residuals are then the operands as
        # they are, not the cond's outputs (a cond's partial evaluation returns even its
        # operands as new values). In a loop, an operand that does not change (a sweep's
        # frames and masses) is then kept once instead of stacked at every iteration: in the
        # impact pass's eight sweeps, 14 arrays a sweep (``python benchmarks/kernels.py
        # --scene impact``: with the impact pass recomputed, its reverse pass 300.1 -> 288.2
        # kernels a step, the same gradient to the last bit).
        # (The form is read here: inside the checkpoint's trace ``p`` looks unbatched.)
        per_member = _per_member(p)
        return jax.checkpoint(lambda *a: member_cond(a[0], linearised(True), linearised(False), *a[1:],
                                                     per_member=per_member, tangents_from=2),
                              policy=saved)(p, ops, consts, ops_dot, consts_dot)

    return differentiable(pred, tuple(operands), (tuple(true_jaxpr.consts), tuple(false_jaxpr.consts)))


def _joined(a: jax.ShapeDtypeStruct, b: jax.ShapeDtypeStruct) -> jax.ShapeDtypeStruct:
    """The type of an output that either branch may produce, joined as ``lax.cond`` joins
    them: a weakly typed value (a Python scalar's) takes the other branch's dtype."""
    if a.shape == b.shape and a.dtype == b.dtype:
        return jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type and b.weak_type)
    if a.shape == b.shape and a.weak_type != b.weak_type:
        return jax.ShapeDtypeStruct(a.shape, (b if a.weak_type else a).dtype)
    raise TypeError(f"branch: true_fn and false_fn must return the same shapes and dtypes, got "
                    f"{a.dtype}{list(a.shape)} and {b.dtype}{list(b.shape)}.")


def _as(x, like: jax.ShapeDtypeStruct):
    """``x`` with the joined output's type."""
    if not hasattr(x, "dtype"):  # a Python literal a branch returned (a constant True)
        return jnp.asarray(x, like.dtype)
    if x.dtype != like.dtype or (jax.typeof(x).weak_type and not like.weak_type):
        return jax.lax.convert_element_type(x, like.dtype)
    return x


def member_switch(index, branches, *operands, per_member: bool | None = None, tangents_from: int | None = None):
    """``lax.switch(index, branches, *operands)`` for code a custom rule runs (a JVP rule,
    or :func:`branch`'s own), where :func:`branch`, itself a custom rule, does not fit:
    under ``jax.vmap`` with a batched ``index`` each branch runs under a ``lax.cond`` of its
    own on whether any member takes it, and a select per member picks the outputs (a
    plain ``lax.switch`` became a ``select`` there, and every member ran every branch).

    ``index``: int or bool scalar in ``[0, len(branches))``. The batching is read when this
    is called, so call it in the rule itself, not inside a branch of a ``lax.cond`` that
    the rule runs (there the operands it closes over look unbatched, and the plain
    ``lax.switch`` is taken, which is correct but runs every branch), or pass the form
    read there as ``per_member``.

    ``tangents_from``: in a derivative rule, the position of the first operand that is a
    tangent (all after it are too). In the per-member form each branch then sees those
    tangents zeroed for the members that do not take it. A branch run for a member that
    does not take it may have infinite partial derivatives there (its formulas hold only
    where it is taken); its output is dropped by the select, but reverse mode transposes
    the branch, and zero cotangents times those infinities are NaN, which flowed into
    that member's gradient. The zeroed tangent is a select, whose transpose drops them.
    (A float32 ensemble of boxes dropped on the ground: 17 of 64 members' gradients were
    all NaN, each finite alone.)
    """
    if not (_per_member(index) if per_member is None else per_member):
        return jax.lax.switch(index, branches, *operands)
    return _per_member_switch(jnp.asarray(index).astype(jnp.int32), branches, *operands, tangents_from=tangents_from)


def member_cond(pred, true_fn: Callable, false_fn: Callable, *operands, per_member: bool | None = None,
                tangents_from: int | None = None):
    """``lax.cond(pred, true_fn, false_fn, *operands)`` as :func:`member_switch` runs a switch."""
    if not (_per_member(pred) if per_member is None else per_member):
        return jax.lax.cond(pred, true_fn, false_fn, *operands)
    pred = jnp.asarray(pred)
    # As lax.cond reads it: any nonzero pred is true (astype clipped -1 and 0.5 to the false branch).
    index = pred.astype(jnp.int32) if pred.dtype == jnp.bool_ else (pred != 0).astype(jnp.int32)
    return _per_member_switch(index, [false_fn, true_fn], *operands, tangents_from=tangents_from)


def _per_member(index) -> bool:
    return _MEMBERS.get() or _is_batched(index)


def _per_member_switch(index, branches, *operands, tangents_from: int | None = None):
    """:func:`member_switch`'s per-member form."""
    # Clamped into range, as lax.switch clamps its index.
    index = jnp.clip(index, 0, len(branches) - 1)
    shape = jax.eval_shape(branches[0], *operands)
    idle = lambda *_: jax.tree.map(_zeros, shape)  # noqa: E731

    def seen_by(k):
        """The operands branch ``k`` runs on: tangents zeroed where a member does not take it."""
        if tangents_from is None:
            return operands
        takes = index == k
        return (*operands[:tangents_from], *jax.tree.map(
            lambda t: t if jnp.result_type(t) == jax.dtypes.float0 else jnp.where(takes, t, jnp.zeros_like(t)),
            operands[tangents_from:]))

    outs = [jax.lax.cond(_any_member(index == k), fn, idle, *seen_by(k)) for k, fn in enumerate(branches)]
    return jax.tree.map(lambda *x: x[0] if x[0].dtype == jax.dtypes.float0 else jnp.select(
        [index == k for k in range(1, len(x))], list(x[1:]), x[0]), *outs)


def _zeros(like: jax.ShapeDtypeStruct):
    """Zeros of ``like``'s type (a ``float0`` tangent's too)."""
    if like.dtype == jax.dtypes.float0:
        return np.zeros(like.shape, jax.dtypes.float0)
    return jnp.zeros(like.shape, like.dtype)


def _is_batched(x) -> bool:
    """Whether ``x`` is being vmapped here (at trace time): ``custom_vmap`` calls its rule
    when, and only when, a ``vmap`` batches its operand."""
    seen = []

    @jax.custom_batching.custom_vmap
    def probe(x):
        return x

    @probe.def_vmap
    def _(axis_size, in_batched, x):
        seen.append(in_batched[0])
        return x, in_batched[0]

    probe(x)
    return any(seen)


@jax.custom_batching.custom_vmap
def _any_member(p):
    """``p`` (scalar bool) alone; under ``jax.vmap``, whether any member's ``p`` holds, one
    value for all members (unbatched, at every level of nested ``vmap``s)."""
    return p


@_any_member.def_vmap
def _(axis_size, in_batched, p):
    return _any_member(jnp.any(p) if in_batched[0] else p), False
