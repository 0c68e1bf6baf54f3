"""Implicit methods: backward Euler on Euler's equations, and the Lie-Poisson implicit midpoint.

Both solve a 3-vector equation per body by Newton's method with a *fixed* number of
iterations (a ``lax.fori_loop`` with static bounds, i.e. a scan), so reverse-mode
differentiation goes through them like any other arithmetic (no ``lax.while_loop`` on
the gradient path). With enough iterations the
derivative of the iterated solve converges to the implicit-function-theorem derivative.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import spatial
from .._branch import branch
from .._static import static_switch
from ..dynamics import linear_acceleration, wrench
from ..state import Params, State, body_inertia, inverse_inertia_body
from ._base import Integrator, truth_value, whole_number
from ._composition import kick_drift_kick

__all__ = ["ImplicitGyroscopic", "ImplicitMidpoint"]


def _solve3(matrix, vector):
    """``matrix^-1 vector`` for one 3x3 system, by the adjugate (exact, element-wise)."""
    return spatial.matvec(spatial.inverse3(matrix), vector)


def _fixed_iterations(update, initial, iterations: int):
    """``iterations`` Newton updates as one ``fori_loop`` with static bounds.

    Static bounds make it a ``lax.scan``, which reverse mode differentiates (a
    ``while_loop`` would not). A loop instead of unrolled Python keeps the compiled
    program small: unrolled, the gradient of a rollout took several times longer to
    compile.
    """
    return jax.lax.fori_loop(0, iterations, update, initial)


def _check_iterations(owner: str, value, name: str = "iterations") -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{owner}({name}=...) must be a positive integer, got {value!r}.")


def _gyroscopic_residual(inertia, momentum_body, torque_body, h, w):
    """``I w + h w x I w - (P_n + h tau_b)`` and ``I w``: backward Euler's equation for step ``h``."""
    iw = spatial.matvec(inertia, w)
    return iw + h * spatial.cross(w, iw) - (momentum_body + h * torque_body), iw


def _gyroscopic_newton(inertia, momentum_body, torque_body, h, w):
    """One Newton step on :func:`_gyroscopic_residual`."""
    r, iw = _gyroscopic_residual(inertia, momentum_body, torque_body, h, w)
    # d/dw (w x I w) = w~ I - (I w)~
    jacobian = inertia + h * (spatial.matmul(spatial.skew(w), inertia) - spatial.skew(iw))
    return w - _solve3(jacobian, r)


def _backward_euler_rates(inertia, momentum_body, torque_body, dt, stages: int, iterations: int, safeguard: bool):
    """Solve ``I w + dt w x I w = P_n + dt tau_b`` for one body's ``w`` (rad/s, body frame).

    Newton's method from ``w_n`` fails to converge on about 1 % of random bodies and spin
    directions at ``|w| dt = 2`` (measured on 2e4 samples), and there the iterate can hold
    many times the kinetic energy. So the solve is a continuation in the step size:
    stage ``k`` solves the equation for ``dt_k = dt k / stages`` by ``iterations`` Newton
    steps from the previous stage's root (stage 0 has the exact root ``w_n``). With
    ``safeguard`` the result is the root of the last stage whose residual converged:
    every converged stage is an exact backward-Euler root for its step ``dt_k``, so
    torque-free it never gains energy, and an unconverged Newton iterate is never
    returned. For ordinary steps the last stage converges and the result is the root for
    ``dt`` itself. Without ``safeguard`` the last Newton iterate is returned as it is.
    """
    eps = jnp.finfo(momentum_body.dtype).eps
    inertia_scale = spatial.safe_norm(inertia.reshape(9))

    def stage(carry, k):
        w, accepted = carry
        h = dt * k / stages
        w = _fixed_iterations(lambda _, w: _gyroscopic_newton(inertia, momentum_body, torque_body, h, w), w, iterations)
        residual, iw = _gyroscopic_residual(inertia, momentum_body, torque_body, h, w)
        # Newton converges quadratically: a converged residual sits at the round-off of
        # the terms it sums (I w, h w x I w, P_n, h tau_b), an unconverged one is orders
        # larger. Scaling by |I| |w| (not |I w|) covers thin bodies, where I w rounds at
        # the size of the largest moment times |w|.
        size = inertia_scale * spatial.safe_norm(w) * (1.0 + h * spatial.safe_norm(w))
        size = size + spatial.safe_norm(momentum_body) + h * spatial.safe_norm(torque_body)
        converged = spatial.safe_norm(residual) <= 64.0 * eps * size
        return (w, jnp.where(converged, w, accepted)), None

    w0 = spatial.matvec(spatial.inverse3(inertia), momentum_body)
    steps = jnp.arange(1, stages + 1, dtype=momentum_body.dtype)
    (last, accepted), _ = jax.lax.scan(stage, (w0, w0), steps)
    return accepted if safeguard else last


