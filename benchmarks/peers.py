"""Peer simulators for jaxrb's contact benchmark: MuJoCo MJX and Brax.

This module is the *peer side* of a jaxrb-vs-peers contact benchmark. It builds the same
two scenes in MuJoCo MJX (``mujoco.mjx``, JAX implementation) and in Brax (its
``generalized`` and ``positional`` pipelines), and measures each peer the same way.

The peers are optional. Nothing here imports ``mujoco``, ``mujoco.mjx`` or ``brax`` at
module level, so ``import benchmarks.peers`` works in jaxrb's own environment; call
:func:`available` to see which peers import (and why not). Install the peers in a
separate virtual environment, since they may pin another jax version::

    python3 -m venv /work/peers-venv
    /work/peers-venv/bin/pip install mujoco mujoco-mjx brax
    /work/peers-venv/bin/python benchmarks/peers.py --out peers.json   # full sizes
    /work/peers-venv/bin/python benchmarks/peers.py --small            # smoke run

A smoke run still compiles 16 functions (4 to 30 s each on 2 CPU cores), so it took
3.5 to 4 minutes on a busy 2-core machine; the full run took 8 minutes. MJX logs that it cannot import
``warp`` (its GPU backend); that is harmless, the JAX implementation is used.

Scenes (SI units, z up, gravity (0, 0, -9.81) m/s^2, timestep h = 1 ms)
    ``box_stack``: 5 cubes of half-extent 0.1 m and 1 kg (uniform density), friction
    coefficient 0.5, stacked on a ground plane at z = 0 and exactly touching (centres at
    z = 0.1, 0.3, 0.5, 0.7, 0.9 m), at rest, simulated for 2 s (2000 steps). Every pair of
    geoms may collide (cube-ground and cube-cube). Accuracy: the drift of the top cube,
    |p(T) - p(0)| in metres (3-D norm; its z and xy parts are given too), and the
    largest penetration depth between any two geoms in the final state, in metres.

    ``ball_drop``: a sphere of radius 0.1 m and 1 kg, released at rest with its centre at
    z = 1.1 m (1 m clearance) above the ground plane, restitution e = 0.8 requested,
    simulated for 3 s. Accuracy: the first three apex clearances H_n (centre z - 0.1 m)
    after the n-th bounce, against the exact H_n = e^(2n) * 1 m, as relative errors
    (H_n - exact) / exact. The apex is refined by a parabola through the three samples
    around the discrete maximum.

How restitution is modelled by each peer
    * MuJoCo MJX has no coefficient of restitution. Contacts are soft constraints whose
      reference acceleration is a damped spring, ``aref = -b v - k r``, set by ``solref``.
      We use the documented *standard* form ``solref="timeconst dampratio"`` (MuJoCo
      docs, Modeling > Solver parameters): with impedance d = dmax the penetration r
      obeys r'' = -(2/timeconst) r' - r / (timeconst * dampratio)^2, a linear
      spring-damper of damping ratio ``dampratio``. A half-period contact of such an
      oscillator rebounds with e = exp(-pi z / sqrt(1 - z^2)), so we set
      ``dampratio = -ln(e) / sqrt(pi^2 + ln(e)^2)`` (0.0709 for e = 0.8) and keep
      MuJoCo's default ``timeconst = 0.02`` s (natural frequency 1/(timeconst*dampratio)
      = 705 rad/s, about 4.5 steps in contact). ``solimp`` stays at MuJoCo's default.
      The rebound is only approximately e: the unilateral force cannot pull, gravity
      acts during contact and the contact starts between steps; the measured apex errors
      show by how much. It depends on timeconst: with MJX 3.17 / float32 the first three
      effective restitutions were (0.84, 0.78, 0.77) at 0.02 s, (0.83, 0.82, 0.81) at
      0.05 s, (0.81, 0.80, 0.80) at 0.1 s (28 mm peak penetration), and the bounce blew
      up at 0.01 s (natural frequency x h = 1.4). ``timeconst`` is an argument of the
      ball-drop functions. We do not use the direct form ``solref="-stiffness -damping"``.
    * Brax ``generalized`` solves MuJoCo-style soft contacts from the same ``solref`` /
      ``solimp`` (through MJX's collision routines), so it gets the same mapping.
    * Brax ``positional`` (position-based dynamics) has an explicit restitution: the
      custom MJCF numeric ``elasticity`` (per geom, averaged over a contact's two geoms),
      set to 0.8 on every geom of the ball scene.
    Both scenes use condim 3 with a pyramidal cone (Brax supports nothing else); in the
    vertical drop friction does no work.

What is measured, per peer (and Brax pipeline) and scene
    * ``compile_s_{E}env``: the wall time of ``jax.jit(f).lower(...).compile()`` for the
      rollout over E environments (tracing, lowering and XLA compilation).
    * ``steps_per_s_1env`` and ``env_steps_per_s_{E}env``: ``E * n / t`` for the best of
      ``repeats`` calls of the compiled rollout after the warm-up calls, each ended by
      ``block_until_ready``. E = 1 runs the plain (un-vmapped) rollout; E > 1 runs
      ``jax.vmap`` of it over E identical copies of the initial state, sharing one model.
      The rollout is ``lax.fori_loop`` over a *traced* step count n (XLA lowers it, like
      ``lax.scan``, to one while loop), so one compiled function serves every n: the
      warm-up calls calibrate n so that a timed call lasts about ``target_call_s``
      seconds, capped at the scene's length (recorded as ``timed_steps_{E}env``, with
      ``timed_repeats_{E}env``). Box-stack calls start from the initial stack. Ball-drop
      calls start 5 steps before the first impact (``timing_start_step``), so each
      window holds a contact phase and then flight, like the scene as a whole.
    * the accuracy figures above, from one environment over the scene's full length.
    JAX runs with its default dtype (float32 unless ``JAX_ENABLE_X64`` is set); the
    dtype, device, CPU count, package versions, ``XLA_FLAGS`` and the 1-minute load
    average are recorded in every result.

XLA:CPU deadlock workaround
    With jaxlib 0.10.2, MJX's vmapped Newton solver deadlocked XLA:CPU's 2-thread
    intra-op pool in batched LAPACK Cholesky calls. :func:`single_thread_xla_pool`
    (called first by every public function) starts JAX's CPU backend with a one-thread
    pool; results record it as ``xla_cpu_pool``. Set ``JAXRB_PEERS_XLA_POOL=default``
    to skip it.

Public functions (each result is a flat ``dict``; a failure gives ``{"error": "..."}``)
    :func:`available`, :func:`mjx_box_stack`, :func:`mjx_ball_drop`,
    :func:`brax_box_stack`, :func:`brax_ball_drop`, :func:`run_all`,
    :func:`gradient_ratios` (reverse-mode cost through a ball_drop rollout; CLI
    ``--gradients``); helpers
    :func:`versions`, :func:`single_thread_xla_pool`, :func:`restitution_dampratio`
    and the MJCF builders :func:`box_stack_mjcf`, :func:`ball_drop_mjcf`.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import json
import math
import os
import platform
import sys
import time
import traceback
from collections.abc import Callable
from typing import Any

import numpy as np

# ------------------------------------------------------------------------- scene constants

GRAVITY = (0.0, 0.0, -9.81)  # m/s^2
TIMESTEP = 1e-3  # s

NUM_BOXES = 5
BOX_HALF_EXTENT = 0.1  # m
BOX_MASS = 1.0  # kg
FRICTION = 0.5  # Coulomb coefficient, sliding
BOX_STACK_SECONDS = 2.0

BALL_RADIUS = 0.1  # m
BALL_MASS = 1.0  # kg
DROP_CLEARANCE = 1.0  # m, lowest point of the ball above the ground at release
RESTITUTION = 0.8
BALL_DROP_SECONDS = 3.0
NUM_APEXES = 3

MUJOCO_TIMECONST = 0.02  # s, MuJoCo's default solref[0]
BRAX_PIPELINES = ("generalized", "positional")

DEFAULT_NUM_ENVS = (1, 1024)
SMALL_NUM_ENVS = (1, 8)
SMALL_STEPS = 50


# ------------------------------------------------------------------------------ availability


POOL_ENV = "JAXRB_PEERS_XLA_POOL"  # set to "default" to skip the workaround below
_POOL_STATE: str | None = None


def single_thread_xla_pool() -> str:
    """Start JAX's CPU backend with a one-thread intra-op pool (a deadlock workaround).

    With jaxlib 0.10.2 on this 2-core machine, MJX's Newton solver under ``jax.vmap``
    over 1024 environments hung for good, at no CPU load, inside ``block_until_ready``:
    gdb showed both intra-op pool threads in jaxlib's batched LAPACK Cholesky kernel
    (``lapack_spotrf_ffi`` -> ``ParallelBatchMap`` -> ``BlockingCounter::Wait``), each
    waiting for sub-tasks queued behind the other (two Cholesky thunks, the mass matrix's
    and the solver Hessian's, run concurrently). ``--xla_cpu_multi_thread_eigen=false``
    did not help. A pool of one thread cannot wait on itself, so this function pins the
    process to one CPU while JAX creates its CPU client, then gives every thread back all
    the CPUs it had: the pool keeps its one thread, which the OS may run on any core.
    XLA:CPU runs one computation on one core anyway; what is lost is the parallel split
    of batched LAPACK calls (and of nothing else we measure).

    Call it before anything initialises JAX's backend (every public function here calls
    it first). Returns what was done, also recorded as ``xla_cpu_pool`` in results:
    ``"one thread (deadlock workaround)"``, ``"default (...)"`` when skipped via
    ``JAXRB_PEERS_XLA_POOL=default``, or ``"default (backend already initialised)"``.
    """
    global _POOL_STATE
    if _POOL_STATE is not None:
        return _POOL_STATE
    if os.environ.get(POOL_ENV, "").lower() == "default":
        _POOL_STATE = f"default ({POOL_ENV}=default)"
        return _POOL_STATE
    if "jax" in sys.modules:
        try:
            from jax._src import xla_bridge

            if getattr(xla_bridge, "_backends", None):
                _POOL_STATE = "default (backend already initialised)"
                return _POOL_STATE
        except Exception:  # noqa: BLE001 - private API; assume not initialised
            pass
    if not hasattr(os, "sched_setaffinity"):
        _POOL_STATE = "default (no sched_setaffinity on this OS)"
        return _POOL_STATE
    cpus = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(cpus)})
    try:
        import jax

        jax.devices("cpu")
    finally:
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setaffinity(int(tid), cpus)
            except OSError:
                pass
    _POOL_STATE = "one thread (deadlock workaround)"
    return _POOL_STATE


def _log(message: str) -> None:
    """Progress on stderr (results go to stdout)."""
    print(f"[peers {time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def _import_reason(module: str) -> bool | str:
    """True if ``module`` imports, else ``"ExceptionType: message"``."""
    try:
        importlib.import_module(module)
        return True
    except Exception as exc:  # noqa: BLE001 - any import failure makes the peer unavailable
        return f"{type(exc).__name__}: {exc}"


def available() -> dict[str, bool | str]:
    """Which peers import here: ``{"mjx": True | reason, "brax": True | reason}``.

    ``mjx`` needs ``mujoco`` and ``mujoco.mjx``; ``brax`` needs ``brax``, ``brax.io.mjcf``
    and both pipelines (Brax also imports ``mujoco.mjx`` for its collision detection).
    When either package is installed it first calls :func:`single_thread_xla_pool`,
    which affects every later JAX computation in this process; when neither is, it
    leaves JAX alone.
    """
    import importlib.util

    if any(importlib.util.find_spec(top) is not None for top in ("mujoco", "brax")):
        single_thread_xla_pool()  # before a peer's import can start JAX's backend
    out: dict[str, bool | str] = {}
    for peer, modules in {
        "mjx": ("mujoco", "mujoco.mjx"),
        "brax": ("brax", "brax.io.mjcf", "brax.generalized.pipeline", "brax.positional.pipeline"),
    }.items():
        status: bool | str = True
        for module in modules:
            status = _import_reason(module)
            if status is not True:
                status = f"import {module} failed: {status}"
                break
        out[peer] = status
    return out


def versions() -> dict[str, str]:
    """Installed versions of jax and the peers (``"absent"`` when not installed), the
    Python version, the CPU count and the machine, for the record."""
    out = {}
    for dist in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "brax", "numpy"):
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            out[dist] = "absent"
    out["python"] = platform.python_version()
    out["cpu_count"] = str(os.cpu_count())
    out["machine"] = platform.machine()
    return out


# ------------------------------------------------------------------------------------ MJCF


def restitution_dampratio(e: float) -> float:
    """Damping ratio z of a linear spring-damper whose half-period contact rebounds with
    restitution ``e`` (0 < e <= 1): e = exp(-pi z / sqrt(1 - z^2)), so
    z = -ln e / sqrt(pi^2 + ln^2 e). Used as MuJoCo's ``solref`` dampratio."""
    if not 0.0 < e <= 1.0:
        raise ValueError(f"restitution must lie in (0, 1], got {e}")
    log_e = math.log(e)
    return -log_e / math.sqrt(math.pi**2 + log_e**2)


