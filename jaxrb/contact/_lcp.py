"""The exact contact solve: all normal impulses at once, as the seed's LCP, by semismooth Newton.

Seed 000 poses resting contact as a linear complementarity problem: with ``A`` the
normal Delassus matrix (``A_ij`` = change of slot i's normal velocity per unit normal
impulse at slot j) and ``w = u_n + A (lambda - lambda_0) - target``,

    lambda >= 0,   w >= 0,   lambda_i w_i = 0.

Projected Gauss-Seidel solves it one slot at a time; on a heavy body resting on a light
one each sweep removes only a fraction ``m/(M+m)`` of the error. Here the LCP is written
as ``min(lambda, w) = 0`` and solved by Newton's method on that piecewise-linear function
(a semismooth Newton / primal-dual active-set method): each iteration picks, per slot, the
branch that is smaller and solves the resulting linear system, and the solve returns the
iterate, projected onto ``lambda >= 0``, with the least merit ``|min(lambda, w)|^2``. For
the small contact sets it is meant for it reaches the exact solution in a few iterations,
independent of the mass ratio, including redundant contacts whose targets no rigid motion
meets. It is not globally convergent: on random positive definite matrices of condition
1e6 (not a contact's), 8 in 60 cycle between active sets, and the best iterate is then
returned. The iteration count is fixed (``lax.scan``), so reverse mode crosses it. The
linear systems use ``A + eps I``, ``eps = eps_machine^(3/4) mean(diag A)``, which makes
redundant contacts (four corners of a face) well posed, and the best iterate on the right
(``(A + eps I) lambda' = -offset + eps lambda``: a proximal-point step), so that the fixed
point is the LCP's own solution, not the regularised one's.

Friction is then handled by projected Gauss-Seidel sweeps between normal solves (Kaufman
et al.'s staggered projections, with one sweep per stage).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .. import spatial
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
    """Solve ``min(lambda, u_n + A (lambda - lam_n) - target) = 0`` for ``lambda`` (active slots).

    Semismooth Newton on ``min(lambda, w)`` (the primal-dual active set method): each
    iteration takes the slots where ``w < lambda`` as closed (``w = 0``) and the rest as
    open (``lambda = 0``), and solves that linear system. The iterates themselves are not
    projected: an impulse that comes out negative opens its slot at the next iteration.
    What is returned is the best of them, projected onto ``lambda >= 0``, by the merit
    ``|min(lambda, w)|^2`` (the start included), so no iteration can make the solve worse
    than its warm start.

    Why not project each iterate, with a line search on the merit (until stop 96). With
    redundant contacts (a face's four corners: ``A`` of rank 3) whose targets no rigid
    motion meets (speculative targets of a tilted approach), the system with all four
    closed has no solution; its regularised solve gave impulses of 1e9 of both signs.
    Projected, no fraction of that step lowered the merit, so every iteration fell back to
    a Gauss-Seidel sweep with the same four slots closed: a 1000 kg box on a 1 kg one with
    targets spread by 0.02 m/s kept a relative complementarity error of 0.8 after 1000
    iterations (stop 96's review). Unprojected, the next iteration opens the corners whose
    impulse came out negative, and the solve is exact in two or three (float64: 1e-12;
    float32: 9e-4 of the largest ``|q|``, its rounding at a condition of 1e4).
    """
    size = a_mat.shape[0]
    eye = jnp.eye(size, dtype=a_mat.dtype)
    # A slot between two bodies that cannot move (both of infinite mass) has a zero row in
    # ``A``: no impulse changes its velocity, and closing it solved ``eps lambda = -offset``
    # (impulses of 5e41, stop 96's review). Gauss-Seidel gives such a slot no impulse
    # (``_safe_reciprocal``); so does this solve.
    active = active & (jnp.diag(a_mat) > 0)
    eps = jnp.finfo(a_mat.dtype).eps ** 0.75 * jnp.maximum(jnp.mean(jnp.diag(a_mat)), 1e-30)
    reg = a_mat + eps * eye
    offset = u_n - target - a_mat @ lam_n  # w(lambda) = A lambda + offset

    def merit(lam):
        """``|min(lambda, w)|^2`` over the active slots: zero exactly at the LCP's solution."""
        return jnp.sum(jnp.where(active, jnp.minimum(lam, a_mat @ lam + offset), 0.0) ** 2)

    def iterate(carry, _):
        best, best_merit, lam = carry
        closed = active & (a_mat @ lam + offset < lam)
        matrix = jnp.where(closed[:, None], reg, eye)
        # The proximal term eps * best: with -offset alone the solution was the regularised
        # LCP's, whose normal velocities are off by eps * lambda. In float32 (eps 6.4e-6 of
        # the mean diagonal) a 1000 kg box on a 1 kg one pressed the light box into the
        # ground at 5.6e-5 m/s, steadily (2.2e-4 m in 4 s; 100:1, 7.5e-6 m/s); now 1e-6 m.
        # About the best iterate, which is bounded, not the last, which may not be.
        rhs = jnp.where(closed, -offset + eps * best, 0.0)
        lam = jnp.where(active, jnp.linalg.solve(matrix, rhs), 0.0)
        candidate = jnp.maximum(lam, 0.0)
        candidate_merit = merit(candidate)
        # A strict improvement only: a NaN merit (a singular system) never replaces the best.
        better = candidate_merit < best_merit
        return (jnp.where(better, candidate, best), jnp.where(better, candidate_merit, best_merit), lam), None

    start = jnp.where(active, jnp.maximum(lam_n, 0.0), 0.0)
    (best, _, _), _ = jax.lax.scan(iterate, (start, merit(start), start), None, length=iterations)
    return best


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
