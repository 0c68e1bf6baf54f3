"""Throughput of jaxrb on a free rigid body: environment-steps per second.

What it measures
    One box (half extents 0.1, 0.2, 0.3 m, 1 kg) under gravity, spinning about all three
    axes, advanced by each integrator of ``rb.integrators`` with dt = 1 ms. For each
    ensemble size E (``--envs``) the timed function is
    ``jax.jit(jax.vmap(rollout))`` over E copies of params and state (E = 1: the plain,
    un-vmapped rollout), running ``--steps`` steps as one ``lax.scan`` with
    ``save_every=steps`` so no trajectory is stored. The score is
    ``E * steps / seconds`` for the best of ``--repeats`` calls, after one warm-up call,
    each ended by ``block_until_ready``. Compile time (tracing, lowering and XLA
    compilation, via ``.lower().compile()``) is timed separately and excluded.

    A bare baseline runs the same semi-implicit Euler physics written directly in
    ``jax.numpy`` on plain arrays (position, quaternion, velocity, angular momentum and
    the inverse body inertia, inverted once outside the loop), element-wise formulas,
    vmapped the same way. ``jaxrb / bare`` is then the cost of jaxrb's abstractions. The
    script checks that both give the same final state before it reports anything.

How to run (from the repository root)
    python benchmarks/free_body.py                        # float32, E = 1 64 1024 4096
    python benchmarks/free_body.py --x64                  # float64
    python benchmarks/free_body.py --envs 1 256 --steps 500 --repeats 5
    python benchmarks/free_body.py --quick                # CI smoke run, writes to a temp dir
    python benchmarks/free_body.py --devices 2            # ensembles split over 2 CPU devices (cores)

It prints a table and writes ``free_body.json`` and ``free_body.png`` to ``--out``
(default ``benchmarks/results``; with ``--quick``, a fresh temporary directory).
XLA runs with its default flags; a run made with ``XLA_FLAGS`` set records them in
the JSON. On CPU with jax 0.10, ``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=-reduce``
changes the large-ensemble numbers several-fold; benchmarks/README.md says why.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.metadata
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import jaxrb as rb

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ is not a package
from _machine import cpu_model  # noqa: E402

DT = 1e-3  # s
INITIAL_VELOCITY = (1.0, 0.0, 2.0)  # m/s, world frame
INITIAL_BODY_ANGULAR_VELOCITY = (0.3, 2.0, -1.0)  # rad/s, body frame
# Every integrator jaxrb exports, in its own order (cheap and first-order first).
INTEGRATORS = {name: getattr(rb.integrators, name) for name in rb.integrators.__all__ if name != "Integrator"}
BARE = "bare SemiImplicitEuler"
DEFAULT_OUT = Path(__file__).resolve().parent / "results"


# ---------------------------------------------------------------------------- jaxrb


def free_body_scene() -> rb.Scene:
    return rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0)], gravity=(0, 0, -9.81))


def initial_condition(scene: rb.Scene, dtype):
    """The params and spinning, moving initial state shared by jaxrb and the bare baseline."""
    params = scene.params(dtype=dtype)
    state = scene.state(
        params,
        velocity=INITIAL_VELOCITY,
        body_angular_velocity=INITIAL_BODY_ANGULAR_VELOCITY,
        dtype=dtype,
    )
    return params, state


def jaxrb_problem(scene: rb.Scene, integrator, dtype, num_steps: int):
    """``(rollout_fn, params, state)`` with ``rollout_fn(params, state) -> final state``."""
    step = rb.make_step(scene, integrator, dt=DT)
    params, state = initial_condition(scene, dtype)
    # ExplicitEuler carries its rotation matrix; add it before batching so the scan
    # carry has the same structure on entry and exit.
    state = step.prepare(state)

    def rollout_fn(params, state):
        final, _ = rb.rollout(step, params, state, num_steps, save_every=num_steps)
        return final

    return rollout_fn, params, state


# ----------------------------------------------------------------------------- bare


class BareState(NamedTuple):
    position: jax.Array  # (3,) m, world
    orientation: jax.Array  # (4,) unit quaternion (w, x, y, z), body to world
    velocity: jax.Array  # (3,) m/s, world
    angular_momentum: jax.Array  # (3,) kg m^2/s, world


class BareParams(NamedTuple):
    inverse_inertia_body: jax.Array  # (3, 3) kg^-1 m^-2
    gravity: jax.Array  # (3,) m/s^2


def _cross(a, b):
    return jnp.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _rotate(w, u, v):
    """Rotate ``v`` by the unit quaternion ``(w, u)``: ``v + 2w (u x v) + 2 u x (u x v)``."""
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def bare_step(p: BareParams, s: BareState) -> BareState:
    """Seed 001's semi-implicit Euler for one torque-free body under gravity, by hand."""
    velocity = s.velocity + DT * p.gravity
    position = s.position + DT * velocity
    q = s.orientation
    l_body = _rotate(q[0], -q[1:], s.angular_momentum)
    m = p.inverse_inertia_body
    omega_body = jnp.stack([m[i, 0] * l_body[0] + m[i, 1] * l_body[1] + m[i, 2] * l_body[2]
                            for i in range(3)])
    r = DT * _rotate(q[0], q[1:], omega_body)  # rotation vector omega dt, world frame
    # exp(r) = (cos(|r|/2), sin(|r|/2) r/|r|), with its Taylor series near |r| = 0.
    theta_sq = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
    small = theta_sq < 1e-6
    theta = jnp.sqrt(jnp.where(small, 1.0, theta_sq))
    cos_half = jnp.where(small, 1.0 - theta_sq / 8.0, jnp.cos(0.5 * theta))
    sin_half_over = jnp.where(small, 0.5 - theta_sq / 48.0, jnp.sin(0.5 * theta) / theta)
    pw, px, py, pz = cos_half, sin_half_over * r[0], sin_half_over * r[1], sin_half_over * r[2]
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    q = jnp.stack([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ])
    q = q * jax.lax.rsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return BareState(position, q, velocity, s.angular_momentum)


