"""Kernels per step: how many XLA kernels one step of a rollout runs, forward and in
reverse mode, and which source operations they come from.

Why count kernels
    On the 2-core CI-class machine, wall times of the same compiled program vary by about
    +-20% from one process to the next, more than most single changes are worth. The
    number of kernels a compiled step executes does not vary. For the small scenes of this
    project (one ball, a few boxes) a step's arrays hold tens of numbers, so on XLA:CPU a
    step's cost is mostly its kernel launches (tens of nanoseconds each): the count is a
    stable proxy for a change's effect, to check beside the timings of
    ``benchmarks/gradients.py``. It is a proxy only: kernels differ in cost (a dot, a
    transcendental fusion, a copy), and it says nothing about large batches.

What it measures
    * ``ball``: the scene of ``benchmarks/gradients.py`` (r = 0.1 m, e = 0.8, mu = 0.5,
      h = 1 ms, dropped from 1 m clearance, ``SymplecticSplitting``), and its loss (the
      sum of the heights). Forward: the jitted rollout. Reverse: ``jax.grad`` with respect
      to all of ``Params`` and the initial ``State``.
    * ``stack``: three boxes (half-extent 0.1 m, 1 kg, mu = 0.5) resting on the ground.
    * ``free``: a tumbling box under gravity, no contacts (compiles in seconds).

    Each program runs once to warm up and once under ``jax.profiler.trace``. Every event on
    an XLA worker thread that is a kernel (not a thunk executor, ``while`` or ``cond``
    wrapper) is counted and attributed to its HLO instruction's ``op_name``: the JAX
    transformation path and primitive it came from. ``T`` marks the reverse pass
    (``transpose(...)``); kernels with no ``op_name`` are mostly copies that XLA inserted
    (loop carries, a ``cond``'s zero-filled residuals).

How to run (from the repository root)
    python benchmarks/kernels.py                  # the ball, 1000 steps
    python benchmarks/kernels.py --scene stack --depth 8   # 10 steps: the profiler records every PGS kernel
    python benchmarks/kernels.py --quick          # CI smoke run, temp dir

It prints a table and writes ``kernels_<scene>.json`` to ``--out`` (default
``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import re
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp

import jaxrb as rb

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ is not a package
from _machine import record_header  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results"
#: Profiler events that wrap kernels (or are bookkeeping) rather than being kernels.
WRAPPERS = ("ThunkExecutor", "cond", "while", "end:", "ThreadpoolListener")


def scene_and_loss(name: str, steps: int):
    if name == "ball":
        scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
        step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
        params = scene.params(restitution=0.8, friction=0.5)
        state = scene.state(params, position=(0.0, 0.0, 1.1), velocity=(0.3, 0.0, 0.0),
                            angular_velocity=(0.0, 2.0, 0.0))
    elif name == "stack":
        bodies = [rb.Body(f"box{i}", shape=rb.Box((0.1, 0.1, 0.1)), mass=1.0) for i in range(3)]
        scene = rb.Scene(bodies, ground=rb.Plane(), contacts="all")
        step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
        params = scene.params(friction=0.5)
        state = scene.state(params, position=[(0.0, 0.0, 0.1 + 0.2 * i) for i in range(3)])
    elif name == "free":
        scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=2.0)])
        step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
        params = scene.params()
        state = scene.state(params, velocity=(1.0, 0.0, 5.0), angular_velocity=(0.3, 4.0, 0.1))
    else:
        raise ValueError(f"--scene must be 'ball', 'stack' or 'free', got {name!r}")
    state = step.prepare(state)

    def loss(p, s):
        _, traj = rb.rollout(step, p, s, steps)
        # The attitude is in the loss too, so that XLA cannot drop the rotation's reverse pass.
        return jnp.sum(traj.position[..., 2]) + jnp.sum(traj.orientation[..., 0])

    return loss, params, state


def op_names(hlo_text: str) -> dict[str, str]:
    """HLO instruction name -> the ``op_name`` in its metadata."""
    return {m.group(1): m.group(2)
            for m in re.finditer(r"%([\w.\-]+) = [^\n]*?op_name=\"([^\"]*)\"", hlo_text)}


def kernel_counts(compiled, args, trace_dir: Path) -> collections.Counter:
    """Kernel events per HLO instruction name in one call of ``compiled``."""
    jax.block_until_ready(compiled(*args))
    with jax.profiler.trace(str(trace_dir)):
        jax.block_until_ready(compiled(*args))
    (path,) = glob.glob(str(trace_dir / "**" / "*.xplane.pb"), recursive=True)
    counts = collections.Counter()
    for plane in jax.profiler.ProfileData.from_file(path).planes:
        for line in plane.lines:
            if not line.name.startswith("tf_XLA"):
                continue
            for event in line.events:
                if not event.name.startswith(WRAPPERS):
                    counts[event.name] += 1
    return counts


def attribute(counts, names, steps: int, depth: int) -> dict[str, float]:
    """Kernels per step, grouped by the first ``depth`` parts of their ``op_name``."""
    groups = collections.Counter()
    for kernel, n in counts.items():
        path = names.get(kernel)
        if path is None:
            key = "(no op_name) " + re.sub(r"[.\d]+$", "", kernel)
        else:
            path = re.sub(r"^jit\(loss\)/", "", path)
            key = ("T " if path.startswith("transpose") else "") + "/".join(path.split("/")[:depth])
        groups[key] += n
    return {k: v / steps for k, v in groups.most_common()}


def measure(scene: str, steps: int, depth: int) -> dict:
    loss, params, state = scene_and_loss(scene, steps)
    record = {}
    for mode, fn in (("forward", loss), ("reverse", jax.grad(loss, argnums=(0, 1)))):
        compiled = jax.jit(fn).lower(params, state).compile()
        with tempfile.TemporaryDirectory(prefix=f"kernels_{mode}_") as trace_dir:
            counts = kernel_counts(compiled, (params, state), Path(trace_dir))
        record[mode] = {
            "kernels_per_step": sum(counts.values()) / steps,
            "by_source": attribute(counts, op_names(compiled.as_text()), steps, depth),
        }
    record["ratio_reverse_over_forward"] = (record["reverse"]["kernels_per_step"]
                                            / record["forward"]["kernels_per_step"])
    return record


def print_table(scene: str, record: dict, top: int):
    f, r = record["forward"]["kernels_per_step"], record["reverse"]["kernels_per_step"]
    print(f"\n{scene}: {f:.1f} kernels per step forward, {r:.1f} with the reverse pass "
          f"({record['ratio_reverse_over_forward']:.2f}x)")
    for mode in ("forward", "reverse"):
        print(f"\n{mode}, kernels per step by source (first {top}):")
        for key, n in list(record[mode]["by_source"].items())[:top]:
            print(f"  {n:7.2f}  {key}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="ball", choices=["ball", "stack", "free"])
    p.add_argument("--steps", type=int, default=None, help="rollout length (default: 1000; stack 10)")
    p.add_argument("--depth", type=int, default=10, help="op_name parts kept when grouping")
    p.add_argument("--top", type=int, default=25)
    p.add_argument("--float32", action="store_true")
    p.add_argument("--quick", action="store_true", help="free body, 20 steps, temp output dir (CI smoke run)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    if args.quick:
        args.scene, args.steps = "free", 20
    steps = args.steps or (10 if args.scene == "stack" else 1000)
    out = args.out or (Path(tempfile.mkdtemp()) if args.quick else DEFAULT_OUT)
    out.mkdir(parents=True, exist_ok=True)
    record = {
        **record_header("kernels.py", argv),
        "scene": args.scene, "steps": steps, "dtype": "float32" if args.float32 else "float64",
        **measure(args.scene, steps, args.depth),
    }
    print_table(args.scene, record, args.top)
    path = out / f"kernels_{args.scene}.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    print(f"\nwrote {path}")
    return record


if __name__ == "__main__":
    main()