def _vec(values) -> str:
    return " ".join(f"{float(v):.9g}" for v in values)


def box_stack_mjcf(num_boxes: int = NUM_BOXES) -> str:
    """MJCF of the ``box_stack`` scene: ``num_boxes`` free cubes (half-extent 0.1 m,
    1 kg, friction 0.5) resting on an infinite ground plane, exactly touching, with
    MuJoCo's default solver settings (Newton, 100 iterations, pyramidal cone) and
    ``solref`` / ``solimp`` at their defaults."""
    mu = FRICTION
    bodies = "\n".join(
        f'    <body name="box{i}" pos="0 0 {BOX_HALF_EXTENT * (2 * i + 1):.9g}">\n'
        f"      <freejoint/>\n"
        f'      <geom name="box{i}" type="box" size="{_vec([BOX_HALF_EXTENT] * 3)}" mass="{BOX_MASS:g}"/>\n'
        f"    </body>"
        for i in range(num_boxes)
    )
    return f"""<mujoco model="jaxrb_peer_box_stack">
  <option timestep="{TIMESTEP:g}" gravity="{_vec(GRAVITY)}" integrator="Euler" cone="pyramidal"/>
  <custom>
    <numeric name="elasticity" data="0"/>
  </custom>
  <default>
    <geom condim="3" friction="{mu:g} 0.005 0.0001"/>
  </default>
  <worldbody>
    <geom name="ground" type="plane" size="0 0 1"/>
{bodies}
  </worldbody>
</mujoco>
"""


