"""Contact dynamics: impulses with restitution, Coulomb friction, resting contact, impacts in the step.

A scene declares its contact pairs (:class:`jaxrb.Scene`, ``contacts=``); its step then runs
the contact stage configured by :class:`ContactSettings` (passed to :func:`jaxrb.make_step`):

* ``_layout``: the scene's contact slots, grouped into one vmapped narrow-phase call per
  shape-pair type and coloured for the solvers;
* ``_impulse``: seed 000's closed-form impulse for one colliding contact;
* ``_solver``: projected Gauss-Seidel with restitution targets and Coulomb's cone, every
  update unable to add energy;
* ``_lcp``: the exact normal solve (semismooth Newton on the seed's LCP);
* ``_penetration``: the deepest overlap at a state (what ``make_step(debug=True)`` checks);
* ``_step``: kick-solve-drift-kick with the time of impact located inside the step, and
  the split-impulse penetration correction.
"""

from ._impulse import collision_impulse as collision_impulse
from ._penetration import penetration as penetration
from ._settings import ContactSettings as ContactSettings
from ._step import resolve_impacts as resolve_impacts
