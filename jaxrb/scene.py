"""Bodies and scenes: the static structure of a simulation, and its builders of Params and State.

A :class:`Scene` is static (hashable; changing it recompiles): which bodies, their
shapes, which force models. It builds the dynamic pytrees with :meth:`Scene.params` and
:meth:`Scene.state`, validating every input on the way: bad input raises a
``ValueError`` that says what is wrong and how to fix it, before anything is compiled.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from . import inertia as _inertia
from . import spatial
from .forces import AngularDamping, ForceModel, Gravity, LinearDamping
from .shapes import Plane, Shape, not_text
from .state import Params, State, body_inertia

__all__ = ["Body", "Scene", "GROUND"]

#: The name of the scene's ground plane in contact pairs.
GROUND = "ground"


def _numbers(what: str, value) -> np.ndarray:
    """``value`` as a float array, or a ValueError that names the input (NumPy's own says
    only "could not convert string to float")."""
    try:
        not_text(value)  # float("0.8") would pass: a mistake, not a number
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be numbers (a number, a sequence or an array), got {value!r}.") from None


def _is_traced(x: Any) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(x))


@dataclasses.dataclass(frozen=True)
class Body:
    """A rigid body: a name, an optional shape and its mass properties.

    Give the mass properties in one of three ways:

    * ``shape`` with ``mass=`` (kg) or ``density=`` (kg/m^3): uniform solid shape;
    * ``mass=`` and ``inertia=`` (kg m^2, body frame about the centre of mass; a
      ``(3,)`` of principal moments or a ``(3, 3)`` tensor), with or without a shape;
    * ``mass_properties=`` (a :class:`jaxrb.MassProperties`, e.g. from
      :func:`jaxrb.inertia.compose` or a mesh).

    The body frame's origin is the centre of mass. ``shape_offset`` (m, body frame) is
    where the shape's (or mass properties') own frame origin sits in the body frame,
    ``-com`` of the mass properties used: non-zero for a mesh or composed parts whose
    centre of mass is off their origin, given by ``shape`` with ``mass=``/``density=`` or by
    ``mass_properties=``. With ``mass=`` and ``inertia=`` it is zero: the shape is then
    taken to be placed with its origin at the centre of mass.
    """

    name: str
    shape: Shape | None = None
    mass: float | None = None
    density: float | None = None
    inertia: Any = None
    mass_properties: Any = dataclasses.field(default=None, compare=False, hash=False, repr=False)
    shape_offset: tuple[float, float, float] = dataclasses.field(init=False)

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"Body.name must be a non-empty string, got {self.name!r}.")
        if self.shape is not None and not isinstance(self.shape, Shape):
            raise ValueError(
                f"Body {self.name!r}: shape must be a jaxrb shape (rb.Box, rb.Sphere, ...), "
                f"got {type(self.shape).__name__}."
            )
        if isinstance(self.shape, Plane):
            # A plane's pair functions read the plane's normal and offset, never a pose: a
            # body carrying one collided as a plane fixed through the world's origin.
            raise ValueError(f"Body {self.name!r}: a Plane is static and has no pose, so it cannot be a body's "
                             f"shape. Give it to the scene: rb.Scene(..., ground=rb.Plane(normal, offset)).")
        mp = self._resolve()
        mass = float(np.asarray(mp.mass))
        # Checked in its own precision (float32 round-off passes), stored symmetric in float64.
        _inertia.check_mass_properties(mass, np.asarray(mp.inertia), name=f"Body {self.name!r}")
        inertia = np.asarray(mp.inertia, dtype=float)
        inertia = 0.5 * (inertia + inertia.T)
        com = np.asarray(mp.com, dtype=float)
        object.__setattr__(self, "mass", mass)
        object.__setattr__(self, "inertia", tuple(map(tuple, inertia.tolist())))
        object.__setattr__(self, "density", None)
        object.__setattr__(self, "mass_properties", None)
        object.__setattr__(self, "shape_offset", tuple((-com).tolist()))

    def _resolve(self):
        where = f"Body {self.name!r}"
        for field, unit in (("mass", "kg"), ("density", "kg/m^3"), ("inertia", "")):
            if getattr(self, field) is not None:
                values = _numbers(f"{where}: {field}", getattr(self, field))
                if unit and values.shape != ():  # float([2.0]) failed with NumPy's own words
                    raise ValueError(f"{where}: {field} must be one number ({unit}), got shape {values.shape}: "
                                     f"{getattr(self, field)!r}.")
        if self.mass_properties is not None:
            if self.mass is not None or self.density is not None or self.inertia is not None:
                raise ValueError(
                    f"{where}: give either mass_properties= or mass/density/inertia, not both."
                )
            mp = self.mass_properties
            if not isinstance(mp, _inertia.MassProperties):
                raise ValueError(f"{where}: mass_properties must be an rb.MassProperties (from rb.mass_properties "
                                 f"or rb.MassProperties(mass, com, inertia)), got {type(mp).__name__}.")
            com = np.asarray(mp.com, dtype=float)
            if np.shape(mp.mass) != () or com.shape != (3,) or not np.all(np.isfinite(com)):
                # A NaN com became the shape's offset, and the body fell through the ground.
                raise ValueError(f"{where}: mass_properties needs a scalar mass and a finite (3,) com (m), got mass "
                                 f"of shape {np.shape(mp.mass)} and com {com!r}. (One body's: not a batch.)")
            return mp
        if self.inertia is not None:
            if self.mass is None or self.density is not None:
                raise ValueError(
                    f"{where}: an explicit inertia= needs mass= (kg) and no density=."
                )
            inertia = np.asarray(self.inertia)
            inertia = inertia if np.issubdtype(inertia.dtype, np.floating) else inertia.astype(float)
            if inertia.shape == (3,):
                inertia = np.diag(inertia)
            if inertia.shape != (3, 3):
                raise ValueError(
                    f"{where}: inertia must be 3 principal moments or a 3x3 tensor (kg m^2), "
                    f"got shape {inertia.shape}."
                )
            return _inertia.MassProperties(
                mass=jnp.asarray(float(self.mass)), com=jnp.zeros(3), inertia=jnp.asarray(inertia)
            )
        if self.shape is None:
            raise ValueError(
                f"{where}: no mass properties. Give a shape with mass= or density=, "
                "or mass= with inertia=, or mass_properties=."
            )
        return _inertia.mass_properties(self.shape, density=self.density, mass=self.mass)


def _canonical_dtype(dtype):
    """``dtype`` checked, or the default float of the JAX configuration (float32 unless x64 is on)."""
    if dtype is None:
        return jnp.zeros(()).dtype
    dtype = jnp.dtype(dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"dtype must be a floating-point type (float32 or float64), got {dtype}: "
                         "an integer dtype would truncate every value.")
    _check_precision(dtype, "dtype")
    if dtype.itemsize == 8 and not jax.config.jax_enable_x64:
        # JAX would quietly give float32 (with a warning per array).
        raise ValueError("dtype=float64 needs 64-bit JAX, which is off: call "
                         "jax.config.update('jax_enable_x64', True) before creating any array, or "
                         "set JAX_ENABLE_X64=1; or leave dtype out for float32.")
    return dtype


def _check_precision(dtype, what: str) -> None:
    """Refuse floats narrower than 32 bits. bfloat16 has 8 significand bits: a ball 1.1 m up
    has an ulp of 8 mm, so a 1 ms step's fall (5e-6 m at the start) rounds away and the ball
    hung in the air for a whole second of simulation, without a word."""
    if jnp.issubdtype(dtype, jnp.floating) and jnp.dtype(dtype).itemsize < 4:
        raise ValueError(f"{what} is {jnp.dtype(dtype)}, too coarse for a simulation: its rounding swallows "
                         f"a step's motion (a bfloat16 ball 1.1 m up never fell at dt = 1 ms). Use float32 "
                         f"or float64, e.g. scene.params(..., dtype=jnp.float32).")


@dataclasses.dataclass(frozen=True)
class Scene:
    """The static description of a world of rigid bodies.

    Args:
        bodies: the bodies, in order; arrays in ``Params`` and ``State`` follow it.
        gravity: ``(3,)`` m/s^2 in the world frame, or ``None`` for no gravity (no
            gravity code is then compiled). The value is only the default of
            ``Params.gravity``, which can be changed or differentiated without
            recompiling.
        forces: extra force models (:class:`jaxrb.LinearDamping`,
            :class:`jaxrb.AngularDamping`, :class:`jaxrb.PointForces`,
            :class:`jaxrb.ExternalWrench`, ...). Only these are compiled into a step.
        ground: an optional static :class:`jaxrb.Plane` (the half-space below it is
            solid), named ``"ground"`` in contact pairs. A tilted normal makes an incline.
        walls: further static planes, by name: a dict ``{name: rb.Plane(normal, offset)}``,
            each solid on the side its normal points away from (the normal points into
            the free space), named like the ground in contact pairs. E.g. a wall at
            ``x = 1`` that keeps bodies at ``x < 1``: ``{"wall": rb.Plane((-1, 0, 0), -1.0)}``.
        contacts: the pairs of bodies that may touch, as ``(name_a, name_b)`` tuples
            (``name_b`` may be ``"ground"`` or a wall), or ``"all"``: every pair of bodies
            that have shapes, plus every such body against the ground and each wall. Pairs whose shapes have no
            narrow-phase function are refused when listed and skipped by ``"all"``.
            Resolved once, here; :attr:`contact_pairs` holds the result. Default: none,
            and then no collision or contact code is compiled (``None`` means the same).
    """

    bodies: Sequence[Body]
    gravity: Sequence[float] | None = (0.0, 0.0, -9.81)
    forces: Sequence[ForceModel] = ()
    ground: Plane | None = None
    contacts: Sequence[tuple[str, str]] | str = ()
    walls: Mapping[str, Plane] = ()

    def __post_init__(self):
        if isinstance(self.bodies, Body):
            raise ValueError("Scene.bodies must be a list of rb.Body objects; got one Body: write bodies=[body].")
        bodies = tuple(self.bodies)
        if not bodies:
            raise ValueError("Scene needs at least one body.")
        for b in bodies:
            if not isinstance(b, Body):
                raise ValueError(f"Scene.bodies must hold rb.Body objects, got {type(b).__name__}.")
        names = [b.name for b in bodies]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"Body names must be unique; repeated: {duplicates}.")
        object.__setattr__(self, "bodies", bodies)
        if self.gravity is not None:
            g = np.asarray(self.gravity, dtype=float)
            if g.shape != (3,) or not np.all(np.isfinite(g)):
                raise ValueError(
                    f"Scene.gravity must be a finite 3-vector in m/s^2 (or None), got {self.gravity!r}."
                )
            object.__setattr__(self, "gravity", tuple(g.tolist()))
        if isinstance(self.forces, ForceModel):
            raise ValueError(f"Scene.forces must be a list of force models; got one: write forces=[{self.forces!r}].")
        forces = tuple(self.forces)
        for f in forces:
            if not isinstance(f, ForceModel):
                raise ValueError(
                    f"Scene.forces must hold force models (rb.LinearDamping(), rb.ExternalWrench(fn), "
                    f"...), got {f!r}."
                )
        if any(isinstance(f, Gravity) for f in forces):
            raise ValueError("Scene.forces holds rb.Gravity(), but gravity is Scene(gravity=...) (on by "
                             "default): listed as well it would be applied twice. Remove it from forces=.")
        for model in (LinearDamping, AngularDamping):
            if sum(isinstance(f, model) for f in forces) > 1:
                raise ValueError(f"Scene.forces lists rb.{model.__name__}() more than once: each copy "
                                 f"would apply Params.{model.__name__.lower()[:-7]}_damping again. List it once.")
        object.__setattr__(self, "forces", forces)
        if self.ground is not None and not isinstance(self.ground, Plane):
            raise ValueError(
                f"Scene.ground must be an rb.Plane (e.g. rb.Plane(normal=(0, 0, 1), offset=0.0)) "
                f"or None, got {self.ground!r}."
            )
        object.__setattr__(self, "walls", self._resolve_walls(self.walls, names))
        object.__setattr__(self, "contacts", self._resolve_contacts(self.contacts))

    @staticmethod
    def _resolve_walls(walls, body_names) -> tuple[tuple[str, Plane], ...]:
        """``walls`` as a tuple of ``(name, Plane)`` (hashable: the scene is static)."""
        items = walls.items() if isinstance(walls, Mapping) else walls
        try:
            items = tuple((name, plane) for name, plane in items)
        except (TypeError, ValueError):
            raise ValueError(f"Scene.walls must be a dict {{name: rb.Plane(normal, offset)}}, got {walls!r}.") from None
        for name, plane in items:
            if not isinstance(name, str) or not name:
                raise ValueError(f"Scene.walls: a wall's name must be a non-empty string, got {name!r}.")
            if not isinstance(plane, Plane):
                raise ValueError(f"Scene.walls[{name!r}] must be an rb.Plane(normal, offset), got {plane!r}.")
            if name == GROUND or name in body_names:
                raise ValueError(f"Scene.walls: {name!r} is already the name of "
                                 f"{'the ground plane' if name == GROUND else 'a body'}; name the wall otherwise.")
        repeated = sorted({n for n, _ in items if [m for m, _ in items].count(n) > 1})
        if repeated:
            raise ValueError(f"Scene.walls: names must be unique; repeated: {repeated}.")
        return items

    @property
    def planes(self) -> dict[str, Plane]:
        """The static planes by the names contact pairs use: ``"ground"`` (if any), then the walls."""
        return {**({GROUND: self.ground} if self.ground is not None else {}), **dict(self.walls)}

    def is_plane(self, name: str) -> bool:
        """Whether ``name`` is the ground's or a wall's (a static plane, B of its pairs)."""
        return name == GROUND or name in dict(self.walls)

    def _resolve_contacts(self, contacts) -> tuple[tuple[str, str], ...]:
        from .collision import max_contacts  # the collision package imports shapes only

        by_name = {b.name: b for b in self.bodies}
        if GROUND in by_name:
            raise ValueError(f"{GROUND!r} is the name of the ground plane; rename that body.")
        if isinstance(contacts, str):
            if contacts != "all":
                raise ValueError(
                    f"Scene.contacts must be 'all' or a list of (name_a, name_b) pairs, got {contacts!r}."
                )
            shaped = [b for b in self.bodies if b.shape is not None]
            candidates = [(a.name, b.name) for i, a in enumerate(shaped) for b in shaped[i + 1:]]
            candidates += [(b.name, plane) for plane in self.planes for b in shaped]
            pairs, left_out = [], []
            for a, b in candidates:
                try:
                    max_contacts(self._shape_of(a), self._shape_of(b))
                except ValueError:
                    left_out.append((a, b))  # "all" means every pair the narrow phase supports
                    continue
                pairs.append((a, b))
            if left_out:
                # Said, not silent: such bodies pass through each other (a capsule resting
                # on a box fell through it to the ground).
                kinds = sorted({" - ".join(sorted(type(self._shape_of(n)).__name__ for n in pair))
                                for pair in left_out})
                warnings.warn(f"Scene(contacts='all'): no contact function for {', '.join(kinds)}, so these pairs "
                              f"are left out and pass through each other: {left_out}. Supported pairs: "
                              "rb.collision.supported_pairs().", stacklevel=4)
            return tuple(pairs)
        pairs = []
        for pair in () if contacts is None else contacts:
            if (not isinstance(pair, (tuple, list)) or len(pair) != 2
                    or not all(isinstance(x, str) for x in pair)):
                raise ValueError(
                    f"Each contact pair must be a (name_a, name_b) tuple of body names (or 'ground' or a wall's), "
                    f"got {pair!r}."
                )
            a, b = pair
            if self.is_plane(a) and self.is_plane(b):
                raise ValueError(f"Contact pair {pair!r} pairs two static planes: a pair needs a body.")
            if self.is_plane(a):
                a, b = b, a  # a plane is always B
            for name in (a, b):
                if name == GROUND and self.ground is None:
                    raise ValueError(
                        f"Contact pair {pair!r} names 'ground' but the scene has no ground: "
                        "pass ground=rb.Plane()."
                    )
                if not self.is_plane(name) and name not in by_name:
                    raise ValueError(f"Contact pair {pair!r}: unknown body {name!r}; bodies are {list(by_name)}"
                                     + (f", walls {[w for w, _ in self.walls]}." if self.walls else "."))
                if not self.is_plane(name) and by_name[name].shape is None:
                    raise ValueError(
                        f"Contact pair {pair!r}: body {name!r} has no shape to collide with; give it shape=."
                    )
            if a == b:
                raise ValueError(f"Contact pair {pair!r} pairs a body with itself.")
            if (a, b) in pairs or (b, a) in pairs:
                raise ValueError(f"Contact pair {pair!r} is listed twice.")
            max_contacts(self._shape_of(a), self._shape_of(b))  # raises, naming the supported pairs
            pairs.append((a, b))
        return tuple(pairs)

    def _shape_of(self, name: str) -> Shape:
        return self.planes[name] if self.is_plane(name) else self.bodies[self.index(name)].shape

    # ------------------------------------------------------------------ structure

    @property
    def contact_pairs(self) -> tuple[tuple[str, str], ...]:
        """The resolved contact pairs ``(name_a, name_b)`` (static); ``Params.restitution``
        and ``Params.friction`` follow this order."""
        return self.contacts

    @property
    def num_contact_pairs(self) -> int:
        return len(self.contacts)

    @property
    def num_bodies(self) -> int:
        return len(self.bodies)

    @property
    def body_names(self) -> tuple[str, ...]:
        return tuple(b.name for b in self.bodies)

    @property
    def force_models(self) -> tuple[ForceModel, ...]:
        """Every force model the step evaluates, gravity first (static)."""
        return ((Gravity(),) if self.gravity is not None else ()) + tuple(self.forces)

    def index(self, name: str) -> int:
        """Position of the body called ``name`` in the body axis."""
        try:
            return self.body_names.index(name)
        except ValueError:
            raise ValueError(f"Unknown body name {name!r}; this scene has {list(self.body_names)}.") from None

    # --------------------------------------------------------------- per-body input

    def _per_body(self, what: str, value, trailing: tuple[int, ...], default: np.ndarray, dtype):
        """Turn a scalar/vector, an ``(N, ...)`` array or a ``{name: value}`` dict into ``(N, ...)``."""
        n = self.num_bodies
        if value is None:
            out = np.broadcast_to(default, (n, *trailing))
            return jnp.asarray(out, dtype=dtype)
        if isinstance(value, Mapping):
            # Set entry by entry in JAX, so that a traced value (under jit or grad) passes
            # through, as in the array form; concrete values are checked here.
            out = jnp.asarray(np.broadcast_to(default, (n, *trailing)), dtype=dtype)
            for name, v in value.items():
                index = self.index(name)
                v = jnp.asarray(v, dtype=dtype) if _is_traced(v) else _numbers(f"{what}[{name!r}]", v)
                if v.shape != trailing:
                    raise ValueError(f"{what}[{name!r}] must have shape {trailing}, got {v.shape}.")
                if isinstance(v, np.ndarray) and not np.all(np.isfinite(v)):
                    raise ValueError(f"{what}[{name!r}] contains NaN or infinite values: {v!r}.")
                out = out.at[index].set(jnp.asarray(v, dtype=dtype))
            return out
        if _is_traced(value):
            arr = jnp.asarray(value, dtype=dtype)
            if arr.shape not in (trailing, (n, *trailing)):
                raise ValueError(f"{what} must have shape {trailing} or ({n}, *{trailing}), got {arr.shape}.")
            return jnp.broadcast_to(arr, (n, *trailing))
        arr = _numbers(what, value)
        if arr.shape == trailing:
            arr = np.broadcast_to(arr, (n, *trailing))
        if arr.shape != (n, *trailing):
            raise ValueError(
                f"{what} must have shape {trailing} (same for every body), ({n}, *{trailing}) "
                f"(one per body, in scene order {list(self.body_names)}), or be a dict "
                f"{{body_name: value}}; got shape {arr.shape}."
            )
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{what} contains NaN or infinite values: {arr!r}.")
        return jnp.asarray(arr, dtype=dtype)

    # ------------------------------------------------------------------- builders

    def params(
        self,
        *,
        mass=None,
        inertia=None,
        gravity=None,
        linear_damping=0.0,
        angular_damping=0.0,
        restitution=0.0,
        friction=0.5,
        extra=None,
        dtype=None,
    ) -> Params:
        """Build :class:`jaxrb.Params`, defaulting to the bodies' mass properties.

        Each per-body argument may be one value for every body, an array with the body
        axis first, or a ``{body_name: value}`` dict overriding some bodies. ``inertia``
        entries may be ``(3,)`` principal moments or ``(3, 3)`` tensors (kg m^2, body
        frame). Values are validated (positive mass, symmetric positive definite inertia
        obeying the triangle inequality, finite numbers) unless they are traced. ``mass``
        and ``inertia`` are independent parameters: a new ``mass`` leaves each body's
        inertia as its ``Body`` gave it (scale it yourself for a uniformly denser body).

        ``restitution`` (in ``[0, 1]``, default 0) and ``friction`` (``>= 0``, default 0.5)
        are stored per contact pair (``Params.restitution``, shape ``(P,)`` in
        :attr:`contact_pairs` order). Give one value for every pair, a ``(P,)`` array, or a
        dict whose keys are pairs ``("ball", "ground")`` (that pair's value) or body names
        and ``"ground"`` (a per-body value). Per-body values are combined per pair by the
        rule of Box2D: **restitution is the larger of the two, friction their geometric
        mean** ``sqrt(mu_a mu_b)``; bodies not named take the default. Pair keys win over
        body keys. A body named must be in a contact pair (its value would be ignored). In a
        scene without pairs the values are kept nowhere, but still checked. Traced values
        pass through, so these are differentiable.
        """
        dtype = _canonical_dtype(dtype)
        declared = {type(m) for m in self.force_models}
        for value, model, arg in ((linear_damping, LinearDamping, "linear_damping"),
                                  (angular_damping, AngularDamping, "angular_damping")):
            if model not in declared and not (np.ndim(value) == 0 and not _is_traced(value) and value == 0.0):
                raise ValueError(
                    f"{arg} was given but the scene has no rb.{model.__name__}(): it would be ignored. "
                    f"Add forces=[rb.{model.__name__}()] to the Scene."
                )
        if gravity is not None and self.gravity is None:
            raise ValueError(
                "gravity was given but the scene was built with gravity=None, so no gravity is "
                "compiled and it would be ignored. Build the Scene with gravity=(gx, gy, gz)."
            )
        defaults_mass = np.array([b.mass for b in self.bodies])
        defaults_inertia = np.array([b.inertia for b in self.bodies])
        if mass is None:
            mass_arr = jnp.asarray(defaults_mass, dtype=dtype)
        elif isinstance(mass, Mapping):
            # Set entry by entry in JAX, so that a traced value (under jit or grad) passes
            # through, as in the array form. Concrete values are validated below.
            mass_arr = jnp.asarray(defaults_mass, dtype=dtype)
            for name, v in mass.items():
                v = jnp.asarray(v if _is_traced(v) else _numbers(f"mass[{name!r}]", v), dtype=dtype)
                if v.shape != ():
                    raise ValueError(f"mass[{name!r}] must be a scalar (kg), got shape {v.shape}.")
                mass_arr = mass_arr.at[self.index(name)].set(v)
        else:
            mass_arr = self._per_body("mass", mass, (), np.zeros(()), dtype)
        if inertia is None:
            inertia_arr = jnp.asarray(defaults_inertia, dtype=dtype)
        elif isinstance(inertia, Mapping):
            inertia_arr = jnp.asarray(defaults_inertia, dtype=dtype)
            for name, v in inertia.items():
                v = jnp.asarray(v if _is_traced(v) else _numbers(f"inertia[{name!r}]", v), dtype=dtype)
                v = jnp.diag(v) if v.shape == (3,) else v
                if v.shape != (3, 3):
                    raise ValueError(f"inertia[{name!r}] must be 3 principal moments or a 3x3 tensor (kg m^2), "
                                     f"got shape {v.shape}.")
                inertia_arr = inertia_arr.at[self.index(name)].set(v)
        else:
            xp = jnp if _is_traced(inertia) else np
            arr = xp.asarray(inertia, dtype=dtype if xp is jnp else float)
            # (3,) or (N, 3) are principal moments; a (3, 3) is always one tensor. Shapes
            # are static, so traced values take the same path as concrete ones.
            if arr.ndim in (1, 2) and arr.shape[-1:] == (3,) and arr.shape != (3, 3):
                arr = arr[..., None] * xp.eye(3, dtype=arr.dtype).reshape((1,) * (arr.ndim - 1) + (3, 3))
            if self.num_bodies == 3 and arr.shape == (3, 3) and xp is np:
                try:  # one tensor, or three bodies' principal moments (rows)?
                    _inertia.check_inertia(arr, name="inertia")
                except ValueError as err:
                    raise ValueError(
                        f"inertia of shape (3, 3) is read as one tensor for every body, and as one it is not "
                        f"physical ({err}). With 3 bodies, give principal moments per body as a dict "
                        "{name: (I1, I2, I3)} or as (3, 3, 3) tensors (np.stack([np.diag(m) for m in moments]))."
                    ) from None
            inertia_arr = self._per_body("inertia", arr, (3, 3), np.eye(3), dtype)
        if gravity is None:
            g = self.gravity if self.gravity is not None else (0.0, 0.0, 0.0)
            gravity_arr = jnp.asarray(g, dtype=dtype)
        else:
            if isinstance(gravity, (Mapping, str)):
                raise ValueError(f"gravity must be a 3-vector (gx, gy, gz) in m/s^2, world frame, got {gravity!r}.")
            gravity_arr = jnp.asarray(gravity, dtype=dtype)
            if gravity_arr.shape != (3,):
                raise ValueError(f"gravity must be a 3-vector (m/s^2), got shape {gravity_arr.shape}.")
        params = Params(
            mass=mass_arr,
            inertia=inertia_arr,
            gravity=gravity_arr,
            linear_damping=self._per_body("linear_damping", linear_damping, (), np.zeros(()), dtype),
            angular_damping=self._per_body("angular_damping", angular_damping, (), np.zeros(()), dtype),
            extra=_checked_extra(extra),
            restitution=self._per_pair("restitution", restitution, 0.0, dtype),
            friction=self._per_pair("friction", friction, 0.5, dtype),
        )
        self.check_params(params)
        return params

    def _per_pair(self, what: str, value, default: float, dtype):
        """One coefficient per contact pair from a scalar, a ``(P,)`` array or a dict (see params)."""
        pairs = self.contact_pairs
        p = len(pairs)
        low, high = (0.0, 1.0) if what == "restitution" else (0.0, np.inf)
        if not isinstance(value, Mapping):
            arr = jnp.asarray(value if _is_traced(value) else _numbers(what, value), dtype=dtype)
            if arr.shape not in ((), (p,)):
                raise ValueError(
                    f"{what} must be one value, a ({p},) array (one per contact pair, in the order "
                    f"{list(pairs)}), or a dict; got shape {arr.shape}."
                )
            # Checked here too, where the scene has no pair to keep it in (the value is then
            # unused, but 5.0 or NaN is a mistake all the same); check_params checks the rest.
            if not p and not _is_traced(value):
                v = np.asarray(value, dtype=float)
                if not np.all(np.isfinite(v) & (low <= v) & (v <= high)):  # v may be () or (0,)
                    raise ValueError(f"{what} must lie in [{low}, {high}], got {value!r}.")
            return jnp.broadcast_to(arr, (p,))
        for key in value:
            if not (isinstance(key, str) or (isinstance(key, tuple) and len(key) == 2
                                             and all(isinstance(n, str) for n in key))):
                raise ValueError(f"{what}: a dict's keys are body or plane names ('ball') or pairs of them "
                                 f"(('ball', 'ground')), got the key {key!r}.")
        per_body = {k: v for k, v in value.items() if isinstance(k, str)}
        per_pair = {tuple(k): v for k, v in value.items() if not isinstance(k, str)}
        in_pairs = {n for pair in pairs for n in pair}
        for name, v in per_body.items():
            if not self.is_plane(name):
                self.index(name)  # raises on unknown names
            elif name == GROUND and self.ground is None:
                raise ValueError(f"{what}[{GROUND!r}]: this scene has no ground (pass ground=rb.Plane()).")
            if name not in in_pairs:
                raise ValueError(f"{what}[{name!r}]: {name!r} is in no contact pair of this scene, so its {what} "
                                 f"would be ignored; the pairs are {list(pairs)}.")
            # Checked before they are combined: max(-3, 0) and sqrt(-0.4 * -0.9) would pass.
            if _is_traced(v) and np.shape(v) != ():
                raise ValueError(f"{what}[{name!r}] must be one number, got shape {np.shape(v)}.")
            if not _is_traced(v):
                v = _numbers(f"{what}[{name!r}]", v)
                if v.shape != () or not np.isfinite(v) or not low <= v <= high:
                    raise ValueError(f"{what}[{name!r}] must be one number in [{low}, {high}], got {v!r}.")
        for key in per_pair:
            if key not in pairs and key[::-1] not in pairs:
                raise ValueError(f"{what}: {key!r} is not a contact pair of this scene; pairs are {list(pairs)}.")
            if key[::-1] in per_pair and key[0] != key[1]:  # one of the two had been dropped without a word
                raise ValueError(f"{what}: the pair {key!r} is given twice, as {key!r} and {key[::-1]!r}; "
                                 f"give it once.")
            # One number per pair (a list had failed in jnp.stack: "Cannot stack arrays with
            # different numbers of dimensions").
            shape = np.shape(per_pair[key]) if _is_traced(per_pair[key]) else _numbers(what, per_pair[key]).shape
            if shape != ():
                raise ValueError(f"{what}[{key!r}] must be one number (the pair's coefficient), got shape {shape}: "
                                 f"{per_pair[key]!r}.")
        out = []
        for a, b in pairs:
            if (a, b) in per_pair or (b, a) in per_pair:
                out.append(jnp.asarray(per_pair.get((a, b), per_pair.get((b, a))), dtype=dtype))
                continue
            va = jnp.asarray(per_body.get(a, default), dtype=dtype)
            vb = jnp.asarray(per_body.get(b, default), dtype=dtype)
            if what == "restitution":
                out.append(jnp.maximum(va, vb))
            else:
                # sqrt(mu_a mu_b), with a zero derivative where the product is 0 (a
                # frictionless ground): sqrt's derivative there is 1/0, and it made the
                # gradient in the other body's friction 0 * inf = NaN.
                product = va * vb
                positive = product > 0
                out.append(jnp.where(positive, jnp.sqrt(jnp.where(positive, product, 1.0)), 0.0))
        return jnp.stack(out) if out else jnp.zeros((0,), dtype)

    def check_shapes(self, params: Params, fields=None) -> None:
        """Raise ``ValueError`` if a field of ``params`` (all, or those named) has the wrong
        shape for this scene. Shapes only, so it also works on traced values."""
        if not isinstance(params, Params):
            raise ValueError(f"params must be an rb.Params (scene.params(...)), got {type(params).__name__}.")
        n = self.num_bodies
        p = self.num_contact_pairs
        expected = {"mass": (n,), "inertia": (n, 3, 3), "gravity": (3,),
                    "linear_damping": (n,), "angular_damping": (n,),
                    "restitution": (p,), "friction": (p,)}
        for field in expected if fields is None else fields:
            value, shape = getattr(params, field), expected[field]
            if value.shape == shape:
                continue
            if field in ("restitution", "friction"):
                raise ValueError(f"Params.{field} has shape {value.shape}; this scene has {p} contact pairs "
                                 f"and needs one per contact pair, in the order of scene.contact_pairs "
                                 f"(scene.params(...) builds it, also from a per-pair dict).")
            batch = (" An ensemble's params (a leading axis) need jax.vmap over the step or rollout."
                     if value.shape[1:] == shape else "")
            raise ValueError(f"Params.{field} has shape {value.shape}; this scene needs {shape}.{batch}")

    def check_state_shapes(self, state: State) -> None:
        """Raise ``ValueError`` if a field of ``state`` has the wrong shape for this scene.
        Shapes only, so it also works on traced values (and per member under vmap)."""
        if not isinstance(state, State):
            raise ValueError(f"state must be an rb.State (scene.state(params, ...)), got {type(state).__name__}.")
        n = self.num_bodies
        expected = {"position": (n, 3), "orientation": (n, 4), "velocity": (n, 3),
                    "angular_momentum": (n, 3), "time": (), "rotation": (n, 3, 3)}
        for field, shape in expected.items():
            value = getattr(state, field)
            if value is not None and jnp.shape(value) != shape:
                raise ValueError(f"State.{field} has shape {jnp.shape(value)}; this scene of {n} bodies needs "
                                 f"{shape}. Build the state with this scene's scene.state(...).")

    def check_inputs(self, params: Params, state: State) -> None:
        """Raise ``ValueError`` unless ``params`` and ``state`` fit this scene and each other:
        their shapes (:meth:`check_shapes`, :meth:`check_state_shapes`), and a state at
        least as precise as the params. A float32 state with float64 params was promoted by
        the step (a rollout's loop then failed on its carry's type; ``ode.solve`` inside
        diffrax). Dtypes and shapes only, so it also works on traced values."""
        self.check_shapes(params)
        self.check_state_shapes(state)
        have, need = jnp.result_type(state.position), jnp.result_type(params.mass)
        _check_precision(need, "Params.mass's dtype")
        _check_precision(have, "State.position's dtype")
        if jnp.promote_types(have, need) != have:
            raise ValueError(f"The state is {have} and the params {need}: the step would compute in {need}. Build "
                             f"both in one dtype: scene.params(..., dtype=...), then scene.state(params, ...), "
                             f"which takes the params' dtype.")

    def check_params(self, params: Params) -> None:
        """Raise ``ValueError`` if ``params`` does not fit this scene or is unphysical.

        Shapes always; values where they are concrete (a traced field, under jit or grad, is
        skipped, and the others are still checked: a concrete inertia beside a traced mass
        too, which had gone unchecked)."""
        self.check_shapes(params)
        mass_known, inertia_known = not _is_traced(params.mass), not _is_traced(params.inertia)
        for i, name in enumerate(self.body_names):
            if mass_known:
                _inertia.check_mass(np.asarray(params.mass[i]), name=f"Body {name!r}")
            if inertia_known:
                _inertia.check_inertia(np.asarray(params.inertia[i]), name=f"Body {name!r}")
        for field in ("linear_damping", "angular_damping"):
            if _is_traced(getattr(params, field)):
                continue
            value = np.asarray(getattr(params, field))
            if not np.all(np.isfinite(value)) or np.any(value < 0):
                raise ValueError(
                    f"Params.{field} must be finite and non-negative (a negative damping "
                    f"coefficient adds energy), got {value}."
                )
        if not _is_traced(params.gravity) and not np.all(np.isfinite(np.asarray(params.gravity))):
            raise ValueError(f"Params.gravity must be finite, got {params.gravity}.")
        e = None if _is_traced(params.restitution) else np.asarray(params.restitution)
        if e is not None and (not np.all(np.isfinite(e)) or np.any(e < 0) or np.any(e > 1)):
            raise ValueError(
                f"Params.restitution must lie in [0, 1] (0: plastic, 1: elastic; above 1 an impact "
                f"would create energy), got {e} for pairs {list(self.contact_pairs)}."
            )
        mu = np.zeros(0) if _is_traced(params.friction) else np.asarray(params.friction)
        if not np.all(np.isfinite(mu)) or np.any(mu < 0):
            raise ValueError(
                f"Params.friction must be finite and >= 0 (Coulomb's coefficient), got {mu} for "
                f"pairs {list(self.contact_pairs)}."
            )

    def _warn_inside_planes(self, centres: np.ndarray) -> None:
        """Warn for each body in a contact pair with a plane whose shape's centre ``centres[i]``
        (m, world frame) lies on that plane's solid side (``normal . x < offset``). A wall given with its
        normal pointing out of the free space makes the whole free side solid, and the
        contact step then pushes every body out of it at once. (A warning, not an error: a
        deliberately deep start is how ``make_step(..., debug=True)`` is tried out.)"""
        planes, index = self.planes, {name: i for i, name in enumerate(self.body_names)}
        for body, plane_name in self.contact_pairs:
            if plane_name not in planes:
                continue
            plane = planes[plane_name]
            depth = plane.offset - float(np.dot(plane.normal, centres[index[body]]))
            if depth > 0:
                flipped = _plane_repr([-x for x in plane.normal], -plane.offset)
                warnings.warn(
                    f"Body {body!r} starts with its shape's centre {depth:.3g} m inside {plane_name!r}, on its solid "
                    f"side: {_plane_repr(plane.normal, plane.offset)} is solid where normal . x < offset, and the "
                    f"contact step will push the body out at once. If the plane should keep bodies on the side "
                    f"where this one is, give it the opposite normal and offset: {flipped}.",
                    UserWarning, stacklevel=3)

    def state(
        self,
        params: Params | None = None,
        *,
        position=None,
        orientation=None,
        velocity=None,
        angular_velocity=None,
        body_angular_velocity=None,
        angular_momentum=None,
        time=0.0,
        dtype=None,
    ) -> State:
        """Build a :class:`jaxrb.State`.

        Per-body arguments take one value for every body, an ``(N, ...)`` array, or a
        ``{body_name: value}`` dict (other bodies keep the default).

        Args:
            params: used to turn an angular velocity into angular momentum. Default:
                ``self.params()``, the bodies' own mass properties; pass your params if
                you changed the inertia. Its dtype is also the state's default dtype.
            position: centres of mass (m, world). Default 0.
            orientation: unit quaternions ``(w, x, y, z)``, body to world. Default identity.
            velocity: centre-of-mass velocities (m/s, world). Default 0.
            angular_velocity: rad/s, world frame; or
            body_angular_velocity: rad/s, body frame; or
            angular_momentum: kg m^2/s, world frame, about the centre of mass.
                At most one of the three. Default: at rest.
            time: s.
        """
        if params is not None:
            if not isinstance(params, Params):
                raise ValueError(f"params must be an rb.Params (from scene.params()), got {type(params).__name__}.")
            if params.inertia.shape != (self.num_bodies, 3, 3):
                raise ValueError(
                    f"params is for {params.inertia.shape[0]} bodies (inertia shape {params.inertia.shape}); "
                    f"this scene has {self.num_bodies}. Build it with this scene's .params()."
                )
            if dtype is None:
                dtype = params.inertia.dtype
        dtype = _canonical_dtype(dtype)
        given = [k for k, v in (("angular_velocity", angular_velocity),
                                ("body_angular_velocity", body_angular_velocity),
                                ("angular_momentum", angular_momentum)) if v is not None]
        if len(given) > 1:
            raise ValueError(f"Give at most one of angular_velocity, body_angular_velocity, "
                             f"angular_momentum; got {given}.")
        zeros3 = np.zeros(3)
        position = self._per_body("position", position, (3,), zeros3, dtype)
        velocity = self._per_body("velocity", velocity, (3,), zeros3, dtype)
        orientation = self._per_body("orientation", orientation, (4,), np.array([1.0, 0, 0, 0]), dtype)
        if not _is_traced(orientation):
            norms, bad = spatial.non_unit_norms(orientation)
            if np.any(bad):
                names = [self.body_names[i] for i in np.flatnonzero(bad)]
                raise ValueError(f"orientation of {names} is not a unit quaternion (norms {norms[bad]}). "
                                 + spatial.UNIT_QUATERNION_ADVICE)
        orientation = spatial.quat_normalize(orientation)
        if not _is_traced((position, orientation)):
            # The shapes' centres (a shape offset from the centre of mass turns with the body),
            # as the narrow phase places them: the centre of mass had been tested, which warned
            # for a sphere 0.3 m clear of a wall and missed one 0.45 m inside it.
            offsets = np.asarray([b.shape_offset for b in self.bodies], dtype=float).reshape(-1, 3)
            centres = np.asarray(position, float) + np.asarray(spatial.quat_rotate(np.asarray(orientation, float),
                                                                                    offsets))
            self._warn_inside_planes(centres)
        if angular_momentum is not None:
            l_world = self._per_body("angular_momentum", angular_momentum, (3,), zeros3, dtype)
        elif angular_velocity is None and body_angular_velocity is None:
            l_world = jnp.zeros_like(position)
        else:
            params = self.params(dtype=dtype) if params is None else params
            if angular_velocity is not None:
                omega_world = self._per_body("angular_velocity", angular_velocity, (3,), zeros3, dtype)
                omega_body = spatial.quat_rotate_inverse(orientation, omega_world)
            else:
                omega_body = self._per_body(
                    "body_angular_velocity", body_angular_velocity, (3,), zeros3, dtype
                )
            l_body = spatial.matvec(body_inertia(params).astype(dtype), omega_body)
            l_world = spatial.quat_rotate(orientation, l_body)
        time = jnp.asarray(time, dtype=dtype)
        if time.shape != () or (not _is_traced(time) and not np.isfinite(float(time))):
            raise ValueError(f"time must be a finite scalar (s), got {time}.")
        return State(
            position=position,
            orientation=orientation,
            velocity=velocity,
            angular_momentum=l_world,
            time=time,
        )


def _plane_repr(normal, offset) -> str:
    return f"rb.Plane(({', '.join(f'{x + 0.0:.6g}' for x in normal)}), {offset + 0.0:.6g})"  # + 0.0: no -0


def _checked_extra(extra):
    """``Params.extra`` as given, once each leaf is a number or a numeric array: a string or
    an object leaf failed later, inside the first step, with a message about
    ``custom_jvp_call``'s arguments."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(extra):
        if _is_traced(leaf) or isinstance(leaf, jax.Array):
            continue
        kind = np.asarray(leaf).dtype.kind if not isinstance(leaf, (str, bytes)) else "U"
        if kind not in "biufc":
            raise ValueError(
                f"extra{jax.tree_util.keystr(path)} is {leaf!r}: every leaf of extra must be a number or an "
                f"array of numbers (extra holds your force functions' differentiable parameters); "
                f"keep names and settings in the force function's closure."
            )
    return extra
