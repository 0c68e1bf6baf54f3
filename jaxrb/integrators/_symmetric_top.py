"""Symplectic splitting of the free rigid body about a sphere of the middle moment.

The kinetic energy in the principal frame (moments ``I_0 <= I_1 <= I_2``, body momentum
``P``) is written as a sphere's plus two corrections::

    T = |P|^2 / 2 I_1  +  k_0 P_0^2 / 2  +  k_2 P_2^2 / 2,    k_i = 1/I_i - 1/I_1.

The sphere's flow turns the body about its momentum, which is the world ``L``, at
``|L| / I_1``; it leaves ``P`` unchanged and commutes with both corrections (it multiplies
the attitude on the world side, they on the body side, and each leaves the other's rate
unchanged). So only the two corrections are split (Strang), and the error constants are
products of ``k_0`` and ``k_2``: the split is exact for every symmetric top (``k_0 = 0``
or ``k_2 = 0``), and its O(dt^2) error vanishes as either pair of moments merges. This is
the kind of split that F. Fasso compares with the principal-axis ones ("Comparison of
splitting algorithms for the rigid body", J. Comput. Phys. 189 (2003)), with the middle
moment as the sphere's so that neither merging pair is split.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from .. import spatial
from ..state import Params, State
from ._base import Integrator
from ._splitting import _coupled_turn, _rotate_about_principal_axis, principal_frame_step, principal_frames

__all__ = ["SymmetricTopSplitting"]

# The (0, 1) and (1, 0) entries: the block of the smaller pair of principal moments.
_SMALLER_PAIR = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


def _turn_about(momentum, half_rate):
    """The quaternion ``(cos a, sin a L/|L|)`` (4,) of a turn about ``momentum`` ``L`` (3,)
    by ``2 a``, with the half angle ``a = half_rate |L|`` (``half_rate = dt / 2 I``,
    s/(kg m^2)); the identity at ``L = 0``, with finite derivatives there
    (``sin a / |L| -> half_rate``)."""
    size = spatial.safe_norm(momentum)
    moving = size > 0
    safe = jnp.where(moving, size, 1.0)
    half_angle = half_rate * size
    scale = jnp.where(moving, jnp.sin(half_angle) / safe, half_rate)
    return jnp.concatenate([jnp.cos(half_angle)[None], scale * momentum])


class SymmetricTopSplitting(Integrator):
    """Splitting about a sphere of the middle principal moment, exact for symmetric tops.

    The free step (moments ascending, ``k_i = 1/I_i - 1/I_1``)::

        S(dt) R_2(k_2, dt/2) R_0(k_0, dt) R_2(k_2, dt/2)

    where ``R_i(k, h)`` turns the body about its ``i``-th principal axis by ``h k P_i`` (the
    flow of ``k P_i^2 / 2``) and ``S(dt)`` about its momentum, the world ``L``, by
    ``dt |L| / I_1`` (the flow of the sphere ``|P|^2 / 2 I_1``, which commutes with both). Forces and torques
    enter by kick-drift-kick (:mod:`jaxrb.integrators._composition`), as in
    :class:`SymplecticSplitting`.

    * Order 2, symplectic and time-reversible (a symmetric composition of exact flows).
    * Torque-free: world angular momentum exactly, ``|P|`` exactly, energy error O(dt^2)
      and bounded. The error constants carry ``k_0 k_2``: **exact** for any symmetric top
      (two equal moments: within 1.5e-14 rad of the closed form after 100 steps of 0.1 s,
      where :class:`SymplecticSplitting` is 0.05 rad off), and small for nearly symmetric
      bodies (moments 1, 1.05, 1.8, dt = 0.01, 10 s: 290x closer than
      :class:`SymplecticSplitting` from omega0 = (0.3, 2.5, -0.5) rad/s, 100x from
      (-0.3, 0.9, -0.5)).
    * The trade, on a strongly asymmetric body (the top ``I = (1, 2, 3)``, dt = 0.01): the
      attitude error is 3.6x smaller than :class:`SymplecticSplitting`'s (3.8e-6 against
      1.4e-5 rad at 10 s), the energy error 12x larger (1.7e-6 against 1.5e-7 over 1e5
      steps; 7.0e-2 against 4.3e-2 at ``|omega| dt = 2``). Both stay bounded. On the
      spinning rod (1e-4, 1, 1 + 5e-5), omega0 = (100, 1, 0), its attitude error is 1.3x
      larger (4.5e-3 against 3.5e-3 rad at 10 s, dt = 0.01).
    * Nearly repeated moments: the split never separates the two moments of a nearly
      degenerate pair (one of them is the sphere's), so its result does not depend on the
      principal axes chosen in their plane, which turn at a rate ~1/delta with the inertia.
      Inertia derivatives therefore stay O(dt^2)-accurate there, where
      :class:`SymplecticSplitting`'s carry an O(dt^2 / delta) term
      (``tests/test_integrators.py``).
    * Cost: three axis rotations and one turn about ``L`` (four sin/cos pairs), against
      :class:`SymplecticSplitting`'s five axis rotations, and the same once-per-rollout
      principal frames. Side by side on this 2-core CPU (``benchmarks/free_body.py``,
      float32): 1.4x more steps per second for one body, 1.6x for 64 to 4096; a single float64
      body over 2,000 steps: forward 1.3x faster, gradient 1.1x slower (benchmarks/README.md,
      stop 89).
    * Large steps: never NaN, ``L`` exact and the attitude a rotation at any step, so the
      energy stays between ``|L|^2 / 2 I_2`` and ``|L|^2 / 2 I_0``; the sphere's turn is
      exact at any rate, so a fast spin of a (nearly) symmetric body stays (nearly) exact.
      On the asymmetric top the energy error reaches 2x at ``|omega| dt`` a little above 2
      (``benchmarks/work_precision.py``'s stability limit: 1.99, as
      :class:`SymplecticSplitting`'s).
    """

    order: ClassVar[int] = 2

    def precompute(self, params: Params):
        """The principal frames, as :meth:`SymplecticSplitting.precompute`, with the repeated
        moments' coupling ``(N, 3, 3)`` split once into its two parts: ``(inverse_moments,
        principal, inner, outer)``, ``inner`` the smaller pair's ``(0, 1)`` block and
        ``outer`` the rest (see :meth:`free_rotation`)."""
        inverse_moments, principal, coupling = principal_frames(params)
        inner = coupling * _SMALLER_PAIR[None]
        return inverse_moments, principal, inner, coupling - inner

    def free_rotation(self, frames, orientation, angular_momentum, dt: float):
        """Torque-free attitude flow over ``dt`` at constant world ``L``; ``(N, 4)``."""

        def rotate(inverse_moments, principal, inner, outer, q, l_world):
            sphere = inverse_moments[1]
            # The repeated moments' coupling (zero in value, with a derivative; see
            # SymplecticSplitting) belongs to the correction whose pair it couples: the
            # smaller pair's (0, 1) block to k_0's turn in the middle of the chain, the rest
            # (the larger pair's, and a sphere's other blocks) outside it, half a step on
            # either side. All of it outside, a top with two equal smaller moments got an
            # inertia gradient O(dt^2) off the derivative of its own map (stop 89's review:
            # 1.0e-3 of the largest entry at dt = 0.1; the finite differences' moments are
            # apart, where k_0's turn in the middle carries the difference). The inner block
            # turns once, for the whole step, beside k_0's turn: where it has a derivative
            # (moments equal within sqrt(eps)) k_0's turn is the identity to that precision,
            # so one side is the middle; in halves on both sides the gradient cost 15% more.
            # (``precompute`` splits it, once per rollout.)
            q = spatial.quat_multiply(q, principal)  # principal frame -> world
            q, momentum = _coupled_turn(q, spatial.quat_rotate_inverse(q, l_world), 0.5 * dt * outer)
            # Each rotation its own kernel, as in SymplecticSplitting: fused, XLA:CPU
            # recomputed the chain's shared terms (there, each extra rotation ~5x slower).
            pose = jax.lax.optimization_barrier(jnp.concatenate([q, momentum]))
            # The largest moment's correction outermost: against the smallest's outermost (the
            # other symmetric order), its attitude error was 1.9x smaller on the top (1, 2, 3)
            # and 2.2x on (1, 1.05, 1.8) at dt = 0.01 over 10 s, and 1.9x larger on the
            # spinning rod (1e-4, 1, 1 + 5e-5); energy errors within 5% of each other on
            # the top.
            pose = _rotate_about_principal_axis(pose, 2, 0.5 * dt * (inverse_moments[2] - sphere))
            pose = jax.lax.optimization_barrier(pose)
            pose = jnp.concatenate(_coupled_turn(pose[:4], pose[4:], dt * inner))
            pose = _rotate_about_principal_axis(pose, 0, dt * (inverse_moments[0] - sphere))
            pose = jax.lax.optimization_barrier(pose)
            pose = _rotate_about_principal_axis(pose, 2, 0.5 * dt * (inverse_moments[2] - sphere))
            pose = jax.lax.optimization_barrier(pose)
            q, _ = _coupled_turn(pose[:4], pose[4:], 0.5 * dt * outer)
            q = spatial.quat_multiply(q, spatial.quat_conjugate(principal))
            # The sphere: a turn about the world L by dt |L| / I_1, on the world side (it
            # commutes with every turn on the body side). Made from L, off the chain's path,
            # and its own kernel: after the chain, from the body momentum, a single body's
            # forward was 1.9x slower than here and its gradient 1.4x (with or without the
            # barrier, one or the other was slow; benchmarks/README.md, stop 89).
            q = spatial.quat_multiply(jax.lax.optimization_barrier(_turn_about(l_world, 0.5 * dt * sphere)), q)
            return spatial.quat_normalize(q)

        return jax.vmap(rotate)(*frames, orientation, angular_momentum)

    def step(self, scene, params: Params, state: State, dt: float, derived=None) -> State:
        return principal_frame_step(self, scene, params, state, dt, derived)
