"""The exact contact solve: all normal impulses at once, as the seed's LCP, by semismooth Newton.

Seed 000 poses resting contact as a linear complementarity problem: with ``A`` the
normal Delassus matrix (``A_ij`` = change of slot i's normal velocity per unit normal
impulse at slot j) and ``w = u_n + A (lambda - lambda_0) - target``,

    lambda >= 0,   w >= 0,   lambda_i w_i = 0.

Projected Gauss-Seidel solves it one slot at a time; on a heavy body resting on a light
one each sweep removes only a fraction ``m/(M+m)`` of the error. Here the LCP is written
as ``min(lambda, w) = 0`` and solved by Newton's method on that piecewise-linear function
(a semismooth Newton / active-set method): each iteration picks, per slot, the branch that
is smaller and solves the resulting linear system, and takes the first of the full, half,
quarter and eighth steps that lowers the merit ``|min(lambda, w)|^2``, or else one
projected Gauss-Seidel sweep. For the small contact sets it is meant
for it reaches the exact solution in a few iterations, independent of the mass ratio. The
iteration count is fixed (``lax.scan``), so reverse mode crosses it. The linear systems
use ``A + eps I``, ``eps = eps_machine^(3/4) mean(diag A)``, which makes redundant
contacts (four corners of a face) well posed, and the previous iterate on the right
(``(A + eps I) lambda' = -offset + eps lambda``: a proximal-point step), so that the fixed
point is the LCP's own solution, not the regularised one's.

Friction is then handled by projected Gauss-Seidel sweeps between normal solves (Kaufman
et al.'s staggered projections, with one sweep per stage).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .. import spatial
from .._branch import branch
from ._solver import Bodies, Frames, apply_impulses, normal_velocities, pad_slots, sweeps

__all__ = ["normal_delassus", "solve_exact"]


def normal_delassus(bodies: Bodies, f: Frames) -> jax.Array:
    """``A = J M^-1 J^T`` for the normal directions of all ``C + 1`` slots, ``(C+1, C+1)``, 1/kg."""
    rows = bodies.inv_mass.shape[0]
    n = f.basis[:, 0]
    # Per slot and body row: the mobility of a unit normal impulse (velocity and spin parts).
    onehot_a = jax.nn.one_hot(f.body_a, rows, dtype=n.dtype)
    onehot_b = jax.nn.one_hot(f.body_b, rows, dtype=n.dtype)
    arm_a = spatial.cross(f.r_a, n)
    arm_b = spatial.cross(f.r_b, n)
    lin = onehot_a[:, :, None] * n[:, None, :] - onehot_b[:, :, None] * n[:, None, :]  # (C, R, 3)
    ang = onehot_a[:, :, None] * arm_a[:, None, :] - onehot_b[:, :, None] * arm_b[:, None, :]
    lin_m = lin * bodies.inv_mass[None, :, None]
    ang_m = jnp.einsum("rij,crj->cri", bodies.inv_inertia, ang)
    return jnp.einsum("cri,dri->cd", lin_m, lin) + jnp.einsum("cri,dri->cd", ang_m, ang)


def _newton_normals(a_mat, u_n, lam_n, target, active, iterations: int):
    """Solve ``min(lambda, u_n + A (lambda - lam_n) - target) = 0`` for ``lambda`` (active slots)."""
    size = a_mat.shape[0]
    eye = jnp.eye(size, dtype=a_mat.dtype)
    eps = jnp.finfo(a_mat.dtype).eps ** 0.75 * jnp.maximum(jnp.mean(jnp.diag(a_mat)), 1e-30)
    reg = a_mat + eps * eye
    offset = u_n - target - a_mat @ lam_n  # w(lambda) = A lambda + offset

    def merit(lam, w):
        """``|min(lambda, w)|^2`` over the active slots: zero exactly at the LCP's solution."""
        return jnp.sum(jnp.where(active, jnp.minimum(lam, w), 0.0) ** 2)

    diag = jnp.where(active, jnp.diag(reg), 1.0)

    def gauss_seidel(lam):
        """One projected Gauss-Seidel sweep over the slots (the regularised ``A``): it never
        raises the LCP's energy ``lambda^T (A lambda / 2 + offset)``, and lowers it wherever
        that is not at its minimum (the merit may rise for a step)."""
        def update(i, lam):
            value = jnp.maximum(lam[i] - (reg[i] @ lam + offset[i]) / diag[i], 0.0)
            return lam.at[i].set(jnp.where(active[i], value, 0.0))

        return jax.lax.fori_loop(0, size, update, lam)

    def shorter(lam, newton, w):
        """The first of the half, quarter and eighth Newton steps that lowers the merit, or
        else a Gauss-Seidel sweep (``w``: ``lam``'s, ``A lam + offset``)."""
        now = merit(lam, w)
        chosen, found = lam, jnp.zeros((), bool)
        for fraction in (0.5, 0.25, 0.125):
            trial = lam + fraction * (newton - lam)
            better = ~found & (merit(trial, a_mat @ trial + offset) < now)
            chosen, found = jnp.where(better, trial, chosen), found | better
        return jnp.where(found, chosen, gauss_seidel(lam))

    def iterate(lam, _):
        w = a_mat @ lam + offset
        use_w = active & (w < lam)
        matrix = jnp.where(use_w[:, None], reg, eye)
        # The proximal term eps * lam: with -offset alone the solution was the regularised
        # LCP's, whose normal velocities are off by eps * lambda. In float32 (eps 6.4e-6 of
        # the mean diagonal) a 1000 kg box on a 1 kg one pressed the light box into the
        # ground at 5.6e-5 m/s, steadily (2.2e-4 m in 4 s; 100:1, 7.5e-6 m/s); now 1e-6 m.
        rhs = jnp.where(use_w, -offset + eps * lam, 0.0)
        newton = jnp.where(active, jnp.maximum(jnp.linalg.solve(matrix, rhs), 0.0), 0.0)
        # Semismooth Newton without a line search is not globally convergent: with redundant
        # contacts (a face's four corners) the active-set system is nearly singular, and in
        # float32 one step can swing the impulses far off (a 5-box stack blew up at 1.5 s).
        # So the step is the first of the full, half, quarter and eighth Newton steps that
        # lowers the merit, and where none does, a Gauss-Seidel sweep (until stop 90 such a
        # step was refused and, the next step being the same, every later one: 171 of 520
        # random LCPs stalled at their start, a 3x3 with condition 12 among them). Near the
        # solution Newton's full steps all pass. The rest only where the full step fails (a
        # branch: computed every iteration, the sweep had made the exact solver's 5-box
        # stack 1.8x slower).
        full = merit(newton, a_mat @ newton + offset) < merit(lam, w)
        return branch(full, lambda lam, newton, w: newton, shorter, lam, newton, w), None

    lam, _ = jax.lax.scan(iterate, jnp.where(active, jnp.maximum(lam_n, 0.0), 0.0), None, length=iterations)
    return lam


def solve_exact(bodies: Bodies, f: Frames, colours, target, mu, active, lam0, iterations: int,
                newton_iterations: int):
    """Same contract as :func:`jaxrb.contact._solver.solve`; normals by semismooth Newton."""
    target, mu, active, lam = pad_slots(target, mu, active, lam0)
    bodies = apply_impulses(bodies, f, lam)
    a_mat = normal_delassus(bodies, f)

    def stage(carry, _):
        bodies, lam = carry
        bodies, lam, _ = sweeps(bodies, f, colours, target, mu, active, lam, 1)
        new_n = _newton_normals(a_mat, normal_velocities(bodies, f), lam[:, 0], target, active, newton_iterations)
        d = new_n - lam[:, 0]
        bodies = apply_impulses(bodies, f, jnp.stack([d, jnp.zeros_like(d), jnp.zeros_like(d)], -1))
        return (bodies, lam.at[:, 0].set(new_n)), None

    (bodies, lam), _ = jax.lax.scan(stage, (bodies, lam), None, length=iterations)
    return bodies, lam[:-1]
