"""Kick-drift-kick: external forces split symmetrically around a torque-free flow.

The structure-preserving methods (:class:`ImplicitMidpoint`, :class:`SymplecticSplitting`)
integrate the *free* rigid body with special care. Forces and torques enter by Strang
splitting (the Stoermer-Verlet "kick-drift-kick"):

    v += dt/2 F_n / m,   L += dt/2 tau_n                       (kick, forces at t_n)
    x += dt v,           q <- free rotation of q under L for dt  (drift)
    v += dt/2 F_{n+1} / m,   L += dt/2 tau_{n+1}               (kick, forces at t_{n+1})

For forces that depend on position, attitude and time only this is the symmetric,
second-order, symplectic composition. For velocity-dependent forces (damping, or any
user function, which jaxrb cannot inspect) the closing kick evaluates the forces at the
predicted end-of-step velocities ``v + dt/2 F/m`` and ``L + dt/2 tau``. Its O(dt^2)
error then cancels that of the opening explicit kick, which keeps the step second order
(a plain Verlet step is only first order in a damping coefficient). That costs a third
force evaluation, and only scenes declaring a force model other than gravity pay it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from .. import spatial
from ..dynamics import linear_acceleration, wrench
from ..forces import Gravity
from ..state import Params, State

__all__ = ["kick_drift_kick"]

#: ``rotate(params, orientation (N, 4), angular_momentum (N, 3), dt) -> orientation (N, 4)``:
#: the torque-free attitude flow over ``dt`` at constant world angular momentum.
FreeRotation = Callable[[Params, object, object, float], object]


def _velocity_dependent(scene) -> bool:
    """Whether some declared force may depend on velocity (static; gravity does not)."""
    return any(not isinstance(model, Gravity) for model in scene.force_models)


def kick_drift_kick(scene, params: Params, state: State, dt: float, rotate: FreeRotation) -> State:
    """One Strang-split step: half kick, drift with the free rotation ``rotate``, half kick."""
    half = 0.5 * dt
    # A scene that declares no force (a torque-free body; the contact step's drift) has no
    # kicks: XLA does not fold ``v + dt/2 (0 / m)`` away (it is not ``v`` where m = 0). In
    # the bouncing ball's flight (benchmarks/README.md, stop 83) that was 0.1 kernels a
    # step forward and 0.4 in reverse mode, its derivative with respect to the mass.
    forced = bool(scene.force_models)
    velocity, angular_momentum = state.velocity, state.angular_momentum
    if forced:
        force, torque = wrench(scene, params, state)
        velocity = velocity + half * linear_acceleration(params, force)
        angular_momentum = angular_momentum + half * torque
    drifted = State(
        position=state.position + dt * velocity,
        orientation=rotate(params, state.orientation, angular_momentum, dt),
        velocity=velocity,
        angular_momentum=angular_momentum,
        time=state.time + dt,
    )
    if forced:
        force, torque = wrench(scene, params, drifted)
        if _velocity_dependent(scene):
            predicted = dataclasses.replace(
                drifted,
                velocity=velocity + half * linear_acceleration(params, force),
                angular_momentum=angular_momentum + half * torque,
            )
            force, torque = wrench(scene, params, predicted)
        velocity = velocity + half * linear_acceleration(params, force)
        angular_momentum = angular_momentum + half * torque
    return dataclasses.replace(
        drifted,
        velocity=velocity,
        angular_momentum=angular_momentum,
        rotation=None if state.rotation is None else spatial.quat_to_matrix(drifted.orientation),
    )