class ImplicitGyroscopic(Integrator):
    """Backward Euler on the body-frame Euler equations, solved by Newton's method.

    Per body, with body angular velocity ``w``, body inertia ``I`` and body torque
    ``tau_b = A_n^T tau``::

        I (w_{n+1} - w_n) = dt (tau_b - w_{n+1} x I w_{n+1})      (solved for w_{n+1})
        q_{n+1} = q_n exp(dt w_{n+1})                              (body-frame increment)
        L_{n+1} = A_{n+1} I w_{n+1}
        v_{n+1} = v_n + dt F / m,   x_{n+1} = x_n + dt v_{n+1}

    The gyroscopic term ``w x I w`` is what makes explicit methods blow up at large
    ``|w| dt``; treating it implicitly makes the step dissipative instead. Torque-free,
    dotting the equation with ``w_{n+1}`` kills the gyroscopic term and leaves
    ``w_{n+1}.I w_{n+1} = w_{n+1}.I w_n <= |w_{n+1}|_I |w_n|_I`` (Cauchy-Schwarz in the
    ``I`` inner product): **kinetic energy never increases**, at any step size, for any
    root of the equation. The same argument in the momentum form shows ``|L|`` never
    increases.

    The equation is quadratic in ``w`` and Newton's method from ``w_n`` does not always
    find a root at large ``|w| dt``. The solve is therefore a continuation in the step
    size (``stages`` stages of ``iterations`` Newton steps each, see
    :func:`_backward_euler_rates`), and if the last stage does not converge, the root of
    the last stage that did is used: an exact backward-Euler root for a shorter step,
    so still dissipative. Measured on 2e4 random bodies and spin directions with the
    default 3 stages of 8 iterations: the fallback is taken on 0 % of steps up to
    ``|w| dt = 1``, 0.22 % at 2 and 0.63 % at 4, and no step gains energy (plain
    Newton from ``w_n``, 12 iterations, failed on 1.1 % at 2, some of those steps
    multiplying the energy by over 1000).

    * Order 1.
    * Conserves nothing exactly: energy and ``|L|`` decay (numerical damping, strongest
      at large ``|w| dt``), and the direction of world ``L`` drifts at O(dt).
    * Cost: one force evaluation and ``stages * iterations`` 3x3 Newton solves per body.
    * Stability: unconditional for the free body; energy is non-increasing at every
      step (to round-off) at any ``|w| dt``.
    * ``stages=1, iterations=1, safeguard=False`` is the single linearised step that
      MuJoCo's implicit integrators and Bullet's implicit gyroscopic force take: it is
      *not* dissipative, and at ``|w| dt = 2`` it multiplied a flat body's energy by 230
      in one step (``tests/test_integrators.py``).
    """

    stages: int = eqx.field(default=3, static=True, converter=whole_number)
    iterations: int = eqx.field(default=8, static=True, converter=whole_number)
    safeguard: bool = eqx.field(default=True, static=True, converter=truth_value)
    order: ClassVar[int] = 1

    def __check_init__(self):
        _check_iterations("ImplicitGyroscopic", self.iterations)
        _check_iterations("ImplicitGyroscopic", self.stages, "stages")
        static_switch("ImplicitGyroscopic(safeguard=...)", self.safeguard)

    def step(self, scene, params: Params, state: State, dt: float) -> State:
        force, torque = wrench(scene, params, state)

        def rotate(inertia, q, angular_momentum, tau):
            momentum_body = spatial.quat_rotate_inverse(q, angular_momentum)
            torque_body = spatial.quat_rotate_inverse(q, tau)
            w = _backward_euler_rates(
                inertia, momentum_body, torque_body, dt, self.stages, self.iterations, self.safeguard
            )
            q = spatial.quat_normalize(spatial.quat_multiply(q, spatial.quat_exp(dt * w)))
            return q, spatial.quat_rotate(q, spatial.matvec(inertia, w))

        orientation, angular_momentum = jax.vmap(rotate)(
            body_inertia(params), state.orientation, state.angular_momentum, torque
        )
        velocity = state.velocity + dt * linear_acceleration(params, force)
        return State(
            position=state.position + dt * velocity,
            orientation=orientation,
            velocity=velocity,
            angular_momentum=angular_momentum,
            time=state.time + dt,
            rotation=None if state.rotation is None else spatial.quat_to_matrix(orientation),
        )


