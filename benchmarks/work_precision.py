"""Work-precision of every jaxrb integrator: error against step size, cost and time, float32 and float64.

What it measures
    Three problems with closed-form references (:mod:`jaxrb.exact`), each one body, gravity=None:

    * ``asymmetric_top``: torque-free, I = diag(1, 2, 3) kg m^2, body omega0 = (-0.3, 0.9, -0.5) rad/s, T = 10 s.
    * ``spinning_rod``: torque-free, I = (1e-4, 1, 1 + 5e-5), omega0 = (100, 1, 0): a fast spin about the
      minor axis with a slow wobble, T = 10 s.
    * ``heavy_top``: the Lagrange top on a fixed pivot, inertia (1, 1, 0.5) about the pivot, Mgl = 4.905 N m,
      omega3 = 20 rad/s, theta0 = 0.6 rad, theta_dot0 = phi_dot0 = 0, T = 10 s. Gravity enters as an
      ``rb.ExternalWrench`` torque about the pivot, Mgl e3_world x (0, 0, -1); the energy includes Mgl cos(theta).

    Every integrator in ``rb.integrators.__all__`` runs at h = T / 2^k (so T / h is a whole number) from a
    large h where methods fail down to ``--max-steps`` steps, stopping early once the float64 error has hit
    the round-off floor (below 1e-9 and less than halved by each of the last two halvings of h); float32
    stops once its error is below 1e-2 and four halvings have not halved it (its U-curve has turned). The
    adaptive diffrax solvers (Tsit5, Dopri5, Dopri8, through ``rb.ode.solve`` with atol = 1e-2 rtol and
    ``step_to_ts`` at the comparison times) sweep rtol instead of h. Each (method, h) compiles one
    ``rb.rollout`` per dtype (h and the step count are static); the float32 and float64 compiles run in
    parallel threads, never during a timed run. Problems with the same scene and T share compiled code.
    Each run records:

    * ``attitude_error``: max over the comparison times T j / 8, j = 1..8, of ``rb.spatial.rotation_angle``
      between the reference and the computed attitude (rad);
    * ``energy_error_max`` / ``energy_error_final``: |E - E0| / E0 over the saved samples (up to 1024 evenly
      spaced states per run; the diffrax runs save only the 8 comparison times);
    * ``momentum_error``: relative error of the world angular momentum (heavy top: of L_z, which every
      method keeps exactly: the gravity torque is horizontal and L is the state);
    * ``manifold_error``: max | |q| - 1 |; for ExplicitEuler, which carries its rotation matrix A, max |A^T A - I|
      (the diffrax solutions come back normalised, so theirs is round-off by construction);
    * ``time_to_failure``: the first saved time at which the state is NaN/inf or E > 2 E0 (None if never).
      Such a run is ``failed`` (as is a diffrax solve that does not succeed) and is left out of fits,
      fronts and tables;
    * ``cost``: wall seconds per simulated second of the compiled rollout (best of ``--repeats`` calls
      after one warm-up, ``block_until_ready``, compile excluded), ``compile_seconds`` (lowering + XLA).
      A compiled call has a fixed overhead (``call_overhead_seconds`` in the JSON, ~50 us here), which
      dominates runs of a few hundred steps.

    ``observed_order`` is the least-squares slope of log(error) against log(h) over the runs with error in
    (1e-11, 1e-1) (float64) or (1e-5, 1e-1) (float32), at h no smaller than the most accurate run's; None
    with fewer than 3 such runs or under two decades of error. For diffrax, h is the mean step T / steps.

    Long horizon: the asymmetric top at h = 0.01 s for ``--long-steps`` steps (float64, or the only dtype
    asked for, as for the stability map), |E - E0| / E0 at
    up to 1e4 evenly spaced times; ``drift_slope`` is the log-log slope of the running max of |dE| over
    the last two decades of time (0: bounded; 1: linear drift).

    Stability map: ``stable at |omega| h`` means that a ``--stability-steps``-step run of the asymmetric top
    does not fail, with failure as for the time to failure above: a NaN/inf, or E >= 2 E0, at any saved
    sample (1000 per run). h is fixed at 0.01 s and omega0's direction kept while its size is scaled: the
    torque-free equations are invariant under t -> c t, omega -> omega / c, so only |omega| h matters, and
    one compile serves the whole grid. Grid: 0.005 to 7.92, 10 values per decade. ``limit`` is the largest
    grid value up to which every grid value is stable (None if the smallest is not). Stability is not
    accuracy: the largest |E - E0| / E0 of each run is recorded beside it (``max_energy_error``), and
    ``accurate_limit`` is the same limit with |E - E0| / E0 <= 0.5 also required (the dissipative
    ImplicitGyroscopic loses energy without blowing up, so its two limits differ most).

How to run (from the repository root)
    python benchmarks/work_precision.py                   # full run (10-15 min, 2 cores) -> benchmarks/results/
    python benchmarks/work_precision.py --quick           # CI smoke run (tens of seconds), temp dir
    python benchmarks/work_precision.py --problems asymmetric_top --methods RK4 Dopri8 --dtypes float64

It prints a summary, writes ``work_precision.json`` (rows, fits, long run, stability map, environment),
``work_precision_table.md`` (cheapest method per attitude tolerance on the asymmetric top, float64, and a
per-method summary) and PNGs: ``_front`` (error vs cost), ``_convergence`` (error vs h), ``_energy``
(|dE|(t)), ``_stability`` and ``_ucurves_<problem>`` (float32 and float64 error vs h per method).
"""

from __future__ import annotations

