"""A scene's contact slots: which bodies each slot joins, and their detection at one pose.

Everything here that decides *structure* runs once, in Python, when a step is built: the
scene's contact pairs are grouped by their (shape type, shape type) so that each group is one
``jax.vmap`` of one narrow-phase function (a scene compiles only the pair functions it
declares, each once however many sizes of its shapes the scene holds), and the slots are
coloured so that no two slots of one colour move the same body. The solvers then update a
whole colour at once and still do Gauss-Seidel.

Body indices: ``0 .. N-1`` are the scene's bodies, ``N`` is the static ground (zero inverse
mass), ``N + 1`` is a padding body for the unused places of a colour (also static).
"""

from __future__ import annotations

import dataclasses
import random

import jax
import jax.numpy as jnp
import numpy as np

from .. import spatial
from .._indexing import literal_array, take_rows
from ..collision import Contact, collide, concatenate_contacts, max_contacts, supported_pairs
from ..collision._box import box_box_separation
from ..collision._capsule import capsule_box_separation, capsule_cylinder_separation
from ..scene import Scene
from ..shapes import Box, Capsule, Cylinder, Sphere
from ..state import State

__all__ = ["Layout", "bodies_with_slots", "build_layout", "detect", "level_of_pairs", "pair_separations",
           "slot_values", "with_pair_slots"]


@dataclasses.dataclass(frozen=True)
class _Group:
    """Pairs sharing one (shape type A, shape type B): one vmapped narrow-phase call.

    ``shapes_a``, ``shapes_b``: each pair's shapes (a plane for the ground or a wall).
    Where a side's shapes differ in size, the narrow phase reads that side's sizes as
    traced values, one row per pair (:func:`_vmapped`), so the pair function is traced
    once, not once per size: a tower of five differently sized cans traced the
    cylinder-cylinder narrow phase three times, and its step compiled in 62 s."""

    shapes_a: tuple
    shapes_b: tuple
    body_a: tuple[int, ...]
    body_b: tuple[int, ...]  # N for the ground
    pair_index: tuple[int, ...]
    slots: int  # K per pair

    @property
    def shape_a(self):
        """The group's first A shape: its type is every pair's A type."""
        return self.shapes_a[0]

    @property
    def shape_b(self):
        return self.shapes_b[0]

    @property
    def levelled(self) -> bool:
        """Whether the split impulse levels each pair's slots (``ContactSettings.correction_slop``):
        every pair of several slots (all but the sphere pairs), whose slots of one contact
        lie on one face (a box's face on a face or on the ground, a can's cap or side, a
        capsule lying down), and which :func:`level_of_pairs` levels only where the pair
        touches at every active slot. Until stop 78 only box pairs were: levelling every
        touching slot, a can standing off centre on another, its slots overhanging the
        lower cap's rim, was turned back and forth every step (the split impulse moves
        bodies without friction), and the top can of a tower crept 6e-5 m in 0.6 s; with
        the all-active-slots rule it moves 5.7e-6 m once and holds."""
        return self.slots > 1


@dataclasses.dataclass(frozen=True)
class Layout:
    """Static description of a scene's ``C`` contact slots (hashable).

    Attributes:
        num_bodies: ``N``.
        groups: the vmapped narrow-phase calls, in slot order.
        body_a, body_b: ``(C,)`` body index of each slot's A and B (``N``: the ground).
        pair: ``(C,)`` index of each slot's contact pair (for its coefficients).
        colours: ``(num_colours, width)`` slot indices, ``C`` marking padding; no two
            real slots of one colour share a dynamic body.
        pair_colours: ``(num_pair_colours, pairs, K)`` slot indices of the pairs (each
            pair's ``K`` slots in a row, ``K`` the most of any pair), ``C`` marking
            padding; no two pairs of one colour share a dynamic body. The impact pass
            visits the pairs in this order (:func:`jaxrb.contact._solver.collisions`).
        central: every slot's normal passes through the centres of mass of both its bodies
            (centred spheres against each other or the static ground), so a normal impulse makes
            no slip there (the Delassus block's ``K_tn`` is 0) and the impact law needs no
            coupling of friction and restitution (:func:`jaxrb.contact._solver.collisions`).
    """

    num_bodies: int
    groups: tuple[_Group, ...]
    body_a: tuple[int, ...]
    body_b: tuple[int, ...]
    pair: tuple[int, ...]
    colours: tuple[tuple[int, ...], ...]
    pair_colours: tuple[tuple[tuple[int, ...], ...], ...]
    central: bool

    @property
    def num_slots(self) -> int:
        return len(self.body_a)