def bare_problem(scene: rb.Scene, dtype, num_steps: int):
    """The bare baseline from the same initial condition as :func:`jaxrb_problem`."""
    params, state = initial_condition(scene, dtype)
    bare_params = BareParams(jnp.linalg.inv(params.inertia[0]), params.gravity)
    bare_state = BareState(
        state.position[0], state.orientation[0], state.velocity[0], state.angular_momentum[0]
    )

    def rollout_fn(p, s):
        final, _ = jax.lax.scan(lambda c, _: (bare_step(p, c), None), s, None, length=num_steps)
        return final

    return rollout_fn, bare_params, bare_state


# --------------------------------------------------------------------------- timing


def batched(tree, envs: int):
    """``envs`` materialised copies of every leaf along a new leading axis."""
    return jax.tree.map(lambda x: jnp.array(jnp.broadcast_to(x, (envs, *x.shape))), tree)


def measure(rollout_fn, params, state, envs: int, num_steps: int, repeats: int, shared_params: bool = False,
            devices: int = 1):
    """``(steps_per_second, compile_seconds, final_state)`` for ``envs`` environments.

    With ``shared_params`` only the state is batched: one set of params (still a traced
    argument of the compiled function, so nothing is constant-folded) drives every
    environment, as in an ensemble of initial conditions. With ``devices > 1`` the
    batched arrays are split over that many devices with :func:`jaxrb.shard_ensemble`
    (ensembles that do not divide evenly, and a single environment, stay on one).
    """
    fn = rollout_fn if envs == 1 else jax.vmap(rollout_fn, in_axes=(None if shared_params else 0, 0))
    if envs > 1:
        params = params if shared_params else batched(params, envs)
        state = batched(state, envs)
        if devices > 1 and envs % devices == 0:
            state = rb.shard_ensemble(state, jax.devices()[:devices])
            if not shared_params:
                params = rb.shard_ensemble(params, jax.devices()[:devices])
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(params, state).compile()
    compile_seconds = time.perf_counter() - t0
    final = jax.block_until_ready(compiled(params, state))  # warm-up
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(params, state))
        best = min(best, time.perf_counter() - t0)
    return envs * num_steps / best, compile_seconds, final


