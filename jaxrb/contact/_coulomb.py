"""One contact's frictional impulse, exactly: Coulomb's law with maximal dissipation.

All quantities are in the contact's ``(n, t1, t2)`` basis. ``k`` ``(3, 3)`` is the
contact's Delassus block (``u -> u + k P`` for an impulse ``P`` on the pair, N s -> m/s),
``u`` ``(3,)`` the relative velocity it starts from (m/s), ``mu`` the friction
coefficient. Coulomb's law for an impulse ``P = (p, x)`` taken as one implicit step
(Moreau's): ``|x| <= mu p``, and either the contact sticks (``u_t' = 0``) or ``x`` is
on the boundary, opposite the slip it leaves, ``x = -mu p u_t' / |u_t'|``. That ``x``
is the minimiser of the kinetic energy over the disk,

    x = argmin_{|x| <= mu p}  x . (u_t + k_tn p) + x . k_tt x / 2,

so friction never adds energy whatever ``p`` is. These functions are written for one
contact and vmapped; their loops have fixed lengths. Reverse mode does not cross the
friction multiplier's Newton loop: its root has the implicit function theorem's derivative.

The impact law (:mod:`._solver`) uses them in two phases (Poisson's hypothesis):
compression to ``u_n = 0`` with friction (:func:`coulomb_impulse` to a velocity), then
restitution, ``e`` times the compression's normal impulse with its own friction
(:func:`coulomb_impulse` with ``p`` given). Each phase is one implicit step, which is exact
where the contact sticks at the end of the phase or slides one way throughout it: the
closed forms of a rod landing on its end (``u_n' = -e u_n``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._branch import branch
from .._implicit import implicit_root

__all__ = ["coulomb_impulse", "energy_change", "fraction_within", "frictionless_impulse", "largest_fraction", "solve2"]

#: Iterations on the friction multiplier of a sliding contact: safeguarded Newton steps
#: (a bisection of the bracket where a step would leave it), in one loop. On 20,000 random
#: contacts (``K = R R^T + 0.1 I``, ``R`` and ``u`` standard normal, mu in [0.05, 2]),
#: bringing ``u_n`` to a target missed it by more than 1e-9 m/s in 7 after 12 iterations,
#: in none after 14 (at most 2.9e-10); with ``p`` given, none missed after 12. Larger mu
#: takes more (stop 90's review, 4,000 such contacts a mu, misses by more than 1e-8 m/s after
#: 16 iterations): mu = 5, 1 (by 0.098 m/s); mu = 100, 16; mu = 1000, 120 (by up to 0.33);
#: after 24, none up to mu = 1000 (at most 1.9e-12 m/s); mu = 1e6 needs ~32.
ITERATIONS = 24


def _where_positive(x, fallback=1.0):
    return jnp.where(x > 0, x, fallback)


def _reciprocal(x):
    """``1 / x`` for ``x >= 0``, with ``x`` held at least ``tiny ** (1/4)`` (float32 3.3e-10 N s,
    float64 1.2e-77): its derivative ``-1/x^2`` stays finite. At a float32 ``|x|`` of 1e-20
    it would overflow, and reverse mode multiply the infinity by a zero cotangent (NaN)."""
    return 1.0 / jnp.maximum(x, jnp.finfo(jnp.result_type(x)).tiny ** 0.25)


def solve2(a, lam, v):
    """``(a + lam I)^-1 v`` for a symmetric positive semi-definite ``a`` ``(2, 2)``; 0 where singular."""
    m00, m01, m11 = a[0, 0] + lam, a[0, 1], a[1, 1] + lam
    det = m00 * m11 - m01 * m01
    solved = jnp.stack([m11 * v[0] - m01 * v[1], m00 * v[1] - m01 * v[0]]) / _where_positive(det)
    return jnp.where(det > 0, solved, 0.0)


def _safe_sqrt(x):
    """``sqrt(x)`` for ``x > 0``, else 0, with a finite derivative everywhere."""
    return jnp.where(x > 0, jnp.sqrt(_where_positive(x)), 0.0)


def _norm(v):
    return _safe_sqrt(jnp.sum(v * v))


def _beyond_rounding(change, u):
    """Whether a change ``change`` (m/s) of ``u_n`` is larger than the rounding of ``u``
    ``(3,)``: the rule by which both impulses below push or give 0."""
    return change > jnp.finfo(jnp.result_type(change, u)).eps * _norm(u)


def _impulse(lam, theta):
    """``(p, x)`` at the friction multiplier ``lam`` (see :func:`coulomb_impulse`);
    ``theta = (k, u, mu, value, to_velocity)``, the flag as a number."""
    k, u, _, value, to_velocity = theta
    a, coupling, slip = k[1:, 1:], k[1:, 0], u[1:]
    a_inv_c, a_inv_slip = solve2(a, lam, coupling), solve2(a, lam, slip)
    normal = (value - u[0] + jnp.dot(coupling, a_inv_slip)) / _where_positive(k[0, 0] - jnp.dot(coupling, a_inv_c))
    p = jnp.where(to_velocity > 0, normal, value)
    return p, -(a_inv_slip + a_inv_c * p)


def _phi(lam, theta):
    """``1/|x(lam)| - 1/(mu p(lam))``, rising through the sliding multiplier's root."""
    p, x = _impulse(lam, theta)
    mu = theta[2]
    # Where p(lam) <= 0 (to a velocity, at too small a lam), it is left of the root.
    return jnp.where(mu * p > 0, _reciprocal(_norm(x)) - _reciprocal(mu * p), -1.0)