def _greedy_colouring(body_a, body_b, num_bodies, order) -> list[list[int]]:
    """Slots in ``order``, each given the first colour none of whose slots moves its bodies."""
    colours: list[list[int]] = []
    used: list[set[int]] = []
    for slot in order:
        moving = {x for x in (body_a[slot], body_b[slot]) if x < num_bodies}
        for c, bodies in enumerate(used):
            if not (bodies & moving):
                colours[c].append(slot)
                bodies |= moving
                break
        else:
            colours.append([slot])
            used.append(set(moving))
    return [sorted(c) for c in colours]


#: Greedy colourings tried per scene at most (and at most this many slot visits in all).
_COLOURING_TRIES, _COLOURING_WORK = 64, 200_000


def _colour(body_a, body_b, pair, num_bodies) -> list[list[int]]:
    """Colour the slots so that slots sharing a dynamic body get different colours.

    Every colour is one step of a Gauss-Seidel sweep, so fewer colours is a faster sweep.
    No colouring has fewer colours than the largest number of slots on one body (their
    *degree*); greedy in slot order can need far more (the 5-box stack with all pairs: 28
    against 20, the slots of one pair taking consecutive colours that then clash). So
    greedy colourings are tried in several orders (slot order, then the pairs in random
    permutations from a fixed seed, each pair's slots together or one slot of every pair
    in turn) until one reaches the degree or the tries run out; the fewest colours wins.
    Static (build time) and deterministic.
    """
    slots = len(body_a)
    if slots == 0:
        return []
    degree: dict[int, int] = {}
    for a, b in zip(body_a, body_b, strict=True):
        for x in {a, b}:
            if x < num_bodies:
                degree[x] = degree.get(x, 0) + 1
    bound = max(degree.values(), default=1)
    by_pair: dict[int, list[int]] = {}
    for slot, p in enumerate(pair):
        by_pair.setdefault(p, []).append(slot)
    groups = list(by_pair.values())
    depth = max(len(g) for g in groups)
    rng = random.Random(0)
    best = _greedy_colouring(body_a, body_b, num_bodies, range(slots))
    tries = min(_COLOURING_TRIES, _COLOURING_WORK // slots)
    for t in range(tries):
        if len(best) <= bound:
            break
        perm = groups if t == 0 else rng.sample(groups, len(groups))
        if t % 2 == 0:  # one slot of every pair in turn
            order = [g[k] for k in range(depth) for g in perm if k < len(g)]
        else:  # each pair's slots together
            order = [s for g in perm for s in g]
        candidate = _greedy_colouring(body_a, body_b, num_bodies, order)
        if len(candidate) < len(best):
            best = candidate
    return best


def build_layout(scene: Scene) -> Layout:
    """Group and colour ``scene.contact_pairs`` (static; called when a step is built)."""
    n = scene.num_bodies
    keyed: dict[tuple, list[tuple[int, int, int, object, object]]] = {}
    registered = set(supported_pairs())
    for p, (a, b) in enumerate(scene.contact_pairs):
        ia = scene.index(a)
        ib = n if scene.is_plane(b) else scene.index(b)  # every static plane is the static "body" n
        shape_a = scene.bodies[ia].shape
        shape_b = scene.planes[b] if scene.is_plane(b) else scene.bodies[ib].shape
        if (type(shape_a).__name__, type(shape_b).__name__) not in registered:
            # Held in its pair function's order (a plane is always B already), so that
            # box-cylinder and cylinder-box pairs are one group. The pair is the same:
            # ``collide`` would run that order and flip the normals, which now point
            # from the new B to the new A, the bodies whose slots they are.
            ia, ib, shape_a, shape_b = ib, ia, shape_b, shape_a
        keyed.setdefault((type(shape_a), type(shape_b)), []).append((ia, ib, p, shape_a, shape_b))
    groups = []
    body_a: list[int] = []
    body_b: list[int] = []
    pair: list[int] = []
    for (type_a, type_b), members in keyed.items():
        k = max_contacts(type_a, type_b)
        ia, ib, ip, sa, sb = (tuple(x) for x in zip(*members, strict=True))
        groups.append(_Group(sa, sb, ia, ib, ip, k))
        for a, b, p, _, _ in members:
            body_a += [a] * k
            body_b += [b] * k
            pair += [p] * k
    colours = _colour(body_a, body_b, pair, n)
    width = max((len(c) for c in colours), default=0)
    padded = tuple(tuple(c + [len(body_a)] * (width - len(c))) for c in colours)
    return Layout(n, tuple(groups), tuple(body_a), tuple(body_b), tuple(pair), padded,
                  _pair_colours(body_a, body_b, pair, n), all(_central(scene, g) for g in groups))


def _central(scene: Scene, g: _Group) -> bool:
    """Whether each contact of the group lies on the line through both centres of mass."""
    def centred_sphere(shape, bodies):  # (the group's shapes all have the first one's type)
        return isinstance(shape, Sphere) and not any(any(scene.bodies[i].shape_offset) for i in bodies)
    return centred_sphere(g.shape_a, g.body_a) and (
        all(i == scene.num_bodies for i in g.body_b) or centred_sphere(g.shape_b, g.body_b))


def _pair_colours(body_a, body_b, pair, num_bodies) -> tuple:
    """:attr:`Layout.pair_colours`: the pairs coloured greedily (in pair order), padded."""
    slots: dict[int, list[int]] = {}
    for slot, p in enumerate(pair):
        slots.setdefault(p, []).append(slot)
    if not slots:
        return ()
    pairs = sorted(slots)
    first = [slots[p][0] for p in pairs]
    colours = _greedy_colouring([body_a[s] for s in first], [body_b[s] for s in first], num_bodies,
                                range(len(pairs)))
    width = max(len(c) for c in colours)
    depth = max(len(v) for v in slots.values())
    pad = len(pair)
    padded_slots = [slots[p] + [pad] * (depth - len(slots[p])) for p in pairs]
    return tuple(tuple(tuple(padded_slots[i]) for i in c) + ((pad,) * depth,) * (width - len(c)) for c in colours)


def _pair_blocks(layout: Layout, per_slot: jax.Array) -> list[jax.Array]:
    """Per group, its slots' entries of ``per_slot`` ``(C, ...)`` as one ``(P_g, K, ...)``
    block: each group's slots are its pairs' ``K`` slots in a row, so these are static
    slices and reshapes, not gathers. The per-pair reductions below all read slots so."""
    blocks, start = [], 0
    for g in layout.groups:
        count = len(g.pair_index) * g.slots
        blocks.append(per_slot[start:start + count].reshape(len(g.pair_index), g.slots, *per_slot.shape[1:]))
        start += count
    return blocks


def _spread(g: _Group, per_pair: jax.Array) -> jax.Array:
    """A group's per-pair rows ``(P_g, ...)`` on its slots ``(P_g K, ...)``: each row
    repeated over its pair's ``K`` slots (a broadcast)."""
    rows = per_pair.shape[0]
    return jnp.broadcast_to(per_pair[:, None], (rows, g.slots, *per_pair.shape[1:])).reshape(
        rows * g.slots, *per_pair.shape[1:])


def _joined(parts: list[jax.Array]) -> jax.Array:
    """The groups' slot arrays as one ``(C, ...)``, in slot order.

    Each part zero-padded to its place and the parts added (or-ed, for masks), not
    concatenated: XLA:CPU's fusion emitters (jaxlib 0.10.1 and 0.10.2; its older emitters
    do not) compiled a concatenation of ``_spread`` blocks of two different slot counts,
    fused with its users, into a kernel that crashed the process (SIGSEGV) when it ran: a
    sphere, a can and a capsule in a pen of four walls, at the first impact the step
    located (``tests/test_contact.py::test_a_scene_whose_slot_layout_crashed_xla_cpu_runs``).
    Every position holds one part's value plus zeros, so the values are the same (a
    ``-0.0`` becomes ``+0.0``)."""
    if len(parts) == 1:
        return parts[0]
    total, start, joined = sum(p.shape[0] for p in parts), 0, None
    for part in parts:
        placed = jnp.pad(part, [(start, total - start - part.shape[0])] + [(0, 0)] * (part.ndim - 1))
        joined = placed if joined is None else (joined | placed if part.dtype == bool else joined + placed)
        start += part.shape[0]
    return joined


def _any_per_pair(layout: Layout, mask: jax.Array) -> list[jax.Array]:
    """Per group, whether each of its pairs has a slot in ``mask`` ``(C,)``: ``(P_g,)`` bool."""
    return [jnp.any(block, axis=-1) for block in _pair_blocks(layout, mask)]


def level_of_pairs(layout: Layout, gap: jax.Array, active: jax.Array) -> jax.Array | None:
    """``(C,)`` metres: for each slot of a pair whose slots lie on one face (see
    :attr:`_Group.levelled`) and which rests on all of them, the least overlap (``-gap``,
    ``gap`` ``(C,)``) of its pair's slots; ``+inf`` for other pairs, for pairs with no active
    slot (``active`` ``(C,)``), and for pairs with an active slot apart (``gap > 0``).

    Only a pair touching at every active slot is levelled. A can rocking on its rim (tilted
    7e-3 rad) reaches the ground with the rim point beside its deepest one only by sinking
    0.25 mm at the deepest: levelled to that neighbour, it was lifted by 0.09 mm in one step
    and gained 8.5e-4 J. A body that rests on some of its slots and not on others is
    tilted by more than its overlaps, and its own dynamics, not the correction, lay it
    down. ``None`` where no pair is levelled (a scene of spheres: its step is then as it
    was)."""
    if not any(g.levelled for g in layout.groups):
        return None
    overlap = jnp.where(active, -gap, jnp.inf)
    parts = []
    for g, block in zip(layout.groups, _pair_blocks(layout, overlap), strict=True):
        if g.levelled:
            least = jnp.min(block, axis=-1)
            parts.append(_spread(g, jnp.where(least >= 0, least, jnp.inf)))
        else:
            parts.append(jnp.full((block.size,), jnp.inf, overlap.dtype))
    return _joined(parts)


def with_pair_slots(layout: Layout, mask: jax.Array) -> jax.Array:
    """``(C,)`` bool: the slots of every pair that has a slot in ``mask`` ``(C,)``."""
    return _joined([_spread(g, rows) for g, rows in zip(layout.groups, _any_per_pair(layout, mask), strict=True)])


def bodies_with_slots(layout: Layout, mask: jax.Array) -> jax.Array:
    """``(N,)`` bool: the bodies that have a slot in ``mask`` ``(C,)``.

    By static slices of the per-pair reduction (no scatter, and no index table: built as
    literals, a 60-slot table took 300 lines of StableHLO at each use)."""
    pairs = jnp.concatenate(_any_per_pair(layout, mask))  # group order
    body_a = [a for g in layout.groups for a in g.body_a]
    body_b = [b for g in layout.groups for b in g.body_b]
    rows = [[i for i, ab in enumerate(zip(body_a, body_b, strict=True)) if body in ab]
            for body in range(layout.num_bodies)]
    return jnp.stack([jnp.any(take_rows(pairs, r)) if r else jnp.zeros((), bool) for r in rows])


def slot_values(layout: Layout, per_pair: jax.Array) -> jax.Array:
    """Each slot's entry of a per-pair array: ``(P, ...)`` -> ``(C, ...)``.

    Slots are laid out group by group, each pair's ``K`` slots together, so this is, per
    group, its pairs' rows (static slices) each repeated ``K`` times (a broadcast), and one
    concatenation. Indexing by the ``(C,)`` list of slot pairs instead (60 rows in 15 runs
    for the 5-box stack) made a slice and a broadcast per run: 15 kernels an array, at
    every contact step.
    """
    return _joined([_spread(g, take_rows(per_pair, g.pair_index)) for g in layout.groups])


def _shape_poses(scene: Scene, state: State):
    """World pose of every body's shape frame: ``(N, 3)`` positions, ``(N, 4)`` orientations."""
    offsets = np.asarray([b.shape_offset for b in scene.bodies], dtype=float)
    if not offsets.any():
        # Shapes centred on their bodies (the usual case): no rotation of zero offsets,
        # which XLA cannot fold away (0 * x is not 0 for every float x), and which kept
        # the whole attitude path of the step's separations alive for a ball.
        return state.position, state.orientation
    offsets = literal_array(offsets, state.position.dtype)
    return state.position + spatial.quat_rotate(state.orientation, offsets), state.orientation


def _group_poses(layout: Layout, g: _Group, positions, orientations):
    """Poses of a group's A and B bodies, ``(G, 3)`` and ``(G, 4)``; ``None`` for the ground.
    (Static slices, not gathers: see :mod:`jaxrb._indexing`.)"""
    pa, qa = take_rows(positions, g.body_a), take_rows(orientations, g.body_a)
    if g.body_b[0] == layout.num_bodies:  # the ground has no pose
        return pa, qa, None, None
    return pa, qa, take_rows(positions, g.body_b), take_rows(orientations, g.body_b)


def _group_contacts(g: _Group, pa, qa, pb, qb, margin: float) -> Contact:
    """The group's narrow phase, vmapped over its pairs: fields ``(G, K, ...)``."""
    return _vmapped(g, lambda *x: collide(*x, margin), pa, qa, pb, qb)


def _vmapped(g: _Group, function, pa, qa, pb, qb):
    """``function(shape_a, pa, qa, shape_b, pb, qb)`` vmapped over the group's pairs (``pb``,
    ``qb``: ``None`` for a plane, which has no pose).

    A side whose pairs share one shape passes it as it is (its sizes are constants of the
    program); a side whose shapes differ passes each pair's sizes as traced rows, and
    ``function`` sees a shape of that type built from them (:func:`_sized_like`). The
    pair functions read sizes through ``jnp`` (see
    :func:`jaxrb.collision._geometry.size_vector`), so both give the same arithmetic."""
    sizes_a, sizes_b = (_size_rows(shapes, pa.dtype) for shapes in (g.shapes_a, g.shapes_b))

    def one(rows_a, rows_b, pa, qa, pb, qb):
        shape_a = g.shape_a if rows_a is None else _sized_like(g.shape_a, rows_a)
        shape_b = g.shape_b if rows_b is None else _sized_like(g.shape_b, rows_b)
        return function(shape_a, pa, qa, shape_b, pb, qb)

    return jax.vmap(one)(sizes_a, sizes_b, pa, qa, pb, qb)


def _size_rows(shapes: tuple, dtype):
    """``None`` where every shape is the same; otherwise each size field of the shapes'
    (common) dataclass stacked, ``{name: (G,) or (G, n)}``, in the poses' ``dtype`` (a
    float64 size would promote a float32 scene's gaps) and built from literals (no
    captured array constant: see :func:`jaxrb._indexing.literal_array`)."""
    if all(s == shapes[0] for s in shapes):
        return None
    return {f.name: literal_array([getattr(s, f.name) for s in shapes], dtype) for f in dataclasses.fields(shapes[0])}


def _sized_like(shape, rows: dict):
    """A shape of ``shape``'s type whose size fields are the (traced) ``rows`` of one pair
    (a tuple field as a tuple of scalars, as the shapes store it). Built without the
    constructor, whose checks need concrete numbers: the sizes are the scene's own, checked
    when its shapes were made."""
    sized = object.__new__(type(shape))
    for name, value in rows.items():
        object.__setattr__(sized, name, tuple(value[i] for i in range(value.shape[0])) if value.ndim else value)
    return sized


def pair_separations(scene: Scene, layout: Layout, state: State, margin: float) -> jax.Array:
    """A signed separation of each contact pair ``(P,)``, m, for locating impacts in time.

    Negative when the pair overlaps, zero exactly when it touches, positive when apart, so
    its roots along a motion are the instants of contact. It is the pair's smallest active
    gap (``margin`` when no slot is within it), except for box-box pairs, which use the
    separating axes alone (:func:`jaxrb.collision._box.box_box_separation`; a lower bound
    of the distance when apart), and capsule-box and capsule-cylinder pairs, the gap at the
    segment's closest point alone (:func:`jaxrb.collision._capsule.capsule_box_separation`,
    :func:`~jaxrb.collision._capsule.capsule_cylinder_separation`): the root search
    evaluates this many times, and the clipped box-box manifold and capsule-box's second
    slot, its refined point and its separating axes are the most expensive narrow phases
    to run and to compile.
    """
    positions, orientations = _shape_poses(scene, state)
    dtype = state.position.dtype
    separations, pair_order = [], []
    for g in layout.groups:
        pa, qa, pb, qb = _group_poses(layout, g, positions, orientations)
        if isinstance(g.shape_a, Box) and isinstance(g.shape_b, Box):
            sep = _vmapped(g, box_box_separation, pa, qa, pb, qb)
        elif isinstance(g.shape_a, Capsule) and isinstance(g.shape_b, (Box, Cylinder)):  # (the pair functions' order)
            separation = capsule_box_separation if isinstance(g.shape_b, Box) else capsule_cylinder_separation
            sep = _vmapped(g, separation, pa, qa, pb, qb)
        else:
            contact = _group_contacts(g, pa, qa, pb, qb, margin)
            sep = jnp.min(jnp.where(contact.active, contact.gap, margin), axis=-1)
        separations.append(sep.astype(dtype))
        pair_order.extend(g.pair_index)
    # The groups' pairs in pair order: a permutation by static slices, not a scatter by an
    # index constant (see jaxrb._indexing). Every pair is in exactly one group.
    assert sorted(pair_order) == list(range(scene.num_contact_pairs))
    return take_rows(jnp.concatenate(separations), np.argsort(pair_order))


def detect(scene: Scene, layout: Layout, state: State, margin: float) -> Contact:
    """All ``C`` contact slots of the scene at ``state``: a :class:`Contact` with ``(C, ...)`` fields.

    Normals point from B to A (A is the pair's first body; the ground is always B).
    """
    positions, orientations = _shape_poses(scene, state)
    parts = []
    for g in layout.groups:
        contact = _group_contacts(g, *_group_poses(layout, g, positions, orientations), margin)
        parts.append(Contact(
            point=contact.point.reshape(-1, 3),
            normal=contact.normal.reshape(-1, 3),
            gap=contact.gap.reshape(-1),
            active=contact.active.reshape(-1),
        ))
    return concatenate_contacts(parts)
