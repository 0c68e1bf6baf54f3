"""Mass properties: mass, centre of mass and inertia tensor of bodies and their parts.

The inertia tensor of a body about its centre of mass (seed 001, "Rigid bodies
dynamics"; seed 000, "Inertia Tensor") is

    I = integral of rho (|r|^2 E - r r^T) dV = sum_i -m_i r~_i r~_i,    r = x - x_cm,

with ``E`` the 3x3 identity and ``r~`` the cross-product matrix. Seed 001 prints the
matrix form with typos: its (3, 3) entry reads ``rho (r_x^2 - r_y^2)`` (it is
``r_x^2 + r_y^2``), and its second, ``dx dy dz`` form drops the minus signs of the
products of inertia and writes ``x^2 + z^2`` in the (1, 1) entry (it is ``y^2 + z^2``).

Frames and units. SI units throughout (kg, m, kg m^2). A :class:`MassProperties` is
expressed in one frame: ``com`` is a position in that frame and ``inertia`` is taken about
``com`` along that frame's axes. Every primitive shape's frame has its origin at its
centre of mass and its axes along the shape's symmetry axes, with the symmetry axis of
rods, disks, cylinders, capsules and cones along **z** (see :mod:`jaxrb.shapes`); sizes
are *half* sizes, except a cone's ``height``, which is its full height. Seed 001's table
puts the axis of the rod, cylinder and cone along x and uses full lengths; each
primitive's docstring maps its row to these conventions and says where the printed row
is garbled.

Differentiability. The primitive functions (:func:`box`, :func:`cylinder`, ...),
:func:`from_point_masses`, :func:`from_mesh`, :func:`compose` and
:func:`principal_axes` take and return arrays and work under ``jit``, ``vmap`` and
``grad``, in float32 and float64 (this module never enables x64). 3x3 products are
element-wise (:mod:`jaxrb.spatial`), never ``@``, so GPUs cannot run them in TF32.
:func:`mass_properties` and :func:`volume` read static :mod:`jaxrb.shapes` sizes;
:func:`check_mass_properties` is a NumPy-side check for scene build time.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from jaxrb import shapes, spatial
from jaxrb.spatial import cross, dot, matmul, matrix_to_quat, matvec, quat_to_matrix, skew, transpose

__all__ = [
    "MassProperties",
    "mass_properties",
    "volume",
    "sphere",
    "hollow_sphere",
    "box",
    "cylinder",
    "elliptical_cylinder",
    "cone",
    "ellipsoid",
    "capsule",
    "rod",
    "plate",
    "disk",
    "from_point_masses",
    "from_mesh",
    "compose",
    "principal_axes",
    "repeated_moment_coupling",
    "check_mass_properties",
    "check_mass",
    "check_inertia",
]


# ----------------------------------------------------------------------------- container


def _parallel_axis(
    mass: Float[Array, "..."], offset: Float[Array, "... 3"]
) -> Float[Array, "... 3 3"]:
    """``m (|d|^2 E - d d^T)``, written as seed 000's ``-m d~ d~``."""
    d_tilde = skew(offset)
    return -jnp.asarray(mass)[..., None, None] * matmul(d_tilde, d_tilde)


class MassProperties(eqx.Module):
    """Mass, centre of mass and central inertia of a rigid body or part, in one frame.

    Attributes:
        mass: ``()``, kg.
        com: ``(3,)``, m: the centre of mass, in the frame the part is described in.
        inertia: ``(3, 3)``, kg m^2: the inertia tensor about ``com``, along the axes of
            that same frame.
    """

    mass: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    com: Float[Array, "3"] = eqx.field(converter=jnp.asarray)
    inertia: Float[Array, "3 3"] = eqx.field(converter=jnp.asarray)

    def transformed(
        self,
        position: Float[ArrayLike, "3"],
        orientation: Float[ArrayLike, "4"] | None = None,
    ) -> MassProperties:
        """The same part moved rigidly: its frame placed at ``position`` with ``orientation``.

        Args:
            position: ``(3,)``, m: where the part's frame origin goes, in the parent frame.
            orientation: ``(4,)`` unit quaternion, scalar first, part frame -> parent
                frame; ``None`` for no rotation. A concrete one whose norm is not 1 is
                refused, as :meth:`jaxrb.Scene.state` refuses it: ``R`` is read by the unit
                quaternion's formula, so ``(1, 0, 0, 1)`` (90 degrees about z, unnormalised)
                gave a sphere the moments (0.02, 0.02, 0.004) for 0.004 each.

        Returns:
            The part in the parent frame: ``com' = position + R com`` and
            ``inertia' = R I R^T`` (seed 000: ``I = A I_bar A^T``).
        """
        position = jnp.asarray(position)
        if orientation is None:
            return MassProperties(self.mass, position + self.com, self.inertia)
        if not isinstance(orientation, jax.core.Tracer):
            norms, bad = spatial.non_unit_norms(orientation)
            if np.any(bad):
                raise ValueError(f"MassProperties.transformed: orientation is not a unit quaternion (norm "
                                 f"{float(np.max(norms[bad])):.6g}). "
                                 + spatial.UNIT_QUATERNION_ADVICE)
        rotation = quat_to_matrix(orientation)
        com = position + matvec(rotation, self.com)
        inertia = matmul(matmul(rotation, self.inertia), transpose(rotation))
        # R I R^T is symmetric; its rounding is not (about 1e-8 relative in float32, which
        # Body's symmetry check, at 1e-9, refused). Symmetrising is exact in exact arithmetic.
        return MassProperties(self.mass, com, 0.5 * (inertia + transpose(inertia)))

    def shifted_inertia(self, point: Float[ArrayLike, "3"]) -> Float[Array, "3 3"]:
        """Inertia (kg m^2) about ``point`` (m, same frame), by the parallel-axis theorem.

        ``I_point = I + m (|d|^2 E - d d^T)`` with ``d = com - point``.
        """
        return self.inertia + _parallel_axis(self.mass, self.com - jnp.asarray(point))

    def principal(self) -> tuple[MassProperties, Float[Array, "4"]]:
        """The same part described in its principal frame, and where that frame sits.

        Returns:
            ``(principal_part, orientation)``: ``principal_part`` has ``com = 0`` and a
            diagonal inertia with ascending moments; ``orientation`` is the unit
            quaternion (scalar first) of the principal axes in this part's frame, so
            ``principal_part.transformed(self.com, orientation)`` is ``self`` again. Use
            it to build a body whose body axes are its principal axes (e.g. to spin it
            about its intermediate axis), and to place that body in the world.
        """
        moments, axes = principal_axes(self.inertia)
        zero = jnp.zeros_like(self.com)
        eye = jnp.eye(3, dtype=moments.dtype)
        part = MassProperties(self.mass, zero, eye * moments[None, :])
        return part, matrix_to_quat(axes)