def coulomb_impulse(k, u, mu, value, to_velocity):
    """The impulse ``(p, x)`` ``(3,)``: ``p = value`` given (N s), or, where ``to_velocity``
    (a bool, traced or not), the one that brings ``u_n`` to ``value`` (m/s); ``x`` by
    Coulomb's law. 0 where ``p`` would not be positive: a contact pushes, it does not pull.

    A sliding contact's friction is ``x(lam) = -(k_tt + lam I)^-1 (u_t + k_tn p)``: then
    ``u_t' = -lam x``, opposite the impulse. ``lam = 0`` is sticking. Where that needs
    more than ``mu p``, ``lam > 0`` is the root of ``1/|x(lam)| = 1/(mu p(lam))`` (Moré and
    Sorensen's form, nearly linear in ``lam``), with ``p(lam)`` fixed, or from the normal
    row, ``k_nn p + k_nt x = value - u_n``, solved for ``p``. Both kinds share one program:
    the impact law's passes select theirs with a traced flag.

    A block with ``k_nn <= 0`` moves nothing (the padding slot that fills a colour's
    pairs, between two rows of zero inverse mass): its impulse is 0, and it is solved on
    the identity block instead, whose derivatives are finite. On its own zero block the
    search's multiplier, unused, came to ``|u_t| / (mu p)``, 3e-10 in float32 scenes with
    resting boxes; the derivative of ``(k_tt + lam I)^-1`` then had ``1 / lam^4`` = 1e38,
    which overflowed, and reverse mode multiplied the infinity by the padding slot's zero
    cotangent: NaN gradients for the whole step (``benchmarks/fuzz_contacts.py
    --gradients --float32``, stop 85).

    An impulse that would change ``u`` by less than its rounding, ``k_nn p <= eps |u|``
    (an approach ``value - u_n`` that small, or a given ``p`` that small), is 0: ``u_n``
    is 0 to rounding there. Searched, its multiplier ``|u_t| / (mu p)`` had no bound: a
    box sliding at 0.05 m/s and approaching at 4.6e-22 m/s (float32) bracketed the root at
    1.5e21, whose square overflowed, and the impulse was NaN. The approach was rounding:
    a batched compilation of the same step made it, the unbatched one did not (stop 86,
    ``benchmarks/repro/vmap_forward_nan_bby.py``). With ``k_nn p > eps |u|`` the bracket
    is of the order of ``k_nn / (mu eps)`` at most (with terms in ``|k_tn| / mu`` and
    ``|k_tn| / eps``). It is capped at ``sqrt(max) / 16`` as well, where the determinant
    of ``k_tt + lam I`` still fits the dtype (a ``mu`` of 1e-10 can reach that in
    float32; then ``x`` is the cap's, brought onto the disk)."""
    empty = k[0, 0] <= 0
    k = jnp.where(empty, jnp.eye(3, dtype=k.dtype), k)
    a, coupling, slip = k[1:, 1:], k[1:, 0], u[1:]
    need = value - u[0]
    # The velocity change the impulse is asked for, against the rounding of ``u``.
    pushes = _beyond_rounding(jnp.where(to_velocity, need, k[0, 0] * value), u)
    theta = (k, u, mu, value, jnp.asarray(to_velocity, k.dtype))  # the flag as a number: a float tangent
    impulse = functools.partial(_impulse, theta=theta)

    p_stick, x_stick = impulse(0.0)
    sticks = (p_stick >= 0) & (jnp.sum(x_stick * x_stick) <= (mu * p_stick) ** 2)

    # A bracket [0, hi] of the root: beyond hi, |x| < mu p. Fixed p: |x| <= |u_t + k_tn p| / lam.
    # To a velocity, once lam >= s, p lies in [p_f / 2, 3 p_f] (p_f the frictionless
    # p), and |x| <= (|u_t| + 3 |k_tn| p_f) / lam.
    reference = jnp.where(to_velocity, need / _where_positive(k[0, 0]), value)
    radius = _where_positive(mu * reference)
    s = jnp.maximum(2 * jnp.dot(coupling, coupling) / _where_positive(k[0, 0]),
                    2 * _norm(coupling) * _norm(slip) / _where_positive(need))
    hi = jnp.where(to_velocity, jnp.maximum(s, 2 * (_norm(slip) + 3 * _norm(coupling) * reference) / radius),
                   _norm(slip + coupling * value) / radius)
    hi = jnp.minimum(hi, float(np.sqrt(jnp.finfo(k.dtype).max)) / 16)
    spread = _safe_sqrt((a[0, 0] - a[1, 1]) ** 2 / 4 + a[0, 1] ** 2)  # 0 for an isotropic k_tt
    start = jnp.clip(_norm(slip + coupling * reference) / radius - (a[0, 0] + a[1, 1]) / 2 - spread, 0.0, hi)

    # The search runs without tangents; the root's derivative is the implicit function
    # theorem's (phi rises through the root). Reverse mode through the Newton steps had
    # differentiated their slopes too: second derivatives of 1/|x|, which overflowed in
    # float32 where the root lies near 1e12 (a contact barely approaching, sliding fast):
    # NaN gradients.
    phi = functools.partial(_phi, theta=jax.lax.stop_gradient(theta))

    def newton(carry, _):
        lam, lo, hi = carry
        value, slope = jax.jvp(phi, (lam,), (jnp.ones_like(lam),))
        lo, hi = jnp.where(value < 0, lam, lo), jnp.where(value < 0, hi, lam)
        step = lam - value / _where_positive(slope)
        inside = (slope > 0) & (step >= lo) & (step <= hi)  # (at the root itself: stay)
        # Else bisect, geometrically: the bracket can span decades.
        middle = jnp.where(hi > 10 * lo, _safe_sqrt(jnp.maximum(lo, 1e-3 * hi) * hi), (lo + hi) / 2)
        return (jnp.where(inside, step, middle), lo, hi), None

    def root(start, hi):
        (lam, _, _), _ = jax.lax.scan(newton, (start, jnp.zeros_like(hi), hi), None, length=ITERATIONS)
        return implicit_root(_phi, lam, theta, 1)

    # The search only where its root is used: a sliding contact that pushes. (Under the
    # impact law's vmap over pairs, ``branch`` still skips it when no pair needs it, in
    # derivatives too.) Recomputed in reverse mode, so that no residuals are zero-filled
    # where it is skipped.
    slides_at_all = (mu > 0) & ~sticks & pushes
    # (Without tangents either way: where the root is not searched, ``lam`` is not used, and
    # the start's ``1 / radius`` has an infinite derivative where ``mu p`` is tiny.)
    lam = branch(slides_at_all, root, lambda start, _: start, *jax.lax.stop_gradient((start, hi)),
                 recompute_in_reverse=True)
    p, x = impulse(lam)
    # On the disk (an iterate short of the root leaves |x| a little over mu p).
    x = x * jnp.minimum(1.0, mu * p * _reciprocal(_norm(x)))
    slides = jnp.concatenate([jnp.reshape(p, (1,)), x])
    stuck = jnp.concatenate([jnp.reshape(p_stick, (1,)), x_stick])
    # Without friction the root is at lam = infinity: the frictionless impulse. A search short
    # of its root (a mu far beyond 1000) can leave p < 0, a pull: that too, which pushes.
    frictionless = jnp.concatenate([jnp.reshape(reference, (1,)), jnp.zeros_like(slip)])
    result = jnp.where(sticks, stuck, jnp.where(p >= 0, slides, frictionless))
    result = jnp.where(mu > 0, result, frictionless)
    return jnp.where(~empty & pushes, result, 0.0)


