"""Random drops of mixed shapes in a walled pen: a fuzz of the contact step.

What it does
    For each composition (one letter a body: ``s`` sphere r = 0.1 m, ``b`` box of half
    extents 0.1 x 0.15 x 0.05 m, ``c`` capsule r = 0.06 m, half length 0.12 m, ``y``
    cylinder r = 0.08 m, half length 0.1 m; masses 0.5, 1, 2, 1.5, 0.7 kg in order), the
    bodies fall in a pen (the ground and four walls at |x|, |y| = 0.4 m, contacts
    ``"all"``) from random poses 0.25-0.35 m apart in height, with random velocities
    (sd 1 m/s) and spins (sd 3 rad/s), and random per-pair restitution and friction in
    [0, 1] (a fifth of each at 0 or 1). ``--cases`` drops run as one ``jax.vmap``ped
    rollout (``SymplecticSplitting``, h = 1 ms) on XLA's default flags, as users run.

    Per case it records: whether any value is non-finite (the process crashing is a
    finding too: stop 80's fuzz found an XLA:CPU miscompilation so); the largest one-step
    gain of total energy (J), and the largest gain over the start (J). With
    ``--gradients``, also whether the case's gradient (of its final positions, attitudes and
    total energy, with respect to every param and the initial state; ``jax.grad`` of a sum
    over ``jax.vmap``) has a NaN or infinite entry, and in which fields. Energy may rise
    in a step by small amounts by design (the split impulse lifting bodies out of an
    overlap restores potential energy the overlap lost; leapfrog's staggered velocity
    shows m (g h / 2)^2 / 2 = 1.2e-5 J a kilogram at rest); see benchmarks/README.md,
    "The warm start bounded by the energy it may add". Nothing here is asserted: the
    table is for reading, and ``--only`` re-runs single cases of a seed.

How to run (from the repository root)
    python benchmarks/fuzz_contacts.py                           # sbc, byc, syc: 32 x 400 steps
    python benchmarks/fuzz_contacts.py --compositions bbs --cases 64 --seed 3 --iterations 4
    python benchmarks/fuzz_contacts.py --compositions syc --seed 1 --only 15   # one case
    python benchmarks/fuzz_contacts.py --gradients --float32 --seed 1           # gradients too
    python benchmarks/fuzz_contacts.py --compositions bb --solver exact --cases 8
    python benchmarks/fuzz_contacts.py --quick                   # CI smoke run, temp dir

It prints a table and writes ``fuzz_contacts.json`` and ``fuzz_contacts.png`` to ``--out``
(default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrb as rb

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ is not a package
from _machine import record_header, write_results  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results"
SHAPES = {"s": rb.Sphere(0.1), "b": rb.Box((0.1, 0.15, 0.05)), "c": rb.Capsule(0.06, 0.12),
          "y": rb.Cylinder(0.08, 0.1)}
MASSES = (0.5, 1.0, 2.0, 1.5, 0.7)
HALF_WIDTH = 0.4  # m, the pen's walls


def pen(composition: str) -> rb.Scene:
    if not composition or len(composition) > len(MASSES) or set(composition) - set(SHAPES):
        raise ValueError(f"a composition is 1 to {len(MASSES)} letters of {''.join(SHAPES)}, got {composition!r}")
    bodies = [rb.Body(f"{k}{i}", shape=SHAPES[k], mass=MASSES[i]) for i, k in enumerate(composition)]
    walls = {"w+x": rb.Plane((-1.0, 0.0, 0.0), -HALF_WIDTH), "w-x": rb.Plane((1.0, 0.0, 0.0), -HALF_WIDTH),
             "w+y": rb.Plane((0.0, -1.0, 0.0), -HALF_WIDTH), "w-y": rb.Plane((0.0, 1.0, 0.0), -HALF_WIDTH)}
    return rb.Scene(bodies, ground=rb.Plane(), walls=walls, contacts="all")


def random_cases(scene: rb.Scene, step, cases: int, seed: int, dtype):
    """``cases`` random (params, state) pairs, stacked on a leading axis."""
    rng = np.random.default_rng(seed)
    n, pairs = len(scene.bodies), len(scene.contact_pairs)
    params, states = [], []
    for _ in range(cases):
        e = rng.uniform(0.0, 1.0, pairs)
        e[rng.uniform(size=pairs) < 0.2] = 1.0
        e[rng.uniform(size=pairs) < 0.2] = 0.0
        mu = rng.uniform(0.0, 1.0, pairs)
        mu[rng.uniform(size=pairs) < 0.2] = 0.0
        p = scene.params(restitution=e, friction=mu, dtype=dtype)
        position = np.stack([rng.uniform(-0.15, 0.15, n), rng.uniform(-0.15, 0.15, n),
                             0.25 + 0.35 * np.arange(n) + rng.uniform(0.0, 0.1, n)], axis=1)
        q = rng.normal(size=(n, 4))
        state = scene.state(p, position=position, orientation=q / np.linalg.norm(q, axis=1, keepdims=True),
                            velocity=rng.normal(0.0, 1.0, (n, 3)), angular_velocity=rng.normal(0.0, 3.0, (n, 3)),
                            dtype=dtype)
        params.append(p)
        states.append(step.prepare(state))
    return jax.tree.map(lambda *x: jnp.stack(x), *params), jax.tree.map(lambda *x: jnp.stack(x), *states)


def fuzz(composition: str, cases: int, steps: int, seed: int, dtype, settings: rb.ContactSettings, only,
         gradients: bool) -> dict:
    scene = pen(composition)
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3, contact=settings)
    params, state = random_cases(scene, step, cases, seed, dtype)
    index = np.arange(cases) if only is None else np.asarray(only)
    params, state = jax.tree.map(lambda x: x[index], (params, state))

    def energies(p, s):
        _, traj = rb.rollout(step, p, s, steps, include_initial=True)
        total = jax.vmap(lambda x: jnp.sum(rb.kinetic_energy(p, x) + rb.potential_energy(p, x)))(traj)
        return total, jnp.all(jnp.isfinite(traj.position)) & jnp.all(jnp.isfinite(traj.angular_momentum))

    t0 = time.perf_counter()
    total, finite = jax.block_until_ready(jax.jit(jax.vmap(energies))(params, state))
    seconds = time.perf_counter() - t0
    total = np.asarray(total, dtype=float)
    finite = np.asarray(finite) & np.all(np.isfinite(total), axis=1)
    gains = np.diff(total, axis=1)  # each step's gain of total energy, J
    start_gain = np.max(total - total[:, :1], axis=1)
    record = {"composition": composition, "pairs": len(scene.contact_pairs), "cases": index.tolist(),
              "seconds_with_compile": seconds, "non_finite_cases": index[~finite].tolist(),
              "worst_step_gain_J": np.max(gains, axis=1).tolist(), "worst_gain_over_start_J": start_gain.tolist(),
              "worst_step_gain_step": np.argmax(gains, axis=1).tolist()}
    if gradients:
        record.update(gradient_fuzz(step, params, state, steps, index))
    return record


def gradient_fuzz(step, params, state, steps: int, index) -> dict:
    """Each case's gradient of its final positions, attitudes and total energy with respect to all its
    params and its initial state, as ``jax.grad`` of a sum over ``jax.vmap`` (the form
    ``rollout``'s docstring recommends for ensembles). Returns the cases with a non-finite
    entry, the leaves (``Params``/``State`` fields) where they are, and the compile + run
    time. Nothing is compared with differences here: across the contacts that a random drop
    makes and breaks, a difference would straddle them."""

    def loss(p, s):
        final, _ = rb.rollout(step, p, s, steps)
        energy = jnp.sum(rb.kinetic_energy(p, final) + rb.potential_energy(p, final))
        return energy + jnp.sum(final.position) + jnp.sum(final.orientation)

    t0 = time.perf_counter()
    grads = jax.block_until_ready(jax.jit(jax.grad(lambda p, s: jnp.sum(jax.vmap(loss)(p, s)), argnums=(0, 1)))(
        params, state))
    seconds = time.perf_counter() - t0
    bad_leaves, bad = [], np.zeros(len(index), bool)
    for path, leaf in jax.tree_util.tree_leaves_with_path(grads):
        leaf = np.asarray(leaf).reshape(len(index), -1)
        here = ~np.all(np.isfinite(leaf), axis=1)
        if here.any():
            bad_leaves.append(jax.tree_util.keystr(path))
        bad |= here
    return {"gradient_seconds_with_compile": seconds, "non_finite_gradient_cases": index[bad].tolist(),
            "non_finite_gradient_leaves": bad_leaves}


def print_table(records) -> None:
    print(f"\n{'composition':<12}{'pairs':>6}{'cases':>6}{'non-finite':>11}{'worst step gain (J)':>21}"
          f"{'case':>6}{'step':>6}{'worst over start (J)':>22}{'s':>7}")
    for r in records:
        gain, over = np.asarray(r["worst_step_gain_J"]), np.asarray(r["worst_gain_over_start_J"])
        k = int(np.argmax(gain))
        print(f"{r['composition']:<12}{r['pairs']:>6}{len(r['cases']):>6}{len(r['non_finite_cases']):>11}"
              f"{gain[k]:>21.2e}{r['cases'][k]:>6}{r['worst_step_gain_step'][k]:>6}{over.max():>22.2e}"
              f"{r['seconds_with_compile']:>7.1f}")
    graded = [r for r in records if "non_finite_gradient_cases" in r]
    if graded:
        print(f"\n{'composition':<12}{'cases':>6}{'non-finite gradients':>22}  {'in leaves':<40}{'s':>7}")
        for r in graded:
            leaves = ", ".join(r["non_finite_gradient_leaves"]) or "-"
            print(f"{r['composition']:<12}{len(r['cases']):>6}{len(r['non_finite_gradient_cases']):>22}  {leaves:<40}"
                  f"{r['gradient_seconds_with_compile']:>7.1f}")


def plot(record, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for r in record["runs"]:
        gain = np.sort(np.maximum(np.asarray(r["worst_step_gain_J"]), 1e-16))
        ax.step(gain, np.arange(1, gain.size + 1) / gain.size, where="post", label=r["composition"])
    ax.set_xscale("log")
    ax.set_xlabel("largest one-step energy gain of a case (J)")
    ax.set_ylabel("fraction of cases")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--compositions", default="sbc,byc,syc", help="comma-separated, e.g. sbc,yy")
    parser.add_argument("--cases", type=int, default=32)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--iterations", type=int, default=None, help="sweeps a solve (default: ContactSettings')")
    parser.add_argument("--solver", choices=["pgs", "exact"], default="pgs", help="ContactSettings(solver=...)")
    parser.add_argument("--only", type=int, nargs="*", default=None, help="run these cases of the seed only")
    parser.add_argument("--float32", action="store_true")
    parser.add_argument("--gradients", action="store_true",
                        help="also each case's gradient (all params and the initial state), checked for NaN/inf")
    parser.add_argument("--quick", action="store_true", help="tiny sizes, to a temp dir (CI)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.only is not None and not all(0 <= k < args.cases for k in args.only):
        raise ValueError(f"--only takes case numbers of the seed's {args.cases} cases (0 to {args.cases - 1}), "
                         f"got {args.only}; raise --cases to reach later ones")
    if args.quick:
        args.compositions, args.cases, args.steps = "sy", 2, 20
    out = args.out or (Path(tempfile.mkdtemp()) if args.quick else DEFAULT_OUT)
    out.mkdir(parents=True, exist_ok=True)
    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.float32 if args.float32 else jnp.float64
    record = record_header("fuzz_contacts.py", argv)
    record.update({"dtype": jnp.dtype(dtype).name, "steps": args.steps, "seed": args.seed,
                   "iterations": args.iterations, "solver": args.solver, "runs": []})
    settings = rb.ContactSettings(solver=args.solver, **({} if args.iterations is None else
                                                         {"iterations": args.iterations}))
    for composition in args.compositions.split(","):
        record["runs"].append(fuzz(composition, args.cases, args.steps, args.seed, dtype, settings,
                                   args.only, args.gradients))
        run = record["runs"][-1]
        print(f"{composition}: done, non-finite cases {run['non_finite_cases']}"
              + (f", non-finite gradients {run['non_finite_gradient_cases']}" if args.gradients else ""), flush=True)
    print_table(record["runs"])
    write_results(out, "fuzz_contacts", record, plot)
    return record


if __name__ == "__main__":
    main()