def _central(mass: ArrayLike, ix: ArrayLike, iy: ArrayLike, iz: ArrayLike) -> MassProperties:
    """A part whose frame is at its com with principal axes along x, y, z."""
    ix, iy, iz = jnp.broadcast_arrays(ix, iy, iz)
    zero = jnp.zeros_like(ix)
    inertia = jnp.stack(
        [
            jnp.stack([ix, zero, zero], axis=-1),
            jnp.stack([zero, iy, zero], axis=-1),
            jnp.stack([zero, zero, iz], axis=-1),
        ],
        axis=-2,
    )
    com = jnp.zeros((*ix.shape, 3), dtype=ix.dtype)
    return MassProperties(jnp.asarray(mass), com, inertia)


def _concrete_array(x) -> np.ndarray | None:
    """``x`` as a float NumPy array, or ``None`` while it is being traced."""
    if isinstance(x, jax.core.Tracer):
        return None
    return np.asarray(x, dtype=float)


def _check_sizes(what: str, mass, zero_allowed: tuple = (), **sizes) -> None:
    """Concrete values only (traced ones pass): the mass and every size must be finite and
    positive (the sizes named in ``zero_allowed`` may be 0). The shape classes check their
    sizes; these functions had taken a negative radius or mass without a word."""
    for name, value in {"mass": mass, **sizes}.items():
        array = _concrete_array(value)
        if array is None:
            continue
        low_ok = array >= 0 if name in zero_allowed else array > 0
        if not np.all(np.isfinite(array) & low_ok):
            bound = ">= 0" if name in zero_allowed else "> 0"
            unit = "kg" if name == "mass" else "m"
            raise ValueError(f"{what}: {name} must be finite and {bound} ({unit}), got {value!r}.")


# ---------------------------------------------------------------------------- primitives
# Each takes the mass (kg) and half sizes (m) as arrays and returns the part in its own
# frame (com at the origin). Seed 001 gives full lengths; with L = 2 * half_length,
# m L^2 / 12 = m half_length^2 / 3, which is the form used below. Concrete inputs are
# checked (_check_sizes); traced ones are not.


def sphere(mass: Float[ArrayLike, ""], radius: Float[ArrayLike, ""]) -> MassProperties:
    """Solid sphere: ``I = 2/5 m r^2 E`` (seed 001's sphere row, printed correctly)."""
    _check_sizes("sphere", mass, radius=radius)
    mass, radius = jnp.asarray(mass), jnp.asarray(radius)
    i = 0.4 * mass * radius**2
    return _central(mass, i, i, i)


def hollow_sphere(
    mass: Float[ArrayLike, ""],
    radius: Float[ArrayLike, ""],
    thickness: Float[ArrayLike, ""] = 0.0,
) -> MassProperties:
    """Spherical shell of outer ``radius`` (m) and wall ``thickness`` (m), ``0 <= t < r``.

    Thick shell, inner radius ``s = r - t``: ``I = 2/5 m (r^5 - s^5) / (r^3 - s^3) E``.
    Thin shell (``t = 0``): ``I = 2/3 m r^2 E``, the limit of the thick formula.
    """
    _check_sizes("hollow_sphere", mass, ("thickness",), radius=radius, thickness=thickness)
    r_value, t_value = _concrete_array(radius), _concrete_array(thickness)
    if r_value is not None and t_value is not None and np.any(t_value >= r_value):
        raise ValueError(f"hollow_sphere: the wall thickness {thickness!r} must be less than the radius {radius!r} "
                         f"(m): thickness = radius is a solid sphere (use sphere()).")
    mass, radius = jnp.asarray(mass), jnp.asarray(radius)
    inner = radius - jnp.asarray(thickness)
    # (r^5 - s^5)/(r^3 - s^3) is 0/0 at t = 0; dividing out the common factor (r - s)
    # leaves a ratio of polynomials whose value (5/3 r^2) and derivatives are finite there.
    r, s = radius, inner
    numerator = r**4 + r**3 * s + r**2 * s**2 + r * s**3 + s**4
    denominator = r**2 + r * s + s**2
    i = 0.4 * mass * numerator / denominator
    return _central(mass, i, i, i)


def box(mass: Float[ArrayLike, ""], half_extents: Float[ArrayLike, "3"]) -> MassProperties:
    """Solid box with ``half_extents = (a, b, c)`` (m) along x, y, z.

    ``I = m/3 diag(b^2 + c^2, a^2 + c^2, a^2 + b^2)``. Seed 001's rectangular prism row,
    ``1/12 m (b^2 + c^2)`` with full lengths (depth x, height y, width z), only shows
    ``I_x``; the others follow by permutation.
    """
    _check_sizes("box", mass, half_extents=half_extents)
    mass, half_extents = jnp.asarray(mass), jnp.asarray(half_extents)
    a2, b2, c2 = half_extents[..., 0] ** 2, half_extents[..., 1] ** 2, half_extents[..., 2] ** 2
    third = mass / 3.0
    return _central(mass, third * (b2 + c2), third * (a2 + c2), third * (a2 + b2))


def cylinder(
    mass: Float[ArrayLike, ""], radius: Float[ArrayLike, ""], half_length: Float[ArrayLike, ""]
) -> MassProperties:
    """Solid circular cylinder, axis along z.

    ``I_z = 1/2 m r^2``, ``I_x = I_y = m (r^2/4 + h^2/3)`` with ``h = half_length``.
    Seed 001 (axis along x, full length ``l``) shows only ``1/12 m (3 r^2 + l^2)`` for
    the transverse moments; its axial moment ``1/2 m r^2`` is missing from the row.
    """
    _check_sizes("cylinder", mass, radius=radius, half_length=half_length)
    mass, radius, half_length = map(jnp.asarray, (mass, radius, half_length))
    transverse = mass * (0.25 * radius**2 + half_length**2 / 3.0)
    return _central(mass, transverse, transverse, 0.5 * mass * radius**2)