def ball_drop_mjcf(restitution: float = RESTITUTION, timeconst: float = MUJOCO_TIMECONST) -> str:
    """MJCF of the ``ball_drop`` scene: a free sphere (radius 0.1 m, 1 kg) with its centre
    at z = 1.1 m above an infinite ground plane.

    Restitution: every geom gets ``solref="timeconst dampratio"`` with
    ``dampratio = restitution_dampratio(restitution)`` (used by MJX and Brax
    ``generalized``) and the custom numeric ``elasticity = restitution`` (used by Brax
    ``positional``); the module docstring explains the mapping.
    """
    dampratio = restitution_dampratio(restitution)
    z0 = BALL_RADIUS + DROP_CLEARANCE
    return f"""<mujoco model="jaxrb_peer_ball_drop">
  <option timestep="{TIMESTEP:g}" gravity="{_vec(GRAVITY)}" integrator="Euler" cone="pyramidal"/>
  <custom>
    <numeric name="elasticity" data="{restitution:.9g}"/>
  </custom>
  <default>
    <geom condim="3" friction="{FRICTION:g} 0.005 0.0001" solref="{timeconst:.9g} {dampratio:.9g}"/>
  </default>
  <worldbody>
    <geom name="ground" type="plane" size="0 0 1"/>
    <body name="ball" pos="0 0 {z0:.9g}">
      <freejoint/>
      <geom name="ball" type="sphere" size="{BALL_RADIUS:.9g}" mass="{BALL_MASS:g}"/>
    </body>
  </worldbody>
</mujoco>
"""


# --------------------------------------------------------------------------- peer adapters
#
# An adapter is a small namespace of pure functions on one environment's state:
#   state0          initial state (a pytree of arrays)
#   step(s)         one physics step of h = 1 ms
#   positions(s)    (num_bodies, 3) world positions of the bodies' centres, m
#   velocities(s)   (num_bodies, 3) world linear velocities of the centres, m/s
#   penetration(s)  scalar: max(0, -min signed distance) over all contacts of state s, m
#   info            dict of solver settings to record
#   init(q, qd)     a state with generalised positions q and velocities qd (free joints:
#                   q = (x, y, z, quaternion), qd = (world linear velocity, angular)),
#                   everything derived from them recomputed; traceable, so a loss can
#                   differentiate through the initial state
#   q0, qd0         state0's q and qd


class _Adapter:
    def __init__(self, state0, step, positions, velocities, penetration, info, init=None, q0=None, qd0=None):
        self.state0 = state0
        self.step = step
        self.positions = positions
        self.velocities = velocities
        self.penetration = penetration
        self.info = info
        self.init = init
        self.q0 = q0
        self.qd0 = qd0


def _max_penetration(dist):
    import jax.numpy as jnp

    if dist.size == 0:
        return jnp.zeros(())
    return jnp.maximum(0.0, -jnp.min(dist))


def _mjx_adapter(xml: str, iterations: int | None = None) -> _Adapter:
    """MJX adapter for the scene ``xml``; ``iterations`` overrides the constraint solver's
    ``opt.iterations`` (default: the MJCF's, i.e. MuJoCo's 100)."""
    import mujoco
    from mujoco import mjx

    model = mujoco.MjModel.from_xml_string(xml)
    if iterations is not None:
        model.opt.iterations = int(iterations)
    try:
        mx = mjx.put_model(model, impl="jax")
        d0 = mjx.make_data(model, impl="jax")
    except TypeError:  # older MJX without the ``impl`` argument
        mx = mjx.put_model(model)
        d0 = mjx.make_data(model)
    nbody = model.nbody - 1  # every non-world body has one free joint

    def contact_of(d):
        impl = getattr(d, "_impl", None)
        return impl.contact if impl is not None and hasattr(impl, "contact") else d.contact

    def penetration(d):
        d = mjx.kinematics(mx, d)
        d = mjx.collision(mx, d)
        return _max_penetration(contact_of(d).dist)

    solver = {0: "PGS", 1: "CG", 2: "Newton"}.get(int(model.opt.solver), str(model.opt.solver))
    info = {
        "solver": solver,
        "solver_iterations": int(model.opt.iterations),
        "solver_ls_iterations": int(model.opt.ls_iterations),
        "cone": "pyramidal" if int(model.opt.cone) == 0 else "elliptic",
        "integrator": "Euler",
    }
    return _Adapter(
        state0=d0,
        step=lambda d: mjx.step(mx, d),
        positions=lambda d: d.qpos.reshape(nbody, 7)[:, :3],
        velocities=lambda d: d.qvel.reshape(nbody, 6)[:, :3],
        penetration=penetration,
        info=info,
        # position-level quantities (xpos, contacts, ...) are recomputed by mjx.step's
        # forward pass, so replacing qpos and qvel is a complete re-initialisation
        init=lambda q, qd: d0.replace(qpos=q, qvel=qd),
        q0=d0.qpos,
        qd0=d0.qvel,
    )


