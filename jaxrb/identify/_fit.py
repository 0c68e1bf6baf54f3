"""Fitting physical parameters to data: optax (Adam by default) or Levenberg-Marquardt.

Both fitters optimise the unconstrained coordinates of :class:`FreeParameters`, so every
iterate is a physical body (positive mass, a possible inertia, ``e`` in ``(0, 1)``), and
both take one experiment or many: with ``batched=True`` the loss (residuals) of each
experiment comes from ``jax.vmap`` over the leading axis of ``data`` and is averaged
(concatenated).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax

from .._static import positive_count
from ..scene import Scene
from ..state import Params
from ._parameters import FreeParameters

__all__ = ["FitResult", "fit", "fit_least_squares", "default_optimizer"]


@dataclasses.dataclass(frozen=True)
class FitResult:
    """What a fit returns.

    Attributes:
        params: the fitted physical :class:`jaxrb.Params` (the iterate of lowest loss).
        loss: its loss.
        loss_history: the loss at every iterate, the initial guess first (empty where the
            guess's loss is not finite; ``fit`` stops at the first non-finite loss).
        converged: whether the stopping criterion was met before ``max_steps``.
        steps: iterations taken.
        message: why it stopped.
        space: the :class:`FreeParameters` used (labels, masks, maps).
        iterates: every iterate's physical ``Params`` (with ``keep_iterates=True``), else ``None``.
        residuals: :func:`fit_least_squares` only: ``(m,)`` the residuals at ``params``.
        jacobian: :func:`fit_least_squares` only: ``(m, n)`` their Jacobian with respect to
            the unconstrained coordinates (``space.unconstrained()``, flattened) at ``params``,
            from the fit's last linearisation. :meth:`identifiability` reuses it.
        relinearise: :func:`fit_least_squares` only: ``relinearise(params, rcond)``, the
            :func:`jaxrb.identify.identifiability` report of the fit's residuals and data
            at ``params`` (a new linearisation in the physical parameters).
        measurement_size: :func:`fit_least_squares` only: the norm of ``data``'s values (0
            without data), which :meth:`identifiability` measures rounding against.
    """

    params: Params
    loss: float
    loss_history: np.ndarray
    converged: bool
    steps: int
    message: str
    space: FreeParameters
    iterates: list | None = None
    residuals: np.ndarray | None = None
    jacobian: np.ndarray | None = None
    relinearise: Callable | None = dataclasses.field(default=None, repr=False, compare=False)
    measurement_size: float = 0.0

    def identifiability(self, rcond: float | None = None):
        """The :func:`jaxrb.identify.identifiability` report at the fit.

        It converts the fit's last Jacobian to the physical parameters by the chain rule
        through the parameter maps, ``dr/dtheta = dr/dz (dtheta/dz)^-1``, so it usually costs
        no simulation and no new compilation of the residuals. Where a map is flat at the
        fit (restitution or friction at an end of its range, an inertia at the triangle
        inequality's limit) that division would lose the answer, and the report comes from
        a new linearisation in the physical parameters instead (one more compilation).
        Only :func:`fit_least_squares` results carry what this needs; for an optax
        :func:`fit`, whose loss is not a residual vector, call
        ``rb.identify.identifiability(residuals, scene, result.params, free, data=...)``.
        """
        from ._identifiability import FlatMapError, from_unconstrained_jacobian

        if self.jacobian is None:
            raise ValueError(
                "This FitResult carries no Jacobian: only rb.identify.fit_least_squares results do. "
                "Call rb.identify.identifiability(residuals, scene, result.params, free, data=...) instead."
            )
        try:
            return from_unconstrained_jacobian(self.space, self.params, self.jacobian, self.residuals, rcond,
                                               self.measurement_size)
        except FlatMapError:
            if self.relinearise is None:
                raise
            return self.relinearise(self.params, rcond)

    def __str__(self) -> str:
        values = np.asarray(self.space.to_vector(self.params))
        lines = [f"fit: {'converged' if self.converged else 'NOT converged'} after {self.steps} steps "
                 f"({self.message}); loss {self.loss:.6g}"]
        lines += [f"  {label:<32} {value: .8g}" for label, value in zip(self.space.labels, values, strict=True)]
        return "\n".join(lines)


def default_optimizer(learning_rate: float = 0.05) -> optax.GradientTransformationExtraArgs:
    """Adam on the unconstrained coordinates, its step halved whenever the loss plateaus.

    The unconstrained coordinates are O(1) (logs and logits), so one learning rate suits
    most problems; the plateau schedule gives the final digits that a fixed Adam step
    (which keeps oscillating at the size of its step) cannot. The momentum is ``b1 = 0.5``
    rather than 0.9: on the stiff one-dimensional valleys of trajectory fits (restitution
    from a bounce) 0.9 overshoots, and the plateau schedule then shrinks the step before
    the iterate is back (measured: e = 0.8035 instead of 0.80002 in 196 steps; with 0.5,
    0.8000165 in 84).
    """
    return optax.chain(optax.adam(learning_rate, b1=0.5), _halved_on_plateau(factor=0.5, patience=10, rtol=1e-9,
                                                                           min_scale=1e-6))


class _PlateauState(NamedTuple):
    best: jax.Array  # the lowest loss seen
    count: jax.Array  # steps since it was last lowered
    scale: jax.Array  # the factor on the updates


def _halved_on_plateau(factor: float, patience: int, rtol: float, min_scale: float):
    """Updates times a scale that drops by ``factor`` (down to ``min_scale``) after every
    ``patience`` steps that do not lower the loss by more than ``rtol |best|``.

    optax's ``contrib.reduce_on_plateau`` counts an improvement where ``value < (1 - rtol)
    best``, which for a negative loss lies *above* the best: every step counted, the scale
    never dropped, and a fit of a loss with a negative offset (a Gaussian negative log
    likelihood) never converged (``|log m - log 3| - 1``: 2000 steps, mass off by 5.6e-4,
    against 287 steps and 7e-9 at offset 0)."""

    def init(params):
        dtype = jnp.result_type(*jax.tree.leaves(params))
        return _PlateauState(jnp.asarray(jnp.inf, dtype), jnp.zeros((), jnp.int32), jnp.ones((), dtype))

    def update(updates, state, params=None, *, value, **extra_args):
        del params, extra_args
        value = jnp.asarray(value, state.best.dtype)
        improved = ~jnp.isfinite(state.best) | (value < state.best - rtol * jnp.abs(state.best))
        count = jnp.where(improved, 0, state.count + 1)
        drop = count >= patience
        scale = jnp.where(drop, jnp.maximum(state.scale * factor, min_scale), state.scale)
        best = jnp.where(improved, value, state.best)
        updates = jax.tree.map(lambda u: scale.astype(u.dtype) * u, updates)
        return updates, _PlateauState(best, jnp.where(drop, 0, count), scale)

    return optax.GradientTransformationExtraArgs(init, update)


def _one_number(shape) -> ValueError:
    return ValueError(f"fit's loss must return one number, got shape {shape}. For a vector of residuals use "
                      "rb.identify.fit_least_squares(residuals, ...), or return their sum of squares.")


def _mean_over_experiments(values: jax.Array) -> jax.Array:
    """``fit``'s loss over a batch: the mean of one number per experiment. (A vector per
    experiment had been averaged into one number without a word: signed residuals, whose
    mean has no minimum.)"""
    if values.size != values.shape[0]:
        raise _one_number(values.shape[1:])
    return jnp.mean(values)


def _objective(fn: Callable, data, batched: bool, reduce: Callable):
    if data is None:
        if batched:
            raise ValueError("batched=True needs data= with a leading experiment axis.")
        return lambda params: fn(params)
    if batched:
        return lambda params: reduce(jax.vmap(fn, in_axes=(None, 0))(params, data))
    return lambda params: fn(params, data)


def _measurement_size(data) -> float:
    """The norm of ``data``'s floating-point values: the size the identifiability report
    measures rounding against (0 with no data)."""
    values = [np.ravel(np.asarray(x, dtype=float)) for x in jax.tree.leaves(data)
              if jnp.issubdtype(jnp.result_type(x), jnp.inexact)]
    return float(np.linalg.norm(np.concatenate(values))) if values else 0.0


class _Progress:
    """A one-line text progress bar on stderr (works in terminals and notebooks)."""

    def __init__(self, total: int, enabled: bool, name: str):
        self.total, self.enabled, self.name = total, enabled, name
        self.last = 0.0

    def update(self, step: int, loss: float, final: bool = False):
        if not self.enabled:
            return
        now = time.monotonic()
        if not final and now - self.last < 0.2:
            return
        self.last = now
        filled = int(30 * step / max(self.total, 1))
        sys.stderr.write(f"\r{self.name} [{'#' * filled}{'.' * (30 - filled)}] {step}/{self.total} loss {loss:.4e}")
        if final:
            sys.stderr.write("\n")
        sys.stderr.flush()


def _space(scene, params, free, friction_max, for_fit: bool = True) -> FreeParameters:
    if isinstance(free, FreeParameters):
        if friction_max != 2.0 and friction_max != free.friction_max:  # 2.0: the fitters' default
            # It had been ignored without a word: the FreeParameters' own bound is the one used.
            raise ValueError(f"friction_max={friction_max!r} was given with a FreeParameters, whose own bound "
                             f"({free.friction_max!r}) is the one used: give it to FreeParameters(...) instead.")
        if for_fit and not free.for_fit:
            # Built for a report (any finite point): a fit also needs every free value inside
            # its domain, or its start is -inf (e = 0: logit 0) and the fit stalls there.
            return dataclasses.replace(free, for_fit=True)
        return free
    return FreeParameters(scene, params, free, friction_max=friction_max, for_fit=for_fit)


def fit(
    loss: Callable,
    scene: Scene,
    params: Params,
    free,
    *,
    data=None,
    batched: bool = False,
    optimizer: optax.GradientTransformation | None = None,
    max_steps: int = 1000,
    xtol: float = 1e-6,
    patience: int = 20,
    gtol: float = 0.0,
    gradient: str = "auto",
    progress: bool = True,
    keep_iterates: bool = False,
    friction_max: float = 2.0,
) -> FitResult:
    """Minimise ``loss`` over the free parameters with an optax optimiser.

    Args:
        loss: ``loss(params, data) -> ()`` (or ``loss(params)`` without ``data``), a pure
            JAX function of the physical :class:`jaxrb.Params`, e.g. a rollout against
            measurements.
        scene, params: the scene, and the initial guess (free entries) and fixed values.
        free: what to fit: see :class:`FreeParameters` (e.g. ``"restitution"``,
            ``["mass", "friction"]``, ``{"mass": ["ball"]}``), or a ``FreeParameters``
            (whose own template is then the initial guess).
        data: passed to ``loss``; with ``batched=True`` a pytree whose leaves have a
            leading experiment axis, and the loss is the mean over experiments (vmapped).
        optimizer: an optax optimiser; default :func:`default_optimizer` (Adam, 0.05,
            halved on plateaus). Extra arguments (the loss ``value``) are passed to it.
        max_steps: iteration limit.
        xtol, patience: converged when no unconstrained coordinate has moved by more than
            ``xtol (1 + |z|)`` over the last ``patience`` steps (the default optimiser
            shrinks its step on plateaus, so this happens at a minimum).
        gtol: also converged when the gradient's largest entry (in unconstrained
            coordinates) falls below it.
        gradient: ``"forward"`` (one JVP per free scalar: compiles far faster through
            contact steps), ``"reverse"`` (one VJP: for many parameters), or ``"auto"``
            (forward up to 16 free scalars).
        progress: draw a progress bar on stderr.
        keep_iterates: keep every iterate's physical ``Params`` in the result.
        friction_max: the upper bound of a free friction coefficient.

    Returns:
        A :class:`FitResult`: the fitted params (lowest loss seen), the loss history and a
        convergence flag.
    """
    max_steps = positive_count("max_steps", max_steps)  # 0 returned loss inf
    space = _space(scene, params, free, friction_max)
    objective = _objective(loss, data, batched, _mean_over_experiments)
    optimizer = optax.with_extra_args_support(default_optimizer() if optimizer is None else optimizer)
    z = space.unconstrained()

    def total(z):
        value = jnp.asarray(objective(space.physical(z)))
        if value.size != 1:
            raise _one_number(value.shape)
        return value.reshape(())

    if not isinstance(patience, int) or isinstance(patience, bool) or patience < 1:
        raise ValueError(f"patience must be a positive integer (steps), got {patience!r}.")
    if gradient not in ("auto", "forward", "reverse"):
        raise ValueError(f"gradient must be 'auto', 'forward' or 'reverse', got {gradient!r}.")
    forward = gradient == "forward" or (gradient == "auto" and len(space.labels) <= 16)

    moving = space.moving()

    def value_and_grad(z):
        if not forward:
            return jax.value_and_grad(total)(z)
        flat, unravel = jax.flatten_util.ravel_pytree(z)
        grad, value = jax.jacfwd(lambda x: (total(unravel(flat.at[moving].set(x))),) * 2, has_aux=True)(flat[moving])
        return value, unravel(jnp.zeros_like(flat).at[moving].set(grad))

    @eqx.filter_jit
    def update(z, opt_state):
        value, grad = value_and_grad(z)
        updates, opt_state = optimizer.update(grad, opt_state, z, value=value)
        gmax = jnp.max(jnp.stack([jnp.max(jnp.abs(g)) for g in jax.tree.leaves(grad)]))
        return optax.apply_updates(z, updates), opt_state, value, gmax

    opt_state = optimizer.init(z)
    bar = _Progress(max_steps, progress, "fit")
    history, iterates, window = [], [] if keep_iterates else None, []
    best_z, best = z, np.inf
    converged, message, step = False, f"max_steps={max_steps} reached", 0
    for step in range(1, max_steps + 1):
        new_z, opt_state, value, gmax = update(z, opt_state)
        value, gmax = float(value), float(gmax)  # the loss at z (before this update)
        if not np.isfinite(value):
            if step == 1:  # no finite iterate: the guess is returned, with its loss
                best, step = value, 0
                message = f"the loss is {value} at the initial guess; it is returned"
            else:
                message = f"the loss became {value} at step {step - 1}; the best finite iterate is returned"
            break
        history.append(value)
        if keep_iterates:
            iterates.append(space.physical(z))
        if value <= best:
            best_z, best = z, value
        bar.update(step, best)
        if not np.isfinite(gmax):
            message = (f"the gradient became {gmax} at step {step - 1} (the loss was finite: {value:g}); "
                       "the best iterate is returned")
            break
        if gmax < gtol:
            converged, message = True, f"gradient below gtol={gtol:g}"
            break
        # ``patience`` steps apart: the window holds ``patience + 1`` iterates.
        window = [*window[-patience:], np.asarray(jax.flatten_util.ravel_pytree(z)[0])]
        if len(window) == patience + 1:
            moved = np.max(np.abs(np.asarray(window) - window[-1]), axis=0)
            if np.all(moved <= xtol * (1.0 + np.abs(window[-1]))):
                converged, message = True, f"moved less than xtol={xtol:g} in {patience} steps"
                break
        z = new_z
    bar.update(step, best, final=True)
    return FitResult(space.physical(best_z), best, np.asarray(history), converged, step, message, space, iterates)


def fit_least_squares(
    residuals: Callable,
    scene: Scene,
    params: Params,
    free,
    *,
    data=None,
    batched: bool = False,
    xtol: float = 1e-10,
    gtol: float = 1e-12,
    max_steps: int = 100,
    damping: float = 1e-3,
    progress: bool = True,
    keep_iterates: bool = False,
    friction_max: float = 2.0,
) -> FitResult:
    """Levenberg-Marquardt on ``cost = sum(residuals**2) / 2`` over the free parameters.

    For least-squares problems (a trajectory against measurements) it needs far fewer
    iterations than a first-order optimiser and reaches the minimum to full precision.
    Each iteration evaluates the residuals and their Jacobian ``J`` together, in forward
    mode (one JVP per free scalar, vmapped: cheap to compile through contact steps), then
    solves the damped least-squares problem ``min |J d + r|^2 + lam |D d|^2`` with
    Marquardt's scaling ``D = diag(J^T J)^(1/2)`` and Nielsen's update of ``lam``. Steps
    that do not lower the cost are rejected (the damping grows instead), so the cost never
    increases.

    Args:
        residuals: ``residuals(params, data) -> (m,)`` (any shape; flattened). With
            ``batched=True`` the experiments' residuals are concatenated.
        xtol: converged when a step changes no unconstrained coordinate ``z`` by more than
            ``xtol (1 + |z|)`` (each by its own size: a large coordinate does not loosen
            the test for the others); not where the steps were cut down that far because
            the residuals are not finite beyond the iterate (``converged=False``).
        gtol: converged when the gradient ``J^T r`` has no entry above it.
        damping: the initial ``lam``, relative to the largest entry of ``J^T J``.
        Other arguments: as :func:`fit`.

    Returns:
        A :class:`FitResult`; ``loss`` is ``sum(residuals**2) / 2``.
    """
    max_steps = positive_count("max_steps", max_steps)  # 0 returned loss inf
    if isinstance(damping, bool) or not (isinstance(damping, (int, float, np.floating)) and 0 < damping < np.inf):
        # lam <= 0 or NaN: rejected steps never damped, or a step against the gradient taken as converged.
        raise ValueError(f"damping must be a positive, finite number (the initial lam, relative to the largest "
                         f"entry of J^T J), got {damping!r}.")
    space = _space(scene, params, free, friction_max)
    vector = _objective(residuals, data, batched, jnp.ravel)
    flat, unravel = jax.flatten_util.ravel_pytree(space.unconstrained())

    moving = space.moving()

    @jax.jit
    def linearise(x):
        # One JVP per free scalar; the coordinates that move nothing keep zero columns.
        def residual(free):
            return jnp.ravel(vector(space.physical(unravel(x.at[moving].set(free)))))
        jac, r = jax.jacfwd(lambda free: (residual(free),) * 2, has_aux=True)(x[moving])
        return r, jnp.zeros((r.size, x.size), jac.dtype).at[:, moving].set(jac)

    bar = _Progress(max_steps, progress, "least squares")
    x = np.asarray(flat, dtype=float)
    r, jac = (np.asarray(a, dtype=float) for a in linearise(flat))
    cost = 0.5 * float(r @ r)
    history = [cost]
    iterates = [space.physical(unravel(flat))] if keep_iterates else None
    lam, nu = None, 2.0
    walled = False  # a step was rejected for non-finite residuals, and only small ones accepted since
    converged, message, step = False, f"max_steps={max_steps} reached", 0
    for step in range(1, max_steps + 1):
        if not np.isfinite(cost) or not np.all(np.isfinite(jac)):
            what = "residuals are" if not np.isfinite(cost) else "residuals' Jacobian is"
            message = f"the {what} not finite at the initial guess"
            break
        gram, grad = jac.T @ jac, jac.T @ r
        if np.max(np.abs(grad), initial=0.0) <= gtol:
            converged, message = True, f"gradient below gtol={gtol:g}"
            break
        scale = np.maximum(np.diag(gram), 1e-30 * max(np.max(np.diag(gram)), 1e-300))
        lam = damping * np.max(np.diag(gram)) if lam is None else lam
        delta = np.linalg.solve(gram + lam * np.diag(scale), -grad)
        predicted = -(grad @ delta + 0.5 * delta @ gram @ delta)
        r_new, jac_new = (np.asarray(a, dtype=float) for a in linearise(jnp.asarray(x + delta, flat.dtype)))
        cost_new = 0.5 * float(r_new @ r_new)
        rho = (cost - cost_new) / predicted if predicted > 0 else -1.0
        small = np.all(np.abs(delta) <= xtol * (1.0 + np.abs(x)))
        if np.isfinite(cost_new) and rho > 0 and not np.all(np.isfinite(jac_new)):
            message = (f"the Jacobian is not finite at the step's new point (cost {cost_new:g}); the last iterate, "
                       "where it is, is returned")
            break
        if np.isfinite(cost_new) and rho > 0:
            x, r, jac, cost = x + delta, r_new, jac_new, cost_new
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            walled = walled and small
        else:
            lam, nu = lam * nu, 2.0 * nu
            walled = walled or not np.isfinite(cost_new)
        history.append(cost)
        if keep_iterates:
            iterates.append(space.physical(unravel(jnp.asarray(x, flat.dtype))))
        bar.update(step, cost)
        if small and walled:
            # Steps rejected for a non-finite simulation (it blows up between the iterate and
            # the minimum) shrink, and those accepted creep up to where it does, until they
            # pass the xtol test: not convergence, and the gradient there need not be small.
            message = (f"the residuals are not finite beyond the last iterate: the steps toward the minimum "
                       f"were rejected or cut down to xtol={xtol:g} (gradient up to {np.max(np.abs(jac.T @ r)):.3g}); "
                       f"the last iterate is returned")
            break
        if small:
            converged, message = True, f"step below xtol={xtol:g}"
            break
    bar.update(step, cost, final=True)
    z = unravel(jnp.asarray(x, flat.dtype))
    def relinearise(at: Params, rcond: float | None):
        from ._identifiability import identifiability

        return identifiability(residuals, scene, at, space, data=data, batched=batched, rcond=rcond)

    return FitResult(space.physical(z), cost, np.asarray(history), converged, step, message, space, iterates,
                     residuals=r, jacobian=jac, relinearise=relinearise, measurement_size=_measurement_size(data))
