"""Two versions of jaxrb side by side: the same programs, timed in one process, in turn.

Why
    On these shared 2-core machines one program's time moves by 10-30% between runs
    minutes apart, more than most changes it is meant to judge. Timed in one process, one
    call of each version after the other for many rounds, a slow spell of the machine
    falls on both alike, and the ratio of their minima (or medians) compares like with
    like. Until this script, such figures in benchmarks/README.md came from scratch
    scripts; this one makes them reproducible.

How
    Each version's ``jaxrb`` package is imported in turn under the name ``jaxrb`` (a git
    revision's is first extracted with ``git archive``), its programs are traced and
    compiled (``jax.jit(...).lower(...).compile()``, timed), and its modules are then set
    aside under other names, so that the next version imports afresh. A compiled program
    does not trace again, so both versions' programs then run side by side. The
    ``jaxrb`` this process had imported, if any, is restored at the end.

    Both versions run with this checkout's JAX. Their results (gradients, final states)
    are compared: ``max_rel_diff`` in the table is the largest relative difference over
    the outputs' leaves (0 for the same arithmetic).

Programs (``--programs``, comma-separated; all by default)
    * ``ball``: the 1000-step bouncing ball of ``gradients.py`` (r = 0.1 m, e = 0.8,
      mu = 0.5, h = 1 ms, float64): its forward rollout (``ball fwd``) and its gradient
      with respect to the params and the initial state (``ball grad``); and both again from
      a start high enough that no step comes near the ground (``ball flight fwd/grad``).
      The figure of issue 5 is ``ball grad`` / ``ball fwd`` within each version.
    * ``stack``: the 5-box stack of ``contacts.py`` (float32, PGS, h = 1 ms): 200 steps
      from the initial stack, where it settles (``stack first 200``), and 200 steps from
      its state after 1000 (``stack settled 200``), each as one call.
    * ``slide``: a box (half-extent 0.1 m, 1 kg) sliding at 5 m/s on the ground, mu = 0.5,
      400 steps, float64: forward and gradient (every step in contact).
    * ``roll``: the ball of ``ball`` on the ground, sliding at 2 m/s without spin, so that
      friction makes it roll, 400 steps, float64: forward and gradient (every step in
      contact, one contact slot: the counterpart of ``slide``'s four).
    * ``drop``: the box of ``slide`` dropped from 0.5 m clearance onto a face, tilted 0.1 rad,
      e = 0.5, 1000 steps, float64: forward and gradient (mostly flight, four slots once it
      lands: the counterpart of ``ball``).
    * ``ensemble``: 8 balls of ``ball``'s scene dropped from 0.15 to 0.6 m clearance,
      vmapped, 300 steps, float64: forward and gradient with respect to the shared params
      (the members land at different steps: a multi-experiment fit's loss).

How to run (from the repository root)
    python benchmarks/ab.py HEAD WORKTREE               # the uncommitted change
    python benchmarks/ab.py HEAD~3 HEAD --programs ball --rounds 60
    python benchmarks/ab.py /path/to/a /path/to/b       # directories that hold jaxrb/
    python benchmarks/ab.py --quick                     # CI smoke run (tiny), temp dir

``A`` and ``B`` are git revisions, ``WORKTREE`` (this checkout's files as they are), or
directories holding a ``jaxrb/`` package. It prints a table and writes ``ab.json`` and
``ab.png`` to ``--out`` (default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import contextlib
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ is not a package
from _machine import record_header, write_results  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DEFAULT_OUT = HERE / "results"
PROGRAMS = ("ball", "stack", "slide", "roll", "drop", "ensemble")


def progress(message: str) -> None:
    print(f"[ab.py {time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


# --- the versions ---------------------------------------------------------------------


def source_of(version: str, scratch: Path) -> Path:
    """A directory whose ``jaxrb/`` is ``version``'s: ``WORKTREE`` (this checkout), a
    directory that holds ``jaxrb/``, or a git revision (extracted into ``scratch``)."""
    if version == "WORKTREE":
        return ROOT
    if (Path(version) / "jaxrb" / "__init__.py").is_file():
        return Path(version).resolve()
    try:
        commit = subprocess.run(["git", "rev-parse", "--verify", f"{version}^{{commit}}"], cwd=ROOT,
                                capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError) as error:
        raise SystemExit(f"ab.py: {version!r} is neither a git revision of {ROOT}, nor WORKTREE, nor a "
                         f"directory holding jaxrb/ ({error}).") from None
    target = scratch / commit[:12]
    target.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "archive", commit, "jaxrb"], cwd=ROOT, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(target)], input=archive, check=True)
    return target


def _jaxrb_modules() -> dict:
    return {name: m for name, m in sys.modules.items() if name == "jaxrb" or name.startswith("jaxrb.")}


@contextlib.contextmanager
def imported(source: Path):
    """``jaxrb`` imported from ``source`` for the body of the ``with``; afterwards its
    modules are removed from ``sys.modules`` (the objects live on in what holds them) and
    whatever ``jaxrb`` was imported before is back."""
    before = _jaxrb_modules()
    for name in before:
        del sys.modules[name]
    sys.path.insert(0, str(source))
    try:
        import jaxrb  # noqa: PLC0415 - imported afresh, from ``source``

        if Path(jaxrb.__file__).resolve().parent != (source / "jaxrb").resolve():
            raise RuntimeError(f"ab.py: imported jaxrb from {jaxrb.__file__}, not from {source}")
        yield jaxrb
    finally:
        sys.path.remove(str(source))
        for name in _jaxrb_modules():
            del sys.modules[name]
        sys.modules.update(before)


# --- the programs (each takes the version's module) --------------------------------------


def compiled(fn, *args):
    """``fn`` jitted and compiled for ``args``; with its trace+lower and compile seconds, and
    the lines of its StableHLO: a program's size, which, unlike its compile time on this
    machine, does not vary from run to run (the same program compiled in 4.8 s as A and
    9.5 s as B in one run)."""
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    t1 = time.perf_counter()
    exe = lowered.compile()
    t2 = time.perf_counter()
    lines = lowered.as_text().count("\n")
    return exe, {"trace_lower_s": t1 - t0, "compile_s": t2 - t1, "stablehlo_lines": lines}


def ball_programs(rb, steps: int) -> dict:
    dtype = jnp.float64
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
    params = scene.params(restitution=0.8, friction=0.5, dtype=dtype)

    def start(z):
        return step.prepare(scene.state(params, position=(0.0, 0.0, z), velocity=(0.3, 0.0, 0.0),
                                        angular_velocity=(0.0, 2.0, 0.0)))

    def loss(p, s):
        _, traj = rb.rollout(step, p, s, steps)
        return jnp.sum(traj.position[:, 0, 2])

    drop, high = start(1.1), start(1.1 + 0.5 * 9.81 * (steps * 1e-3) ** 2)
    forward, fwd_cost = compiled(loss, params, drop)
    gradient, grad_cost = compiled(jax.grad(loss, argnums=(0, 1)), params, drop)
    return {"ball fwd": (forward, (params, drop), fwd_cost),
            "ball grad": (gradient, (params, drop), grad_cost),
            "ball flight fwd": (forward, (params, high), None),
            "ball flight grad": (gradient, (params, high), None)}


def stack_programs(rb, steps: int) -> dict:
    dtype = jnp.float32
    box = rb.Box((0.1, 0.1, 0.1))
    scene = rb.Scene([rb.Body(f"box{i}", shape=box, mass=1.0) for i in range(5)], ground=rb.Plane(), contacts="all")
    params = scene.params(friction=0.5, dtype=dtype)
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
    state = step.prepare(scene.state(params, position=[[0.0, 0.0, 0.1 + 0.2 * i] for i in range(5)]))

    def run(p, s):
        return rb.rollout(step, p, s, steps, save_every=steps)[0]

    program, cost = compiled(run, params, state)
    settled = state
    for _ in range(1000 // steps):
        settled = program(params, settled)
    return {f"stack first {steps}": (program, (params, state), cost),
            f"stack settled {steps}": (program, (params, settled), None)}


def one_body_programs(rb, name: str, shape, steps: int, restitution: float, axes: tuple, **start) -> dict:
    """Forward and gradient of a ``steps``-step rollout of one body on the ground (float64,
    mu = 0.5, h = 1 ms, ``SymplecticSplitting``), its loss the sum of the body's recorded
    coordinates ``axes``."""
    scene = rb.Scene([rb.Body(name, shape=shape, mass=1.0)], ground=rb.Plane(), contacts="all")
    params = scene.params(friction=0.5, restitution=restitution, dtype=jnp.float64)
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
    state = step.prepare(scene.state(params, **start))

    def loss(p, s):
        _, traj = rb.rollout(step, p, s, steps)
        return jnp.sum(traj.position[:, 0, axes])

    forward, fwd_cost = compiled(loss, params, state)
    gradient, grad_cost = compiled(jax.grad(loss, argnums=(0, 1)), params, state)
    return {f"{name} fwd": (forward, (params, state), fwd_cost),
            f"{name} grad": (gradient, (params, state), grad_cost)}


def slide_programs(rb, steps: int) -> dict:
    return one_body_programs(rb, "slide", rb.Box((0.1, 0.1, 0.1)), steps, 0.0, (0,), position=(0.0, 0.0, 0.1),
                             velocity=(5.0, 0.0, 0.0))


def roll_programs(rb, steps: int) -> dict:
    return one_body_programs(rb, "roll", rb.Sphere(0.1), steps, 0.8, (0, 2), position=(0.0, 0.0, 0.1),
                             velocity=(2.0, 0.0, 0.0))


def drop_programs(rb, steps: int) -> dict:
    tilt = (float(np.cos(0.05)), float(np.sin(0.05)), 0.0, 0.0)  # 0.1 rad about x
    return one_body_programs(rb, "drop", rb.Box((0.1, 0.1, 0.1)), steps, 0.5, (0, 2), position=(0.0, 0.0, 0.6),
                             orientation=tilt, velocity=(0.3, 0.0, 0.0))


def ensemble_programs(rb, members: int, steps: int) -> dict:
    """Forward and gradient (with respect to the shared params) of an ensemble: ``members``
    balls of ``ball``'s scene dropped from 0.15 to 0.6 m clearance, vmapped, ``steps`` steps,
    float64. They land at different steps, so the members' branches disagree now and then."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
    params = scene.params(restitution=0.8, friction=0.5, dtype=jnp.float64)
    starts = [step.prepare(scene.state(params, position=(0.0, 0.0, z), velocity=(0.3, 0.0, 0.0),
                                       angular_velocity=(0.0, 2.0, 0.0))) for z in np.linspace(0.15, 0.6, members)]
    states = jax.tree.map(lambda *x: jnp.stack(x), *starts)

    def loss(p, s):
        return jnp.sum(jax.vmap(lambda s: rb.rollout(step, p, s, steps)[1].position[:, 0, 2])(s))

    forward, fwd_cost = compiled(loss, params, states)
    gradient, grad_cost = compiled(jax.grad(loss), params, states)
    return {"ensemble fwd": (forward, (params, states), fwd_cost),
            "ensemble grad": (gradient, (params, states), grad_cost)}


