"""The interface every integrator implements."""

from __future__ import annotations

import abc
import numbers
from typing import TYPE_CHECKING, Any, ClassVar

import equinox as eqx
import numpy as np

if TYPE_CHECKING:
    from ..scene import Scene
    from ..state import Params, State

__all__ = ["Integrator"]


class Integrator(eqx.Module):
    """One time step of the rigid-body equations of motion.

    An integrator is an option object (like a diffrax solver): build it once, pass it to
    :func:`jaxrb.make_step`. Subclasses are final and state in their docstring their
    order, what they conserve, their cost per step and how they fail.

    ``step(scene, params, state, dt)`` must be a pure function of ``params`` and
    ``state``; ``scene`` and ``dt`` are static. ``prepare(state)`` brings a state built
    by :meth:`jaxrb.Scene.state` into the form the integrator carries (the identity for
    all but the rotation-matrix method); it must be idempotent.

    An integrator whose step needs quantities derived from ``params`` alone (such as
    principal axes) returns them from ``precompute(params)`` and accepts them as
    ``step(scene, params, state, dt, derived)``. :func:`jaxrb.rollout` then evaluates
    them once, outside its loop: XLA does not always hoist such loop-invariant work out
    of a vmapped ``lax.scan`` by itself.
    """

    #: Order of global accuracy in ``dt`` for smooth problems.
    order: ClassVar[int]

    @abc.abstractmethod
    def step(self, scene: Scene, params: Params, state: State, dt: float) -> State:
        raise NotImplementedError

    def prepare(self, state: State) -> State:
        return state

    def precompute(self, params: Params) -> Any:
        """Quantities derived from ``params`` alone for :meth:`step`; ``None`` if none."""
        return None

    def step_using(self, scene: Scene, params: Params, state: State, dt, derived) -> State:
        """:meth:`step`, given ``derived = self.precompute(params)``: passed on only where it
        is not ``None``, so that integrators without derived quantities keep the plain
        signature."""
        if derived is None:
            return self.step(scene, params, state, dt)
        return self.step(scene, params, state, dt, derived)


def truth_value(value):
    """``value`` as a Python ``bool`` when it is NumPy's; anything else unchanged, for
    the class's check (``jaxrb._static.static_switch``) to refuse. A field converter, as
    :func:`whole_number`."""
    return bool(value) if isinstance(value, np.bool_) else value


def whole_number(value):
    """``value`` as a Python ``int`` when it is a whole number of any integer type (a NumPy
    ``int64`` from a config array, say); anything else unchanged, for the class's check to
    refuse. A field converter: static fields must hash and compare as plain ints."""
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        return int(value)
    return value