def elliptical_cylinder(
    mass: Float[ArrayLike, ""], semi_axes: Float[ArrayLike, "2"], half_length: Float[ArrayLike, ""]
) -> MassProperties:
    """Solid cylinder of elliptical cross-section, axis along z.

    ``semi_axes = (a, b)`` along x and y, ``h = half_length``:
    ``I_x = m (b^2/4 + h^2/3)``, ``I_y = m (a^2/4 + h^2/3)``, ``I_z = m (a^2 + b^2)/4``.

    Seed 001 names the axes differently: "l = length (x), b = height/2 (y),
    c = width/2 (z)". Its x, y, z are our z, x, y (a cyclic relabelling, so still
    right-handed): its ``b`` is our ``a``, its ``c`` our ``b``, its ``l`` is ``2 h``.
    The three values it prints are right, but in the order ``I_y = 1/12 m (3c^2 + l^2)``,
    ``I_z = 1/12 m (3b^2 + l^2)``, ``I_x = 1/4 m (b^2 + c^2)`` of its own axes: the axial
    moment comes last although its heading says ``I_x``.
    """
    _check_sizes("elliptical_cylinder", mass, semi_axes=semi_axes, half_length=half_length)
    mass, semi_axes, half_length = map(jnp.asarray, (mass, semi_axes, half_length))
    a2, b2 = semi_axes[..., 0] ** 2, semi_axes[..., 1] ** 2
    length_term = half_length**2 / 3.0
    return _central(
        mass,
        mass * (0.25 * b2 + length_term),
        mass * (0.25 * a2 + length_term),
        0.25 * mass * (a2 + b2),
    )


def cone(
    mass: Float[ArrayLike, ""], radius: Float[ArrayLike, ""], height: Float[ArrayLike, ""]
) -> MassProperties:
    """Solid circular cone, axis along +z, about its centre of mass (``h/4`` above the base).

    ``I_z = 3/10 m r^2`` and ``I_x = I_y = 3/20 m r^2 + 3/80 m h^2``.

    Seed 001's row is garbled: it prints ``3/5 m (1/4 r^2 + 1/2)``; the ``1/2`` is ``h^2``,
    and ``3/5 m (r^2/4 + h^2)`` is the transverse moment about the **apex**, not the
    centre of mass. The apex is ``3h/4`` from the com, so by the parallel-axis theorem
    ``3/5 m (r^2/4 + h^2) - m (3h/4)^2 = 3/20 m r^2 + 3/80 m h^2``.
    """
    _check_sizes("cone", mass, radius=radius, height=height)
    mass, radius, height = map(jnp.asarray, (mass, radius, height))
    transverse = mass * (0.15 * radius**2 + 0.0375 * height**2)
    return _central(mass, transverse, transverse, 0.3 * mass * radius**2)


def ellipsoid(mass: Float[ArrayLike, ""], semi_axes: Float[ArrayLike, "3"]) -> MassProperties:
    """Solid ellipsoid with ``semi_axes = (a, b, c)`` (m) along x, y, z.

    ``I = m/5 diag(b^2 + c^2, a^2 + c^2, a^2 + b^2)``: seed 001's row, which holds for
    **semi**-axes (its labels "depth, height, width" would suggest full lengths, for
    which the factor would be 1/20).
    """
    _check_sizes("ellipsoid", mass, semi_axes=semi_axes)
    mass, semi_axes = jnp.asarray(mass), jnp.asarray(semi_axes)
    a2, b2, c2 = semi_axes[..., 0] ** 2, semi_axes[..., 1] ** 2, semi_axes[..., 2] ** 2
    fifth = mass / 5.0
    return _central(mass, fifth * (b2 + c2), fifth * (a2 + c2), fifth * (a2 + b2))


def capsule(
    mass: Float[ArrayLike, ""], radius: Float[ArrayLike, ""], half_length: Float[ArrayLike, ""]
) -> MassProperties:
    """Cylinder (``radius``, ``half_length`` h, axis z) capped by two solid hemispheres.

    The mass is split by volume (uniform density) between the cylinder,
    ``2 pi r^2 h``, and the two caps, ``4/3 pi r^3``. Each cap's com lies ``3r/8`` from
    its flat face, i.e. ``h + 3r/8`` from the capsule's centre.
    ``I_z = 1/2 m_cyl r^2 + 2/5 m_caps r^2``;
    ``I_x = I_y = m_cyl (r^2/4 + h^2/3) + m_caps (2/5 r^2 - (3r/8)^2 + (h + 3r/8)^2)``.
    """
    _check_sizes("capsule", mass, ("half_length",), radius=radius, half_length=half_length)
    mass, radius, half_length = map(jnp.asarray, (mass, radius, half_length))
    r, h = radius, half_length
    cylinder_volume = 2.0 * h * r**2  # pi dropped: only the ratio matters
    caps_volume = 4.0 / 3.0 * r**3
    m_cylinder = mass * cylinder_volume / (cylinder_volume + caps_volume)
    m_caps = mass - m_cylinder
    # A hemisphere's moment about a diameter of its flat face is the full sphere's
    # 2/5 m r^2, but that axis is not through its com: move it to the com (subtract the
    # 3r/8 offset's term) before moving it out to the capsule's centre (add h + 3r/8).
    cap_offset = 0.375 * r
    caps_transverse = m_caps * (0.4 * r**2 - cap_offset**2 + (h + cap_offset) ** 2)
    transverse = m_cylinder * (0.25 * r**2 + h**2 / 3.0) + caps_transverse
    axial = 0.5 * m_cylinder * r**2 + 0.4 * m_caps * r**2
    return _central(mass, transverse, transverse, axial)


def rod(mass: Float[ArrayLike, ""], half_length: Float[ArrayLike, ""]) -> MassProperties:
    """Slender rod along z with no thickness: ``I = diag(m L^2/12, m L^2/12, 0)``, ``L = 2h``.

    Seed 001's row (axis along x: ``I_x = 0``, ``I_y = I_z = 1/12 m l^2``) relabelled.
    The inertia is singular, so a rod can only be a part of a body.
    """
    _check_sizes("rod", mass, half_length=half_length)
    mass, half_length = jnp.asarray(mass), jnp.asarray(half_length)
    transverse = mass * half_length**2 / 3.0
    return _central(mass, transverse, transverse, jnp.zeros_like(transverse))


