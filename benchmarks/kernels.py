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
    * ``impact``: the same ball 4.5 steps above the ground, falling at 4.43 m/s (what it
      reaches from 1 m), with the same spin and drift: of a 20-step rollout's two chunks of
      10, the first fails its free-flight attempt and runs as contact steps, one of them
      the impact. What one impact adds to the ball's counts (divide by 1000, not 20).
    * ``stack``: three boxes (half-extent 0.1 m, 1 kg, mu = 0.5) resting on the ground.
    * ``table``: one impact step of a scene with a four-slot pair: balls a and b (r = 0.1 m,
      1 kg) land on the ground 0.15 and 0.60 of the way through the same step (h = 10 ms,
      e = 0.8, frictionless, ``SymplecticSplitting``), beside a 1000 kg table (a box
      (0.3, 0.3, 0.05) m) resting on it. The rollout is that one step, from the state after
      45 steps of a drop from 1 m clearance, so its impacts go through the multi-slot impact
      law (``_pair_impact``), whose reverse pass was once 30-60x the forward.
    * ``free``: a tumbling box under gravity, no contacts (compiles in seconds).

    Each program runs once to warm up and once under ``jax.profiler.trace``. Every event on
    an XLA worker thread that is a kernel (not a thunk executor, ``while`` or ``cond``
    wrapper) is counted and attributed twice: to its HLO instruction's ``op_name`` (the JAX
    transformation path and primitive it came from; ``T`` marks the reverse pass,
    ``transpose(...)``), and to the Python source lines that traced it (``by_line``: the
    innermost ``--frames`` frames of its call stack inside ``jaxrb/``, from the stack frames
    the compiled HLO carries). Kernels with neither are mostly copies that XLA inserted
    (loop carries, a ``cond``'s zero-filled residuals).

How to run (from the repository root)
    python benchmarks/kernels.py                  # the ball, 1000 steps
    python benchmarks/kernels.py --scene stack --depth 8   # 10 steps: the profiler records every PGS kernel
    python benchmarks/kernels.py --scene stack --frames 2  # which lines of jaxrb the kernels come from
    python benchmarks/kernels.py --scene impact   # 20 steps through one impact
    python benchmarks/kernels.py --scene table    # one impact step with a four-slot pair
    python benchmarks/kernels.py --quick          # CI smoke run, temp dir

It prints a table and writes ``kernels_<scene>.json`` to ``--out`` (default
``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import collections
import glob
import re
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp

import jaxrb as rb

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ is not a package
from _machine import record_header, write_results  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results"
#: Profiler events that wrap kernels (or are bookkeeping) rather than being kernels.
WRAPPERS = ("ThunkExecutor", "cond", "while", "end:", "ThreadpoolListener")


def scene_and_loss(name: str, steps: int):
    if name in ("ball", "impact"):
        scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
        step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
        params = scene.params(restitution=0.8, friction=0.5)
        height, fall = (1.1, 0.0) if name == "ball" else (0.1 + 4.5 * 4.43e-3, -4.43)
        state = scene.state(params, position=(0.0, 0.0, height), velocity=(0.3, 0.0, fall),
                            angular_velocity=(0.0, 2.0, 0.0))
    elif name == "stack":
        bodies = [rb.Body(f"box{i}", shape=rb.Box((0.1, 0.1, 0.1)), mass=1.0) for i in range(3)]
        scene = rb.Scene(bodies, ground=rb.Plane(), contacts="all")
        step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
        params = scene.params(friction=0.5)
        state = scene.state(params, position=[(0.0, 0.0, 0.1 + 0.2 * i) for i in range(3)])
    elif name == "table":
        g, dt = 9.81, 1e-2
        t_first = (2 * 1.0 / g) ** 0.5
        scene = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0), rb.Body("b", shape=rb.Sphere(0.1), mass=1.0),
                          rb.Body("table", shape=rb.Box((0.3, 0.3, 0.05)), mass=1000.0)],
                         ground=rb.Plane(), contacts="all")
        step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), dt)
        params = scene.params(restitution=0.8, friction=0.0)
        clearance_b = 0.5 * g * (t_first + 0.45 * dt) ** 2
        state = scene.state(params, position=[[0.0, 0.0, 1.1], [3.0, 0.0, 0.1 + clearance_b], [-3.0, 0.0, 0.05]])
        state = jax.jit(lambda p, s: rb.rollout(step, p, s, 45)[0])(params, step.prepare(state))
    elif name == "free":
        scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=2.0)])
        step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
        params = scene.params()
        state = scene.state(params, velocity=(1.0, 0.0, 5.0), angular_velocity=(0.3, 4.0, 0.1))
    else:
        raise ValueError(f"--scene must be 'ball', 'impact', 'stack', 'table' or 'free', got {name!r}")
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


