"""Derivatives of roots by the implicit function theorem.

A root found by a loop (secant, Newton, bisection) is a value, not a formula: reverse mode
through the loop would store its iterations and differentiate each step, slope and all, and
in float32 the slope's own derivatives can overflow. :func:`implicit_root` gives the root
the derivative ``d r = -(df/dtheta) dtheta / (df/dr)`` at the root instead, from one
evaluation of ``f``'s derivatives there.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

__all__ = ["implicit_root"]


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 3))
def implicit_root(f, root, theta, slope_sign):
    """``root``, a root of ``f(r, theta)`` in ``r`` (found without tangents), with the
    implicit function theorem's derivative.

    Args:
        f: ``f(r, theta) -> scalar``, traced once more in the derivative rule.
        root: the root, a scalar (its own tangent is ignored).
        theta: a pytree of arrays, what ``f`` depends on besides ``r``.
        slope_sign: ``+1`` or ``-1``, the sign ``df/dr`` has at a regular root. Where the
            slope is 0 or has the other sign (a grazing or degenerate root) the rule divides
            by ``slope_sign`` instead, so the derivative stays finite.
    """
    del f, theta, slope_sign
    return root


@implicit_root.defjvp
def _implicit_root_jvp(f, slope_sign, primals, tangents):
    root, theta = primals
    _, d_theta = tangents
    # The root again as this function of theta, so that it carries theta's tangents inside
    # the rule: a second derivative then differentiates the slope and ``d_value`` along the
    # root's own motion. (With the bare ``root``, which has no tangent, ``grad(grad(...))``
    # of the root of ``r^2 - p`` came out 0 instead of -p^(-3/2)/4; stop 92's review.)
    root = implicit_root(f, jax.lax.stop_gradient(root), theta, slope_sign)
    _, slope = jax.jvp(lambda r: f(r, theta), (root,), (jnp.ones_like(root),))
    _, d_value = jax.jvp(lambda th: f(root, th), (theta,), (d_theta,))
    slope = jnp.where(slope_sign * slope > 0, slope, slope_sign)
    return root, -d_value / slope