def plate(mass: Float[ArrayLike, ""], half_extents: Float[ArrayLike, "2"]) -> MassProperties:
    """Thin rectangular plate in the x-y plane, ``half_extents = (a, b)``, normal z.

    ``I = m/3 diag(b^2, a^2, a^2 + b^2)``, on the boundary ``I_x + I_y = I_z`` of the
    triangle inequality. Seed 001's plate has its normal along x, height ``b`` (y) and
    width ``c`` (z), full lengths: it prints ``I_x = 1/12 m (b^2 + c^2)`` and
    ``I_z = 1/12 m b^2``; the missing ``I_y`` is ``1/12 m c^2``.
    """
    _check_sizes("plate", mass, half_extents=half_extents)
    mass, half_extents = jnp.asarray(mass), jnp.asarray(half_extents)
    a2, b2 = half_extents[..., 0] ** 2, half_extents[..., 1] ** 2
    third = mass / 3.0
    return _central(mass, third * b2, third * a2, third * (a2 + b2))


def disk(mass: Float[ArrayLike, ""], radius: Float[ArrayLike, ""]) -> MassProperties:
    """Thin circular disk in the x-y plane, normal z: ``I = m r^2 diag(1/4, 1/4, 1/2)``.

    Seed 001's thin-disk row lost one entry; the values are ``1/4 m r^2`` about a
    diameter and ``1/2 m r^2`` about the normal.
    """
    _check_sizes("disk", mass, radius=radius)
    mass, radius = jnp.asarray(mass), jnp.asarray(radius)
    diameter = 0.25 * mass * radius**2
    return _central(mass, diameter, diameter, 2.0 * diameter)


# ----------------------------------------------------------------- particles and meshes


def from_point_masses(
    masses: Float[ArrayLike, " n"], positions: Float[ArrayLike, "n 3"]
) -> MassProperties:
    """Mass properties of a cloud of point masses: seed 000's pre-compute, step for step.

    ``M = sum m_i``; ``x_cm = sum m_i x_i / M``; ``r_i = x_i - x_cm``;
    ``I = sum -m_i r~_i r~_i``. (The seed's algorithm slide writes ``-m_i r r^T``; its
    inertia-tensor slide has the right ``-m_i r~_i r~_i``.)

    Args:
        masses: ``(n,)``, kg.
        positions: ``(n, 3)``, m, in any frame.

    Returns:
        The body in that same frame: ``com = x_cm``, inertia about ``x_cm``.
    """
    masses, positions = jnp.asarray(masses), jnp.asarray(positions)
    if masses.ndim != 1 or positions.shape != (*masses.shape, 3):
        raise ValueError(f"from_point_masses: masses must have shape (n,) and positions (n, 3), got "
                         f"{masses.shape} and {positions.shape}.")
    known = None if isinstance(masses, jax.core.Tracer) else np.asarray(masses, dtype=float)
    if known is not None and not (np.all(np.isfinite(known)) and np.all(known >= 0) and known.sum() > 0):
        # A zero total (or masses of both signs) put the com at inf or NaN without a word.
        raise ValueError(f"from_point_masses: masses must be finite and >= 0 with a positive total (kg), "
                         f"got {known}.")
    # A NaN position had given a NaN inertia, and an infinite one a com of [inf, 0, 0].
    where = _concrete_array(positions)
    if where is not None and not np.all(np.isfinite(where)):
        raise ValueError(f"from_point_masses: positions must be finite (m); rows "
                         f"{np.flatnonzero(~np.all(np.isfinite(where), axis=1)).tolist()} are not.")
    return _point_masses(masses, positions)


# The kernels below are jitted so that eager calls (at scene build time) compile once per
# input shape instead of dispatching and compiling dozens of small operations one by one;
# inside a caller's jit they are simply inlined.
@jax.jit
def _point_masses(masses, positions):
    total = jnp.sum(masses)
    com = jnp.sum(masses[:, None] * positions, axis=0) / total
    offsets = positions - com[None, :]
    inertia = jnp.sum(_parallel_axis(masses, offsets), axis=0)
    return MassProperties(total, com, inertia)


def _check_mass_or_density(density, mass, what: str) -> None:
    if (density is None) == (mass is None):
        raise ValueError(
            f"{what}: give exactly one of density= (kg/m^3) or mass= (kg), "
            f"got density={density!r}, mass={mass!r}."
        )
    # A concrete value must be positive and finite (a traced one passes): density=-1000 had
    # given a negative mass without a word.
    name, value = ("density", density) if density is not None else ("mass", mass)
    array = _concrete_array(value)  # every entry: mass=[-1.0] had passed where -1.0 did not
    if array is not None and not np.all(np.isfinite(array) & (array > 0)):
        unit = "kg/m^3" if name == "density" else "kg"
        raise ValueError(f"{what}: {name} must be positive and finite ({unit}), got {value!r}.")


def _concrete_float(x) -> float | None:
    """``float(x)``, or ``None`` while ``x`` is being traced (under jit, grad, vmap)."""
    try:
        return float(x)
    except (jax.errors.ConcretizationTypeError, TypeError):
        return None


def _inside_out_message(volume: float | str) -> str:
    return (
        f"from_mesh: the mesh's signed volume is {volume} m^3, but it must be positive. "
        "The mesh is open or inside-out: check the face orientation (vertices of every "
        "triangle counter-clockwise seen from outside, so normals point out); reversing "
        "each face's vertex order fixes an inside-out mesh."
    )


