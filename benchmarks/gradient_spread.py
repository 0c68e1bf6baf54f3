"""How far a gradient through many impacts can be trusted: its spread over nearby starts,
in float64 and float32, as the horizon grows.

What it measures
    The dropped box of ``benchmarks/ab.py`` (``drop``): a cube of half-extent 0.1 m, 1 kg,
    dropped from 0.5 m clearance tilted 0.1 rad about x, moving at 0.3 m/s along x,
    e = 0.5, mu = 0.5, h = 1 ms, ``SymplecticSplitting``. It lands after about 0.3 s and
    then hops on its edges and corners for the rest of the second (eight turns of the
    vertical velocity by step 660), with only short spells of contact.

    The loss is the sum of the box's recorded x and z up to a horizon ``H`` (one compiled
    gradient, the horizon a 0/1 weight per step). For each horizon and dtype: the
    derivative of the loss in the mass at ``--starts`` starts whose x velocity differs
    from 0.3 m/s by up to 1e-5 relative (uniform, seed 0; the first start is 0.3 itself),
    and its mean, standard deviation and range over them.

    Where the float64 spread is small, the gradient is a property of the scene; where it
    grows, the trajectory's derivative depends on which contacts happen, and a gradient at
    one start says little about its neighbours (what ``tests/test_gradients.py`` calls
    contact switching). Where float32 departs from float64 while float64's spread is
    still small, float32's rounding is what changes the contacts.

How to run (from the repository root)
    python benchmarks/gradient_spread.py             # float64 and float32, 1000 steps
    python benchmarks/gradient_spread.py --quick     # CI smoke run (float64, 60 steps), temp dir

It prints a table and writes ``gradient_spread.json`` and ``gradient_spread.png`` to
``--out`` (default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrb as rb

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ is not a package
from _machine import record_header, write_results  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results"
HORIZONS = (300, 400, 600, 700, 800, 850, 900, 950, 1000)


def spread(dtype, steps: int, horizons, starts: int) -> dict:
    """The mass derivative's statistics over ``starts`` nearby starts, for each horizon."""
    tilt = (float(np.cos(0.05)), float(np.sin(0.05)), 0.0, 0.0)  # 0.1 rad about x
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.1, 0.1)), mass=1.0)], ground=rb.Plane(), contacts="all")
    params = scene.params(friction=0.5, restitution=0.5, dtype=dtype)
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)

    def start(vx):
        return step.prepare(scene.state(params, position=(0.0, 0.0, 0.6), orientation=tilt, velocity=(vx, 0.0, 0.0)))

    def loss(mass, state, weight):
        _, traj = rb.rollout(step, params.replace(mass=mass), state, steps)
        return jnp.sum(weight[:, None] * traj.position[:, 0, jnp.array([0, 2])])

    gradient = jax.jit(jax.grad(loss))
    _, traj = jax.jit(lambda s: rb.rollout(step, params, s, steps))(start(0.3))
    vz = np.asarray(traj.velocity[:, 0, 2], float)
    turns = [int(k) + 1 for k in np.nonzero(np.diff(np.sign(vz)))[0]]
    deltas = np.concatenate([[0.0], np.random.default_rng(0).uniform(-1e-5, 1e-5, starts - 1)])
    rows = []
    for horizon in horizons:
        weight = jnp.asarray(np.arange(steps) < horizon, dtype)
        values = np.array([float(gradient(params.mass, start(0.3 * (1.0 + d)), weight)[0]) for d in deltas])
        if not np.all(np.isfinite(values)):
            raise RuntimeError(f"a non-finite gradient at horizon {horizon} ({jnp.dtype(dtype)}): {values}")
        rows.append({"horizon": horizon, "mean": float(values.mean()), "std": float(values.std()),
                     "min": float(values.min()), "max": float(values.max()), "values": values.tolist()})
    return {"vertical_velocity_turns_at_steps": turns, "rows": rows}


def print_table(record: dict):
    print(f"\nd(loss)/d(mass) of the dropped box over {record['starts']} starts (vx within 1e-5 relative)")
    dtypes = list(record["results"])
    print(f"{'H':>6}" + "".join(f"  {d + ' mean':>14} {d + ' std':>12}" for d in dtypes))
    for i, horizon in enumerate(record["horizons"]):
        rows = [record["results"][d]["rows"][i] for d in dtypes]
        print(f"{horizon:>6}" + "".join(f"  {r['mean']:14.4f} {r['std']:12.4g}" for r in rows))
    for d in dtypes:
        turns = record["results"][d]["vertical_velocity_turns_at_steps"][:12]
        print(f"{d}: the vertical velocity turns at steps {turns}")


def plot(record: dict, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for d, result in record["results"].items():
        horizons = [r["horizon"] for r in result["rows"]]
        ax.semilogy(horizons, [max(r["std"], 1e-12) for r in result["rows"]], "o-", label=d)
    ax.set_xlabel("horizon (steps of 1 ms)")
    ax.set_ylabel("std of d(loss)/d(mass) over nearby starts")
    ax.set_title("dropped box: the gradient's spread")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--starts", type=int, default=12)
    p.add_argument("--quick", action="store_true", help="float64 only, 60 steps, 2 starts, temp output dir")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    steps, horizons, dtypes, starts = 1000, HORIZONS, (jnp.float64, jnp.float32), args.starts
    if args.quick:
        steps, horizons, dtypes, starts = 60, (30, 60), (jnp.float64,), 2
    if starts < 2:
        raise ValueError(f"--starts must be at least 2 (a spread needs two starts), got {starts}")
    jax.config.update("jax_enable_x64", True)
    out = args.out or (Path(tempfile.mkdtemp()) if args.quick else DEFAULT_OUT)
    out.mkdir(parents=True, exist_ok=True)
    record = {**record_header("gradient_spread.py", argv), "steps": steps, "horizons": list(horizons),
              "starts": starts,
              "results": {str(jnp.dtype(d)): spread(d, steps, horizons, starts) for d in dtypes}}
    print_table(record)
    write_results(out, "gradient_spread", record, plot)
    return record


if __name__ == "__main__":
    main()