def _table(hlo_text: str, name: str) -> list[str]:
    """The lines of one of the tables the HLO text ends with (``FileNames``, ...)."""
    match = re.search(r"^" + name + r"\n(.*?)(?:\n\n|\Z)", hlo_text, re.S | re.M)
    return match.group(1).split("\n") if match else []


def source_lines(hlo_text: str, frames: int) -> dict[str, str]:
    """HLO instruction name -> its innermost ``frames`` source frames inside ``jaxrb/``,
    as ``file:function:line`` joined by `` < `` (innermost first); ``""`` where none.

    The compiled HLO's ``stack_frame_id`` metadata indexes a ``StackFrames`` table (each
    entry a ``FileLocations`` entry and its parent frame, one-based, 0 for none) whose
    locations name a ``FileNames`` and a ``FunctionNames`` entry."""
    def numbered(name):
        return {int(line.split(" ", 1)[0]): line.split(" ", 1)[1] for line in _table(hlo_text, name)}

    files = {k: v.strip('"') for k, v in numbered("FileNames").items()}
    functions = {k: v.strip('"') for k, v in numbered("FunctionNames").items()}
    locations = {}
    for k, v in numbered("FileLocations").items():
        m = re.search(r"file_name_id=(\d+) function_name_id=(\d+) line=(\d+)", v)
        locations[k] = (files[int(m.group(1))], functions[int(m.group(2))], int(m.group(3)))
    parents = {}
    for k, v in numbered("StackFrames").items():
        m = re.search(r"file_location_id=(\d+) parent_frame_id=(\d+)", v)
        parents[k] = (int(m.group(1)), int(m.group(2)) - 1)

    def label(frame):
        out = []
        while frame in parents and len(out) < frames:
            location, frame = parents[frame]
            path, function, line = locations[location]
            if "/jaxrb/" in path:
                out.append(f"{path.rsplit('/jaxrb/', 1)[1]}:{function}:{line}")
        return " < ".join(out)

    return {m.group(1): label(int(m.group(2)))
            for m in re.finditer(r"%([\w.\-]+) = [^\n]*?stack_frame_id=(\d+)", hlo_text)}


def kernel_counts(compiled, args, trace_dir: Path) -> tuple[collections.Counter, int]:
    """Kernel events per HLO instruction name in one call of ``compiled``, and the number
    of tasks XLA:CPU's thunk executor handed to its thread pool in that call.

    A handoff: when more than 8 kernels of a loop body or program are ready at once, the
    executor gives half of them to another thread (``ThunkExecutor::SplitReadyQueue``,
    ``kSplitThreshold = 8`` in jaxlib 0.10.2), which costs that thread's wake-up. The
    profiler records each as a ``ThreadpoolListener::StartRegion`` event. It varies a
    little between calls (a handoff needs a free worker)."""
    jax.block_until_ready(compiled(*args))
    with jax.profiler.trace(str(trace_dir)):
        jax.block_until_ready(compiled(*args))
    (path,) = glob.glob(str(trace_dir / "**" / "*.xplane.pb"), recursive=True)
    counts, handoffs = collections.Counter(), 0
    for plane in jax.profiler.ProfileData.from_file(path).planes:
        for line in plane.lines:
            if not line.name.startswith("tf_XLA"):
                continue
            for event in line.events:
                if event.name.startswith("ThreadpoolListener::StartRegion"):
                    handoffs += 1
                elif not event.name.startswith(WRAPPERS):
                    counts[event.name] += 1
    return counts, handoffs


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