def _brax_adapter(xml: str, pipeline_name: str) -> _Adapter:
    import jax
    import jax.numpy as jnp
    from brax import contact as brax_contact
    from brax.io import mjcf

    if pipeline_name == "generalized":
        from brax.generalized import pipeline
    elif pipeline_name == "positional":
        from brax.positional import pipeline
    else:
        raise ValueError(f"unknown Brax pipeline {pipeline_name!r}; expected one of {BRAX_PIPELINES}")

    sys_ = mjcf.loads(xml)
    if abs(float(sys_.opt.timestep) - TIMESTEP) > 1e-6 * TIMESTEP:  # stored as float32
        raise RuntimeError(f"Brax read timestep {sys_.opt.timestep}, expected {TIMESTEP}")
    act = jnp.zeros(sys_.act_size())
    # jitted: run eagerly, ``generalized``'s init (contacts, Jacobians) took ~40 s on CPU
    state0 = jax.jit(lambda q, qd: pipeline.init(sys_, q, qd))(sys_.init_q, jnp.zeros(sys_.qd_size()))

    def penetration(s):
        c = brax_contact.get(sys_, s.x)
        return jnp.zeros(()) if c is None else _max_penetration(c.dist)

    info = {"pipeline": pipeline_name}
    if pipeline_name == "generalized":
        info.update(
            solver="projected gradient (jaxopt)",
            solver_iterations=int(sys_.solver_iterations),
            solver_maxls=int(sys_.solver_maxls),
        )
    else:
        info.update(solver="position-based (XPBD-style)")
    return _Adapter(
        state0=state0,
        step=lambda s: pipeline.step(sys_, s, act),
        positions=lambda s: s.x.pos,
        velocities=lambda s: s.xd.vel,
        penetration=penetration,
        info=info,
        # ``positional`` steps the maximal coordinates (x, xd), so the state must be rebuilt
        # from (q, qd) by ``pipeline.init``, not just have its q / qd replaced
        init=lambda q, qd: pipeline.init(sys_, q, qd),
        q0=state0.q,
        qd0=state0.qd,
    )


# ------------------------------------------------------------------------------- measuring


def _block(tree):
    import jax

    return jax.block_until_ready(tree)


def _batch(tree, num_envs: int):
    """``num_envs`` identical copies of a pytree, stacked on a new leading axis."""
    import jax
    import jax.numpy as jnp

    return jax.tree_util.tree_map(lambda x: jnp.array(jnp.broadcast_to(x, (num_envs, *jnp.shape(x)))), tree)


def _rollout_fn(step: Callable) -> Callable:
    """``rollout(state, n)``: ``n`` steps (``n`` traced) in one ``lax.fori_loop``."""
    from jax import lax

    def rollout(state, n):
        return lax.fori_loop(0, n, lambda _, s: step(s), state)

    return rollout


def _time_rollout(
    adapter: _Adapter,
    num_envs: int,
    steps: int,
    target_call_s: float,
    repeats: int,
    start_state=None,
) -> dict[str, Any]:
    """Compile time and throughput of the rollout over ``num_envs`` environments.

    The rollout starts from ``start_state`` (one environment's state; default
    ``adapter.state0``), copied ``num_envs`` times when ``num_envs > 1``. Two calibration
    calls (1 step, then about a quarter of the target) also warm the function up; the
    timed call length n is ``target_call_s`` divided by the measured cost of a step,
    clamped to [1, steps]. The best of ``repeats`` timed calls is kept; a step so dear
    that one call of n = 1 exceeds ``target_call_s`` is timed once only.

    Returns ``compile_s``, ``timed_steps``, ``timed_repeats``, ``best_call_s``,
    ``steps_per_s`` (per environment), ``env_steps_per_s``
    (``num_envs * timed_steps / best_call_s``), the final state of the last timed call
    (``"_final"``) and the compiled function (``"_compiled"``).
    """
    import jax
    import jax.numpy as jnp

    rollout = _rollout_fn(adapter.step)
    state = adapter.state0 if start_state is None else start_state
    if num_envs == 1:
        fn = rollout
    else:
        fn, state = jax.vmap(rollout, in_axes=(0, None)), _batch(state, num_envs)
    state = _block(state)

    _log(f"compiling the rollout for {num_envs} env(s)")
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(state, jnp.int32(1)).compile()
    compile_s = time.perf_counter() - t0
    _log(f"compiled in {compile_s:.1f} s; calibrating")

    def call(n: int) -> float:
        t = time.perf_counter()
        _block(compiled(state, jnp.int32(n)))
        return time.perf_counter() - t

    per_step = call(1)  # first call: warm-up and a coarse cost estimate
    if per_step < 0.25 * target_call_s and steps > 1:
        n_cal = int(min(steps, max(2, round(0.25 * target_call_s / per_step))))
        per_step = call(n_cal) / n_cal
    n = int(min(steps, max(1, round(target_call_s / max(per_step, 1e-9)))))
    timed_repeats = max(1, repeats) if per_step * n <= 1.5 * target_call_s else 1

    _log(f"timing {timed_repeats} x {n} steps of {num_envs} env(s)")
    best = math.inf
    final = None
    for _ in range(timed_repeats):
        t0 = time.perf_counter()
        final = _block(compiled(state, jnp.int32(n)))
        best = min(best, time.perf_counter() - t0)
    return {
        "compile_s": compile_s,
        "timed_steps": n,
        "timed_repeats": timed_repeats,
        "best_call_s": best,
        "steps_per_s": n / best,
        "env_steps_per_s": num_envs * n / best,
        "_final": final,
        "_compiled": compiled,
    }