def from_mesh(
    vertices: Float[ArrayLike, "v 3"],
    faces: Int[ArrayLike, "f 3"],
    *,
    density: Float[ArrayLike, ""] | None = None,
    mass: Float[ArrayLike, ""] | None = None,
) -> MassProperties:
    """Mass properties of a solid bounded by a closed triangle mesh, uniform density.

    The divergence theorem turns the volume integrals into a sum over signed tetrahedra
    that join each face ``(a, b, c)`` to a common apex. With ``D = a . (b x c)`` (six
    times the signed volume), each tetrahedron adds ``D/6`` to the volume, ``D/24 s`` to
    ``integral x dV`` and ``D/120 (a a^T + b b^T + c c^T + s s^T)`` to
    ``integral x x^T dV``, where ``s = a + b + c`` (exact for polyhedra). The inertia
    about the com is then ``m (tr(C) E - C)`` with ``C`` the second moment per unit mass
    about the com.

    Args:
        vertices: ``(v, 3)``, m, in the mesh's frame.
        faces: ``(f, 3)`` integer vertex indices, each triangle counter-clockwise seen
            from outside (outward normals).
        density: kg/m^3, or
        mass: kg (exactly one of the two).

    Returns:
        The body in the mesh's frame (``com`` need not be the origin).

    Raises:
        ValueError: neither or both of ``density``/``mass``; a mesh that is not closed
            and consistently oriented (checked where ``vertices`` and ``faces`` are
            concrete, as :class:`jaxrb.shapes.Mesh` checks them), or with a connected
            part that encloses no volume beyond rounding (a flat one); or a signed volume
            ``<= 0`` (an inside-out mesh). Under ``jit``/``grad``/``vmap`` the volume is
            not known at trace time, and that message comes from ``eqx.error_if`` at run
            time instead (the closure is then not checked).
    """
    _check_mass_or_density(density, mass, "from_mesh")
    if not isinstance(vertices, jax.core.Tracer) and not isinstance(faces, jax.core.Tracer):
        shapes.check_mesh(vertices, faces, "from_mesh")
    signed_volume, com, unit_inertia = _mesh_moments(jnp.asarray(vertices), jnp.asarray(faces))
    known_volume = _concrete_float(signed_volume)
    if known_volume is not None:
        if not known_volume > 0.0:
            raise ValueError(_inside_out_message(known_volume))
    else:
        # Attached to the outputs, not to the volume, which is unused when mass= is given
        # and would be dead code that jit removes together with the check.
        com, unit_inertia = eqx.error_if(
            (com, unit_inertia), signed_volume <= 0.0, _inside_out_message("<= 0")
        )
    total = jnp.asarray(mass) if mass is not None else jnp.asarray(density) * signed_volume
    return MassProperties(total, com, total * unit_inertia)


@jax.jit
def _mesh_moments(vertices, faces):
    """Signed volume, com and inertia per unit mass of a uniform closed mesh."""
    # Apex of the tetrahedra at the vertex mean rather than the frame origin: for a mesh
    # far from its origin, the moments about the origin are large and nearly cancel when
    # shifted back to the com.
    apex = jnp.mean(vertices, axis=0)
    local = vertices - apex[None, :]
    a, b, c = local[faces[:, 0]], local[faces[:, 1]], local[faces[:, 2]]
    s = a + b + c
    six_volumes = dot(a, cross(b, c))
    signed_volume = jnp.sum(six_volumes) / 6.0
    first_moment = jnp.sum(six_volumes[:, None] * s, axis=0) / 24.0

    def outer(u):
        return u[:, :, None] * u[:, None, :]

    second_moment = (
        jnp.sum(six_volumes[:, None, None] * (outer(a) + outer(b) + outer(c) + outer(s)), axis=0)
        / 120.0
    )
    com_local = first_moment / signed_volume
    # Second moment per unit mass about the com.
    spread = second_moment / signed_volume - com_local[:, None] * com_local[None, :]
    trace = spread[0, 0] + spread[1, 1] + spread[2, 2]
    unit_inertia = trace * jnp.eye(3, dtype=spread.dtype) - spread
    return signed_volume, apex + com_local, unit_inertia


def compose(parts: Sequence[MassProperties]) -> MassProperties:
    """One body from several parts, all already expressed in one common frame.

    Pose each part with :meth:`MassProperties.transformed` first. ``M = sum m_k``,
    ``com = sum m_k c_k / M`` and ``I = sum I_k + m_k (|d_k|^2 E - d_k d_k^T)`` with
    ``d_k = c_k - com`` (parallel-axis theorem). The result is in the same frame. A part
    may have a negative mass (a hole cut out of a solid part); the total must be positive.
    The primitives take positive masses only, so make a hole from the solid it removes,
    with mass and inertia negated: ``MassProperties(-p.mass, p.com, -p.inertia)`` for
    ``p = box(density * volume, half_extents).transformed(where)``.
    """
    if len(parts) == 0:
        raise ValueError("compose: give at least one part.")
    masses = jnp.stack([p.mass for p in parts])
    total = _concrete_array(jnp.sum(masses, axis=0))  # None while traced
    if total is not None and not np.all(np.isfinite(total) & (total > 0)):
        # A part may be negative (a hole cut out of a solid), but not the whole: its com
        # divides by the total (masses -1 and +1 gave a com of [inf, nan, nan]).
        raise ValueError(f"compose: the parts' total mass must be finite and > 0 (kg), got {total}.")
    coms = jnp.stack([p.com for p in parts])
    inertias = jnp.stack([p.inertia for p in parts])
    # A part with a NaN com or inertia had made the whole body NaN without a word (a
    # non-finite mass makes the total so, refused above).
    for name, values in (("com", coms), ("inertia", inertias)):
        known = _concrete_array(values)
        if known is not None and not np.all(np.isfinite(known)):
            bad = np.flatnonzero(~np.all(np.isfinite(known.reshape(len(parts), -1)), axis=1)).tolist()
            raise ValueError(f"compose: every part's {name} must be finite; parts {bad} are not.")
    return _compose(masses, coms, inertias)


@jax.jit
def _compose(masses, coms, inertias):
    total = jnp.sum(masses)
    com = jnp.sum(masses[:, None] * coms, axis=0) / total
    inertia = jnp.sum(inertias + _parallel_axis(masses, coms - com[None, :]), axis=0)
    return MassProperties(total, com, inertia)


# ------------------------------------------------------------------------ principal axes


# Cyclic Jacobi sweeps for a 3x3 symmetric matrix. Jacobi converges quadratically once
# the off-diagonal entries are small; 6 sweeps (18 rotations) leave them at round-off for
# any symmetric 3x3 (checked in tests/test_inertia.py against numpy's eigh).
_JACOBI_SWEEPS = 6