def cayley_quat(rotation_vector):
    """Quaternion of the Cayley transform ``(E - a~/2)^-1 (E + a~/2)``, ``(..., 3) -> (..., 4)``.

    It is the rotation about ``a`` by ``2 atan(|a|/2)``, whose quaternion is ``(1, a/2)``
    normalised: a rational map, exact for every ``a``, that agrees with ``exp(a)`` to
    O(|a|^3).
    """
    half = 0.5 * jnp.asarray(rotation_vector)
    return spatial.quat_normalize(jnp.concatenate([jnp.ones_like(half[..., :1]), half], axis=-1))


# A body whose midpoint equation has no root near P_n over the whole step takes it as this
# many exact midpoint steps of dt / FALLBACK_SUBSTEPS instead (see midpoint_free_rotation).
FALLBACK_SUBSTEPS = 4


def midpoint_free_rotation(
    params: Params, orientation, angular_momentum, dt: float, iterations: int, stages: int = 1, safeguard: bool = True
):
    """Torque-free attitude flow of the Lie-Poisson implicit midpoint rule, ``(N, 4)``.

    With body momentum ``P_n = A_n^T L``, solve ``P_m = P_n + dt/2 P_m x I^-1 P_m`` (the
    midpoint ``P_m = (P_n + P_{n+1})/2`` of the implicit midpoint rule on Euler's
    equations) and set ``A_{n+1} = A_n cay(dt I^-1 P_m)``. Then
    ``P_{n+1} = A_{n+1}^T L = cay(-dt w_m) P_n`` is exactly the midpoint rule's
    ``P_n + dt P_m x w_m``, so world ``L`` is unchanged (it is not even updated) while
    ``|P|`` and the energy ``P.I^-1 P/2`` are the midpoint rule's quadratic invariants,
    conserved to the Newton tolerance (Austin, Krishnaprasad & Wang 1993).

    At large ``|w| dt`` the quadratic equation can have no real root near ``P_n`` (50
    Newton iterations, damped or not, failed where 8 did), and the last iterate conserves
    nothing. So the solve is a continuation in the step size, as in
    :func:`_backward_euler_rates`: stage ``k`` of ``stages`` solves for ``h_k = dt k /
    stages`` from the previous stage's root. With ``safeguard``, a body whose full step
    fails takes it instead as ``FALLBACK_SUBSTEPS`` (4) exact midpoint steps of ``dt / 4``
    (each a continuation of at least 3 stages; one that still fails turns by its last
    converged stage, ``h = 0`` at worst), so energy and ``|P|`` stay conserved and the whole step is
    taken where the shorter steps converge. (Until stop 88 the body turned by its last
    converged stage alone: with ``stages=1`` that was no turn, ``P`` did not change, the
    next step failed the same way, and the body stopped turning for good.) The sub-steps
    run only when some body needs them (a ``branch``). Converged steps give the same
    values as without ``safeguard``, to the last bit.
    """
    eps = jnp.finfo(jnp.asarray(angular_momentum).dtype).eps

    def rotate(inverse_inertia, q, l_world, dt, stages):
        """One step of length ``dt``: the new attitude, and whether its full step converged."""
        momentum = spatial.quat_rotate_inverse(q, l_world)
        mid, accepted_mid, accepted_h = momentum, momentum, jnp.zeros_like(momentum[0])
        converged = jnp.zeros((), bool)
        for k in range(1, stages + 1):  # static and few: each stage is one fori_loop
            h = dt * k / stages
            half = 0.5 * h

            def newton(_, mid, half=half):
                w = spatial.matvec(inverse_inertia, mid)
                residual = mid - momentum - half * spatial.cross(mid, w)
                # d/dP (P x I^-1 P) = P~ I^-1 - (I^-1 P)~
                jacobian = jnp.eye(3, dtype=mid.dtype) - half * (
                    spatial.matmul(spatial.skew(mid), inverse_inertia) - spatial.skew(w)
                )
                return mid - _solve3(jacobian, residual)

            mid = _fixed_iterations(newton, mid, iterations)
            w = spatial.matvec(inverse_inertia, mid)
            residual = mid - momentum - half * spatial.cross(mid, w)
            # Converged residuals sit at round-off (~1e-16 of the terms' size in float64),
            # unconverged ones at 1e-3 and above; eps^(3/4) (2e-12; 6.5e-6 in float32) accepts
            # the few between that stopped short of round-off.
            size = spatial.safe_norm(momentum) + spatial.safe_norm(mid) * (1.0 + half * spatial.safe_norm(w))
            converged = spatial.safe_norm(residual) <= eps**0.75 * size
            accepted_mid = jnp.where(converged, mid, accepted_mid)
            accepted_h = jnp.where(converged, h, accepted_h)
        if not safeguard:
            accepted_mid, accepted_h = mid, dt
        w_mid = spatial.matvec(inverse_inertia, accepted_mid)
        return spatial.quat_normalize(spatial.quat_multiply(q, cayley_quat(accepted_h * w_mid))), converged

    inverse_inertia = inverse_inertia_body(params)
    every_body = jax.vmap(rotate, in_axes=(0, 0, 0, None, None))
    turned, converged = every_body(inverse_inertia, orientation, angular_momentum, dt, stages)
    if not safeguard:
        return turned

    def substeps(turned):
        q = orientation
        for _ in range(FALLBACK_SUBSTEPS):
            q = every_body(inverse_inertia, q, angular_momentum, dt / FALLBACK_SUBSTEPS, max(stages, 3))[0]
        return jnp.where(converged[:, None], turned, q)

    return branch(jnp.any(~converged), substeps, lambda turned: turned, turned)


