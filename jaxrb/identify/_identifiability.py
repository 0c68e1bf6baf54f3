"""What the data can and cannot determine: sensitivities, singular values, covariance.

Around a fit ``theta`` (the free physical values, :meth:`FreeParameters.to_vector`), the
residuals ``r(theta)`` have the sensitivity matrix ``J = dr/dtheta`` (``m x p``). With
Gaussian noise of variance ``sigma^2`` the Gauss-Newton (Cramer-Rao) covariance of the
estimate is ``sigma^2 (J^T J)^-1``, with ``sigma^2`` estimated as ``|r|^2 / (m - rank)``
(``rank``: the directions the data determine, ``p`` when all are).

Which combinations the data pin down is read from the singular values of ``J D``, where
``D = diag(|theta|)`` (an entry that is zero counts 1): its columns are the residuals'
sensitivities to *relative* changes, so the singular values do not depend on units. A
singular value that is a tiny fraction of the largest (below ``rcond``) names a direction
``v`` in which the parameters can move together, ``theta (1 + eps v)``, without changing
the residuals: it is unidentifiable from these data. So is one whose residual change is at
the level of rounding, whatever the others' (a single free parameter has no other to be
compared with): a singular value below ``sqrt(eps)`` times the size of the data (the
norm of the measurements, ``data``'s values unless ``measurement_size`` is given, and of
the residuals, the larger; with neither, at an exact fit, a warning says the test cannot
be made). Two classic cases: free fall alone
says nothing about mass (the column is zero), and torque-free tumbling, given its initial
angular velocity, says nothing about the inertia's scale (``v`` is the inertia itself).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from ..scene import Scene
from ..state import Params
from ._fit import _measurement_size, _objective, _space

__all__ = ["Identifiability", "identifiability", "from_unconstrained_jacobian", "FlatMapError"]


class FlatMapError(ValueError):
    """A parameter map is flat at the fit, so a Jacobian in the unconstrained coordinates
    cannot be converted to the physical parameters: linearise in them instead."""


@dataclasses.dataclass(frozen=True)
class Identifiability:
    """The report of :func:`identifiability`.

    Attributes:
        labels: ``(p,)`` names of the free parameters.
        values: ``(p,)`` their values at the point of analysis.
        jacobian: ``(m, p)`` ``dr/dtheta``, in each parameter's own units.
        singular_values: ``(p,)`` of the relative sensitivity matrix ``J diag(|theta|)``,
            largest first (with fewer residuals than parameters, ``m < p``, the last
            ``p - m`` are 0).
        directions: ``(p, p)`` the matching right singular vectors (relative changes).
        unidentifiable: ``[(relative singular value, direction), ...]`` for every singular
            value below ``rcond`` times the largest, or below ``floor``: combinations the
            data do not determine.
        sigma2: the residual variance ``|r|^2 / (m - rank)``, ``rank = p - len(unidentifiable)``
            the number of determined directions; NaN when ``m <= rank`` (no residual to
            estimate it from; the covariance and the standard errors are then NaN too).
        covariance: ``(p, p)`` ``sigma^2 (J^T J)^+``, the pseudo-inverse over the determined
            directions only (those not in ``unidentifiable``): it is the covariance of the
            estimate's determined part and says nothing of the rest (zero along it).
        std: ``(p,)`` standard errors: the square roots of ``covariance``'s diagonal, and
            ``inf`` for every parameter with a component of 0.1 or more in an unidentifiable
            direction.
        rcond: the threshold used.
        floor: the absolute threshold: ``sqrt(eps)`` times the size of the data (the norm
            of the measurements, ``measurement_size`` or ``data``'s values, and of the
            residuals, the larger). A sensitivity below it is rounding, as the mass's in
            free fall is (1e-17 against data of size 4).
        scale: ``(p,)`` the relative coordinates' scale ``|theta|`` (1 for zero entries):
            a direction ``v`` is the change ``scale * v`` in each parameter's own units.
    """

    labels: tuple
    values: np.ndarray
    jacobian: np.ndarray
    singular_values: np.ndarray
    directions: np.ndarray
    unidentifiable: list
    sigma2: float
    covariance: np.ndarray
    std: np.ndarray
    rcond: float
    scale: np.ndarray
    floor: float = 0.0

    @property
    def identifiable(self) -> bool:
        """True when every free parameter is determined by the data."""
        return not self.unidentifiable

    def std_of(self, quantity: Callable) -> np.ndarray:
        """Standard errors of quantities derived from the free parameters (the delta method).

        ``quantity(values)`` takes the ``(p,)`` free values in the order of ``labels`` and
        returns an array; the result has its shape: ``sqrt(g C g^T)`` per entry, with ``g``
        its gradient at ``values`` and ``C`` :attr:`covariance`. ``inf`` where the entry
        changes along an unidentifiable direction by 0.1 or more of its largest relative
        sensitivity (for a parameter itself, the rule of :attr:`std`).

        A combination the data do determine keeps a finite error even where its parts do
        not: from torque-free tumbling, ``lambda v: v[1] / v[0]`` (the ratio of the first
        two moments) where ``std`` is ``inf`` for every moment.
        """
        values = jnp.asarray(self.values)
        outputs = np.asarray(quantity(values))
        gradient = np.asarray(jax.jacobian(lambda v: jnp.ravel(jnp.asarray(quantity(v))))(values), float)
        gradient = gradient.reshape(-1, values.size)
        std = np.sqrt(np.maximum(np.einsum("qi,ij,qj->q", gradient, self.covariance, gradient), 0.0))
        size = np.linalg.norm(gradient * self.scale[None, :], axis=1)
        for _, direction in self.unidentifiable:
            change = np.abs(gradient @ (self.scale * direction))
            std = np.where(change >= 0.1 * size, np.inf, std)
        return std.reshape(outputs.shape)

    def describe(self, direction, threshold: float = 0.1) -> str:
        """A direction as a change in the parameters' own units, normalised, largest first.

        E.g. ``+0.80 inertia[b].zz +0.53 inertia[b].yy +0.27 inertia[b].xx``: the inertia
        scaled as a whole. Terms below ``threshold`` are left out.
        """
        direction = np.asarray(direction) * self.scale
        direction = direction / np.linalg.norm(direction)
        order = np.argsort(-np.abs(direction))
        sign = np.sign(direction[order[0]]) or 1.0
        terms = [f"{sign * direction[i]:+.2f} {self.labels[i]}" for i in order if abs(direction[i]) >= threshold]
        return " ".join(terms)

    def __str__(self) -> str:
        lines = ["parameter                         value           std error"]
        for label, value, std in zip(self.labels, self.values, self.std, strict=True):
            lines.append(f"{label:<32} {value: .6g}   {std:.3g}")
        rel = self.singular_values / self.singular_values[0] if self.singular_values[0] > 0 else self.singular_values
        lines.append("relative singular values: " + ", ".join(f"{s:.2e}" for s in rel))
        if not self.unidentifiable:
            lines.append("every parameter is identifiable from these data")
        top = self.singular_values[0]
        for s, direction in self.unidentifiable:
            why = (f"singular value {s * top:.1e}, at rounding level (below {self.floor:.1e})"
                   if s * top <= self.floor else f"relative singular value {s:.1e}")
            lines.append(f"UNIDENTIFIABLE ({why}): {self.describe(direction)}")
        return "\n".join(lines)


def identifiability(
    residuals: Callable,
    scene: Scene,
    params: Params,
    free,
    *,
    data=None,
    batched: bool = False,
    rcond: float | None = None,
    friction_max: float = 2.0,
    measurement_size: float | None = None,
) -> Identifiability:
    """Sensitivities, identifiable directions and the Gauss-Newton covariance at ``params``.

    Args:
        residuals: ``residuals(params, data) -> (m,)`` (any shape; flattened), as for
            :func:`fit_least_squares`. Evaluate it at the fitted ``params``.
        scene, params, free: as :func:`fit`; ``params`` is the point of analysis.
        data, batched: as :func:`fit`.
        rcond: relative singular values below it are reported unidentifiable. Default
            ``100 sqrt(eps)`` of the dtype: 1.5e-6 in float64, 0.03 in float32 (use
            float64 for this analysis when you can). Singular values below the report's
            ``floor`` (rounding level, see :class:`Identifiability`) are reported too.
        friction_max: as given to the fit. ``params`` need not be a fit's start: any
            finite values will do (``e = 0``, a flat plate's inertia, a friction above
            ``friction_max``), as the report moves the physical values themselves.
        measurement_size: the size of the measurements, in the residuals' units (e.g. the
            norm of the measured heights, m), which sets the rounding ``floor``. Default:
            the norm of ``data``'s floating-point values, so give it when ``data`` also
            holds other arrays (sample times, inputs: microsecond time stamps beside
            heights once made a restitution known to 3e-5 "unidentifiable"), or when the
            measurements live in ``residuals`` itself (``data=None``) and the residuals are
            zero (a study on noise-free data), where the floor is otherwise zero.

    Returns:
        An :class:`Identifiability` report (``print`` it).
    """
    space = _space(scene, params, free, friction_max, for_fit=False)  # any finite point: no map is used
    vector = _objective(residuals, data, batched, jnp.ravel)
    theta = space.to_vector(params)

    @jax.jit
    def linearise(theta):
        # Residuals and Jacobian from one forward-mode pass: one compiled program.
        r = lambda t: jnp.ravel(vector(space.from_vector(t, params)))  # noqa: E731
        return jax.jacfwd(lambda t: (r(t),) * 2, has_aux=True)(theta)

    jac, res = (np.asarray(a, dtype=float) for a in linearise(theta))
    size = _measurement_size(data) if measurement_size is None else _checked_size(measurement_size)
    return _report(space, params, np.asarray(theta, dtype=float), jac, res, rcond, size)


def _checked_size(size) -> float:
    if isinstance(size, bool) or not (isinstance(size, (int, float, np.floating)) and 0 <= size < np.inf):
        raise ValueError(f"measurement_size must be a finite number >= 0 (the norm of the measurements, in the "
                         f"residuals' units), got {size!r}.")
    return float(size)


def from_unconstrained_jacobian(space, params: Params, jacobian, residuals, rcond: float | None = None,
                                measurement_size: float = 0.0):
    """The report at ``params`` from ``dr/dz`` ``(m, n)`` in the unconstrained coordinates.

    ``dr/dtheta = dr/dz (dtheta/dz)^-1``, with ``dtheta/dz`` the Jacobian of the parameter
    maps alone (no simulation). The rounding floor is measured against
    ``measurement_size`` (a fit passes its data's) and the residuals, the larger.
    Coordinates that move no free value (fixed entries of a free field) are dropped first,
    which leaves the square, invertible Jacobian of the per-field bijections.
    """
    again = "Call rb.identify.identifiability(residuals, scene, params, free, data=...) instead."
    try:
        flat, unravel = jax.flatten_util.ravel_pytree(space.unconstrained(params))
    except ValueError as err:  # e.g. a fit that ended exactly at the triangle inequality's limit
        raise FlatMapError(f"A free value lies where its parameter map has no inverse ({err}) {again}") from err
    to_theta = jax.jacfwd(lambda x: space.to_vector(space.physical(unravel(x))))
    maps = np.asarray(to_theta(flat), dtype=float)
    jacobian = np.asarray(jacobian, dtype=float)
    if jacobian.shape[1] != maps.shape[1]:
        raise ValueError(f"The Jacobian has {jacobian.shape[1]} columns, but the free parameters have "
                         f"{maps.shape[1]} unconstrained coordinates.")
    moving = np.any(maps != 0.0, axis=0)
    square = maps[:, moving]
    if not np.all(np.isfinite(jacobian)):
        raise ValueError(f"The fit's Jacobian is not finite, so it cannot give a report. {again}")
    if square.shape[0] != square.shape[1]:
        raise FlatMapError("A free parameter's map is flat to rounding here (restitution or friction at an "
                         f"end of its range), so the fit's Jacobian cannot be converted. {again}")
    # A one-to-one map per entry loses nothing in the division; the inertia's coupled map
    # does, by its condition number, which is unbounded at the triangle inequality's limit
    # (the flat direction's column, computed by cancellation, is then noise: the tumbling
    # fit of notebooks/04 converted that way gave a Jacobian 61% off a new linearisation).
    # Each row is scaled to a largest entry of 1 first, so that the parameters' units do
    # not count (a 1 mm ball's inertia, 4e-13 kg m^2, beside gravity: 2e12 unscaled, 2.0
    # scaled); the columns are not, as that would hide the flattening.
    rows = np.abs(square).max(axis=1, keepdims=True)
    rows = np.where(rows > 0, rows, 1.0)  # a zero row stays zero: singular, refused below
    if np.linalg.cond(square / rows) > 1e10:  # more than ~1e-6 relative would be lost
        raise FlatMapError("An inertia sits at the triangle inequality's limit (a flat body, I1 + I2 = I3), "
                           f"where its log-Cholesky map is flat, so the fit's Jacobian cannot be converted. {again}")
    # dr/dtheta = dr/dz square^-1, with square = diag(rows) (square / rows).
    jac_theta = np.linalg.solve((square / rows).T, jacobian[:, moving].T).T / rows.T
    theta = np.asarray(space.to_vector(params), dtype=float)
    return _report(space, params, theta, jac_theta, np.asarray(residuals, dtype=float).ravel(), rcond,
                   _checked_size(measurement_size))


def _report(space, params: Params, theta, jac, res, rcond, size: float = 0.0) -> Identifiability:
    eps = float(np.finfo(np.asarray(params.mass).dtype).eps)
    if rcond is None:
        rcond = 100.0 * float(np.sqrt(eps))
    # By row: forward mode spreads one infinite slope to every column as inf * 0 = NaN.
    bad = np.flatnonzero(~np.all(np.isfinite(jac), axis=1) | ~np.isfinite(res))
    if bad.size:
        rows = ", ".join(map(str, bad[:8])) + (", ..." if bad.size > 8 else "")
        raise ValueError(f"At these parameters residuals {rows} (of {res.size}) or their sensitivities are not "
                         "finite (NaN or inf), so there is nothing to analyse: check that the simulation is "
                         "finite there (e.g. run it with jax_debug_nans).")
    scale = np.where(np.abs(theta) > 0, np.abs(theta), 1.0)
    m, p = jac.shape
    # All p directions, and p singular values: with fewer residuals than parameters
    # (m < p) the SVD has only m, and the p - m directions the data cannot see at all have
    # singular value 0.
    _, sv, vt = np.linalg.svd(jac * scale[None, :], full_matrices=True)
    sv = np.concatenate([sv, np.zeros(p - sv.size)])
    top = sv[0] if sv.size and sv[0] > 0 else 1.0
    # Relative to the largest, and absolute: the residuals' change at rounding level. A
    # single free parameter, or several that all cancel out of the simulation (the mass in
    # free fall, 1e-17 m per unit relative change), has no larger one to be compared with.
    floor = float(np.sqrt(eps)) * max(size, float(np.linalg.norm(res)))
    if floor == 0.0:
        # No measurement size and an exact fit: a sensitivity that is rounding (the mass's in
        # free fall) cannot be told from a real one, and would be reported identifiable.
        warnings.warn("The report has no scale for rounding (no measurement size and zero residuals), so a "
                      "parameter the data do not determine may be reported identifiable. Pass data= to the "
                      "fit or report, or measurement_size= to rb.identify.identifiability.", stacklevel=3)
    kept = sv > max(rcond * top, floor)  # the directions the data determine
    weak = [(float(s / top), vt[k]) for k, s in enumerate(sv) if not kept[k]]
    # The fit spends one degree of freedom per direction it determines (the rank), not per
    # parameter: an undetermined direction moves no residual. With none to spare (m <= rank)
    # the noise variance cannot be estimated from the fit (an exact fit would claim zero
    # error): NaN, not |r|^2 / 1.
    rank = p - len(weak)
    sigma2 = float(res @ res / (m - rank)) if m > rank else float("nan")
    # (J^T J)^+ over the directions the report calls determined, from the SVD: the
    # pseudo-inverse's own cut (rcond^2 on J^T J) kept those below the absolute floor, so a
    # lone parameter at rounding level (the mass in free fall) got a covariance of 1e28 beside
    # its infinite standard error.
    scaled_cov = (vt[kept].T / sv[kept] ** 2) @ vt[kept]
    covariance = sigma2 * scale[:, None] * scaled_cov * scale[None, :]
    std = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    for _, direction in weak:
        std = np.where(np.abs(direction) >= 0.1, np.inf, std)
    return Identifiability(space.labels, theta, jac, sv, vt, weak, sigma2, covariance, std, rcond, scale, floor)
