"""Where a settled box stack's contact step goes: each piece of it alone, in a loop.

Why
    Issue 4 asks the 5-box stack of ``benchmarks/contacts.py`` to run at 5x MJX's
    single-environment speed. On the 2-core CI-class machines MJX ran it at 5,263-7,438
    steps/s in this project's committed runs, so 5x is a step of 27-38 microseconds. This
    script measures what the step's pieces cost on their own, each run as a loop of
    ``--steps`` iterations from the settled stack (the loop feeds each iteration's output
    to the next, so XLA cannot hoist it): which pieces alone already spend that budget.

What it measures (float32, the stack of ``contacts.py`` with ``--boxes`` cubes)
    * ``step``: the whole contact step (``rb.make_step``, ``SymplecticSplitting``, h = 1 ms);
    * ``step, time_of_impact=False``: the same without the time-of-impact search;
    * ``detect``: the narrow phase of every pair (``contacts="all"``: box-box and box-plane);
    * ``separations``: the pairs' separations (the branch test's narrow phase);
    * ``free step``: the step's free branch (kick, drift, kick; no contact work);
    * ``detect + frames``: the narrow phase and the solver's frames (lever arms, tangent
      bases, Delassus blocks);
    * ``detect + frames + k sweeps``: and the resting PGS solve from the settled warm start,
      exactly ``k`` sweeps (``k`` = 1, 2): what a settled step's solve costs at least
      (it runs one sweep a step, which finds nothing left to change).
    For each: kernels per iteration (the XLA:CPU kernels one call runs, counted with
    ``jax.profiler`` as ``benchmarks/kernels.py`` does; deterministic) and microseconds per
    iteration (best and median of ``--repeats`` calls). The pieces use jaxrb's internal
    functions (``jaxrb.contact``), the ones the step calls.

How to run (from the repository root)
    python benchmarks/step_pieces.py             # the 5-box stack, 200-iteration loops
    python benchmarks/step_pieces.py --quick     # CI smoke run (2 boxes, tiny), temp dir

It prints a table and writes ``step_pieces.json`` and ``step_pieces.png`` to ``--out``
(default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrb as rb
from jaxrb._indexing import literal_array
from jaxrb.contact import _step
from jaxrb.contact._layout import detect, pair_separations
from jaxrb.contact._solver import frames, solve

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ is not a package
from _machine import record_header, write_results  # noqa: E402
from contacts import box_stack  # noqa: E402
from kernels import kernel_counts  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results"
DT = 1e-3


def pieces(scene, settings: rb.ContactSettings):
    """``{name: piece(params, state) -> state}``; each piece's result feeds the next iteration."""
    integrator = rb.integrators.SymplecticSplitting()
    step = rb.make_step(scene, integrator, DT, contact=settings)
    without_search = rb.make_step(scene, integrator, DT, contact=dataclasses.replace(settings, time_of_impact=False))
    layout = _step.layout_of(scene)
    ctx = _step._Ctx(scene, layout, integrator, settings, DT)

    def nudge(state, x):
        # A dependence on the piece's output that changes nothing (1e-30 m), so that the
        # loop's next iteration cannot start before this one ends, nor be hoisted.
        return dataclasses.replace(state, position=state.position + 1e-30 * jnp.sum(x).astype(state.position.dtype))

    def solver_inputs(params, state):
        contact = detect(scene, layout, state, ctx.margin)
        bodies, position = _step._solver_bodies(params, state, state.velocity, state.angular_momentum)
        f = frames(bodies, layout.body_a, layout.body_b, contact.point, contact.normal, position)
        return contact, bodies, f

    def with_sweeps(k):
        def piece(params, state):
            contact, bodies, f = solver_inputs(params, state)
            _, mu = _step._slot_coefficients(ctx, params)
            target = jnp.where(contact.gap > 0, -contact.gap / DT, 0.0)
            _, lam = solve(bodies, f, literal_array(layout.colours), target, mu, contact.active,
                           state.contact_impulse, k, tolerance=None)
            return nudge(state, lam)
        return piece

    return {
        "step": step,
        "step, time_of_impact=False": without_search,
        "detect": lambda p, s: nudge(s, detect(scene, layout, s, ctx.margin).gap),
        "separations": lambda p, s: nudge(s, pair_separations(scene, layout, s, ctx.margin)),
        "free step": lambda p, s: _step.free_step(scene, integrator, settings, DT, p, s, None),
        "detect + frames": lambda p, s: nudge(s, solver_inputs(p, s)[2].delassus),
        "detect + frames + 1 sweep": with_sweeps(1),
        "detect + frames + 2 sweeps": with_sweeps(2),
    }, step


def measure(boxes: int, settle: int, steps: int, repeats: int, skip=()) -> dict:
    scene, params, state = box_stack(jnp.float32, boxes)
    named, step = pieces(scene, rb.ContactSettings())
    named = {name: piece for name, piece in named.items() if name not in skip}
    state = step.prepare(state)
    settled = jax.jit(lambda p, s: rb.rollout(step, p, s, settle, save_every=settle)[0])(params, state)
    results = {}
    for name, piece in named.items():
        loop = jax.jit(lambda p, s, piece=piece: jax.lax.fori_loop(0, steps, lambda i, x: piece(p, x), s))
        compiled = loop.lower(params, settled).compile()
        with tempfile.TemporaryDirectory(prefix="step_pieces_") as trace_dir:
            counts, _ = kernel_counts(compiled, (params, settled), Path(trace_dir))
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(params, settled))
            times.append(time.perf_counter() - t0)
        results[name] = {"kernels": sum(counts.values()) / steps,
                         "us_best": 1e6 * min(times) / steps, "us_median": 1e6 * float(np.median(times)) / steps}
        print(f"  {name:28s} {results[name]['kernels']:7.1f} kernels  {results[name]['us_best']:7.1f} us best  "
              f"{results[name]['us_median']:7.1f} us median", flush=True)
    return results


def plot(record: dict, path: Path) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    names = list(record["results"])
    best = [record["results"][n]["us_best"] for n in names]
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.barh(names[::-1], best[::-1])
    ax.set_xlabel("microseconds per iteration (best)")
    ax.set_title(f"{record['boxes']}-box stack, settled: each piece alone ({record['machine']['cpu']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--boxes", type=int, default=5)
    p.add_argument("--settle", type=int, default=1000, help="steps run before the pieces are measured")
    p.add_argument("--steps", type=int, default=200, help="iterations of each piece's loop")
    p.add_argument("--repeats", type=int, default=30, help="timed calls of each loop")
    p.add_argument("--quick", action="store_true", help="1 box, tiny loops, temp output dir (CI smoke run)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if args.quick:
        args.boxes, args.settle, args.steps, args.repeats = 1, 10, 3, 2
    out = args.out or (Path(tempfile.mkdtemp()) if args.quick else DEFAULT_OUT)
    out.mkdir(parents=True, exist_ok=True)
    print(f"{args.boxes}-box stack (float32, h = 1 ms), settled for {args.settle} steps; "
          f"each piece alone, {args.steps}-iteration loops, {args.repeats} calls:")
    record = {**record_header("step_pieces.py", argv), "boxes": args.boxes, "settle_steps": args.settle,
              "loop_iterations": args.steps, "repeats": args.repeats, "dtype": "float32",
              "results": measure(args.boxes, args.settle, args.steps, args.repeats,
                                 # (the smoke run compiles one whole step, not two)
                                 skip=("step, time_of_impact=False",) if args.quick else ())}
    write_results(out, "step_pieces", record, plot)
    return record


if __name__ == "__main__":
    main()