class ImplicitMidpoint(Integrator):
    """The Lie-Poisson implicit midpoint rule with a Cayley attitude update.

    The free rotation is :func:`midpoint_free_rotation`; forces and torques enter by
    kick-drift-kick (:mod:`jaxrb.integrators._composition`), with ``x`` drifting at the
    half-kicked velocity.

    * Order 2 (symmetric).
    * Torque-free, conserves world angular momentum exactly (``L`` is never touched by
      the free flow) and, wherever Newton has converged, the kinetic energy and ``|L|``
      in the body to the Newton tolerance, with no drift. Symplectic (a Lie-Poisson
      integrator).
    * Cost: two force evaluations (three with velocity-dependent forces), and
      ``iterations`` 3x3 Newton solves per body.
    * Stability: no step-size limit for the free body as long as Newton converges. With
      the default 8 iterations, from the initial guess ``P_n``, it converged on every one
      of 2000 random bodies up to ``|w| dt = 2.5``. Beyond that the midpoint equation
      can have no root near ``P_n``, and with ``safeguard`` (the default) such a body
      takes the step as four exact midpoint steps of ``dt / 4`` instead
      (:func:`midpoint_free_rotation`): energy and ``|L|`` stay conserved, and the body
      keeps turning (a top with moments 1, 2, 3 turned on every step up to
      ``|w| dt = 100``; until stop 88 it stopped turning for good once its full step
      failed). ``stages=3`` takes the root for 1/3 or 2/3 of the step where it can
      (three times the Newton work). Measured on 1000 random bodies, 20 steps each
      (before the sub-steps): the full step failed on 0 % of steps at ``|w| dt = 2.5``,
      0.84 % at 3, 3.2 % at 4 and 11.7 % at 6 with ``stages=1``; 0 %, 0.10 %, 0.27 % and
      0.58 % with ``stages=3``; no step changed the energy by more than 3e-12 (relative).
      The safeguard's own cost where every body converges, one residual per body and a
      skipped ``branch`` per step: see benchmarks/README.md, stop 88. Without
      ``safeguard`` the unconverged iterate is used, and energy is not conserved (at
      ``|w| dt = 3``, 0.25% of 2000 bodies changed their energy by more than 1e-6, the
      worst 4.6x in one step; at 4, 2.9% and 5.2x).
    """

    iterations: int = eqx.field(default=8, static=True, converter=whole_number)
    stages: int = eqx.field(default=1, static=True, converter=whole_number)
    safeguard: bool = eqx.field(default=True, static=True, converter=truth_value)
    order: ClassVar[int] = 2

    def __check_init__(self):
        _check_iterations("ImplicitMidpoint", self.iterations)
        _check_iterations("ImplicitMidpoint", self.stages, "stages")
        static_switch("ImplicitMidpoint(safeguard=...)", self.safeguard)

    def step(self, scene, params: Params, state: State, dt: float) -> State:
        def rotate(params, orientation, angular_momentum, dt):
            return midpoint_free_rotation(
                params, orientation, angular_momentum, dt, self.iterations, self.stages, self.safeguard
            )

        return kick_drift_kick(scene, params, state, dt, rotate)
