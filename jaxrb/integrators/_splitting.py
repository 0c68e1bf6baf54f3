"""Symplectic splitting of the free rigid body (Dullweber, Leimkuhler & McLachlan 1997)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .. import spatial
from ..inertia import principal_axes, repeated_moment_coupling
from ..state import Params, State
from ._base import Integrator, whole_number
from ._composition import kick_drift_kick

__all__ = ["SymplecticSplitting"]


def _rotate_about_principal_axis(pose, k: int, rate):
    """Rotate the body about its ``k``-th principal axis ``e`` by ``a = rate P_k`` (rad).

    ``pose`` packs the attitude ``q`` (principal frame to world) and the body momentum
    ``P`` as ``(q_w, q_x, q_y, q_z, P_x, P_y, P_z)`` (7,); ``rate`` is the sub-flow's
    duration over the principal moment, ``dt_sub / I_k`` (s/(kg m^2)). ``q`` becomes
    ``q (cos a/2, sin a/2 e)`` and ``P`` turns the opposite way, ``Rot(e, -a) P``
    (Rodrigues' formula with ``e`` a coordinate axis: only the two other components move).
    ``cos a`` and ``sin a`` come from the half angle's by the double-angle formulas: one sine
    and one cosine per rotation, and the same rotation of ``q`` and ``P`` to rounding.
    """
    i, j = (k + 1) % 3, (k + 2) % 3  # (i, j, k) cyclic
    # One split, not an index read per component: reverse mode transposes it to one
    # concatenation, where each read became a zero-padded copy of its own (the ball's
    # gradient: 21 pad kernels a step). The pieces are made scalars again, and stacked at
    # the end as before: left (1,)-shaped and concatenated, the chain ran 1.7x slower for
    # 4096 vmapped bodies (benchmarks/README.md, "Sub-rotations read by one split").
    w, *rest = [x.reshape(()) for x in jnp.split(pose, 7)]
    v, p = rest[:3], rest[3:]
    half_angle = 0.5 * rate * p[k]
    c, s = jnp.cos(half_angle), jnp.sin(half_angle)
    q = [w * c - s * v[k], None, None, None]  # q (c, s e) = (w c - s v.e, c v + s w e + s v x e)
    q[1 + k] = c * v[k] + s * w
    q[1 + i] = c * v[i] + s * v[j]  # (v x e)_i = v_j, (v x e)_j = -v_i
    q[1 + j] = c * v[j] - s * v[i]
    cos_full, sin_full = c * c - s * s, 2.0 * s * c
    momentum = [None, None, None]
    momentum[k] = p[k]
    momentum[i] = cos_full * p[i] + sin_full * p[j]
    momentum[j] = cos_full * p[j] - sin_full * p[i]
    return jnp.stack(q + momentum)


@jax.custom_jvp
def _coupled_turn(q, momentum, coupling):
    """The flow of a zero off-diagonal inverse inertia: ``(q, P)`` unchanged, at no cost.

    ``q`` (4,) the attitude (principal frame to world), ``momentum`` (3,) the body momentum
    ``P`` in the principal frame, ``coupling`` ``(3, 3)`` a sub-flow's duration times the
    off-diagonal part ``W`` of the inverse inertia in the principal frame (s/(kg m^2)),
    exactly zero in value (see :func:`jaxrb.inertia.repeated_moment_coupling`). Its flow
    turns the body at ``W P``: to first order in ``W``, ``q (1, a/2)`` with ``a = coupling
    P``, and the body momentum the opposite way, ``P - a x P`` (the world momentum is
    unchanged). So the values are ``q`` and ``P`` themselves, and the derivatives carry
    ``d a = d coupling P`` (``coupling d P`` is zero). Where ``coupling`` is not
    differentiated the rule adds nothing (a symbolic zero).

    The momentum's turn is in the rule, not left to the caller to recompute from ``q`` and
    the world momentum: that second rotation of ``L`` into the body frame cost reverse mode
    a ``quat_rotate`` transpose of its own (about 4 kernels a ball step).
    """
    del coupling
    return q, momentum


def _coupled_turn_jvp(primals, tangents):
    q, momentum, _ = primals
    d_q, d_momentum, d_coupling = tangents
    if type(d_coupling) is SymbolicZero:
        return (q, momentum), (d_q, d_momentum)
    if type(d_q) is SymbolicZero:
        d_q = jnp.zeros_like(q)
    if type(d_momentum) is SymbolicZero:
        d_momentum = jnp.zeros_like(momentum)
    angle = spatial.matvec(d_coupling, momentum)
    d_q = d_q + 0.5 * spatial.quat_multiply(q, jnp.concatenate([jnp.zeros_like(angle[:1]), angle]))
    return (q, momentum), (d_q, d_momentum - spatial.cross(angle, momentum))


_coupled_turn.defjvp(_coupled_turn_jvp, symbolic_zeros=True)


def _axes(value):
    """A sequence of axis indices as a tuple of Python ints (a list is not hashable, and
    static fields must hash); anything else unchanged, for the check to refuse."""
    if isinstance(value, (list, tuple, range)) or (isinstance(value, np.ndarray) and value.ndim == 1):
        # A NumPy array or a range as well (np.array([2, 1, 0]) had been refused as "not a
        # permutation of (0, 1, 2)"); its entries then pass the same check.
        return tuple(whole_number(a.item() if isinstance(a, np.generic) else a) for a in value)
    return value


def principal_frames(params: Params):
    """Inverse principal moments ``(N, 3)`` (1/(kg m^2), the moments in ascending order),
    principal-to-body quaternions ``(N, 4)``, and the off-diagonal inverse inertia in the
    principal frame at repeated moments ``(N, 3, 3)`` (zero in value; see
    :func:`jaxrb.inertia.repeated_moment_coupling`).

    Inverted here, once per rollout (the splittings' ``precompute``): a step then multiplies.
    Divided in the step, reverse mode recomputed the three quotients (and their derivatives)
    at every step, which XLA did not hoist out of the backward loop: 3 kernels a step of the
    ball's gradient.
    """
    moments, axes_matrix = jax.vmap(principal_axes)(params.inertia)
    inverse = 1.0 / moments
    # (L + C)^-1 = L^-1 - L^-1 C L^-1 to first order in the coupling C, which is zero.
    coupling = -inverse[:, :, None] * jax.vmap(repeated_moment_coupling)(params.inertia) * inverse[:, None, :]
    return inverse, spatial.matrix_to_quat(axes_matrix), coupling


class SymplecticSplitting(Integrator):
    """DLM splitting of the free rigid body, with kick-drift-kick for forces.

    In the principal frame the kinetic energy ``T = sum_k P_k^2 / 2 I_k`` splits into
    three terms, and the flow of each alone is an exact rotation about one principal
    axis by ``dt P_k / I_k`` (``P`` the body momentum, which rotates the opposite way).
    The free step is the symmetric (Strang) composition::

        R_a(dt/2) R_b(dt/2) R_c(dt) R_b(dt/2) R_a(dt/2)

    with ``(a, b, c) = axes`` indexing the principal moments in ascending order. A
    non-diagonal body inertia is handled by going through its principal frame
    (:func:`jaxrb.principal_axes`). Forces and torques enter by kick-drift-kick
    (:mod:`jaxrb.integrators._composition`).

    * Order 2, symplectic and time-reversible (Dullweber, Leimkuhler & McLachlan,
      J. Chem. Phys. 107, 5840 (1997)).
    * Torque-free: world angular momentum exactly (each sub-flow is a rigid rotation of
      the body about its own axis, and ``L`` is never updated); ``|P|`` exactly; energy
      error O(dt^2), bounded with no drift (backward error analysis of a symplectic map).
    * Cost: two force evaluations (three with velocity-dependent forces) and five axis
      rotations (five sin/cos pairs) per step. The principal frames (a 3x3
      eigen-decomposition per body) are computed once per rollout (``precompute``).
    * Large steps: never NaN, ``L`` exact and the attitude a rotation at any step, so the
      energy stays between ``|L|^2 / 2 I_2`` and ``|L|^2 / 2 I_0``; a fast spin about a
      principal axis is integrated exactly. Away from the axes the energy error grows
      with ``|omega| dt``: on the asymmetric top it reaches 2x at ``|omega| dt`` a little
      above 2 (``benchmarks/work_precision.py``'s stability limit: 1.99).
    * Ordering: the default ``axes = (0, 1, 2)`` (smallest moment outermost, largest
      innermost) gave the smallest energy error of the six orderings on both the
      asymmetric top ``I = (1, 2, 3)`` (max 1.5e-7 over 1e5 steps of 0.01 s; the worst
      ordering, 2.6e-5) and the spinning rod ``I = (1e-4, 1, 1 + 5e-5)``,
      ``omega = (100, 1, 0)`` (5e-6 over 10 s at dt = 0.01; the worst, 0.31).
    * Derivatives in the inertia at repeated moments (a sphere, a cube, an axisymmetric
      body; "repeated" within ``sqrt(eps)`` of the trace): the principal axes are not
      unique there, and :func:`jaxrb.principal_axes` holds them fixed, so a perturbation
      that breaks the symmetry (``I_01`` of a sphere) would move no axis and get a zero
      derivative. It appears instead as an off-diagonal inverse inertia ``W`` in the
      principal frame (:func:`jaxrb.inertia.repeated_moment_coupling`), zero in value,
      whose flow runs for half a step on either side of the five rotations: the identity
      in value (no cost in a forward run), and to first order in ``W`` a turn by
      ``dt/2 W P`` in the derivative. Against central differences of scipy's solution of
      the flow, the derivatives converge at second order (``tests/test_integrators.py``).
    * Known limit (stop 88's review): *nearly* repeated moments, outside that
      window. The split's result depends, by O(dt^2), on which axes are chosen in the
      nearly degenerate plane, and those axes turn at a rate ~1/delta with the inertia
      (delta the two moments' gap). So the inertia derivative, exact for this map (it
      agrees with finite differences), carries an O(dt^2 / delta) term that the flow does
      not have: moments (1, 1 + delta, 1.8), dt = 0.01, 100 steps, against RK4's gradient
      (size 0.14): off by 2.8e-4 at delta = 1e-3, 2.8e-2 at 1e-5, 2.8 at 1e-7. The values
      stay accurate. For an inertia fit of a nearly symmetric body use
      :class:`SymmetricTopSplitting` (which never splits a nearly degenerate pair: 3.9e-6
      at delta = 1e-7 in the same kind of test, where this split is off by 2.7e2), ``RK4``
      or ``ImplicitMidpoint``.
    """

    axes: tuple[int, int, int] = eqx.field(default=(0, 1, 2), static=True, converter=_axes)
    order: ClassVar[int] = 2

    def __check_init__(self):
        if not isinstance(self.axes, tuple) or not all(type(a) is int for a in self.axes) \
                or sorted(self.axes) != [0, 1, 2]:
            raise ValueError(
                f"SymplecticSplitting(axes=...) must order the three principal axes, i.e. be a "
                f"permutation of (0, 1, 2); got {self.axes!r}."
            )

    def precompute(self, params: Params):
        """The principal frames of every body, once per rollout: :func:`principal_frames`."""
        return principal_frames(params)

    def free_rotation(self, principal_frames, orientation, angular_momentum, dt: float):
        """Torque-free attitude flow over ``dt`` at constant world ``L``; ``(N, 4)``."""
        outer, middle, inner = self.axes
        flows = ((outer, 0.5), (middle, 0.5), (inner, 1.0), (middle, 0.5), (outer, 0.5))

        def sub_rotations(inverse_moments, q, momentum):
            # The chain starts from one materialised pose, and its five rates are computed in
            # the step: without this barrier XLA:CPU fused the attitude and momentum
            # arithmetic before it into the first rotation's kernel and its neighbours (some
            # of it twice), and hoisted each rotation's rate out of the rollout's loops as a
            # loop-carried constant of its own, once per use (the reverse pass passed the same
            # five values in twice). Measured with benchmarks/kernels.py: the ball 29.8 ->
            # 28.5 kernels a step forward and 87.4 -> 84.8 in reverse mode; the tumbling box
            # 19.8 -> 18.8 and 69.4 -> 65.9.
            inverse_moments, pose = jax.lax.optimization_barrier((inverse_moments, jnp.concatenate([q, momentum])))
            for k, fraction in flows:
                pose = _rotate_about_principal_axis(pose, k, fraction * dt * inverse_moments[k])
                # The barrier keeps each rotation its own kernel: fused into one, XLA:CPU
                # recomputed the chain's shared terms exponentially (each extra rotation
                # ~5x slower; the vmapped step 20x slower than RK4).
                pose = jax.lax.optimization_barrier(pose)
            return pose

        # Unrolled: the axes are static, so each rotation moves two components only. Against
        # the former lax.scan over the five rotations, side by side (benchmarks/README.md):
        # 4096 float32 bodies' forward 1.45x faster, gradients 7-17% faster, and a single
        # body's forward 12-18% slower. Not checkpointed here: every step that reaches it
        # (rollout's, Step.__call__'s, the contact step's branches) is checkpointed as a
        # whole, and a checkpoint inside that one made reverse mode run the chain twice,
        # once in the step's recomputation (for the quotient's derivative after it) and
        # again for its own (benchmarks/README.md, "One recomputation of the rotations").

        def rotate(inverse_moments, principal, coupling, q, l_world):
            q = spatial.quat_multiply(q, principal)  # principal frame -> world
            # The repeated moments' coupling (zero, with a derivative) turns the body for half
            # the step on either side of the chain: symmetric, so its derivative is second
            # order too. The first turn turns the body momentum with the body (the same
            # value: the turn is the identity).
            q, momentum = _coupled_turn(q, spatial.quat_rotate_inverse(q, l_world), 0.5 * dt * coupling)
            pose = sub_rotations(inverse_moments, q, momentum)
            q, _ = _coupled_turn(pose[:4], pose[4:], 0.5 * dt * coupling)
            q = spatial.quat_multiply(q, spatial.quat_conjugate(principal))
            return spatial.quat_normalize(q)

        return jax.vmap(rotate)(*principal_frames, orientation, angular_momentum)

    def step(self, scene, params: Params, state: State, dt: float, derived=None) -> State:
        return principal_frame_step(self, scene, params, state, dt, derived)


def principal_frame_step(integrator, scene, params: Params, state: State, dt: float, derived=None) -> State:
    """Kick-drift-kick around ``integrator.free_rotation(frames, q, L, dt)``, with ``frames``
    the given ``derived`` or ``integrator.precompute(params)`` (both splittings' ``step``)."""
    frames = integrator.precompute(params) if derived is None else derived

    def rotate(params, orientation, angular_momentum, dt):
        return integrator.free_rotation(frames, orientation, angular_momentum, dt)

    return kick_drift_kick(scene, params, state, dt, rotate)