def frictionless_impulse(k, u, target):
    """The impulse ``(p, 0, 0)`` ``(3,)`` that brings ``u_n`` to ``target`` (m/s) without
    friction, ``p = (target - u_n) / k_nn``: what :func:`coulomb_impulse` gives at
    ``mu = 0``, the same arithmetic and the same rule for when it pushes (0 where
    ``target - u_n <= eps |u|``, an approach below the rounding of ``u``, and where
    ``k_nn <= 0``), without its search."""
    need = target - u[0]
    pushes = _beyond_rounding(need, u) & (k[0, 0] > 0)
    p = jnp.where(pushes, need / _where_positive(k[0, 0]), 0.0)
    return jnp.concatenate([jnp.reshape(p, (1,)), jnp.zeros_like(u[1:])])


def energy_change(k, u, impulse):
    """The kinetic energy (J) an impulse ``(3,)`` adds: ``u . P + P . k P / 2``."""
    return jnp.dot(u, impulse) + 0.5 * jnp.dot(impulse, k @ impulse)


def fraction_within(linear, quadratic, budget):
    """The largest ``theta`` in ``[0, 1]`` with ``theta linear + theta^2 quadratic <= budget``
    (J; ``quadratic >= 0``, ``budget >= 0``): the quadratic is convex and 0 at ``theta = 0``.

    The root is written without a cancellation: ``2 budget / (root + linear)`` where
    ``linear > 0``, else ``(root - linear) / (2 quadratic)`` with ``quadratic > budget -
    linear >= 0``. Both are evaluated only where the budget binds, so a derivative through
    the unbinding case (a ``quadratic`` of rounding size) stays finite."""
    fits = linear + quadratic <= budget
    rising = linear > 0
    linear = jnp.where(fits, 1.0, linear)
    budget = jnp.where(fits, 0.0, budget)
    quadratic = jnp.where(fits, 1.0, quadratic)
    root = _safe_sqrt(linear * linear + 4 * quadratic * budget)
    theta = jnp.where(rising, 2 * budget / jnp.where(rising, root + linear, 1.0),
                      (root - linear) / (2 * _where_positive(jnp.where(rising, 1.0, quadratic))))
    return jnp.where(fits, 1.0, jnp.clip(theta, 0.0, 1.0))


def largest_fraction(k, u, impulse, budget):
    """The largest ``theta`` in ``[0, 1]`` with ``energy_change(k, u, theta impulse) <= budget``."""
    return fraction_within(jnp.dot(u, impulse), 0.5 * jnp.dot(impulse, k @ impulse), budget)