def _jacobi_rotation(matrix, axes, p: int, q: int):
    """One Jacobi rotation zeroing ``matrix[p, q]``; returns ``(J^T M J, V J)``."""
    a_pp, a_qq, a_pq = matrix[..., p, p], matrix[..., q, q], matrix[..., p, q]
    # tan of the rotation angle, the smaller root of t^2 + 2 tau t - 1 = 0 with
    # tau = d / (2 a_pq) (Golub & Van Loan, Algorithm 8.4.1), multiplied through by
    # 2 |a_pq|: |t| <= 1, no cancellation, and no overflow once a_pq is tiny (tau^2
    # overflowed in float32 near convergence and corrupted the result under jit).
    d = a_qq - a_pp
    denominator = jnp.abs(d) + jnp.sqrt(d * d + 4.0 * a_pq * a_pq)
    empty = denominator == 0  # a_pq = 0 and d = 0: nothing to rotate
    t = jnp.where(empty, 0.0, jnp.where(d >= 0, 2.0, -2.0) * a_pq / jnp.where(empty, 1.0, denominator))
    c = 1.0 / jnp.sqrt(1.0 + t * t)
    s = t * c
    one = jnp.ones_like(c)
    nil = jnp.zeros_like(c)
    rows = [[one, nil, nil], [nil, one, nil], [nil, nil, one]]
    rows[p][p], rows[q][q], rows[p][q], rows[q][p] = c, c, s, -s
    rotation = jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)
    return matmul(matmul(transpose(rotation), matrix), rotation), matmul(axes, rotation)


def _jacobi_eigh(matrix):
    """Eigenvalues (ascending) and eigenvectors (columns) of symmetric 3x3 matrices.

    Element-wise arithmetic only, so a batch of matrices vectorises; LAPACK's ``eigh``
    runs one small matrix at a time on CPU, which made a vmapped splitting step 20x
    slower than RK4 (benchmarks/free_body.py). Not differentiated itself: the custom
    JVP of ``_principal_axes`` gives the derivatives.
    """
    def sweep(_, carry):
        for p, q in ((0, 1), (0, 2), (1, 2)):
            carry = _jacobi_rotation(*carry, p, q)
        return carry

    # Scaled to a largest entry in [0.5, 1) by a power of two (exact): the rotations square
    # the entries, which underflowed to 0 in float32 below ~1e-19 kg m^2 (a 10 um steel box:
    # no rotation, moments 36% off) and overflowed above ~1e19 (a 2 km rock).
    largest = jnp.max(jnp.abs(matrix), axis=(-2, -1))
    _, exponent = jnp.frexp(jnp.where(largest > 0, largest, 1.0))
    power = jnp.ldexp(jnp.ones_like(largest), exponent)[..., None, None]
    matrix = matrix / power
    axes = jnp.broadcast_to(jnp.eye(3, dtype=matrix.dtype), matrix.shape)
    # A loop, not unrolled: unrolled, the sweeps were 988 of the 6,021 equations of the
    # bouncing ball's forward rollout (5,033 now), for a computation that runs once per
    # rollout. Forward trace + compile fell about 16%: the ball 8.3, 8.0 -> 6.4, 7.1 s and
    # the 5-box stack 16.6, 13.8 -> 12.0, 13.6 s (two runs each, noisy). A scan over
    # Step.__call__, which runs it every step, is as fast as before (XLA hoists it).
    matrix, axes = jax.lax.fori_loop(0, _JACOBI_SWEEPS, sweep, (matrix, axes))
    moments = jnp.diagonal(matrix, axis1=-2, axis2=-1) * power[..., 0]
    # Sort ascending with a three-comparator network, swapping eigenvector columns along.
    for i, j in ((0, 1), (1, 2), (0, 1)):
        swap = moments[..., i] > moments[..., j]
        order = [0, 1, 2]
        order[i], order[j] = j, i
        moments = jnp.where(swap[..., None], moments[..., order], moments)
        axes = jnp.where(swap[..., None, None], axes[..., :, order], axes)
    return moments, axes


def _eigh_right_handed(matrix):
    moments, axes = _jacobi_eigh(matrix)
    # eigh's eigenvectors have arbitrary signs; flipping the last one makes R a rotation.
    det = dot(axes[..., :, 0], cross(axes[..., :, 1], axes[..., :, 2]))
    sign = jnp.where(det < 0, -1.0, 1.0).astype(axes.dtype)
    axes = axes.at[..., :, 2].multiply(sign[..., None])
    return moments, axes


def _repeated_pairs(moments):
    """``(..., 3, 3)`` bool: which pairs of moments count as equal, the diagonal included.

    "Equal" is relative to the trace at ``sqrt(eps)``: above eigh's round-off (~eps), so a
    rotated cube counts, and it keeps ``1 / (l_j - l_i)`` of the other pairs at most
    ``1 / (sqrt(eps) trace)``, so that derivatives stay finite.
    """
    gap = moments[..., None, :] - moments[..., :, None]
    scale = jnp.sum(jnp.abs(moments), axis=-1)[..., None, None]
    return jnp.abs(gap) <= jnp.finfo(moments.dtype).eps ** 0.5 * scale


@jax.custom_jvp
def _principal_axes(matrix):
    return _eigh_right_handed(matrix)


@_principal_axes.defjvp
def _principal_axes_jvp(primals, tangents):
    (matrix,), (d_matrix,) = primals, tangents
    moments, axes = _eigh_right_handed(matrix)
    d_matrix = 0.5 * (d_matrix + transpose(d_matrix))
    projected = matmul(matmul(transpose(axes), d_matrix), axes)
    # Eigenvalue derivatives diag(V^T dA V) are exact even for repeated eigenvalues
    # whenever the perturbation keeps the symmetry (as changing a cube's size does).
    d_moments = jnp.diagonal(projected, axis1=-2, axis2=-1)
    # dV = V (F o V^T dA V), F_ij = 1/(l_j - l_i). For (nearly) equal moments, as in a cube
    # or a cylinder, the axes are not unique and F is 1/0: those entries are set to 0,
    # i.e. the axes inside a degenerate eigenspace are held fixed (what that leaves out:
    # repeated_moment_coupling).
    gap = moments[..., None, :] - moments[..., :, None]
    degenerate = _repeated_pairs(moments)
    inverse_gap = jnp.where(degenerate, 0.0, 1.0 / jnp.where(degenerate, 1.0, gap))
    d_axes = matmul(axes, inverse_gap * projected)
    return (moments, axes), (d_moments, d_axes)