def check_bare_matches_jaxrb(jaxrb_final, bare_final, dtype) -> float:
    """Largest difference between the two final states, which must agree to round-off."""
    pairs = [
        (jaxrb_final.position, bare_final.position),
        (jaxrb_final.velocity, bare_final.velocity),
        (jaxrb_final.angular_momentum, bare_final.angular_momentum),
        (jaxrb_final.orientation, bare_final.orientation),
    ]
    err = max(
        float(np.max(np.abs(np.reshape(a, b.shape) - np.asarray(b)))) for a, b in pairs
    )
    # The states are O(1) and the two differ only in the order of floating-point
    # operations: measured 3e-7 (float32) and 1e-16 (float64) after 1000 steps. The
    # tolerances leave room for longer runs while still catching a physics mismatch.
    tol = 1e-3 if dtype == jnp.float32 else 1e-9
    if not err <= tol:
        raise AssertionError(f"bare and jaxrb SemiImplicitEuler disagree by {err:.2e} > {tol}")
    return err


# --------------------------------------------------------------------------- output


def print_table(results, envs_list):
    print(f"\n{'integrator':24s} {'envs':>6s} {'env-steps/s':>12s} {'compile s':>10s}")
    for r in results:
        print(f"{r['integrator']:24s} {r['envs']:6d} {r['steps_per_second']:12.3e} "
              f"{r['compile_seconds']:10.2f}")
    rate = {(r["integrator"], r["envs"]): r["steps_per_second"] for r in results}
    if all(("SemiImplicitEuler", e) in rate and (BARE, e) in rate for e in envs_list):
        print("\njaxrb SemiImplicitEuler / bare:  " + ",  ".join(
            f"{e} envs {rate['SemiImplicitEuler', e] / rate[BARE, e]:.2f}" for e in envs_list))


