"""Time integrators behind one interface, :class:`Integrator`.

| integrator | order | conserves (torque-free) | force evaluations per step |
|---|---|---|---|
| :class:`ExplicitEuler` | 1 | ``L`` exactly | 1 |
| :class:`SemiImplicitEuler` | 1 | ``L`` exactly, ``|q| = 1`` | 1 |
| :class:`RK4` | 4 | ``L`` exactly | 4 |
"""

from ._base import Integrator as Integrator
from ._euler import ExplicitEuler as ExplicitEuler
from ._euler import SemiImplicitEuler as SemiImplicitEuler
from ._runge_kutta import RK4 as RK4

__all__ = ["Integrator", "ExplicitEuler", "SemiImplicitEuler", "RK4"]