def build(rb, names, quick: bool) -> dict:
    """``name: (compiled program, args, costs or None)`` for the ``names`` asked for."""
    makers = {"ball": lambda: ball_programs(rb, 100 if quick else 1000),
              "stack": lambda: stack_programs(rb, 20 if quick else 200),
              "slide": lambda: slide_programs(rb, 40 if quick else 400),
              "roll": lambda: roll_programs(rb, 40 if quick else 400),
              "drop": lambda: drop_programs(rb, 100 if quick else 1000),
              "ensemble": lambda: ensemble_programs(rb, 2 if quick else 8, 50 if quick else 300)}
    programs = {}
    for name in names:
        programs.update(makers[name]())
    return programs


# --- timing and comparison ----------------------------------------------------------------


def side_by_side(versions: dict, rounds: int) -> dict:
    """Wall times (s) of ``rounds`` calls of every program of every version, after one
    warm-up call each: program by program, both versions' calls one after the other, A's
    first in even rounds and B's in odd ones. (The first of two calls runs after another
    program has filled the caches: with A always first, A's forward of the ball, the same
    code as B's, timed 24% slower.)"""
    names, tags = list(next(iter(versions.values()))), list(versions)
    for programs in versions.values():
        for fn, args, _ in programs.values():
            jax.block_until_ready(fn(*args))
    times = {(tag, name): [] for tag in tags for name in names}
    for i in range(rounds):
        for name in names:
            for tag in (tags if i % 2 == 0 else tags[::-1]):
                fn, args, _ = versions[tag][name]
                t0 = time.perf_counter()
                jax.block_until_ready(fn(*args))
                times[(tag, name)].append(time.perf_counter() - t0)
    return {key: np.asarray(t) for key, t in times.items()}