@jax.jit
def principal_axes(
    inertia: Float[ArrayLike, "3 3"],
) -> tuple[Float[Array, "3"], Float[Array, "3 3"]]:
    """Principal moments and axes: ``inertia = R diag(moments) R^T`` (seed 001's ``A I_O A^T``).

    Args:
        inertia: ``(3, 3)`` symmetric, kg m^2 (only its symmetric part is used).

    Returns:
        ``moments``: ``(3,)`` ascending, kg m^2. ``R``: ``(3, 3)`` rotation (``det R = +1``)
        whose columns are the principal axes in the inertia's frame, i.e. it maps the
        principal frame to that frame.

    Computed by cyclic Jacobi rotations (element-wise, so it vectorises under ``vmap``).
    Differentiable: a custom JVP around the eigen-decomposition keeps gradients finite when
    moments repeat (cube, cylinder). There the axes within the repeated eigenspace are not
    unique and their derivative is taken as 0; the moments' derivatives stay exact, and
    what the axes do not absorb is :func:`repeated_moment_coupling`'s derivative.

    First derivatives only, where moments repeat: second derivatives (``jax.hessian``) differentiate the
    rule's own eigen-decomposition, and are right for distinct moments (1e-15) but wrong where two
    moments are equal, even of smooth functions of the inertia (the Hessian of ``sum(moments**2)``
    of an axisymmetric box 0.5% off, of a cube's by 1e10: stop 90's review), and NaN
    through :func:`repeated_moment_coupling`'s tangent at an exactly diagonal inertia with
    repeated moments (reverse mode over its rule: stop 96's review). Individual
    moments are not differentiable there in a direction that breaks the symmetry.
    """
    inertia = jnp.asarray(inertia)
    return _principal_axes(0.5 * (inertia + transpose(inertia)))


@jax.custom_jvp
def repeated_moment_coupling(inertia: Float[ArrayLike, "3 3"]) -> Float[Array, "3 3"]:
    """Zero, with the derivative that :func:`principal_axes` leaves out at repeated moments.

    With ``inertia = R diag(l) R^T``, a perturbation ``dI`` changes the inertia in the
    principal frame by ``R^T dI R``. Where ``l_i != l_j`` its ``(i, j)`` entry is absorbed by
    turning the axes (``dR``); where ``l_i = l_j`` (a sphere, a cube, an axisymmetric body)
    the axes are not unique, ``principal_axes`` holds them fixed, and the entry remains as
    an off-diagonal inertia in the principal frame: this function's derivative, ``(R^T dI
    R)_ij`` on those pairs (``i != j``) and 0 elsewhere. Its value is exactly 0 (the
    principal frame diagonalises the inertia), so an integrator that works in the principal
    frame adds the flow of this coupling to its steps at no cost in value and gets the
    symmetry-breaking derivatives right (:class:`jaxrb.integrators.SymplecticSplitting`).

    Args:
        inertia: ``(3, 3)`` symmetric, kg m^2 (only its symmetric part is used).

    Returns:
        ``(3, 3)`` zeros, kg m^2, in the principal frame of :func:`principal_axes`.
    """
    # Made from the input (not a constant), so that under vmap the value is batched as its
    # derivative is: a constant value with a batched tangent failed jax's linearisation.
    return 0.0 * jnp.asarray(inertia)


@repeated_moment_coupling.defjvp
def _repeated_moment_coupling_jvp(primals, tangents):
    (matrix,), (d_matrix,) = primals, tangents
    moments, axes = _eigh_right_handed(0.5 * (matrix + transpose(matrix)))
    projected = matmul(matmul(transpose(axes), 0.5 * (d_matrix + transpose(d_matrix))), axes)
    off_block = _repeated_pairs(moments) & ~np.eye(3, dtype=bool)
    return 0.0 * matrix, jnp.where(off_block, projected, 0.0)


# ----------------------------------------------------------------- shapes -> properties


def _mesh_signed_volume(mesh: shapes.Mesh) -> float:
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces)
    v = v - v.mean(axis=0)
    return float(np.sum(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])))) / 6.0


_VOLUME: dict[type, Callable[[shapes.Shape], float]] = {
    shapes.Sphere: lambda s: 4.0 / 3.0 * math.pi * s.radius**3,
    shapes.HollowSphere: lambda s: (
        4.0 / 3.0 * math.pi * (s.radius**3 - (s.radius - s.thickness) ** 3)
    ),
    shapes.Box: lambda s: 8.0 * math.prod(s.half_extents),
    shapes.Capsule: lambda s: math.pi * s.radius**2 * (2.0 * s.half_length + 4.0 / 3.0 * s.radius),
    shapes.Cylinder: lambda s: 2.0 * math.pi * s.radius**2 * s.half_length,
    shapes.EllipticalCylinder: lambda s: 2.0 * math.pi * math.prod(s.semi_axes) * s.half_length,
    shapes.Cone: lambda s: math.pi * s.radius**2 * s.height / 3.0,
    shapes.Ellipsoid: lambda s: 4.0 / 3.0 * math.pi * math.prod(s.semi_axes),
    shapes.Mesh: _mesh_signed_volume,
}


def _sized(values, mass: Array) -> Array:
    # Shape sizes are Python floats; a tuple of them would become a default-precision
    # array, so cast to the mass's dtype to keep a float32 mass giving float32 results.
    return jnp.asarray(values, dtype=mass.dtype)


_MASS_PROPERTIES: dict[type, Callable[[shapes.Shape, Array], MassProperties]] = {
    shapes.Sphere: lambda s, m: sphere(m, _sized(s.radius, m)),
    shapes.HollowSphere: lambda s, m: hollow_sphere(m, _sized(s.radius, m), _sized(s.thickness, m)),
    shapes.Box: lambda s, m: box(m, _sized(s.half_extents, m)),
    shapes.Capsule: lambda s, m: capsule(m, _sized(s.radius, m), _sized(s.half_length, m)),
    shapes.Cylinder: lambda s, m: cylinder(m, _sized(s.radius, m), _sized(s.half_length, m)),
    shapes.EllipticalCylinder: lambda s, m: elliptical_cylinder(
        m, _sized(s.semi_axes, m), _sized(s.half_length, m)
    ),
    shapes.Cone: lambda s, m: cone(m, _sized(s.radius, m), _sized(s.height, m)),
    shapes.Ellipsoid: lambda s, m: ellipsoid(m, _sized(s.semi_axes, m)),
    shapes.Rod: lambda s, m: rod(m, _sized(s.half_length, m)),
    shapes.Plate: lambda s, m: plate(m, _sized(s.half_extents, m)),
    shapes.Disk: lambda s, m: disk(m, _sized(s.radius, m)),
    shapes.Mesh: lambda s, m: _mesh_properties(s, m),
}


