"""Which parameters a fit may change, and unconstrained coordinates that keep them physical.

An optimiser moves freely in ``R^n``; the physical parameters it stands for must stay
physical at every iterate, not only at the end. Each field of :class:`jaxrb.Params` has
its own smooth, invertible map from unconstrained coordinates ``z``:

============================  ======================================  ==================
field                         physical value from ``z``               keeps
============================  ======================================  ==================
``mass``, ``*_damping``       ``exp(z)``                              ``> 0``
``restitution``               ``sigmoid(z)``                          ``(0, 1)``
``friction``                  ``mu_max sigmoid(z)``                   ``(0, mu_max)``
``inertia`` (6 per body)      ``I = tr(S) E - S``, ``S = L L^T``,     SPD and the strict
                              ``L`` lower triangular with             triangle inequality
                              diagonal ``exp(z_0..2)``
``gravity``, ``extra``        ``z``                                   (unconstrained)
============================  ======================================  ==================

The inertia map is the log-Cholesky parameterisation of the pseudo-inertia (Rucker and
Wensing, 2022) about the centre of mass: ``S = int r r^T dm`` is the second moment of the
mass distribution, ``I = tr(S) E - S``, and ``S`` positive definite is exactly the
condition that ``I`` is positive definite *and* satisfies ``I_i + I_j > I_k`` (the
principal moments are ``I_i = s_j + s_k``). So every ``z`` in ``R^6`` is a body that could
exist, and every such body has exactly one ``z``.

Entries that are not free keep their value from the template ``Params``; free entries
are chosen per field: all of it, a list of body names (per-body fields) or contact pairs
(per-pair fields), or a boolean mask.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from .._static import static_switch
from ..forces import AngularDamping, LinearDamping
from ..scene import Scene
from ..state import Params

__all__ = ["FreeParameters", "inertia_from_unconstrained", "inertia_to_unconstrained", "FIELDS"]

_PER_BODY = ("mass", "inertia", "linear_damping", "angular_damping")
_PER_PAIR = ("restitution", "friction")
FIELDS = (*_PER_BODY, *_PER_PAIR, "gravity", "extra")
_INERTIA_ENTRIES = ("xx", "yy", "zz", "xy", "xz", "yz")
_LOWER = ((1, 0), (2, 0), (2, 1))


# ------------------------------------------------------------------- inertia map


def inertia_from_unconstrained(z: jax.Array) -> jax.Array:
    """``(..., 6)`` log-Cholesky coordinates -> ``(..., 3, 3)`` inertia (kg m^2), always physical."""
    diag = jnp.exp(z[..., :3])
    zero = jnp.zeros_like(z[..., 0])
    chol = jnp.stack([
        jnp.stack([diag[..., 0], zero, zero], -1),
        jnp.stack([z[..., 3], diag[..., 1], zero], -1),
        jnp.stack([z[..., 4], z[..., 5], diag[..., 2]], -1),
    ], -2)
    second_moment = chol @ jnp.swapaxes(chol, -1, -2)
    # I = tr(S) E - S, with each moment summed from the other two, I_ii = S_jj + S_kk: the
    # trace minus S_ii cancelled, and a thin rod's small moment came back with a relative
    # error of eps I_max / I_min (8e-8 for diag(1e-10, 1, 1), round trip).
    s = jnp.diagonal(second_moment, axis1=-2, axis2=-1)
    moments = jnp.stack([s[..., 1] + s[..., 2], s[..., 0] + s[..., 2], s[..., 0] + s[..., 1]], -1)
    eye = jnp.eye(3, dtype=z.dtype).reshape((1,) * (z.ndim - 1) + (3, 3))
    return moments[..., None] * eye - second_moment * (1.0 - eye)


def inertia_to_unconstrained(inertia) -> np.ndarray:
    """Inverse of :func:`inertia_from_unconstrained` (NumPy, concrete values).

    Raises:
        ValueError: if the inertia is not ``(..., 3, 3)``, not finite, not symmetric (to
            1e-6 of its largest entry), or not positive definite with the strict triangle
            inequality (its second moment ``S`` is not positive definite).
    """
    inertia = np.asarray(inertia, dtype=float)
    if inertia.ndim < 2 or inertia.shape[-2:] != (3, 3):
        raise ValueError(f"An inertia must have shape (..., 3, 3), got {inertia.shape}.")
    if not np.all(np.isfinite(inertia)):
        raise ValueError(f"An inertia is not finite: {inertia}.")
    _check_symmetric(inertia, "An inertia")
    # S = tr(I)/2 E - I, each S_ii = (I_jj + I_kk - I_ii)/2 summed as (small + (large - I_ii))/2:
    # by the triangle inequality the difference of the two large moments is exact where a rod's
    # small one would otherwise be lost in their sum.
    symmetric = 0.5 * (inertia + np.swapaxes(inertia, -1, -2))
    moments = np.diagonal(symmetric, axis1=-2, axis2=-1)
    others = np.stack([moments[..., [1, 2]], moments[..., [0, 2]], moments[..., [0, 1]]], -2)  # (..., 3, 2)
    s_diag = 0.5 * (others.min(-1) + (others.max(-1) - moments))
    second_moment = -symmetric * (1.0 - np.eye(3)) + s_diag[..., None] * np.eye(3)
    try:
        chol = np.linalg.cholesky(second_moment)
    except np.linalg.LinAlgError:
        raise ValueError(
            "An initial inertia is not a physical body's: it must be symmetric positive definite "
            "and satisfy the strict triangle inequality I1 + I2 > I3 (a flat plate or a thin rod is "
            "its limit). Start the fit from a solid body's inertia, e.g. rb.mass_properties(...)."
        ) from None
    diag = np.diagonal(chol, axis1=-2, axis2=-1)
    return np.concatenate([np.log(diag), np.stack([chol[..., i, j] for i, j in _LOWER], -1)], -1)


def _check_symmetric(inertia: np.ndarray, what: str) -> None:
    """Raise if an inertia ``(..., 3, 3)`` differs from its transpose by more than 1e-6 of
    its largest entry: its six entries are what a fit moves, and the map would replace an
    asymmetric one by its symmetric part without a word."""
    asymmetry = np.max(np.abs(inertia - np.swapaxes(inertia, -1, -2)), initial=0.0)
    if asymmetry > 1e-6 * np.max(np.abs(inertia), initial=0.0):
        raise ValueError(f"{what} is not symmetric (|I - I^T| up to {asymmetry:.3g}): an inertia tensor is, and "
                         f"its six entries are what is fitted. Give (I + I^T) / 2 if that is what you meant.")


# ------------------------------------------------------------------ free entries


def _logit(p):
    return np.log(p) - np.log1p(-p)


@dataclasses.dataclass(frozen=True, eq=False)
class FreeParameters:
    """The free entries of a :class:`jaxrb.Params`, and their unconstrained coordinates.

    Args:
        scene: the scene the parameters belong to (for names and shapes).
        params: the template: the initial guess for free entries, the fixed value of the
            others.
        free: the field name, a sequence of field names, or a dict ``{field: which}`` with
            ``which`` ``True`` (all entries), a list of body names (``mass``, ``inertia``,
            ``*_damping``), a list of contact pairs ``("a", "b")`` or pair indices
            (``restitution``, ``friction``), or a boolean mask of the field's leading axis.
            ``gravity`` and ``extra`` are all-or-nothing.
        friction_max: upper bound of a free friction coefficient (the scaled sigmoid's scale).
        for_fit: ``params`` is a fit's start, so every free value must lie strictly inside
            its field's domain (a boundary, e.g. ``e = 0``, has no unconstrained
            coordinate). ``False`` for a point of analysis that uses no map
            (:func:`jaxrb.identify.identifiability` at ``e = 0`` or at a flat plate's
            inertia): free values must then only be finite.

    Every free value must be finite, and a free inertia symmetric (its six entries are
    what a fit or a report moves; an asymmetric one would be replaced by its symmetric
    part without a word).

    Attributes:
        masks: ``{field: bool array}`` for the free fields (``None`` for ``extra``).
        labels: one name per free scalar, in :meth:`to_vector` order, e.g. ``mass[ball]``,
            ``inertia[box].xy``, ``restitution[ball-ground]``, ``gravity.z``.
    """

    scene: Scene
    params: Params
    free: object
    friction_max: float = 2.0
    for_fit: bool = True
    masks: dict = dataclasses.field(init=False)
    labels: tuple = dataclasses.field(init=False)

    def __post_init__(self):
        if not isinstance(self.params, Params):
            raise ValueError(f"params must be an rb.Params (scene.params()), got {type(self.params).__name__}.")
        self.scene.check_shapes(self.params)  # params of another scene
        object.__setattr__(self, "for_fit", static_switch("for_fit", self.for_fit))
        if isinstance(self.friction_max, bool) or not (isinstance(self.friction_max, (int, float, np.floating))
                                                        and 0 < self.friction_max < np.inf):
            raise ValueError(f"friction_max must be a positive, finite number (the free friction's upper bound; "
                             f"its map is friction_max * sigmoid(u)), got {self.friction_max!r}.")
        spec = self.free
        if spec is None or isinstance(spec, (bool, int, float)):
            raise ValueError(f"free must name what to fit: a field name, a list of them, or a dict (e.g. "
                             f"'restitution' or {{'mass': ['ball']}}), got {spec!r}. Fields: {FIELDS}.")
        if isinstance(spec, str):
            spec = {spec: True}
        elif not isinstance(spec, dict):
            spec = list(spec)
            if not all(isinstance(name, str) for name in spec):  # ["mass", {...}] failed as "unhashable type"
                raise ValueError(f"free as a list takes field names only, got {spec!r}; to select entries of a "
                                 f"field use a dict, e.g. {{'mass': ['ball'], 'restitution': True}}.")
            spec = dict.fromkeys(spec, True)
        if not spec:
            raise ValueError(f"Nothing is free: give at least one of {FIELDS} in free=.")
        masks = {}
        for field, which in spec.items():
            if field not in FIELDS:
                raise ValueError(f"Unknown parameter {field!r} in free=; choose from {FIELDS}.")
            masks[field] = self._mask(field, which)
            if masks[field] is not None and not masks[field].any():
                raise ValueError(f"free[{field!r}] selects no entry; drop it or select some.")
        object.__setattr__(self, "masks", masks)
        self._check_inside()
        object.__setattr__(self, "labels", tuple(self._labels()))

    # -- building

    def _mask(self, field, which):
        scene = self.scene
        declared = {type(m) for m in scene.force_models}
        if field == "extra":
            if which is not True:
                raise ValueError("free['extra'] must be True: the user pytree is fitted as a whole.")
            if self.params.extra is None:
                raise ValueError("free includes 'extra' but params.extra is None.")
            for path, leaf in jax.tree_util.tree_leaves_with_path(self.params.extra):
                if not jnp.issubdtype(jnp.result_type(leaf), jnp.floating):
                    raise ValueError(f"params.extra{jax.tree_util.keystr(path)} has dtype {jnp.result_type(leaf)}: "
                                     f"a fitted value must be floating point (e.g. 3.0, not 3).")
            return None
        unused = {"gravity": scene.gravity is None and "the scene was built with gravity=None",
                  "linear_damping": LinearDamping not in declared and "the scene has no rb.LinearDamping()",
                  "angular_damping": AngularDamping not in declared and "the scene has no rb.AngularDamping()"}
        if unused.get(field):
            raise ValueError(f"free includes {field!r}, but {unused[field]}: it is not simulated, so the data "
                             f"cannot determine it (a fit would stop at once, its gradient zero).")
        size = {"gravity": 3}.get(field, scene.num_contact_pairs if field in _PER_PAIR else scene.num_bodies)
        if which is True:
            return np.ones(size, bool)
        if field == "gravity":
            raise ValueError("free['gravity'] must be True (all three components).")
        if isinstance(which, (str, bool, int, float, np.generic)) or (hasattr(which, "dtype") and np.ndim(which) == 0):
            raise ValueError(f"free[{field!r}] must be True, a list of names or indices, or a boolean mask of "
                             f"shape ({size},); got {which!r}. (One entry: put it in a list.)")
        array = np.asarray(which) if hasattr(which, "dtype") else None  # NumPy or JAX arrays
        if array is not None and array.dtype == bool or (
                array is None and len(which) and all(isinstance(x, (bool, np.bool_)) for x in which)):
            mask = np.asarray(which, bool)
            if mask.shape != (size,):
                raise ValueError(f"free[{field!r}] mask has shape {mask.shape}; {field} needs ({size},).")
            return mask
        if array is not None and not np.issubdtype(array.dtype, np.integer):
            raise ValueError(f"free[{field!r}]: an array must be a boolean mask or integer indices, got dtype "
                             f"{array.dtype}.")
        mask = np.zeros(size, bool)
        for item in (array.tolist() if array is not None else which):
            mask[self._index(field, item)] = True
        return mask

    def _index(self, field, item) -> int:
        scene = self.scene
        if field in _PER_BODY:
            if isinstance(item, str):
                return scene.index(item)
            if not isinstance(item, (int, np.integer)) or isinstance(item, bool) or not 0 <= item < scene.num_bodies:
                raise ValueError(f"free[{field!r}]: {item!r} is not a body of the scene: give a name or an index "
                                 f"in [0, {scene.num_bodies}).")
            return int(item)
        pairs = list(scene.contact_pairs)
        if isinstance(item, (int, np.integer)) and not isinstance(item, bool):
            if not 0 <= item < len(pairs):
                raise ValueError(f"free[{field!r}]: pair index {item} out of range; the scene has {len(pairs)} pairs.")
            return int(item)
        if isinstance(item, str):
            raise ValueError(f"free[{field!r}]: {item!r} is a body, not a contact pair: give pairs as tuples in a "
                             f"list, e.g. [{pairs[0]!r}], or pair indices.")
        pair = tuple(item)
        for candidate in (pair, pair[::-1]):
            if candidate in pairs:
                return pairs.index(candidate)
        raise ValueError(f"free[{field!r}]: {pair} is not a contact pair of the scene; its pairs are {pairs}.")

    def _check_inside(self):
        """Free entries must be finite, a free inertia symmetric, and, for a fit, every free
        value strictly inside its domain (a boundary has no ``z``)."""
        p = self.params
        for field, mask in self.masks.items():
            values = jax.tree.leaves(p.extra) if field == "extra" else [np.asarray(getattr(p, field))[mask]]
            if not all(np.all(np.isfinite(np.asarray(v, float))) for v in values):
                raise ValueError(f"The free {field} is not finite: {values if field == 'extra' else values[0]}. "
                                 f"Give a finite {'guess' if self.for_fit else 'point of analysis'}.")
        if "inertia" in self.masks:
            _check_symmetric(np.asarray(p.inertia, float)[self.masks["inertia"]], "A free inertia")
        if not self.for_fit:
            return
        checks = {
            "mass": (p.mass, lambda x: x > 0, "positive"),
            "linear_damping": (p.linear_damping, lambda x: x > 0, "positive (start from a small value, not 0)"),
            "angular_damping": (p.angular_damping, lambda x: x > 0, "positive (start from a small value, not 0)"),
            "restitution": (p.restitution, lambda x: (x > 0) & (x < 1), "strictly inside (0, 1), e.g. 0.5"),
            "friction": (p.friction, lambda x: (x > 0) & (x < self.friction_max),
                         f"strictly inside (0, friction_max={self.friction_max})"),
        }
        for field, (value, ok, what) in checks.items():
            if field in self.masks:
                value = np.asarray(value, float)
                bad = self.masks[field] & ~ok(value)
                if bad.any():
                    raise ValueError(f"The initial {field} {value[bad]} must be {what} for a fit.")
        if "inertia" in self.masks:
            inertia_to_unconstrained(np.asarray(p.inertia, float)[self.masks["inertia"]])

    def _labels(self):
        names = self.scene.body_names
        pairs = ["-".join(pair) for pair in self.scene.contact_pairs]
        for field in FIELDS:
            if field not in self.masks:
                continue
            mask = self.masks[field]
            if field == "inertia":
                yield from (f"inertia[{names[i]}].{e}" for i in np.flatnonzero(mask) for e in _INERTIA_ENTRIES)
            elif field in _PER_BODY:
                yield from (f"{field}[{names[i]}]" for i in np.flatnonzero(mask))
            elif field in _PER_PAIR:
                yield from (f"{field}[{pairs[i]}]" for i in np.flatnonzero(mask))
            elif field == "gravity":
                yield from ("gravity.x", "gravity.y", "gravity.z")
            else:
                leaves = jax.tree.leaves(self.params.extra)
                yield from (f"extra[{k}][{j}]" for k, leaf in enumerate(leaves) for j in range(np.size(leaf)))

    # -- unconstrained coordinates

    def unconstrained(self, params: Params | None = None) -> dict:
        """``z``: a dict ``{field: array}`` for the free fields (full leading axes), from ``params``.

        Fixed entries of a free field get a harmless value; they never reach the output.
        """
        p = self.params if params is None else params
        z = {}
        for field, mask in self.masks.items():
            if field == "extra":
                z[field] = jax.tree.map(jnp.asarray, p.extra)
                continue
            value = np.asarray(getattr(p, field), float)
            dtype = jnp.asarray(getattr(p, field)).dtype
            if field == "inertia":
                safe = np.where(mask[:, None, None], value, np.eye(3))
                z[field] = jnp.asarray(inertia_to_unconstrained(safe), dtype)
                continue
            if field in ("mass", "linear_damping", "angular_damping"):
                u = np.log(np.where(mask, value, 1.0))
            elif field == "restitution":
                u = _logit(np.where(mask, value, 0.5))
            elif field == "friction":
                u = _logit(np.where(mask, value, 0.5 * self.friction_max) / self.friction_max)
            else:
                u = value
            z[field] = jnp.asarray(u, dtype)
        return z

    def moving(self) -> np.ndarray:
        """Indices ``(p,)`` of the entries of ``ravel_pytree(z)`` that move a free value (a
        free field's fixed entries have coordinates too, which move nothing). Forward mode
        differentiates these alone: one JVP per free scalar, not per coordinate of every
        free field (one free mass of 40 bodies: 1 JVP an iteration, not 40)."""
        ones = {field: np.ones(np.shape(x)) if field in ("gravity", "extra") else
                np.broadcast_to(self.masks[field].reshape(-1, *[1] * (np.ndim(x) - 1)), np.shape(x)).astype(float)
                for field, x in self.unconstrained().items() if field != "extra"}
        if "extra" in self.masks:
            ones["extra"] = jax.tree.map(lambda x: np.ones(np.shape(x)), self.params.extra)
        flat, _ = jax.flatten_util.ravel_pytree(jax.tree.map(jnp.asarray, ones))
        return np.flatnonzero(np.asarray(flat))

    def physical(self, z: dict) -> Params:
        """The :class:`jaxrb.Params` that ``z`` stands for (traceable; physical for every ``z``)."""
        changes = {}
        for field, mask in self.masks.items():
            if field == "extra":
                changes[field] = z[field]
                continue
            u = z[field]
            if field == "inertia":
                value = inertia_from_unconstrained(u)
                changes[field] = jnp.where(mask[:, None, None], value, self.params.inertia)
                continue
            if field in ("mass", "linear_damping", "angular_damping"):
                # Within the dtype's normal range: a Levenberg-Marquardt step of -1e3 in a log
                # coordinate had made a mass exactly 0 (exp underflowed).
                info = jnp.finfo(u.dtype)
                value = jnp.exp(jnp.clip(u, math.log(info.tiny), math.log(info.max)))
            elif field == "restitution":
                value = jax.nn.sigmoid(u)
            elif field == "friction":
                value = self.friction_max * jax.nn.sigmoid(u)
            else:
                value = u
            changes[field] = jnp.where(mask, value, getattr(self.params, field))
        return dataclasses.replace(self.params, **changes)

    # -- the free physical values as one vector (for sensitivities and covariances)

    def to_vector(self, params: Params) -> jax.Array:
        """The free physical values ``(p,)``, in :attr:`labels` order (inertia: xx yy zz xy xz yz)."""
        parts = []
        for field in FIELDS:
            if field not in self.masks:
                continue
            mask = self.masks[field]
            if field == "extra":
                parts += [jnp.ravel(leaf) for leaf in jax.tree.leaves(params.extra)]
            elif field == "inertia":
                i = params.inertia[np.flatnonzero(mask)]
                parts.append(jnp.stack([i[:, 0, 0], i[:, 1, 1], i[:, 2, 2], i[:, 0, 1], i[:, 0, 2], i[:, 1, 2]],
                                       -1).ravel())
            else:
                parts.append(jnp.ravel(getattr(params, field))[np.flatnonzero(mask)])
        return jnp.concatenate(parts)

    def from_vector(self, vector: jax.Array, params: Params | None = None) -> Params:
        """Inverse of :meth:`to_vector`: ``params`` (default: the template) with the free values set.

        Not constrained: it is for sensitivities around a physical point, not for optimising.
        """
        p = self.params if params is None else params
        changes, start = {}, 0
        for field in FIELDS:
            if field not in self.masks:
                continue
            mask = self.masks[field]
            if field == "extra":
                leaves, treedef = jax.tree.flatten(p.extra)
                new = []
                for leaf in leaves:
                    size = int(np.size(leaf))
                    new.append(vector[start:start + size].reshape(np.shape(leaf)))
                    start += size
                changes[field] = jax.tree.unflatten(treedef, new)
                continue
            idx = np.flatnonzero(mask)
            if field == "inertia":
                e = vector[start:start + 6 * len(idx)].reshape(-1, 6)
                start += 6 * len(idx)
                mat = jnp.stack([jnp.stack([e[:, 0], e[:, 3], e[:, 4]], -1),
                                 jnp.stack([e[:, 3], e[:, 1], e[:, 5]], -1),
                                 jnp.stack([e[:, 4], e[:, 5], e[:, 2]], -1)], -2)
                changes[field] = jnp.asarray(p.inertia).at[idx].set(mat)
            else:
                changes[field] = jnp.asarray(getattr(p, field)).at[idx].set(vector[start:start + len(idx)])
                start += len(idx)
        return dataclasses.replace(p, **changes)
