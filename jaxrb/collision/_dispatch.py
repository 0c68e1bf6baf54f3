"""Pair dispatch: one narrow-phase function per (shape type, shape type), looked up statically.

The table is keyed by shape *types*, which are static scene data, so the lookup happens at
trace time and a scene compiles only the pair functions it declares (as in MuJoCo MJX).
Either order of a supported pair works: ``collide(box, ..., sphere, ...)`` runs
``sphere_box`` with the roles swapped and flips the result (normals negated), so the
normal always points from the **second** shape (B) towards the **first** (A).
"""

from __future__ import annotations

from collections.abc import Callable

from jaxtyping import ArrayLike, Float

from ..shapes import Box, Capsule, Cylinder, Plane, Shape, Sphere
from ._box import box_box
from ._capsule import capsule_box, capsule_capsule, capsule_cylinder
from ._contact import Contact
from ._cylinder import cylinder_box, cylinder_cylinder
from ._geometry import check_unit_quaternion
from ._plane import box_plane, capsule_plane, cylinder_plane, sphere_plane
from ._sphere import sphere_box, sphere_capsule, sphere_cylinder, sphere_sphere

__all__ = ["collide", "max_contacts", "supported_pairs"]


def _with_plane(function):
    """Adapt ``f(shape, pos, ori, plane, margin)`` to the two-pose signature (the plane has no pose)."""

    def adapted(shape_a, position_a, orientation_a, plane, position_b, orientation_b, margin):
        del position_b, orientation_b
        return function(shape_a, position_a, orientation_a, plane, margin)

    return adapted


# (type A, type B) -> (function with signature (a, pa, qa, b, pb, qb, margin), K).
_PAIRS: dict[tuple[type, type], tuple[Callable[..., Contact], int]] = {
    (Sphere, Plane): (_with_plane(sphere_plane), 1),
    (Box, Plane): (_with_plane(box_plane), 4),
    (Capsule, Plane): (_with_plane(capsule_plane), 2),
    (Cylinder, Plane): (_with_plane(cylinder_plane), 5),
    (Sphere, Sphere): (sphere_sphere, 1),
    (Sphere, Box): (sphere_box, 1),
    (Sphere, Capsule): (sphere_capsule, 1),
    (Sphere, Cylinder): (sphere_cylinder, 1),
    (Capsule, Capsule): (capsule_capsule, 2),
    (Capsule, Box): (capsule_box, 2),
    (Capsule, Cylinder): (capsule_cylinder, 2),
    (Cylinder, Box): (cylinder_box, 5),
    (Cylinder, Cylinder): (cylinder_cylinder, 5),
    (Box, Box): (box_box, 4),
}


def supported_pairs() -> list[tuple[str, str]]:
    """The supported ``(A, B)`` shape pairs by class name; each also works as ``(B, A)``."""
    return [(a.__name__, b.__name__) for a, b in _PAIRS]


def _as_type(shape) -> type:
    if isinstance(shape, type) and issubclass(shape, Shape):
        return shape
    if isinstance(shape, Shape):
        return type(shape)
    raise ValueError(f"Expected a jaxrb shape or shape class, got {shape!r}.")


def _lookup(type_a: type, type_b: type) -> tuple[Callable[..., Contact], int, bool]:
    if (type_a, type_b) in _PAIRS:
        function, k = _PAIRS[type_a, type_b]
        return function, k, False
    if (type_b, type_a) in _PAIRS:
        function, k = _PAIRS[type_b, type_a]
        return function, k, True
    names = ", ".join(f"{a}-{b}" for a, b in supported_pairs())
    raise ValueError(
        f"No collision function for the pair ({type_a.__name__}, {type_b.__name__}). Supported pairs "
        f"(in either order): {names}."
    )


def max_contacts(type_a: type[Shape] | Shape, type_b: type[Shape] | Shape) -> int:
    """Static number of contact slots ``K`` that :func:`collide` returns for this pair (either order)."""
    _, k, _ = _lookup(_as_type(type_a), _as_type(type_b))
    return k


def collide(
    shape_a: Shape,
    position_a: Float[ArrayLike, "3"] | None,
    orientation_a: Float[ArrayLike, "4"] | None,
    shape_b: Shape,
    position_b: Float[ArrayLike, "3"] | None = None,
    orientation_b: Float[ArrayLike, "4"] | None = None,
    margin: float = 0.0,
) -> Contact:
    """Narrow phase for one pair of shapes: ``K = max_contacts(A, B)`` masked contact slots.

    Args:
        shape_a, shape_b: static shapes; a :class:`~jaxrb.Plane` may be either one.
        position_a, position_b: ``(3,)`` m, world frame, the centre of each shape's own
            frame (ignored, may be ``None``, for a plane).
        orientation_a, orientation_b: ``(4,)`` unit quaternions, scalar first, shape frame
            to world (ignored, may be ``None``, for a plane). A concrete one whose norm is
            not 1 (to 1e-3) is refused.
        margin: m, ``>= 0``. Slots with ``gap < margin`` are active, so contacts about to
            happen are reported before the shapes touch.

    Returns:
        A :class:`Contact` whose normals point from B towards A. Works under ``jit``,
        ``vmap`` (over poses) and ``grad``.

    Raises:
        ValueError: the pair is not supported (the message lists the supported pairs), a
            pose has the wrong shape, a concrete orientation is not a unit quaternion, or a
            static margin is negative.
    """
    for shape, label in ((shape_a, "shape_a"), (shape_b, "shape_b")):
        if isinstance(shape, type):
            raise ValueError(f"collide: {label} is the class rb.{shape.__name__}; pass a shape with its sizes, "
                             f"e.g. rb.Sphere(0.1) or rb.Plane().")
    function, _, reverse = _lookup(_as_type(shape_a), _as_type(shape_b))
    # Checked here too, under the caller's names (the pair function sees A and B swapped
    # when ``reverse``).
    for shape, label, orientation in ((shape_a, "orientation_a", orientation_a),
                                      (shape_b, "orientation_b", orientation_b)):
        if not isinstance(shape, Plane):
            check_unit_quaternion(label, orientation)
    if reverse:
        return function(shape_b, position_b, orientation_b, shape_a, position_a, orientation_a, margin).flip()
    return function(shape_a, position_a, orientation_a, shape_b, position_b, orientation_b, margin)