import argparse
import datetime
import functools
import importlib.metadata
import json
import math
import os
import platform
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import jaxrb as rb

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ is not a package
from _machine import cpu_model  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results"
FIXED = [n for n in rb.integrators.__all__ if n != "Integrator"]
ADAPTIVE = {"Tsit5": (diffrax.Tsit5, 5), "Dopri5": (diffrax.Dopri5, 5), "Dopri8": (diffrax.Dopri8, 8)}
METHODS = FIXED + list(ADAPTIVE)
DTYPES = {"float32": jnp.float32, "float64": jnp.float64}
MGL = 4.905  # N m, heavy top
NUM_COMPARE = 8  # comparison times T j / 8
MAX_SAMPLES = 1024  # saved states per sweep run: failure time and energy are resolved to T / 1024
TOLERANCES = [10.0**-e for e in range(2, 9)]
LONG_DT, STABILITY_DT = 0.01, 0.01  # s
STABILITY_GRID = 0.005 * 10 ** (0.1 * np.arange(33))  # |omega| h from 0.005 to 7.92, 10 per decade
RTOLS = {"float64": [10.0**-e for e in range(2, 14)], "float32": [10.0**-e for e in range(2, 9)]}


class Problem(NamedTuple):  # not a dataclass: tests load this file as a module outside sys.modules
    name: str
    duration: float  # s
    k_min: int  # h = duration / 2^k for k = k_min, k_min + 1, ... up to k_max
    k_max: int | None  # None: up to --max-steps
    inertia: tuple[float, float, float]  # principal moments, kg m^2 (heavy top: about the pivot)
    omega0_body: tuple[float, float, float]  # rad/s
    heavy: bool = False
    theta0: float = 0.0  # rad, heavy top only


def gravity_torque(t, params, state):
    """Zero force and Mgl e3_world x (0, 0, -1) about the pivot (N m, world); e3 = the symmetry axis."""
    e3 = rb.rotation_matrix(state)[:, :, 2]
    torque = MGL * jnp.stack([-e3[:, 1], e3[:, 0], jnp.zeros_like(e3[:, 0])], axis=-1)
    return jnp.zeros_like(state.position), torque


# Built once so that every problem with the same structure shares the static scene (and compiled code).
FREE_SCENE = rb.Scene([rb.Body("b", mass=1.0, inertia=(1.0, 2.0, 3.0))], gravity=None)
HEAVY_SCENE = rb.Scene([rb.Body("top", mass=1.0, inertia=(1.0, 1.0, 0.5))], gravity=None,
                       forces=[rb.ExternalWrench(gravity_torque)])


def make_problems(quick: bool) -> dict[str, Problem]:
    # k_min: an h where every method fails (|omega| h ~ 1 to 10); k_max: --max-steps. Quick: T = 2.5 s.
    t, top, rod, heavy = (2.5, (4, 5), (5, 5), (5, 5)) if quick else (10.0, (3, None), (7, None), (5, None))
    return {p.name: p for p in [
        Problem("asymmetric_top", t, *top, (1.0, 2.0, 3.0), (-0.3, 0.9, -0.5)),
        Problem("spinning_rod", t, *rod, (1e-4, 1.0, 1.0 + 5e-5), (100.0, 1.0, 0.0)),
        Problem("heavy_top", t, *heavy, (1.0, 1.0, 0.5), (0.0, 0.0, 20.0), heavy=True, theta0=0.6),
    ]}


@functools.cache
def initial(problem: Problem, dtype, omega0_body=None):
    scene = HEAVY_SCENE if problem.heavy else FREE_SCENE
    params = scene.params(inertia=problem.inertia, dtype=dtype)
    # Heavy top: R(0) = Rx(theta0), body omega (0, 0, omega3) (theta_dot0 = phi_dot0 = 0).
    q0 = (math.cos(problem.theta0 / 2), math.sin(problem.theta0 / 2), 0.0, 0.0)
    state = scene.state(params, orientation=q0, body_angular_velocity=omega0_body or problem.omega0_body,
                        dtype=dtype)
    return scene, params, state


def reference(problem: Problem, times):
    """Exact attitude at ``times`` and the invariants: energy E0 (J) and momentum (L_world, or L_z)."""
    if problem.heavy:
        i_perp, _, i_axis = problem.inertia
        m = rb.exact.heavy_symmetric_top(i_perp, i_axis, MGL, problem.omega0_body[2], problem.theta0, times)
        return m.rotation, m.energy, np.array([m.L_z])
    m = rb.exact.torque_free_top(problem.inertia, problem.omega0_body, times)
    return m.rotation, m.energy, m.angular_momentum_world