def plot(results, envs_list, title, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for name in [*INTEGRATORS, BARE]:
        rows = [r for r in results if r["integrator"] == name]
        if rows:
            ax.plot([r["envs"] for r in rows], [r["steps_per_second"] for r in rows],
                    marker="o", ls="--" if name == BARE else "-", label=name)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks(envs_list, [str(e) for e in envs_list])
    ax.set_xlabel("environments (vmap)")
    ax.set_ylabel("environment-steps per second")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ----------------------------------------------------------------------------- main


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", type=int, nargs="+", default=[1, 64, 1024, 4096],
                   help="ensemble sizes (1 = single environment, no vmap)")
    p.add_argument("--steps", type=int, default=1000, help="steps per timed call")
    p.add_argument("--repeats", type=int, default=5, help="timed calls; the best counts")
    p.add_argument("--integrators", nargs="+", choices=list(INTEGRATORS),
                   default=list(INTEGRATORS))
    p.add_argument("--x64", action="store_true", help="float64 (sets jax_enable_x64)")
    p.add_argument("--shared-params", action="store_true",
                   help="vmap over states only (one params for all environments); "
                        "writes free_body_shared_params.{json,png}")
    p.add_argument("--devices", type=int, default=1,
                   help="split each ensemble over this many devices with rb.shard_ensemble; on CPU "
                        "this asks JAX for that many CPU devices (one per core); "
                        "writes free_body[_shared_params]_<D>dev.{json,png}")
    p.add_argument("--quick", action="store_true",
                   help="CI smoke run: envs 1 8, 20 steps, 1 repeat, output to a temp dir")
    p.add_argument("--out", type=Path, default=None,
                   help=f"output directory (default {DEFAULT_OUT}, or a temp dir with --quick)")
    args = p.parse_args(argv)
    if args.quick:
        args.envs, args.steps, args.repeats = [1, 8], 20, 1
    if args.out is None:
        args.out = Path(tempfile.mkdtemp(prefix="free_body_")) if args.quick else DEFAULT_OUT
    if min(args.envs) < 1 or args.steps < 1 or args.repeats < 1 or args.devices < 1:
        p.error("--envs, --steps, --repeats and --devices must be positive")
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.x64:
        # Before any array is created. Without --x64 the flag is left as it is: every
        # array here is built with an explicit dtype, so float32 runs either way.
        jax.config.update("jax_enable_x64", True)
    if args.devices > 1:
        # A CPU shows one device unless asked before JAX starts; jaxrb itself never asks.
        # (Calling jax.devices() first would start JAX, so the request comes first.)
        try:
            jax.config.update("jax_num_cpu_devices", args.devices)
        except RuntimeError as err:  # JAX already running (e.g. main() called from a test)
            raise SystemExit(f"--devices {args.devices}: {err}") from None
        if len(jax.devices()) < args.devices:
            raise SystemExit(f"--devices {args.devices}: only {len(jax.devices())} devices available")
    dtype = jnp.float64 if args.x64 else jnp.float32
    envs_list = sorted(set(args.envs))
    device = jax.devices()[0]
    print(f"jax {jax.__version__} on {device.platform} ({device.device_kind}) x {args.devices}, "
          f"{os.cpu_count()} CPUs, {jnp.dtype(dtype).name}, {args.steps} steps per call, "
          f"best of {args.repeats}", flush=True)

    scene = free_body_scene()
    results, semi_finals = [], {}
    names = [n for n in INTEGRATORS if n in args.integrators]
    if "SemiImplicitEuler" in names:
        names.append(BARE)
    for name in names:
        if name == BARE:
            problem = bare_problem(scene, dtype, args.steps)
        else:
            problem = jaxrb_problem(scene, INTEGRATORS[name](), dtype, args.steps)
        for envs in envs_list:
            rate, compile_s, final = measure(*problem, envs, args.steps, args.repeats, args.shared_params,
                                             args.devices)
            if final.position.dtype != dtype:
                raise AssertionError(f"{name} ran in {final.position.dtype}, not {dtype}")
            row = dict(integrator=name, envs=envs, steps_per_second=rate,
                       seconds_per_call=envs * args.steps / rate, compile_seconds=compile_s)
            if name == "SemiImplicitEuler":
                semi_finals[envs] = final
            if name == BARE:
                row["max_abs_difference_from_jaxrb"] = check_bare_matches_jaxrb(
                    semi_finals[envs], final, dtype)
            results.append(row)
            print(f"  {name:24s} {envs:6d} envs  {rate:10.3e} env-steps/s  "
                  f"compile {compile_s:5.2f} s", flush=True)

    print_table(results, envs_list)
    rate = {(r["integrator"], r["envs"]): r["steps_per_second"] for r in results}
    ratio = {str(e): rate["SemiImplicitEuler", e] / rate[BARE, e]
             for e in envs_list if (BARE, e) in rate}
    record = dict(
        benchmark="free_body",
        description="env-steps/s of one free box under gravity with rotation, dt = 1 ms; "
                    "jax.jit(jax.vmap(rollout)) with save_every = steps; best of repeats",
        ensemble="states only, shared params" if args.shared_params else "params and states",
        devices=args.devices,
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        command=" ".join([Path(sys.executable).name, *sys.argv]),
        jax_version=jax.__version__,
        jaxlib_version=importlib.metadata.version("jaxlib"),
        jaxrb_version=rb.__version__,
        device=f"{device.platform}: {device.device_kind}",
        cpu_model=cpu_model(),
        cpu_count=os.cpu_count(),
        python=platform.python_version(),
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        dtype=jnp.dtype(dtype).name,
        dt=DT,
        steps=args.steps,
        repeats=args.repeats,
        results=results,
        semi_implicit_over_bare=ratio,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "free_body_shared_params" if args.shared_params else "free_body"
    stem += f"_{args.devices}dev" if args.devices > 1 else ""
    json_path, png_path = args.out / f"{stem}.json", args.out / f"{stem}.png"
    json_path.write_text(json.dumps(record, indent=2) + "\n")
    title = (f"free body, {record['dtype']}, {record['ensemble']}, {args.devices} device(s), {args.steps} steps/call, "
             f"jax {jax.__version__}, {record['cpu_count']} CPU cores")
    if record["xla_flags"]:
        title += f"\nXLA_FLAGS={record['xla_flags']}"
    plot(results, envs_list, title, png_path)
    print(f"\nwrote {json_path} and {png_path}")
    return record


if __name__ == "__main__":
    main()