def _throughput(
    adapter: _Adapter,
    num_envs_list,
    steps: int,
    target_call_s: float,
    repeats: int,
    start_state=None,
) -> tuple[dict[str, Any], Any]:
    """Timing figures for every E in ``num_envs_list``, flat, plus the compiled 1-env
    rollout (``None`` if E = 1 was not asked for)."""
    out: dict[str, Any] = {}
    compiled_1 = None
    for num_envs in num_envs_list:
        r = _time_rollout(adapter, int(num_envs), steps, target_call_s, repeats, start_state)
        tag = f"{int(num_envs)}env"
        out[f"compile_s_{tag}"] = r["compile_s"]
        out[f"timed_steps_{tag}"] = r["timed_steps"]
        out[f"timed_repeats_{tag}"] = r["timed_repeats"]
        out[f"best_call_s_{tag}"] = r["best_call_s"]
        if int(num_envs) == 1:
            out["steps_per_s_1env"] = r["steps_per_s"]
            compiled_1 = r["_compiled"]
        else:
            out[f"env_steps_per_s_{tag}"] = r["env_steps_per_s"]
        finite = all(
            bool(np.all(np.isfinite(np.asarray(x))))
            for x in _leaves(r["_final"])
            if np.issubdtype(np.asarray(x).dtype, np.floating)
        )
        out[f"finite_{tag}"] = finite
    return out, compiled_1


def _leaves(tree):
    import jax

    return jax.tree_util.tree_leaves(tree)


def _steps(seconds: float) -> int:
    return max(1, int(round(seconds / TIMESTEP)))


