"""The colours of one solve: only the pairs that touch, coloured again at run time.

A layout's static colouring (:func:`jaxrb.contact._layout.build_layout`) keeps apart every
two slots that *could* share a body, so it has at least as many colours as the most slots
on one body over all the scene's pairs: 20 for the 5-box stack with ``contacts="all"``
(each box in five pairs of four slots), 82 for 20 boxes. A Gauss-Seidel sweep visits the
colours one after the other, and each visit is a gather, about seven fused kernels and a
scatter, however few of its slots touch. At rest the stack touches in five of its fifteen
pairs (a chain: ground, box 0, ..., box 4), which two colours of pairs hold.

:func:`active_colours` colours the pairs that have an active slot, each time a solve
runs, by rounds over the layout's static pair colours: in round ``k`` the pairs of static
colour ``k`` (which share no body) each take the smallest colour that no active pair
sharing a dynamic body with it holds. A pair's colour is then never above its static one
(that one is free for it: the pairs of earlier rounds avoided it, those of later ones
still hold their own), so there are at most ``num_pair_colours`` colours. Each is
visited ``K`` times (``K`` slots a pair), once for each of its pairs' slots, so that the
slots of one pair, which share both bodies, come one after the other.

Only the step's resting solve (``jaxrb.contact._step._run_solver``, PGS) sweeps these
colours; the impact pass, the split impulse and the exact solver keep the static ones.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._indexing import literal_array
from ._layout import Layout

__all__ = ["active_colours", "solve_colours"]


@functools.lru_cache(maxsize=64)
def _tables(layout: Layout):
    """Static tables of the pairs, ordered by their static pair colour.

    Returns ``(slots, body_a, body_b, bounds, width)``: the pairs' slot indices ``(P + 1,
    K)`` (the last row is the padding slot ``C``); their bodies ``(P,)`` (``N`` is the
    ground, which joins no two pairs); where each static colour's pairs start and end in
    this order; and the most pairs one colour can hold (each has a dynamic body of its own:
    at most ``N``, and at most ``P``)."""
    num_slots = layout.num_slots
    first = {}
    start = 0
    for g in layout.groups:
        for a, b in zip(g.body_a, g.body_b, strict=True):
            first[start] = (list(range(start, start + g.slots)), a, b)
            start += g.slots
    pairs, bounds = [], [0]
    for members in layout.pair_colours:
        pairs += [first[m[0]] for m in members if m[0] != num_slots]
        bounds.append(len(pairs))
    depth = max(len(s) for s, _, _ in pairs)
    table = np.full((len(pairs) + 1, depth), num_slots, np.int32)
    for p, (s, _, _) in enumerate(pairs):
        table[p, :len(s)] = s
    body_a = np.array([a for _, a, _ in pairs], np.int32)
    body_b = np.array([b for _, _, b in pairs], np.int32)
    width = min(len(pairs), layout.num_bodies)
    return table, body_a, body_b, tuple(bounds), width


def _per_pair_active(layout: Layout, table: np.ndarray, active: jax.Array) -> jax.Array:
    """``(P,)`` bool, in the order of ``table``: the pairs with a slot in ``active`` ``(C,)``."""
    padded = jnp.concatenate([active, jnp.zeros((1,), bool)])
    return jnp.any(padded[literal_array(table[:-1])], axis=-1)


def _neighbours(body_a, body_b, num_bodies: int) -> jax.Array:
    """``(P, P)`` float: how many dynamic bodies pair ``q`` shares with pair ``p`` (0 for
    ``p = q``), from the pairs' bodies ``(P,)``."""
    count = 0.0
    for x in (body_a, body_b):
        for y in (body_a, body_b):
            count = count + ((x[:, None] == y[None, :]) & (x[:, None] < num_bodies)).astype(jnp.float32)
    index = jnp.arange(body_a.shape[0])
    return jnp.where(index[:, None] == index[None, :], 0.0, count)


def active_colours(layout: Layout, active: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The slot colours of one solve, and how many of them to visit.

    Args:
        layout: the scene's (static) contact layout, with at least one pair.
        active: ``(C,)`` bool, the slots the solve acts on.

    Returns:
        ``(colours, visits)``: ``colours`` ``(num_pair_colours * K, width)`` int32 slot
        indices (``C`` for padding), of which the first ``visits`` (int32 scalar) hold every
        slot of every pair with an active slot, once; no two slots of one colour share a
        dynamic body. The later rows are padding only. The colouring depends on ``active``
        alone, so it is the same in every sweep of the solve and in its derivative.
    """
    table, body_a, body_b, bounds, width = _tables(layout)
    num_pairs, depth = table.shape[0] - 1, table.shape[1]
    num_colours = len(bounds) - 1
    n = layout.num_bodies
    on = _per_pair_active(layout, table, active)
    neighbours = _neighbours(literal_array(body_a), literal_array(body_b), n)
    palette = jnp.arange(num_colours, dtype=jnp.int32)
    colour = jnp.repeat(palette, np.diff(bounds), total_repeat_length=num_pairs)  # the static colours
    for k in range(num_colours):
        lo, hi = bounds[k], bounds[k + 1]
        if lo == hi:
            continue
        held = ((colour[:, None] == palette[None, :]) & on[:, None]).astype(jnp.float32)  # (P, colours)
        taken = neighbours[lo:hi] @ held  # active neighbours of each colour, for colour k's pairs
        new = jnp.where(on[lo:hi], jnp.argmax(taken == 0, axis=-1).astype(jnp.int32), k)
        colour = jax.lax.dynamic_update_slice(colour, new, (lo,))

    # Each active pair's place in its colour: the active pairs before it of the same colour.
    colour = jnp.where(on, colour, num_colours)
    index = jnp.arange(num_pairs, dtype=jnp.int32)
    place = jnp.sum((colour[:, None] == colour[None, :]) & (index[None, :] < index[:, None]), axis=-1)
    pairs = jnp.full((num_colours + 1, width), num_pairs, jnp.int32)
    pairs = pairs.at[colour, place].set(index, mode="drop")[:num_colours]
    # Colour by colour, each pair's slots in a row (visit ``c K + s`` holds slot ``s`` of the
    # pairs of colour ``c``). Interleaving the pairs' slots instead (``s`` outer) settled
    # the 5-box stack in fewer sweeps at first, but left it needing several sweeps a step
    # for longer (benchmarks/README.md, "A solve's own colours").
    colours = jnp.swapaxes(literal_array(table)[pairs], 1, 2).reshape(num_colours * depth, width)
    visits = depth * (jnp.max(jnp.where(on, colour, -1)) + 1)
    return colours, visits.astype(jnp.int32)


def solve_colours(layout: Layout, active: jax.Array):
    """The colours a resting solve sweeps: :func:`active_colours` where the pairs need more
    than one colour and all have the same number of slots, else the layout's static ones.

    With one colour of pairs (one pair, or balls each on the ground alone) there is nothing
    to gain. With pairs of different sizes (balls beside a box: 1 and 4 slots) each colour
    of pairs would take ``K`` visits whatever its pairs' own sizes, and a sweep that is
    differentiated visits all ``num_pair_colours x K`` of them: two balls and a box on the
    ground, with all pairs, would take 12 visits a sweep against 6 static colours."""
    if len(layout.pair_colours) < 3 or len({g.slots for g in layout.groups}) > 1:
        return literal_array(layout.colours)
    return active_colours(layout, active)