def max_rel_diff(x, y) -> float:
    """The largest ``|x - y| / max(|x|, |y|, tiny)`` over the leaves of two results."""
    x, y = jax.tree.leaves(x), jax.tree.leaves(y)
    if [np.shape(a) for a in x] != [np.shape(b) for b in y]:
        return float("nan")  # the versions' results differ in structure (an API change)
    worst = 0.0
    for a, b in zip(x, y, strict=True):
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        scale = np.maximum(np.maximum(np.abs(a), np.abs(b)), np.finfo(np.float64).tiny)
        worst = max(worst, float(np.max(np.abs(a - b) / scale, initial=0.0)))
    return worst


def summarise(versions: dict, times: dict) -> dict:
    (a, progs_a), (b, progs_b) = versions.items()
    rows = {}
    for name in progs_a:
        ta, tb = times[(a, name)], times[(b, name)]
        fa, args_a, cost_a = progs_a[name]
        fb, args_b, cost_b = progs_b[name]
        rows[name] = {
            "a_min_ms": 1e3 * ta.min(), "a_median_ms": 1e3 * np.median(ta),
            "b_min_ms": 1e3 * tb.min(), "b_median_ms": 1e3 * np.median(tb),
            "b_over_a_min": tb.min() / ta.min(), "b_over_a_median": np.median(tb) / np.median(ta),
            "max_rel_diff": max_rel_diff(fa(*args_a), fb(*args_b)),
            "a_cost": cost_a, "b_cost": cost_b,
            "a_times_s": ta.tolist(), "b_times_s": tb.tolist(),
        }
    ratios = {}
    for tag, key in ((a, "a"), (b, "b")):
        for pair in (("ball grad", "ball fwd"), ("ball flight grad", "ball flight fwd"), ("slide grad", "slide fwd"),
                     ("roll grad", "roll fwd"), ("drop grad", "drop fwd"),
                     ("ensemble grad", "ensemble fwd")):
            if pair[0] in rows:
                g, f = times[(tag, pair[0])], times[(tag, pair[1])]
                ratios.setdefault(f"{pair[0]} / fwd", {})[key] = {"min": g.min() / f.min(),
                                                                "median": np.median(g) / np.median(f)}
    return {"programs": rows, "gradient_over_forward": ratios}