def _common(peer: str, scene: str, steps: int) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    v = versions()
    return {
        "peer": peer,
        "scene": scene,
        "timestep_s": TIMESTEP,
        "steps": steps,
        "simulated_s": steps * TIMESTEP,
        "dtype": str(jnp.zeros(()).dtype),
        "device": str(jax.devices()[0]),
        "jax_version": v["jax"],
        "jaxlib_version": v["jaxlib"],
        "mujoco_version": v["mujoco"],
        "mujoco_mjx_version": v["mujoco-mjx"],
        "brax_version": v["brax"],
        "cpu_count": os.cpu_count(),
        "xla_cpu_pool": single_thread_xla_pool(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        # other work on the machine skews timings; the 1-minute load average says how much
        "loadavg_1min_at_start": os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan"),
    }


# ------------------------------------------------------------------------------ the scenes


def _box_stack(adapter: _Adapter, num_envs_list, steps, target_call_s, repeats) -> dict[str, Any]:
    """Timings plus the box-stack accuracy figures for one adapter."""
    import jax
    import jax.numpy as jnp

    out, compiled_1 = _throughput(adapter, num_envs_list, steps, target_call_s, repeats)
    rollout = compiled_1 if compiled_1 is not None else jax.jit(_rollout_fn(adapter.step))
    final = _block(rollout(adapter.state0, jnp.int32(steps)))
    p0 = np.asarray(adapter.positions(adapter.state0), dtype=np.float64)
    p1 = np.asarray(adapter.positions(final), dtype=np.float64)
    top = int(np.argmax(p0[:, 2]))
    d = p1[top] - p0[top]
    out.update(
        top_box_drift_m=float(np.linalg.norm(d)),
        top_box_drift_z_m=float(d[2]),
        top_box_drift_xy_m=float(np.hypot(d[0], d[1])),
        max_box_drift_m=float(np.max(np.linalg.norm(p1 - p0, axis=1))),
        max_penetration_end_m=float(jax.jit(adapter.penetration)(final)),
    )
    return out


def _apexes(z: np.ndarray, count: int = NUM_APEXES, min_height: float = 1e-3) -> list[float]:
    """Clearances (m) of the first ``count`` apexes after a bounce, from the per-step
    centre heights ``z`` (z[0] is the release). An apex is a strict local maximum of z
    more than ``min_height`` above the resting height that is the largest value within
    +-5 steps; it is refined by the vertex of the parabola through its 3 samples."""
    clearance = np.asarray(z, dtype=np.float64) - BALL_RADIUS
    found: list[float] = []
    for k in range(1, len(clearance) - 1):
        a, b, c = clearance[k - 1], clearance[k], clearance[k + 1]
        if not (b > a and b >= c and b > min_height):
            continue
        if b < np.max(clearance[max(0, k - 5) : k + 6]):
            continue
        curvature = a - 2.0 * b + c
        peak = b - (c - a) ** 2 / (8.0 * curvature) if curvature < 0 else b
        found.append(float(peak))
        if len(found) == count:
            break
    return found


def _first_impact_step() -> int:
    """The last step before the ball first touches the ground: floor(sqrt(2 H / g) / h)."""
    return int(math.sqrt(2.0 * DROP_CLEARANCE / abs(GRAVITY[2])) / TIMESTEP)


def _ball_drop(adapter: _Adapter, num_envs_list, steps, target_call_s, repeats) -> dict[str, Any]:
    """Apex-height accuracy figures and timings for one adapter.

    The accuracy trajectory (one environment, ``steps`` steps, the ball's centre height
    and the largest penetration after every step) is one ``lax.scan``, split at the
    first impact so that the state there comes out too. Timed calls start from that
    state (when the run is long enough to reach it), so every timed window opens with
    the first bounce's contact phase and then follows the flight, the same mix of steps
    as the scene; the window is at most ``steps - start`` steps.
    """
    import jax
    from jax import lax

    start = _first_impact_step() - 5
    start = start if steps > start + 1 else 0  # short (smoke) runs never reach the ground

    def body(s, _):
        s = adapter.step(s)
        return s, (adapter.positions(s)[0, 2], adapter.penetration(s))

    def trajectory(state):
        mid, first = lax.scan(body, state, None, length=start)
        _, rest = lax.scan(body, mid, None, length=steps - start)
        return mid, jax.tree_util.tree_map(lambda a, b: jax.numpy.concatenate([a, b]), first, rest)

    t0 = time.perf_counter()
    mid, (z, pen) = _block(jax.jit(trajectory)(adapter.state0))
    trajectory_s = time.perf_counter() - t0

    out, _ = _throughput(adapter, num_envs_list, steps - start, target_call_s, repeats, start_state=mid)
    out["timing_start_step"] = start
    out["trajectory_run_s"] = trajectory_s  # compile + run, for information only
    z0 = float(np.asarray(adapter.positions(adapter.state0))[0, 2])
    z = np.concatenate([[z0], np.asarray(z, dtype=np.float64)])
    heights = _apexes(z)
    for n in range(1, NUM_APEXES + 1):
        exact = RESTITUTION ** (2 * n) * DROP_CLEARANCE
        h = heights[n - 1] if n <= len(heights) else float("nan")
        out[f"apex{n}_m"] = h
        out[f"apex{n}_exact_m"] = exact
        out[f"apex{n}_rel_err"] = (h - exact) / exact
        prev = DROP_CLEARANCE if n == 1 else out[f"apex{n - 1}_m"]
        out[f"apex{n}_effective_restitution"] = math.sqrt(h / prev) if h > 0 and prev > 0 else float("nan")
    out["max_penetration_run_m"] = float(np.max(np.asarray(pen)))
    return out


def _run_guarded(fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """``fn()``, or ``{"error": "..."}`` with the exception and the last traceback line."""
    try:
        return fn()
    except Exception as exc:  # noqa: BLE001 - a failing peer is a result, not a crash
        tb = traceback.format_exc().strip().splitlines()
        return {"error": f"{type(exc).__name__}: {exc}", "traceback_tail": " | ".join(tb[-3:])}


def _require(peer: str) -> str | None:
    status = available()[peer]
    return None if status is True else str(status)


# ----------------------------------------------------------------------------- public API


def mjx_box_stack(
    num_envs_list=DEFAULT_NUM_ENVS,
    seconds: float = BOX_STACK_SECONDS,
    target_call_s: float = 2.0,
    repeats: int = 3,
) -> dict[str, Any]:
    """MuJoCo MJX (JAX implementation) on ``box_stack``.

    Keys: the common record (``peer``, ``scene``, ``timestep_s``, ``steps``,
    ``simulated_s``, ``dtype``, ``device``, ``*_version``, ``cpu_count``), the solver
    settings (``solver``, ``solver_iterations``, ``solver_ls_iterations``, ``cone``,
    ``integrator``), per E: ``compile_s_{E}env`` (s), ``timed_steps_{E}env``,
    ``best_call_s_{E}env`` (s), ``timed_repeats_{E}env``, ``finite_{E}env`` (the
    final timed state has no NaN/inf), and ``steps_per_s_1env`` /
    ``env_steps_per_s_{E}env`` (E > 1); accuracy: ``top_box_drift_m``,
    ``top_box_drift_z_m``, ``top_box_drift_xy_m``, ``max_box_drift_m``,
    ``max_penetration_end_m`` (all m). ``{"error": ...}`` if MJX is missing or fails.
    """
    missing = _require("mjx")
    if missing:
        return {"error": f"MJX unavailable: {missing}"}

    def run():
        _log("MJX box_stack")
        steps = _steps(seconds)
        adapter = _mjx_adapter(box_stack_mjcf())
        out = _common("mjx", "box_stack", steps)
        out.update(adapter.info)
        out.update(_box_stack(adapter, num_envs_list, steps, target_call_s, repeats))
        return out

    return _run_guarded(run)


def mjx_ball_drop(
    num_envs_list=DEFAULT_NUM_ENVS,
    seconds: float = BALL_DROP_SECONDS,
    target_call_s: float = 2.0,
    repeats: int = 3,
    timeconst: float = MUJOCO_TIMECONST,
) -> dict[str, Any]:
    """MuJoCo MJX (JAX implementation) on ``ball_drop``, restitution through
    ``solref="timeconst dampratio"`` (see the module docstring).

    Keys: as :func:`mjx_box_stack` for the record, solver settings and timings, plus
    ``restitution_model``, ``solref_timeconst_s``, ``solref_dampratio``,
    ``timing_start_step``, ``trajectory_run_s``; accuracy:
    ``apex{n}_m``, ``apex{n}_exact_m``, ``apex{n}_rel_err``,
    ``apex{n}_effective_restitution`` for n = 1, 2, 3 (NaN when the run is too short
    to reach that apex), and ``max_penetration_run_m`` (m).
    """
    missing = _require("mjx")
    if missing:
        return {"error": f"MJX unavailable: {missing}"}

    def run():
        _log("MJX ball_drop")
        steps = _steps(seconds)
        adapter = _mjx_adapter(ball_drop_mjcf(RESTITUTION, timeconst))
        out = _common("mjx", "ball_drop", steps)
        out.update(adapter.info)
        out.update(
            restitution_model="solref timeconst/dampratio",
            solref_timeconst_s=timeconst,
            solref_dampratio=restitution_dampratio(RESTITUTION),
        )
        out.update(_ball_drop(adapter, num_envs_list, steps, target_call_s, repeats))
        return out

    return _run_guarded(run)


def _brax_scene(scene: str, xml: str, scene_fn, num_envs_list, seconds, target_call_s, repeats, pipelines):
    missing = _require("brax")
    if missing:
        return {"error": f"Brax unavailable: {missing}"}
    steps = _steps(seconds)
    out: dict[str, Any] = {}
    common = _run_guarded(lambda: _common("brax", scene, steps))
    out.update(common)
    for name in pipelines:

        def run(name=name):
            _log(f"Brax {name} {scene}")
            adapter = _brax_adapter(xml, name)
            r = dict(adapter.info)
            r.update(scene_fn(adapter, num_envs_list, steps, target_call_s, repeats))
            return r

        for key, value in _run_guarded(run).items():
            out[f"{name}/{key}"] = value
    return out


def brax_box_stack(
    num_envs_list=DEFAULT_NUM_ENVS,
    seconds: float = BOX_STACK_SECONDS,
    target_call_s: float = 2.0,
    repeats: int = 3,
    pipelines=BRAX_PIPELINES,
) -> dict[str, Any]:
    """Brax on ``box_stack``, once per pipeline in ``pipelines``.

    Keys: the common record (as :func:`mjx_box_stack`), then every per-pipeline figure
    prefixed by the pipeline's name, e.g. ``generalized/steps_per_s_1env``,
    ``positional/top_box_drift_m``, ``generalized/solver_iterations``; a pipeline that
    fails gives ``{name}/error`` (and ``{name}/traceback_tail``) instead. ``{"error":
    ...}`` if Brax does not import at all.
    """
    return _brax_scene(
        "box_stack", box_stack_mjcf(), _box_stack, num_envs_list, seconds, target_call_s, repeats, pipelines
    )


def brax_ball_drop(
    num_envs_list=DEFAULT_NUM_ENVS,
    seconds: float = BALL_DROP_SECONDS,
    target_call_s: float = 2.0,
    repeats: int = 3,
    pipelines=BRAX_PIPELINES,
    timeconst: float = MUJOCO_TIMECONST,
) -> dict[str, Any]:
    """Brax on ``ball_drop``, once per pipeline: ``generalized`` bounces through the
    ``solref`` mapping, ``positional`` through ``elasticity = 0.8``.

    Keys: as :func:`brax_box_stack`, with the ball-drop accuracy keys of
    :func:`mjx_ball_drop` (``{pipeline}/apex1_m``, ``{pipeline}/apex1_rel_err``, ...).
    """
    out = _brax_scene(
        "ball_drop",
        ball_drop_mjcf(RESTITUTION, timeconst),
        _ball_drop,
        num_envs_list,
        seconds,
        target_call_s,
        repeats,
        pipelines,
    )
    if "error" not in out:
        out.update(
            solref_timeconst_s=timeconst,
            solref_dampratio=restitution_dampratio(RESTITUTION),
            elasticity=RESTITUTION,
        )
    return out


# ------------------------------------------------------------------------------ gradients

GRADIENT_STEPS = 1000  # 1 s of ball_drop: the free fall, the first bounce and some flight
# m/s, central-difference steps for reference slopes of the loss: the local one to check
# the autodiff value, the coarse one to show the slope over a visible change of the drop
# (after a bounce the loss is jagged at small scales, so the two can differ in sign)
GRADIENT_FD_EPS = {"local": 1e-4, "coarse": 1e-2}
_VZ = 2  # index of the ball's vertical velocity in qd (a free joint's linear part comes first)


def _gradient_loss(adapter: _Adapter, steps: int) -> Callable:
    """``loss(x)``: the time integral h * sum_k z_k (m s) of the ball's centre height over
    ``steps`` steps, the ball released with an extra vertical velocity ``x`` (m/s; x = 0
    is the ball_drop scene).

    The initial state is rebuilt by ``adapter.init`` from x, so the derivative flows
    through it, and the rollout is a fixed-length ``lax.scan``: reverse mode cannot
    transpose ``fori_loop`` with a traced trip count or ``while_loop``, which is why
    the throughput rollout (:func:`_rollout_fn`) is not reused here.
    """
    import jax.numpy as jnp
    from jax import lax

    def body(s, _):
        s = adapter.step(s)
        return s, adapter.positions(s)[0, 2]

    def loss(x):
        state = adapter.init(adapter.q0, adapter.qd0.at[_VZ].add(x))
        _, z = lax.scan(body, state, None, length=steps)
        return TIMESTEP * jnp.sum(z)

    return loss


def _best_call(compiled: Callable, x, repeats: int) -> tuple[float, Any]:
    """Best wall time (s) of ``repeats`` calls of ``compiled(x)`` after one warm-up call,
    each ended by ``block_until_ready``, and the last call's value."""
    value = _block(compiled(x))
    best = math.inf
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        value = _block(compiled(x))
        best = min(best, time.perf_counter() - t0)
    return best, value


def _gradient_figures(adapter: _Adapter, steps: int, repeats: int) -> dict[str, Any]:
    """Forward and reverse-mode cost of :func:`_gradient_loss` for one adapter.

    The forward part runs first and is kept when the gradient fails: that failure is
    reported as ``error`` / ``traceback_tail`` (with ``failed_stage = "gradient"``) next
    to the forward figures, since "the forward works, reverse mode does not" is itself
    the result. Central differences of the compiled forward, ``grad_fd_local`` (step
    1e-4 m/s) and ``grad_fd_coarse`` (1e-2 m/s), are references for the gradient's
    value; ``grad_rel_diff_vs_fd`` compares with the local one. They need not agree with
    each other: contact switching on and off at step boundaries makes the loss jagged
    (with MJX 3.17, 1000 steps: -35, 19, -0.46 and 0.78 s^2 for steps of 1e-4, 1e-3,
    1e-2 and 3e-2 m/s). In float32 the local difference is also noisy: over 50 steps of
    free fall (exact slope h^2 n (n + 1) / 2 = 1.275e-3 s^2) it was off by 1e-5 s^2 for
    MJX and 2.5e-4 s^2 for Brax ``positional``.
    """
    import jax
    import jax.numpy as jnp

    out: dict[str, Any] = dict(adapter.info)
    loss = _gradient_loss(adapter, steps)
    x = jnp.zeros((), dtype=jnp.asarray(adapter.qd0).dtype)

    _log(f"compiling the forward loss ({steps} steps)")
    t0 = time.perf_counter()
    forward = jax.jit(loss).lower(x).compile()
    out["forward_compile_s"] = time.perf_counter() - t0
    forward_s, value = _best_call(forward, x, repeats)
    out["forward_run_s"] = forward_s
    out["loss_m_s"] = float(value)
    for tag, eps in GRADIENT_FD_EPS.items():
        out[f"grad_fd_{tag}"] = (float(forward(x + eps)) - float(forward(x - eps))) / (2.0 * eps)
    fd = out["grad_fd_local"]

    def gradient() -> dict[str, Any]:
        _log("compiling the gradient")
        t0 = time.perf_counter()
        grad = jax.jit(jax.grad(loss)).lower(x).compile()
        r: dict[str, Any] = {"grad_compile_s": time.perf_counter() - t0}
        grad_s, g = _best_call(grad, x, repeats)
        g = float(g)
        r.update(
            grad_run_s=grad_s,
            grad_over_forward=grad_s / forward_s,
            grad_finite=bool(np.isfinite(g)),
            grad=g,
            grad_rel_diff_vs_fd=(g - fd) / abs(fd) if fd != 0 else float("nan"),
        )
        return r

    r = _run_guarded(gradient)
    if "error" in r:
        r["failed_stage"] = "gradient"
    out.update(r)
    return out


def gradient_ratios(steps: int = GRADIENT_STEPS, repeats: int = 3) -> dict[str, Any]:
    """Cost of reverse-mode differentiation through a ``steps``-step ball_drop rollout,
    per peer: MJX (as configured for the benchmark: Newton, 100 iterations), MJX with
    ``opt.iterations = 1`` (a labelled variant, see below), Brax ``generalized`` and Brax
    ``positional``.

    The loss (:func:`_gradient_loss`) is the time integral of the ball's height, as a
    function of an extra initial vertical velocity x (m/s), evaluated and differentiated
    at x = 0. For the forward ``jax.jit(loss)`` and the gradient ``jax.jit(jax.grad(loss))``
    it records the compile time (``lower(x).compile()``, s) and the best of ``repeats``
    calls after a warm-up (s), then ``grad_over_forward`` (gradient time / forward time),
    ``grad_finite``, ``grad`` (m s per m/s = s^2), and central differences
    ``grad_fd_local`` / ``grad_fd_coarse`` of the forward with ``grad_rel_diff_vs_fd``
    (see :func:`_gradient_figures`).

    MJX's constraint solver runs a ``lax.while_loop`` over its iterations, which reverse
    mode cannot transpose; the benchmark's configuration is measured as is and a failure
    is reported. ``mjx_iterations1`` is the variant the MuJoCo maintainers point to for
    gradients (google-deepmind/mujoco issue #2259): with ``opt.iterations == 1``
    ``mjx.solve`` calls its loop body once instead of the while loop (its line search
    is already a scan). One Newton iteration is a different, less converged simulation,
    so it is not the benchmark's MJX; its ``loss_m_s`` shows how far it moves.

    Brax ``generalized`` (0.14.2) returns a NaN gradient here, even for one step of free
    fall: its free-joint integrator (``_integrate_q_free``) divides by
    ``jnp.linalg.norm`` of the angular velocity, whose derivative at the ball's zero spin
    is 0/0 (forward mode gives NaN too). It is reported as measured, not worked around.

    Returns ``{"available", "versions", "steps", "repeats", "input", "loss", "dtype",
    "xla_cpu_pool", "loadavg_1min_at_start", "mjx", "mjx_iterations1",
    "brax_generalized", "brax_positional", "wall_s"}``; an engine that is missing or
    fails outright gives ``{"error", "traceback_tail"}``.
    """
    single_thread_xla_pool()
    t_start = time.perf_counter()
    out: dict[str, Any] = {
        "available": available(),
        "versions": versions(),
        "steps": int(steps),
        "repeats": int(repeats),
        "input": "x = extra initial vertical velocity of the ball, m/s, evaluated at x = 0",
        "loss": "TIMESTEP * sum over the steps of the ball centre height after each step, m s",
        "xla_cpu_pool": single_thread_xla_pool(),
        "loadavg_1min_at_start": os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan"),
    }
    import jax.numpy as jnp

    out["dtype"] = str(jnp.zeros(()).dtype)
    xml = ball_drop_mjcf(RESTITUTION, MUJOCO_TIMECONST)

    engines: list[tuple[str, str, Callable[[], _Adapter]]] = [
        ("mjx", "mjx", lambda: _mjx_adapter(xml)),
        ("mjx_iterations1", "mjx", lambda: _mjx_adapter(xml, iterations=1)),
    ]
    engines += [(f"brax_{name}", "brax", lambda name=name: _brax_adapter(xml, name)) for name in BRAX_PIPELINES]
    for key, peer, make in engines:
        missing = _require(peer)
        if missing:
            out[key] = {"error": f"{peer} unavailable: {missing}"}
            continue

        def run(key=key, make=make):
            _log(f"gradients: {key}")
            r = _gradient_figures(make(), int(steps), int(repeats))
            if key == "mjx_iterations1":
                r["variant"] = "opt.iterations = 1 (differentiable workaround, not the benchmark's MJX)"
            return r

        out[key] = _run_guarded(run)
    out["wall_s"] = time.perf_counter() - t_start
    return out


def run_all(small: bool = False) -> dict[str, Any]:
    """Every peer on every scene: ``{"available", "versions", "mjx_box_stack",
    "mjx_ball_drop", "brax_box_stack", "brax_ball_drop", "wall_s"}``.

    ``small=True`` is a smoke run: 50 steps, E = (1, 8), one short timed call each; its
    ball-drop apexes are NaN (the ball is still falling). ``small=False`` uses the full
    scenes (2 s and 3 s) and E = (1, 1024).
    """
    t0 = time.perf_counter()
    if small:
        kw = dict(num_envs_list=SMALL_NUM_ENVS, target_call_s=0.05, repeats=1)
        box_s = ball_s = SMALL_STEPS * TIMESTEP
    else:
        kw = dict(num_envs_list=DEFAULT_NUM_ENVS, target_call_s=2.0, repeats=3)
        box_s, ball_s = BOX_STACK_SECONDS, BALL_DROP_SECONDS
    out: dict[str, Any] = {"available": available(), "versions": versions(), "small": small}
    out["mjx_box_stack"] = mjx_box_stack(seconds=box_s, **kw)
    out["mjx_ball_drop"] = mjx_ball_drop(seconds=ball_s, **kw)
    out["brax_box_stack"] = brax_box_stack(seconds=box_s, **kw)
    out["brax_ball_drop"] = brax_ball_drop(seconds=ball_s, **kw)
    out["wall_s"] = time.perf_counter() - t0
    return out


def _main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--small", action="store_true", help="smoke run: 50 steps, E = (1, 8)")
    parser.add_argument("--out", help="write the JSON result here as well as to stdout")
    parser.add_argument(
        "--gradients",
        action="store_true",
        help=f"run gradient_ratios instead ({GRADIENT_STEPS} steps, 3 repeats; --small: {SMALL_STEPS} steps, 1)",
    )
    args = parser.parse_args(argv)
    if args.gradients:
        if args.small:
            result = gradient_ratios(steps=SMALL_STEPS, repeats=1)
        else:
            result = gradient_ratios(steps=GRADIENT_STEPS, repeats=3)
    else:
        result = run_all(small=args.small)
    text = json.dumps(result, indent=2, sort_keys=False, default=str)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(_main())
