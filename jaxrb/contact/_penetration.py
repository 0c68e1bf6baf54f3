"""How deep the scene's bodies overlap: for checks, the debug mode and benchmarks."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..scene import Scene
from ..shapes import Cylinder
from ..state import State
from ._layout import detect
from ._step import layout_of

__all__ = ["penetration", "thinnest_size"]


def penetration(scene: Scene, state: State) -> Float[Array, ""]:
    """The deepest overlap of any of the scene's contact pairs at ``state``, in metres.

    ``0`` when nothing overlaps (or the scene declares no contact pairs). One narrow-phase
    pass over the declared pairs; works under ``jit``, ``vmap`` and ``grad``.
    """
    scene.check_state_shapes(state)
    if not scene.contact_pairs:
        return jnp.zeros((), state.position.dtype)
    contact = detect(scene, layout_of(scene), state, 0.0)
    return jnp.max(jnp.where(contact.active, jnp.maximum(-contact.gap, 0.0), 0.0))


def thinnest_size(scene: Scene) -> float | None:
    """The smallest radius, half extent or cylinder half-length (m) among the bodies in the
    scene's contact pairs. (A capsule's half-length is its segment's, not a thickness.)"""
    sizes = []
    for name in {n for pair in scene.contact_pairs for n in pair if not scene.is_plane(n)}:
        shape = scene.bodies[scene.index(name)].shape
        sizes += [getattr(shape, "radius", float("inf")), *getattr(shape, "half_extents", ())]
        if isinstance(shape, Cylinder):  # a coin: its half-thickness, not its radius
            sizes.append(shape.half_length)
    return min(sizes) if sizes and min(sizes) < float("inf") else None