def print_table(record: dict) -> None:
    a, b = record["a"], record["b"]
    print(f"\nA = {a['version']} ({a['source']})\nB = {b['version']} ({b['source']})")
    print(f"{record['rounds']} interleaved rounds; ms: minimum (median)\n")
    print(f"{'program':<20} {'A':>18} {'B':>18} {'B/A min (median)':>18} {'max rel diff':>13}")
    for name, r in record["summary"]["programs"].items():
        print(f"{name:<20} {r['a_min_ms']:8.3f} ({r['a_median_ms']:7.3f})"
              f" {r['b_min_ms']:8.3f} ({r['b_median_ms']:7.3f})"
              f" {r['b_over_a_min']:9.3f} ({r['b_over_a_median']:5.3f}) {r['max_rel_diff']:13.1e}")
    for name, r in record["summary"]["gradient_over_forward"].items():
        print(f"{name:<20} A {r['a']['min']:.2f} ({r['a']['median']:.2f})"
              f"   B {r['b']['min']:.2f} ({r['b']['median']:.2f})")
    print("\ncompile (s): trace+lower / XLA, and the program's lines of StableHLO")
    for name, r in record["summary"]["programs"].items():
        if r["a_cost"]:
            ca, cb = r["a_cost"], r["b_cost"]
            print(f"{name:<20} A {ca['trace_lower_s']:5.1f} / {ca['compile_s']:5.1f} {ca['stablehlo_lines']:>8,}   "
                  f"B {cb['trace_lower_s']:5.1f} / {cb['compile_s']:5.1f} {cb['stablehlo_lines']:>8,}")