def _mesh_properties(mesh: shapes.Mesh, mass: Array) -> MassProperties:
    """:func:`from_mesh` of a stored mesh, its vertices taken about their mean in float64
    before the cast to the mass's dtype: cast first, a 5 cm box 1000 m from its frame's
    origin lost 4e-4 of its inertia in float32 (stop 90's review)."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    centre = vertices.mean(axis=0)
    local = from_mesh(_sized(vertices - centre, mass), mesh.faces, mass=mass)
    return MassProperties(local.mass, local.com + _sized(centre, mass), local.inertia)


def _lookup(table: dict, shape, what: str):
    try:
        return table[type(shape)]
    except KeyError:
        if isinstance(shape, shapes.Plane):
            raise ValueError(f"{what}: a Plane is static scenery with no mass or volume.") from None
        raise ValueError(
            f"{what}: unsupported shape {type(shape).__name__}; "
            f"expected one of {', '.join(t.__name__ for t in _MASS_PROPERTIES)}."
        ) from None


def volume(shape: shapes.Shape) -> float:
    """Volume (m^3) of a solid shape. Thin shapes (rod, plate, disk, thin shell) have none."""
    if shape.thin:
        raise ValueError(
            f"volume: {type(shape).__name__} is a thin shape and has no volume; "
            "give its mass= instead of a density."
        )
    result = _lookup(_VOLUME, shape, "volume")(shape)
    if isinstance(shape, shapes.Mesh) and not result > 0.0:
        raise ValueError(_inside_out_message(result))
    return result


def mass_properties(
    shape: shapes.Shape,
    *,
    density: Float[ArrayLike, ""] | None = None,
    mass: Float[ArrayLike, ""] | None = None,
) -> MassProperties:
    """Mass properties of a uniform-density shape, in the shape's own frame.

    Give exactly one of ``density`` (kg/m^3; ``mass = density * volume(shape)``) or
    ``mass`` (kg). Thin shapes (:class:`~jaxrb.shapes.Rod`, :class:`~jaxrb.shapes.Plate`,
    :class:`~jaxrb.shapes.Disk`, a :class:`~jaxrb.shapes.HollowSphere` of zero thickness)
    have no volume and accept only ``mass``. ``com`` is the origin for every shape except
    :class:`~jaxrb.shapes.Mesh`, whose com is computed in the vertices' frame. The
    numbers may be traced (jit/grad over ``density`` or ``mass``); the shape is static.
    """
    name = type(shape).__name__
    _check_mass_or_density(density, mass, f"mass_properties({name})")
    build = _lookup(_MASS_PROPERTIES, shape, "mass_properties")
    if density is not None:
        if shape.thin:
            raise ValueError(
                f"mass_properties: {name} is a thin shape and has no volume, so a density "
                "cannot give it a mass; give mass= (kg) instead."
            )
        mass = jnp.asarray(density) * volume(shape)
    mass = jnp.asarray(mass)
    if not jnp.issubdtype(mass.dtype, jnp.floating):  # an integer mass= 2
        mass = mass.astype(float)
    return build(shape, mass)


# ------------------------------------------------------------------------------ checking


def check_mass_properties(mass: ArrayLike, inertia: ArrayLike, *, name: str = "body") -> None:
    """Check that a body's mass and central inertia are physical (NumPy, concrete values).

    Meant for scene build time. Raises ``ValueError``, naming the body and the fix, if
    the mass is not finite and positive, or the inertia (kg m^2) is not a finite,
    symmetric, positive-definite ``(3, 3)`` matrix whose principal moments obey the
    triangle inequality ``I1 + I2 >= I3``.
    """
    check_mass(mass, name=name)
    check_inertia(inertia, name=name)


def check_mass(mass: ArrayLike, *, name: str = "body") -> None:
    """The mass half of :func:`check_mass_properties`: a finite, positive scalar (kg)."""
    m = np.asarray(mass, dtype=np.float64)
    if m.shape != ():
        raise ValueError(f"{name}: mass must be a scalar (kg), got shape {m.shape}.")
    if not np.isfinite(m) or m <= 0.0:
        raise ValueError(f"{name}: mass must be positive and finite (kg), got {float(m)}.")


def check_inertia(inertia: ArrayLike, *, name: str = "body") -> None:
    """The inertia half of :func:`check_mass_properties`: a finite, symmetric, positive
    definite ``(3, 3)`` matrix (kg m^2) whose principal moments obey the triangle inequality."""
    given = np.asarray(inertia)
    i = given.astype(np.float64)
    if i.shape != (3, 3):
        raise ValueError(f"{name}: inertia must be a 3x3 matrix (kg m^2), got shape {i.shape}.")
    if not np.all(np.isfinite(i)):
        raise ValueError(f"{name}: inertia contains NaN or infinite entries:\n{i}")
    largest = np.max(np.abs(i))
    asymmetry = np.max(np.abs(i - i.T))
    # Round-off of the input's own precision passes: a float32 R diag(l) R^T is asymmetric
    # at ~1e-8 of its largest entry. Steps read the symmetric part (state.body_inertia).
    precision = np.finfo(given.dtype).eps if np.issubdtype(given.dtype, np.floating) else 0.0
    if asymmetry > max(1e-9, 16 * precision) * largest:
        raise ValueError(
            f"{name}: inertia must be symmetric, but |I - I^T| reaches {asymmetry:.3g} "
            f"(largest entry {largest:.3g}). Use (I + I^T)/2 if the asymmetry is round-off."
        )
    moments = np.linalg.eigvalsh(0.5 * (i + i.T))
    trace = float(np.sum(moments))
    if not moments[0] > 1e-12 * abs(trace):
        raise ValueError(
            f"{name}: inertia must be positive definite, but its principal moments are "
            f"{moments} kg m^2. A zero moment means a body with no extent across an axis "
            "(a rod or point mass): give it some thickness, e.g. a thin Cylinder instead "
            "of a Rod."
        )
    # The same allowance for round-off: a flat body (a Plate) has I1 + I2 = I3 exactly, which
    # rounding each moment to float32 broke by ~1e-8 of the trace (half of all plates refused).
    if moments[0] + moments[1] < moments[2] - max(1e-9, 16 * precision) * trace:
        raise ValueError(
            f"{name}: principal moments {moments} kg m^2 violate the triangle inequality "
            "I1 + I2 >= I3. For any real mass distribution I1 + I2 - I3 = 2 * integral of "
            "rho r3^2 dV >= 0 (r3 the coordinate along the third axis), so no body has "
            "these moments; check their values and units, or compute them from a shape."
        )