def attitude(traj) -> np.ndarray:
    """(S, 3, 3) float64 attitude of body 0 as ``rb.rotation_matrix`` reads it (the carried matrix, else the
    quaternion, unnormalised). numpy, like the metrics below: eager jax would dispatch op by op, and
    compile each op anew for every trajectory length."""
    if traj.rotation is not None:
        return np.asarray(traj.rotation, np.float64)[:, 0]
    w, x, y, z = np.moveaxis(np.asarray(traj.orientation, np.float64)[:, 0], -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def energy_and_momentum(problem: Problem, params, traj, rotation):
    """Per saved state (S,): total energy (J) and momentum (S, 3), or (S, 1) L_z for the heavy top."""
    momentum = np.asarray(traj.angular_momentum, np.float64)[:, 0]
    inverse_inertia = np.linalg.inv(np.asarray(params.inertia, np.float64)[0])
    omega_body = np.einsum("ij,skj,sk->si", inverse_inertia, rotation, momentum)  # I^-1 A^T L
    energy = 0.5 * np.einsum("sij,sj,si->s", rotation, omega_body, momentum)  # omega . L / 2, as rb computes it
    if problem.heavy:  # + Mgl cos(theta), cos(theta) = e3_world . z; L about the pivot along world z
        return energy + MGL * rotation[:, 2, 2], momentum[:, 2:]
    return energy, momentum


_rotation_angle = jax.jit(rb.spatial.rotation_angle)  # always (8, 3, 3) float64: one compile


def errors(problem: Problem, ref, params, traj, times, compare) -> dict:
    """Metrics of ``traj`` (stacked at ``times`` (S,)); ``compare`` indexes the comparison times in it.

    Everything is evaluated in float64 from the (possibly float32) states, so a float32 row measures the
    error of its state, not the rounding of the metric.
    """
    ref_rotation, energy0, momentum0 = ref
    leaves = np.concatenate([np.reshape(np.asarray(x), (len(times), -1)) for x in jax.tree.leaves(traj)], axis=1)
    finite = np.all(np.isfinite(leaves), axis=1)  # per saved state
    rotation = attitude(traj)
    energy, momentum = energy_and_momentum(problem, params, traj, rotation)
    bad = ~finite | ~(energy < 2.0 * energy0)
    rel_energy = np.abs(energy - energy0) / abs(energy0)
    angle = np.asarray(_rotation_angle(jnp.asarray(ref_rotation), jnp.asarray(rotation[compare])))
    if traj.rotation is not None:  # ExplicitEuler's attitude is its matrix A
        gram = np.einsum("sji,sjk->sik", rotation, rotation) - np.eye(3)
        manifold = np.max(np.abs(gram), axis=(1, 2))
    else:
        manifold = np.abs(np.linalg.norm(np.asarray(traj.orientation, np.float64)[:, 0], axis=-1) - 1.0)
    momentum_error = np.linalg.norm(momentum - momentum0, axis=-1) / np.linalg.norm(momentum0)
    ok = finite.all()
    return dict(
        attitude_error=float(np.max(angle)) if ok else math.nan,
        energy_error_max=float(np.max(rel_energy)) if ok else math.nan,
        energy_error_final=float(rel_energy[-1]),
        momentum_error=float(np.max(momentum_error)) if ok else math.nan,
        manifold_error=float(np.nanmax(manifold)) if finite.any() else math.nan,
        time_to_failure=float(times[np.argmax(bad)]) if bad.any() else None,
        failed=bool(bad.any()),
    )


# ------------------------------------------------------------------------------------------------ compiling

_POOL = ThreadPoolExecutor(max_workers=2)  # XLA compiles in C++, outside the GIL: two compiles use both cores


def compile_many(jobs, workers: int):
    """Lower each ``(fn, *example_args)`` here (Python tracing holds the GIL), compile them in parallel.

    Returns ``[(compiled, seconds)]``; seconds = lowering + XLA compile of that function (with
    ``workers = 2``, measured while one other compile ran beside it).
    """
    lowered = []
    for fn, *example in jobs:
        start = time.perf_counter()
        lowered.append((jax.jit(fn).lower(*example), time.perf_counter() - start))

    def finish(item):
        low, spent = item
        start = time.perf_counter()
        return low.compile(), spent + time.perf_counter() - start

    return list(_POOL.map(finish, lowered)) if workers > 1 else [finish(item) for item in lowered]


def timed(compiled, args, repeats: int, budget: float = 1.0):
    """``(output, best seconds)``: one untimed warm-up call, then up to ``repeats`` timed calls (fewer
    once ``budget`` seconds have been spent timing: a long run's timing noise is small anyway)."""
    out = jax.block_until_ready(compiled(*args))
    best, spent = math.inf, 0.0
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        elapsed = time.perf_counter() - start
        best, spent = min(best, elapsed), spent + elapsed
        if spent > budget:
            break
    return out, best


def call_overhead(repeats: int = 50) -> float:
    """Best time (s) of a compiled call that only returns its (params, state): the fixed cost in every
    measured cost, which dominates runs of a few hundred steps or fewer."""
    _, params, state = initial(make_problems(False)["asymmetric_top"], jnp.float64)
    compiled = jax.jit(lambda p, s: (p, s)).lower(params, state).compile()
    return timed(compiled, (params, state), repeats, budget=math.inf)[1]


def rollout_fn(scene, method: str, dt: float, num_steps: int, save_every: int):
    step = rb.make_step(scene, getattr(rb.integrators, method)(), dt)
    return step, lambda params, state: rb.rollout(step, params, state, num_steps, save_every=save_every)[1]


# ------------------------------------------------------------------------------------------------ sweeps


def sweep_fixed(problems, methods, dtypes, args):
    """Rows for every fixed-step method, h and dtype. Problems with the same scene and T share compiles."""
    rows = {p.name: [] for p in problems}
    groups = {}
    for p in problems:
        groups.setdefault((p.heavy, p.duration), []).append(p)
    max_k = int(math.log2(args.max_steps))
    for (heavy, duration), group in groups.items():
        scene = HEAVY_SCENE if heavy else FREE_SCENE
        setups = {(p.name, d): initial(p, DTYPES[d]) for p in group for d in dtypes}
        refs = {p.name: reference(p, duration * np.arange(1, NUM_COMPARE + 1) / NUM_COMPARE) for p in group}
        for method in methods:
            errs = {(p.name, d): [] for p in group for d in dtypes}  # attitude errors by k
            active = set(errs)
            for k in range(min(p.k_min for p in group), max_k + 1):
                todo = [(p, d) for p in group for d in dtypes
                        if (p.name, d) in active and p.k_min <= k <= (p.k_max or max_k)]
                if not todo:
                    continue
                n = 2**k
                samples = min(n, MAX_SAMPLES)
                times = duration * np.arange(1, samples + 1) / samples
                compare = samples * np.arange(1, NUM_COMPARE + 1) // NUM_COMPARE - 1
                run_dtypes = [d for d in dtypes if any(d == dd for _, dd in todo)]
                jobs, steps = [], {}
                for d in run_dtypes:
                    steps[d], fn = rollout_fn(scene, method, duration / n, n, n // samples)
                    _, params, state = setups[todo[0][0].name, d]
                    jobs.append((fn, params, steps[d].prepare(state)))
                compiled = dict(zip(run_dtypes, compile_many(jobs, args.compile_workers), strict=True))
                for p, d in todo:
                    _, params, state = setups[p.name, d]
                    fn, compile_s = compiled[d]
                    traj, best = timed(fn, (params, steps[d].prepare(state)), args.repeats)
                    row = dict(method=method, kind="fixed", dtype=d, h=duration / n, steps=n, rtol=None,
                               **errors(p, refs[p.name], params, traj, times, compare),
                               cost=best / duration, seconds=best, compile_seconds=compile_s,
                               compile_shared_with=[q.name for q, dd in todo if dd == d and q is not p])
                    rows[p.name].append(row)
                    e = errs[p.name, d]
                    e.append(row["attitude_error"] if not row["failed"] else math.inf)
                    if d == dtypes[-1]:  # float64 (unless float32 alone): stop at its round-off floor
                        if len(e) >= 3 and e[-1] < (1e-9 if d == "float64" else 1e-4) and 2 * e[-1] > e[-2] \
                                and 2 * e[-2] > e[-3]:
                            active -= {(p.name, dd) for dd in dtypes}  # smaller h would only cost time
                    elif len(e) > 4 and min(e) < 1e-2 and min(e[-4:]) > min(e[:-4]) / 2:
                        active.discard((p.name, d))  # float32 at its floor: 4 halvings of h without gain
            for p in group:
                report(p.name, method, rows[p.name])
            jax.clear_caches()  # the traces of every (method, h) would otherwise pile up (GBs over a full run)
    return rows


def solve_fn(scene, solver, t1, ts, max_steps):
    """``(params, state, rtol) -> (trajectory at ts, accepted steps, rejected steps, success)``, atol = 1e-2 rtol."""

    def solve(params, state, rtol):
        # rtol is traced (an array), so one compile serves the whole sweep.
        sol = rb.ode.solve(scene, params, state, t1, solver=solver, rtol=rtol, atol=1e-2 * rtol, ts=ts,
                           step_to_ts=True, max_steps=max_steps, throw=False)
        return (sol.trajectory, sol.stats["num_accepted_steps"], sol.stats["num_rejected_steps"],
                sol.result == diffrax.RESULTS.successful)

    return solve


def sweep_adaptive(problems, solvers, dtypes, args):
    """Rows for the diffrax solvers over an rtol sweep; one compile per (solver, dtype, scene, T)."""
    rows = {p.name: [] for p in problems}
    cache = {}
    for p in problems:
        times = p.duration * np.arange(1, NUM_COMPARE + 1) / NUM_COMPARE
        ref = reference(p, times)
        for name in solvers:
            key = (p.heavy, p.duration, name)
            if key not in cache:
                jobs = []
                for d in dtypes:
                    scene, params, state = initial(p, DTYPES[d])
                    solve = solve_fn(scene, ADAPTIVE[name][0](), p.duration, jnp.asarray(times, DTYPES[d]),
                                     args.max_steps)
                    jobs.append((solve, params, state, jnp.asarray(1e-6, DTYPES[d])))
                cache[key] = dict(zip(dtypes, compile_many(jobs, args.compile_workers), strict=True))
            for d in dtypes:
                fn, compile_s = cache[key][d]
                _, params, state = initial(p, DTYPES[d])
                for rtol in args.rtols[d]:
                    (traj, accepted, rejected, ok), best = timed(fn, (params, state, jnp.asarray(rtol, DTYPES[d])),
                                                                args.repeats)
                    row = dict(method=name, kind="adaptive", dtype=d, h=None, steps=int(accepted), rtol=rtol,
                               atol=1e-2 * rtol, rejected_steps=int(rejected),
                               mean_h=p.duration / max(int(accepted), 1),
                               **errors(p, ref, params, traj, times, np.arange(NUM_COMPARE)),
                               cost=best / p.duration, seconds=best, compile_seconds=compile_s, solver_ok=bool(ok))
                    row["failed"] = row["failed"] or not ok
                    rows[p.name].append(row)
                    if not ok:  # max_steps reached (tolerance beyond the dtype's reach): tighter only costs more
                        break
            report(p.name, name, rows[p.name])
    return rows


def observed_order(rows, method, dtype, key="h"):
    """Least-squares slope of log(error) vs log(h) in the asymptotic, above-round-off band (see docstring)."""
    pts = sorted(((r[key], r["attitude_error"]) for r in rows if r["method"] == method and r["dtype"] == dtype
                  and not r["failed"] and r["attitude_error"] > 0), reverse=True)
    if not pts:
        return None
    best = int(np.argmin([e for _, e in pts]))
    # Up to 0.1 rad in both: under 1e-2, the float64 errors of the first-order methods that
    # are not ExplicitEuler spanned under two decades (SemiImplicitEuler's on the asymmetric
    # top: 3.1e-4 at 2^18 steps to 5.1e-3, 16x), and their orders read "—" in the table.
    lo, hi = (1e-11, 1e-1) if dtype == "float64" else (1e-5, 1e-1)
    band = [(h, e) for h, e in pts[: best + 1] if lo < e < hi]
    if len(band) < 3 or band[0][1] < 100 * band[-1][1]:  # too few points, or under two decades of error
        return None
    return float(np.polyfit(np.log(np.array(band)[:, 0]), np.log(np.array(band)[:, 1]), 1)[0])


def report(problem, method, rows):
    mine = [r for r in rows if r["method"] == method]
    parts = []
    for d in dict.fromkeys(r["dtype"] for r in mine):
        ok = [r["attitude_error"] for r in mine if r["dtype"] == d and not r["failed"]]
        order = observed_order(rows, method, d, "h" if mine[0]["kind"] == "fixed" else "mean_h")
        parts.append(f"{d}: best " + (f"{min(ok):8.1e} rad" if ok else "  failed    ") + ", order "
                     + (f"{order:4.2f}" if order is not None else "  - "))
    # The rows of one diffrax compile repeat its time (their h is None): count it once.
    compile_s = sum(c for _, _, c in {(r["dtype"], r["h"], r["compile_seconds"]) for r in mine})
    print(f"  {problem:15s} {method:20s} {len(mine):3d} runs  " + "   ".join(parts)
          + f"   compiles {compile_s:5.1f} s", flush=True)


# ------------------------------------------------------------------------------------- long run, stability


_ROLLOUTS = {}


def cached_rollout(method, dt, num_steps, save_every, params, state):
    """``(step, compiled, compile seconds)`` of a free-body rollout, compiled once per settings and dtype
    (with --quick the long run and the stability map have the same settings and share it)."""
    key = (method, dt, num_steps, save_every, params.mass.dtype)
    if key not in _ROLLOUTS:
        step, fn = rollout_fn(FREE_SCENE, method, dt, num_steps, save_every)
        _ROLLOUTS[key] = (step, *compile_many([(fn, params, step.prepare(state))], 1)[0])
    return _ROLLOUTS[key]


def long_horizon(methods, dtype_name, num_steps):
    problem = make_problems(False)["asymmetric_top"]
    samples = min(num_steps, 10_000)
    num_steps -= num_steps % samples
    times = LONG_DT * (num_steps // samples) * np.arange(1, samples + 1)
    ref = reference(problem, [0.0])
    out = {}
    for method in methods:
        _, params, state = initial(problem, DTYPES[dtype_name])
        step, compiled, compile_s = cached_rollout(method, LONG_DT, num_steps, num_steps // samples, params, state)
        state = step.prepare(state)
        start = time.perf_counter()  # one call: at ~1e6 steps its timing noise is small
        traj = jax.block_until_ready(compiled(params, state))
        seconds = time.perf_counter() - start
        energy, _ = energy_and_momentum(problem, params, traj, attitude(traj))
        rel = np.abs(energy - ref[1]) / ref[1]
        running = np.maximum.accumulate(np.nan_to_num(rel, nan=np.inf))
        window = (times >= times[-1] / 100) & np.isfinite(running) & (running > 0)
        slope = float(np.polyfit(np.log(times[window]), np.log(running[window]), 1)[0]) if window.sum() > 2 else None
        keep = np.unique(np.geomspace(1, len(times), 400).astype(int) - 1)  # log-spaced, for the JSON
        out[method] = dict(max_energy_error=float(np.max(running)), final_energy_error=float(rel[-1]),
                           drift_slope=slope, seconds=seconds, cost=seconds / times[-1], compile_seconds=compile_s,
                           t=times[keep].tolist(), energy_error=rel[keep].tolist(), _t=times, _rel=rel)
        print(f"  long {method:20s} max |dE|/E0 {out[method]['max_energy_error']:9.2e}  drift slope "
              + (f"{slope:5.2f}" if slope is not None else "  -  ") + f"  {seconds:6.2f} s", flush=True)
    return dict(dtype=dtype_name, h=LONG_DT, steps=num_steps, samples=samples, methods=out)


def stability_map(methods, dtype_name, num_steps, grid):
    problem = make_problems(False)["asymmetric_top"]
    direction = np.array(problem.omega0_body) / np.linalg.norm(problem.omega0_body)
    samples = min(num_steps, 1000)
    out = {}
    for method in methods:
        stable, accurate, worst = [], [], []
        for x in grid:
            omega = tuple(float(w) for w in direction * x / STABILITY_DT)
            _, params, state = initial(problem, DTYPES[dtype_name], omega0_body=omega)
            # The spin is data, not structure: one compile serves the whole grid.
            step, compiled, _ = cached_rollout(method, STABILITY_DT, num_steps, num_steps // samples, params, state)
            traj = compiled(params, step.prepare(state))
            energy, _ = energy_and_momentum(problem, params, traj, attitude(traj))
            energy0 = 0.5 * float(np.sum(np.array(problem.inertia) * np.array(omega) ** 2))
            rel = np.abs(energy - energy0) / energy0
            finite = all(bool(np.all(np.isfinite(np.asarray(leaf)))) for leaf in jax.tree.leaves(traj))
            stable.append(bool(finite and np.all(energy < 2 * energy0)))
            accurate.append(bool(stable[-1] and np.max(rel) <= 0.5))
            worst.append(float(np.max(rel)) if finite else math.inf)

        def limit_of(flags):
            first_bad = flags.index(False) if False in flags else len(grid)
            return float(grid[first_bad - 1]) if first_bad > 0 else None

        limit = limit_of(stable)
        largest = max((float(x) for x, s in zip(grid, stable, strict=True) if s), default=None)
        out[method] = dict(limit=limit, largest_stable=largest, stable=stable, accurate_limit=limit_of(accurate),
                           max_energy_error=worst)
        print(f"  stability {method:20s} limit |omega| h = {fmt(limit, '.3g')}  "
              f"(with |dE|/E0 <= 0.5: {fmt(limit_of(accurate), '.3g')})", flush=True)
    return dict(dtype=dtype_name, h=STABILITY_DT, steps=num_steps, grid=[float(x) for x in grid],
                definition="stable at x = |omega| h: a run of `steps` steps of the asymmetric top (omega0 "
                           "direction kept, |omega| = x / h) stays finite with E < 2 E0 at every one of "
                           "min(steps, 1000) evenly spaced saved states. limit: the largest grid value with every "
                           "grid value up to it stable (None if the smallest is unstable); largest_stable: the "
                           "largest stable grid value anywhere; accurate_limit: as limit, also requiring "
                           "|E - E0| / E0 <= 0.5.",
                methods=out)


# ------------------------------------------------------------------------------------------------ output


def cheapest_table(rows, dtype):
    """Markdown table: the least-cost row of ``dtype`` reaching each attitude tolerance."""
    ok = [r for r in rows if r["dtype"] == dtype and not r["failed"]]
    lines = ["| attitude tolerance (rad) | cheapest method | h (s) or rtol | steps | attitude error (rad) "
             "| cost (s per simulated s) |", "|---|---|---|---|---|---|"]
    for tol in TOLERANCES:
        meeting = [r for r in ok if r["attitude_error"] <= tol]
        if not meeting:
            lines.append(f"| {tol:.0e} | not reached | | | | |")
            continue
        r = min(meeting, key=lambda r: r["cost"])
        setting = f"h = {r['h']:.3g}" if r["kind"] == "fixed" else f"rtol = {r['rtol']:.0e}"
        lines.append(f"| {tol:.0e} | {r['method']} | {setting} | {r['steps']} | {r['attitude_error']:.1e} "
                     f"| {r['cost']:.1e} |")
    return "\n".join(lines)


def fmt(value, spec):
    return "—" if value is None else format(value, spec)


def summary_table(rows, orders, long, stability):
    lines = ["| method | order | observed order (float64 / float32) | best error float64 / float32 (rad) "
             "| stability limit \\|ω\\|h | long run max \\|ΔE\\|/E0 | drift slope |", "|---|---|---|---|---|---|---|"]
    for m in dict.fromkeys(r["method"] for r in rows):
        best = [min((r["attitude_error"] for r in rows if r["method"] == m and r["dtype"] == d
                     and not r["failed"]), default=None) for d in ("float64", "float32")]
        order = ADAPTIVE[m][1] if m in ADAPTIVE else getattr(rb.integrators, m).order
        lr = (long or {}).get("methods", {}).get(m, {})
        lines.append(f"| {m} | {order} | {fmt(orders[m].get('float64'), '.2f')} "
                     f"/ {fmt(orders[m].get('float32'), '.2f')} "
                     f"| {fmt(best[0], '.1e')} / {fmt(best[1], '.1e')} "
                     f"| {fmt((stability or {}).get('methods', {}).get(m, {}).get('limit'), '.3g')} "
                     f"| {fmt(lr.get('max_energy_error'), '.1e')} | {fmt(lr.get('drift_slope'), '.2f')} |")
    return "\n".join(lines)


def fitted_orders(rows, dtypes):
    """``{problem: {method: {dtype: observed order or None}}}``."""
    return {name: {m: {d: observed_order(r, m, d, "h" if m in FIXED else "mean_h") for d in dtypes}
                   for m in dict.fromkeys(x["method"] for x in r)} for name, r in rows.items()}


def tables(rows, orders, long, stability, table_problem, main_dtype, duration):
    """``work_precision_table.md``'s text."""
    return (f"Cheapest method reaching each attitude tolerance, {table_problem}, {main_dtype}, "
            f"T = {duration} s:\n\n"
            + cheapest_table(rows[table_problem], main_dtype)
            + f"\n\nPer method ({table_problem}; stability and long run on the asymmetric top):\n\n"
            + summary_table(rows[table_problem], orders[table_problem], long, stability) + "\n")


def replot(path: Path, out: Path | None = None) -> dict:
    """Redo the fitted orders, the tables and the figures of a recorded run from its JSON,
    without simulating anything: for a change to how the measurements are presented. The
    JSON is rewritten with the new orders and tables and a ``replotted`` entry (date,
    command); the measured rows, times and errors are left as they were."""
    record = json.loads(path.read_text())
    out = path.parent if out is None else out
    rows = {name: problem["rows"] for name, problem in record["problems"].items()}
    orders = fitted_orders(rows, record["dtypes"])
    for name, problem in record["problems"].items():
        problem["observed_order"] = orders[name]
    table_problem = record["table"]["problem"]
    markdown = tables(rows, orders, record["long_horizon"], record["stability"], table_problem,
                      record["dtypes"][-1], record["problems"][table_problem]["duration"])
    record["table"]["markdown"] = markdown
    record["replotted"] = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                               command=" ".join([Path(sys.executable).name, *sys.argv]))
    out.mkdir(parents=True, exist_ok=True)
    (out / "work_precision_table.md").write_text(markdown)
    plots(out, record, rows, record["long_horizon"], record["stability"])
    (out / "work_precision.json").write_text(json.dumps(clean(record), indent=1, allow_nan=False) + "\n")
    print(markdown)
    return record


def plots(out, record, rows_by_problem, long, stability):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    # tab10, then colours of its own for each method past ten: 11 methods on tab10 had given
    # Dopri8 (index 10, clipped) Dopri5's colour, line and marker.
    palette = [plt.get_cmap("tab10")(i) for i in range(10)] + ["black", "saddlebrown", "darkkhaki"]
    if len(METHODS) > len(palette):
        raise ValueError(f"{len(METHODS)} methods, {len(palette)} colours: give the plots more colours")
    color = {m: palette[i] for i, m in enumerate(METHODS)}
    style = {m: ("--" if m in ADAPTIVE else "-") for m in METHODS}
    names = list(rows_by_problem)
    paths = []

    def curve(ax, rows, method, dtype, x, **kw):
        pts = sorted((r[x], r["attitude_error"]) for r in rows if r["method"] == method and r["dtype"] == dtype
                     and not r["failed"] and r["attitude_error"] > 0)
        if pts:
            ax.plot(*zip(*pts, strict=True), ms=4, color=color[method], **{"marker": "o", **kw})
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # decade labels only

    def save(fig, stem):
        fig.tight_layout()
        fig.savefig(out / f"{stem}.png", dpi=110)
        plt.close(fig)
        paths.append(out / f"{stem}.png")

    for stem, x, xlabel in (("work_precision_front", "cost", "cost (wall s per simulated s)"),
                            ("work_precision_convergence", "h", "h (s); diffrax: mean step T / steps")):
        fig, axes = plt.subplots(1, len(names), figsize=(5.2 * len(names), 4.4), squeeze=False)
        for ax, name in zip(axes[0], names, strict=True):
            rows = rows_by_problem[name]
            for m in dict.fromkeys(r["method"] for r in rows):
                key = "mean_h" if (x == "h" and m in ADAPTIVE) else x
                curve(ax, rows, m, record["dtypes"][-1], key, ls=style[m], label=m)
            if x == "h" and ax.lines:  # reference slopes, all through (largest h, 1 rad)
                hs = np.array([r["h"] for r in rows if r["h"]])
                h = np.geomspace(hs.min(), hs.max(), 10)
                for order, c in ((1, "0.3"), (2, "0.5"), (4, "0.7")):
                    ax.plot(h, (h / hs.max()) ** order, ":", color=c, lw=1.5, label=f"h^{order}")
            ax.set(xscale="log", yscale="log", xlabel=xlabel, ylabel="attitude error (rad)",
                   title=f"{name}, {record['dtypes'][-1]}, T = {record['problems'][name]['duration']} s")
            ax.set_ylim(bottom=1e-16, top=10)
            ax.grid(True, which="both", alpha=0.3)
        axes[0, 0].legend(fontsize=7, ncol=2)
        save(fig, stem)

    for name in names:
        rows = rows_by_problem[name]
        methods = list(dict.fromkeys(r["method"] for r in rows))
        cols = min(len(methods), 5)
        fig, axes = plt.subplots(math.ceil(len(methods) / cols), cols, figsize=(3.4 * cols, 3.0 *
                                 math.ceil(len(methods) / cols)), squeeze=False)
        for ax, m in zip(axes.flat, methods, strict=False):
            x = "rtol" if m in ADAPTIVE else "h"
            for d, ls, marker in (("float64", "-", "o"), ("float32", "--", "x")):
                curve(ax, rows, m, d, x, ls=ls, marker=marker, label=d)
            ax.set(xscale="log", yscale="log", title=m, xlabel=x)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
        for ax in list(axes.flat)[len(methods):]:
            ax.axis("off")
        fig.suptitle(f"{name}: attitude error (rad), float32 vs float64")
        save(fig, f"work_precision_ucurves_{name}")

    # (A replot has no energy curves: the JSON keeps their summaries, not the curves.)
    if long and all("_t" in r for r in long["methods"].values()):
        fig, ax = plt.subplots(figsize=(6.4, 4.6))
        for m, r in long["methods"].items():
            ax.plot(r["_t"], np.maximum(r["_rel"], 1e-17), color=color[m], lw=1, label=m)
        ax.set(xscale="log", yscale="log", xlabel="t (s)", ylabel="|E - E0| / E0",
               title=f"asymmetric top, h = {long['h']} s, {long['steps']:.0e} steps, {long['dtype']}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        save(fig, "work_precision_energy")

    if stability:
        fig, ax = plt.subplots(figsize=(6.4, 3.8))
        methods = list(stability["methods"])
        base = stability["grid"][0] / 2  # bars start here: a log axis has no 0
        limits = [stability["methods"][m]["limit"] or base for m in methods]
        ax.barh(methods, [v - base for v in limits], left=base, color=[color[m] for m in methods])
        for i, v in enumerate(limits):
            ax.text(v, i, f" {v:.3g}" if v > base else f" < {stability['grid'][0]:.3g}", va="center", fontsize=8)
        ax.set(xscale="log", xlabel="largest stable |omega| h (rad)",
               title=f"stability, asymmetric top, {stability['steps']} steps: finite, E < 2 E0")
        ax.invert_yaxis()
        save(fig, "work_precision_stability")
    return paths


def clean(value):
    """JSON-safe: NaN/inf -> None, numpy scalars -> Python, keys starting with _ dropped."""
    if isinstance(value, dict):
        return {k: clean(v) for k, v in value.items() if not str(k).startswith("_")}
    if isinstance(value, list | tuple):
        return [clean(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer | np.bool_):
        return value.item()
    return value


# ------------------------------------------------------------------------------------------------ main


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--problems", nargs="+", choices=list(make_problems(False)),
                   help="default: all three (with --quick: asymmetric_top)")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=METHODS)
    p.add_argument("--dtypes", nargs="+", choices=list(DTYPES), default=list(DTYPES))
    p.add_argument("--repeats", type=int, default=3, help="timed calls per run (fewer past 1 s); the best counts")
    p.add_argument("--max-steps", type=lambda s: int(float(s)), default=2**18,
                   help="largest step count of the h sweep (rounded down to a power of 2), and diffrax's max_steps")
    p.add_argument("--long-steps", type=lambda s: int(float(s)), default=10**6, help="long-horizon steps (h = 0.01 s)")
    p.add_argument("--stability-steps", type=lambda s: int(float(s)), default=10**4, help="steps per stability run")
    p.add_argument("--compile-workers", type=int, choices=[1, 2], default=2, help="parallel XLA compiles")
    p.add_argument("--quick", action="store_true",
                   help="CI smoke run: asymmetric top only, T = 2.5 s, 2 h values, Tsit5 and Dopri8 at 2 rtols, "
                        "1e3-step long and stability runs, coarse stability grid, 1 repeat, output to a temp dir")
    p.add_argument("--replot", type=Path, metavar="JSON",
                   help="no simulation: redo the orders, tables and PNGs of a recorded run's work_precision.json "
                        "(in --out, default the JSON's folder)")
    p.add_argument("--out", type=Path, default=None,
                   help=f"output directory (default {DEFAULT_OUT}, or a temp dir with --quick)")
    args = p.parse_args(argv)
    if args.problems is None:
        args.problems = ["asymmetric_top"] if args.quick else list(make_problems(False))
    args.rtols = {d: RTOLS[d] for d in args.dtypes}
    args.grid = STABILITY_GRID
    if args.quick:
        args.repeats, args.long_steps, args.stability_steps = 1, 1000, 1000
        args.methods = [m for m in args.methods if m not in ADAPTIVE or m in ("Tsit5", "Dopri8")]
        args.rtols = {d: [1e-3, 1e-6] for d in args.dtypes}
        args.grid = STABILITY_GRID[::4]
    if args.out is None and args.replot is None:
        args.out = Path(tempfile.mkdtemp(prefix="work_precision_")) if args.quick else DEFAULT_OUT
    if min(args.repeats, args.max_steps, args.long_steps, args.stability_steps) < 1:
        p.error("--repeats, --max-steps, --long-steps and --stability-steps must be positive")
    args.dtypes = sorted(set(args.dtypes), key=list(DTYPES).index)  # float64 last: it decides the floor
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.replot is not None:
        return replot(args.replot, args.out)
    # float64 for the float64 runs and for every metric; float32 runs build float32 params and states.
    jax.config.update("jax_enable_x64", True)
    started = time.perf_counter()
    device = jax.devices()[0]
    problems = [make_problems(args.quick)[n] for n in args.problems]
    fixed = [m for m in FIXED if m in args.methods]
    adaptive = [m for m in ADAPTIVE if m in args.methods]
    print(f"jax {jax.__version__} on {device.platform} ({device.device_kind}), {os.cpu_count()} CPUs, "
          f"dtypes {args.dtypes}, max {args.max_steps} steps, best of {args.repeats}", flush=True)

    phases = {}

    def phase(name, fn, *fn_args):
        start = time.perf_counter()
        result = fn(*fn_args)
        phases[name] = time.perf_counter() - start
        print(f"  [{name}: {phases[name]:.0f} s]", flush=True)
        return result

    overhead = call_overhead()
    print(f"  per-call overhead of a compiled function: {overhead * 1e6:.0f} us", flush=True)
    rows = phase("fixed-step sweep", sweep_fixed, problems, fixed, args.dtypes, args)
    for name, extra in phase("diffrax sweep", sweep_adaptive, problems, adaptive, args.dtypes, args).items():
        rows[name] += extra
    main_dtype = args.dtypes[-1]
    long = phase("long horizon", long_horizon, fixed, main_dtype, args.long_steps) if fixed else None
    stability = (phase("stability map", stability_map, fixed, main_dtype, args.stability_steps, args.grid)
                 if fixed else None)

    orders = fitted_orders(rows, args.dtypes)
    table_problem = "asymmetric_top" if "asymmetric_top" in rows else next(iter(rows))
    markdown = tables(rows, orders, long, stability, table_problem, main_dtype,
                      make_problems(args.quick)[table_problem].duration)
    record = dict(
        benchmark="work_precision",
        description="attitude/energy/momentum/manifold error, time to failure and cost of every jaxrb "
                    "integrator and diffrax solver against closed-form references; see the script's docstring",
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        command=" ".join([Path(sys.executable).name, *sys.argv]),
        argv=list(argv) if argv is not None else sys.argv[1:],
        quick=args.quick,
        jax_version=jax.__version__,
        jaxlib_version=importlib.metadata.version("jaxlib"),
        diffrax_version=diffrax.__version__,
        jaxrb_version=rb.__version__,
        device=f"{device.platform}: {device.device_kind}",
        cpu_model=cpu_model(),
        cpu_count=os.cpu_count(),
        python=platform.python_version(),
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        dtypes=args.dtypes,
        call_overhead_seconds=overhead,
        settings=dict(repeats=args.repeats, max_steps=args.max_steps, num_compare=NUM_COMPARE,
                      max_samples=MAX_SAMPLES, rtols=args.rtols, atol="1e-2 * rtol",
                      compile_workers=args.compile_workers),
        problems={p.name: dict(p._asdict(), rows=rows[p.name], observed_order=orders[p.name],
                               comparison_times=(p.duration * np.arange(1, NUM_COMPARE + 1) / NUM_COMPARE).tolist())
                  for p in problems},
        long_horizon=long,
        stability=stability,
        table=dict(problem=table_problem, tolerances=TOLERANCES, markdown=markdown),
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "work_precision_table.md").write_text(markdown)
    pngs = plots(args.out, record, rows, long, stability)
    record["seconds_total"] = time.perf_counter() - started
    record["phase_seconds"] = phases
    (args.out / "work_precision.json").write_text(json.dumps(clean(record), indent=1, allow_nan=False) + "\n")
    print("\n" + markdown)
    print(f"wrote {args.out / 'work_precision.json'}, work_precision_table.md and {len(pngs)} PNGs "
          f"in {record['seconds_total']:.0f} s")
    return record


if __name__ == "__main__":
    main()