def by_line(counts, lines, steps: int) -> dict[str, float]:
    """Kernels per step, grouped by :func:`source_lines`."""
    groups = collections.Counter()
    for kernel, n in counts.items():
        groups[lines.get(kernel) or "(no jaxrb frame) " + re.sub(r"[.\d]+$", "", kernel)] += n
    return {k: v / steps for k, v in groups.most_common()}


def measure(scene: str, steps: int, depth: int, frames: int = 1) -> dict:
    loss, params, state = scene_and_loss(scene, steps)
    record = {}
    for mode, fn in (("forward", loss), ("reverse", jax.grad(loss, argnums=(0, 1)))):
        compiled = jax.jit(fn).lower(params, state).compile()
        with tempfile.TemporaryDirectory(prefix=f"kernels_{mode}_") as trace_dir:
            counts, handoffs = kernel_counts(compiled, (params, state), Path(trace_dir))
        text = compiled.as_text()
        record[mode] = {
            "kernels_per_step": sum(counts.values()) / steps,
            "threadpool_handoffs_per_step": handoffs / steps,
            "by_source": attribute(counts, op_names(text), steps, depth),
            "by_line": by_line(counts, source_lines(text, frames), steps),
        }
    record["ratio_reverse_over_forward"] = (record["reverse"]["kernels_per_step"]
                                            / record["forward"]["kernels_per_step"])
    return record


def print_table(scene: str, record: dict, top: int):
    f, r = record["forward"]["kernels_per_step"], record["reverse"]["kernels_per_step"]
    print(f"\n{scene}: {f:.1f} kernels per step forward, {r:.1f} with the reverse pass "
          f"({record['ratio_reverse_over_forward']:.2f}x)")
    print("thread-pool handoffs per step (see kernel_counts): "
          f"forward {record['forward']['threadpool_handoffs_per_step']:.2f}, "
          f"with the reverse pass {record['reverse']['threadpool_handoffs_per_step']:.2f}")
    for mode in ("forward", "reverse"):
        for table in ("by_source", "by_line"):
            print(f"\n{mode}, kernels per step {table.replace('_', ' ')} (first {top}):")
            for key, n in list(record[mode][table].items())[:top]:
                print(f"  {n:7.2f}  {key}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="ball", choices=["ball", "impact", "stack", "table", "free"])
    p.add_argument("--steps", type=int, default=None,
                   help="rollout length (default: 1000; stack 10, impact 20, table 1)")
    p.add_argument("--depth", type=int, default=10, help="op_name parts kept when grouping")
    p.add_argument("--frames", type=int, default=1, help="source frames (inside jaxrb/) per by_line key")
    p.add_argument("--top", type=int, default=25)
    p.add_argument("--float32", action="store_true")
    p.add_argument("--quick", action="store_true", help="free body, 20 steps, temp output dir (CI smoke run)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    if args.quick:
        args.scene, args.steps = "free", 20
    steps = args.steps or {"stack": 10, "impact": 20, "table": 1}.get(args.scene, 1000)
    out = args.out or (Path(tempfile.mkdtemp()) if args.quick else DEFAULT_OUT)
    out.mkdir(parents=True, exist_ok=True)
    record = {
        **record_header("kernels.py", argv),
        "scene": args.scene, "steps": steps, "dtype": "float32" if args.float32 else "float64",
        **measure(args.scene, steps, args.depth, args.frames),
    }
    print_table(args.scene, record, args.top)
    write_results(out, f"kernels_{args.scene}", record)
    return record


if __name__ == "__main__":
    main()
