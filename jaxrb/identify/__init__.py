"""Gradient-based identification of mass, inertia, restitution and friction.

A fit in ten lines::

    def loss(params, measured):
        _, traj = rb.rollout(step, params, scene.state(params, position=x0), 200)
        return jnp.mean((traj.position[:, 0, 2] - measured) ** 2)

    result = rb.identify.fit(loss, scene, guess, free="restitution", data=measured)
    print(result)                                   # fitted values, convergence
    report = rb.identify.identifiability(residuals, scene, result.params, "restitution", data=measured)
    print(report)                                   # std errors, unidentifiable directions

* :class:`FreeParameters`: which entries are free, and the maps from unconstrained
  coordinates that keep every iterate physical (log mass, sigmoid restitution, scaled
  sigmoid friction, log-Cholesky pseudo-inertia).
* :func:`fit`: optax (Adam by default), one experiment or many (vmapped), a progress bar,
  a convergence test. :func:`fit_least_squares`: Levenberg-Marquardt (forward-mode Jacobian).
* :func:`identifiability`: the sensitivity matrix's singular values, the directions the
  data cannot determine, and the Gauss-Newton covariance ``sigma^2 (J^T J)^-1``.
"""

from ._fit import FitResult as FitResult
from ._fit import default_optimizer as default_optimizer
from ._fit import fit as fit
from ._fit import fit_least_squares as fit_least_squares
from ._identifiability import Identifiability as Identifiability
from ._identifiability import identifiability as identifiability
from ._parameters import FreeParameters as FreeParameters
from ._parameters import inertia_from_unconstrained as inertia_from_unconstrained
from ._parameters import inertia_to_unconstrained as inertia_to_unconstrained
