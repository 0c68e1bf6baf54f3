"""Time integrators behind one interface, :class:`Integrator`.

| integrator | order | conserves (torque-free) | force evaluations per step |
|---|---|---|---|
| :class:`ExplicitEuler` | 1 | ``L`` exactly | 1 |
| :class:`SemiImplicitEuler` | 1 | ``L`` exactly, ``|q| = 1`` | 1 |
| :class:`ImplicitGyroscopic` | 1 | nothing; energy and ``|L|`` never increase | 1 (+ Newton) |
| :class:`ImplicitMidpoint` | 2 | ``L`` exactly, energy to solver tolerance | 2 (+ Newton) |
| :class:`SymplecticSplitting` | 2 | ``L`` exactly, energy error bounded | 2 |
| :class:`SymmetricTopSplitting` | 2 | ``L`` exactly, energy error bounded (exact for symmetric tops) | 2 |
| :class:`RK4` | 4 | ``L`` exactly | 4 |
| :class:`RKMK4` | 4 | ``L`` exactly, ``|q| = 1`` | 4 |

Adaptive, error-controlled solvers (diffrax) are in :mod:`jaxrb.ode`.
"""

from ._base import Integrator as Integrator
from ._euler import ExplicitEuler as ExplicitEuler
from ._euler import SemiImplicitEuler as SemiImplicitEuler
from ._implicit import ImplicitGyroscopic as ImplicitGyroscopic
from ._implicit import ImplicitMidpoint as ImplicitMidpoint
from ._lie_group import RKMK4 as RKMK4
from ._runge_kutta import RK4 as RK4
from ._splitting import SymplecticSplitting as SymplecticSplitting
from ._symmetric_top import SymmetricTopSplitting as SymmetricTopSplitting

__all__ = [
    "Integrator",
    "ExplicitEuler",
    "SemiImplicitEuler",
    "ImplicitGyroscopic",
    "ImplicitMidpoint",
    "SymplecticSplitting",
    "SymmetricTopSplitting",
    "RK4",
    "RKMK4",
]