def plot(record: dict, path: Path) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    rows = record["summary"]["programs"]
    names = list(rows)
    y = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(6.5, 0.45 * len(names) + 1.2))
    ax.barh(y - 0.18, [rows[n]["b_over_a_min"] for n in names], height=0.36, label="minima")
    ax.barh(y + 0.18, [rows[n]["b_over_a_median"] for n in names], height=0.36, label="medians")
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_yticks(y, names)
    ax.invert_yaxis()
    ax.set_xlabel(f"time B / time A  (A = {record['a']['version']}, B = {record['b']['version']})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a", nargs="?", default="HEAD", help="git revision, WORKTREE, or a directory holding jaxrb/")
    p.add_argument("b", nargs="?", default="WORKTREE", help="as A (default: this checkout as it is)")
    p.add_argument("--programs", default=",".join(PROGRAMS), help=f"comma-separated, of {', '.join(PROGRAMS)}")
    p.add_argument("--rounds", type=int, default=40)
    p.add_argument("--quick", action="store_true", help="tiny sizes, 3 rounds, temp output dir (CI smoke run)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    names = [n.strip() for n in args.programs.split(",") if n.strip()]
    unknown = sorted(set(names) - set(PROGRAMS))
    if unknown or not names:
        raise SystemExit(f"ab.py: --programs takes a comma-separated list of {', '.join(PROGRAMS)}; "
                         f"got {args.programs!r}.")
    if args.quick:
        args.rounds = 3
    jax.config.update("jax_enable_x64", True)  # the float32 stack asks for its dtype itself
    out = args.out or (Path(tempfile.mkdtemp()) if args.quick else DEFAULT_OUT)
    out.mkdir(parents=True, exist_ok=True)

    versions, sources = {}, {}
    with tempfile.TemporaryDirectory() as scratch:
        for tag, version in (("A", args.a), ("B", args.b)):
            sources[tag] = source_of(version, Path(scratch) / tag)
            progress(f"{tag} = {version}: tracing and compiling {', '.join(names)}")
            with imported(sources[tag]) as rb:
                versions[tag] = build(rb, names, args.quick)
        progress(f"timing, {args.rounds} rounds")
        times = side_by_side(versions, args.rounds)
        record = {**record_header("ab.py", argv), "rounds": args.rounds, "quick": args.quick,
                  "a": {"version": args.a, "source": str(sources["A"])},
                  "b": {"version": args.b, "source": str(sources["B"])},
                  "summary": summarise(versions, times)}
    print_table(record)
    write_results(out, "ab", record, plot)
    return record


if __name__ == "__main__":
    main()
