"""Contact scenes: speed, compile time and accuracy of jaxrb, beside MuJoCo MJX and Brax.

What it measures
    * ``box_stack``: five cubes (half-extent 0.1 m, 1 kg) stacked at rest on the ground,
      mu = 0.5, h = 1 ms, 2 s, contacts ``"all"`` (15 pairs, 60 slots). Accuracy: the top
      box's drift (m) and the largest penetration (m) over the run. jaxrb runs with its
      PGS solver and with its exact (semismooth Newton) normal solve.
    * ``ball_drop``: a sphere (r = 0.1 m, 1 kg) dropped from 1 m clearance, e = 0.8,
      h = 1 ms, 3 s. Accuracy: the relative error of the first three apex heights
      against ``e^(2n)`` m (apex from energy, ``z + vz^2 / 2g``, where ``vz`` turns).
    For each: compile time (``jax.jit(...).lower().compile()``, tracing included),
    steps per second with one environment (``rollout`` over the scene, best of
    ``--repeats`` timed runs; ``timed_steps_1env`` steps, as many as the peers' calls,
    which are calibrated to 2 s and capped at the scene's length), and environment-steps
    per second with ``--envs`` environments (``jax.vmap``, best of ``--repeats`` timed
    calls of ``--batch-steps`` steps; one call moved the stack's figure by 40% between two
    runs an hour apart), each after a warm-up and ended by ``block_until_ready``.
    The stack runs from the initial stack as a chain of calls of ``--timing-steps`` steps,
    so its first call, where it settles, is also reported alone
    (``steps_per_s_1env_first_200``). The ball's timed call starts 5 steps before its
    first impact (``timing_start_step``), like the peers', and runs to the end of the scene.

    Peers (``benchmarks/peers.py``) run in the same process when they import here, or in
    another interpreter given by ``--peer-python`` (e.g. a venv with ``pip install
    .[peers]``), whose JSON is merged into the table. Their figures come from the same
    run of this script, on the same machine.

How to run (from the repository root)
    python benchmarks/contacts.py                       # full sizes, float32
    python benchmarks/contacts.py --peer-python /path/to/venv/bin/python
    python benchmarks/contacts.py --quick               # CI smoke run (tiny), temp dir

It prints a table and writes ``contacts.json`` and ``contacts.png`` to ``--out``
(default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrb as rb

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/ is not a package
from _machine import json_from_python, record_header, timed, write_results  # noqa: E402

G = 9.81
DEFAULT_OUT = Path(__file__).resolve().parent / "results"
HERE = Path(__file__).resolve().parent


def box_stack(dtype, boxes: int = 5):
    box = rb.Box((0.1, 0.1, 0.1))
    scene = rb.Scene([rb.Body(f"box{i}", shape=box, mass=1.0) for i in range(boxes)], ground=rb.Plane(),
                     contacts="all")
    params = scene.params(friction=0.5, dtype=dtype)
    state = scene.state(params, position=[[0.0, 0.0, 0.1 + 0.2 * i] for i in range(boxes)])
    return scene, params, state


def ball_drop(dtype):
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    params = scene.params(restitution=0.8, dtype=dtype)
    return scene, params, scene.state(params, position=(0.0, 0.0, 1.1))


def stack_accuracy(scene, state, traj):
    """The top box's drift from its start (m), and the deepest overlap of any pair (m), by
    the narrow phase (``rb.contact.penetration``: tilts count), at every step of the run and
    at its end (the peers report the end's). Until stop 92 the overlap came from the boxes'
    centre heights at every 10th step: 1.3e-6 m where every step's true overlap reached
    1.7e-6 m."""
    drift = float(np.linalg.norm(np.asarray(traj.position[-1, 4], float) - np.asarray(state.position[4], float)))
    overlaps = np.asarray(jax.jit(jax.vmap(lambda s: rb.contact.penetration(scene, s)))(traj), float)
    return {"top_drift_m": drift, "max_penetration_m": float(overlaps.max()), "penetration_end_m": float(overlaps[-1])}


def ball_accuracy(traj):
    z = np.asarray(traj.position[:, 0, 2], float)
    vz = np.asarray(traj.velocity[:, 0, 2], float)
    turn = np.where((vz[:-1] > 0) & (vz[1:] <= 0))[0][:3]
    apex = z[turn] + vz[turn] ** 2 / (2 * G) - 0.1
    exact = 0.8 ** (2 * np.arange(1, len(apex) + 1))
    return {"apex_rel_error": [float(x) for x in np.abs(apex / exact - 1)]}


def run_jaxrb(name, make, settings, seconds, envs, repeats, timing_steps, batch_steps, dtype):
    scene, params, state = make(dtype)
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3, contact=settings)
    state = step.prepare(state)
    num_steps = int(round(seconds / 1e-3))

    def full(p, s):
        return rb.rollout(step, p, s, num_steps)

    _, traj = jax.jit(full)(params, state)
    accuracy = stack_accuracy(scene, state, traj) if name == "box_stack" else ball_accuracy(traj)
    finite = bool(np.all(np.isfinite(np.asarray(traj.position))))

    # The single-environment calls cover the scene as the peers' do (benchmarks/peers.py:
    # calls calibrated to 2 s, capped at the scene's length; MJX's and Brax positional's
    # reach all 2,000 stack steps). The stack's start from the initial stack and run the
    # whole scene. The ball's start 5 steps before its first impact and run to the end of
    # the scene: each window holds the bounce's contact phase and then flight, the mix of
    # steps of the scene. (From the drop, 200 steps are all flight, which jaxrb's
    # free-step branch runs far faster than a contact step.)
    start, window = 0, num_steps
    if name == "ball_drop":
        first_impact = int(math.sqrt(2.0 * 1.0 / G) / 1e-3)  # 1 m clearance, h = 1 ms
        if num_steps > first_impact:  # short (smoke) runs never reach the ground
            start, window = first_impact - 5, num_steps - (first_impact - 5)
    timed_from = state if start == 0 else jax.tree.map(lambda x: x[start - 1], traj)  # after `start` steps

    # The stack's scene runs as a chain of calls of its first ``timing_steps`` steps' program,
    # each from the last one's end: one compiled program gives the whole scene's rate and
    # that of its first steps alone, where it settles and the PGS runs most of its sweeps
    # (7.4 a step over the first 200 in float32, 1.1 later). Until 2026-11-25 those first
    # steps were jaxrb's only figure, against the peers' whole scene. The chain's extra
    # dispatches cost microseconds against a call's tens of milliseconds.
    chunk = timing_steps if name == "box_stack" and window % timing_steps == 0 else window

    def short(p, s):
        return rb.rollout(step, p, s, chunk, save_every=chunk)[0]

    t0 = time.perf_counter()
    compiled = jax.jit(short).lower(params, timed_from).compile()
    compile_s = time.perf_counter() - t0

    def chain():
        s, calls = timed_from, []
        for _ in range(window // chunk):
            t = time.perf_counter()
            s = jax.block_until_ready(compiled(params, s))
            calls.append(time.perf_counter() - t)
        return calls

    chain()  # warm-up
    runs = [chain() for _ in range(repeats)]
    one = window / min(sum(calls) for calls in runs)
    settling = {}
    if chunk < window:
        settling = {f"steps_per_s_1env_first_{chunk}": chunk / min(calls[0] for calls in runs)}
    batch = lambda t: jax.tree.map(lambda x: jnp.broadcast_to(x, (envs, *x.shape)), t)  # noqa: E731
    def short_batch(p, s):
        return rb.rollout(step, p, s, batch_steps, save_every=batch_steps)[0]

    vmapped = jax.jit(jax.vmap(short_batch))
    many = envs * batch_steps / timed(vmapped, (batch(params), batch(timed_from)), repeats)
    return {"compile_s": compile_s, "steps_per_s_1env": one, f"env_steps_per_s_{envs}env": many,
            "timed_steps_1env": window, "timing_start_step": start, **settling, "finite": finite, **accuracy}


def run_peers(peer_python, quick, x64: bool):
    """The peers' figures, in this process or in ``peer_python``'s (float64 too with ``x64``:
    until stop 92 a separate interpreter stayed in float32 under ``--x64``)."""
    if peer_python is None:
        try:
            sys.path.insert(0, str(HERE))
            import peers  # noqa: PLC0415

            if not any(v is True for v in peers.available().values()):
                return {"note": f"peers not installed here: {peers.available()}"}
            return peers.run_all(small=quick)
        except Exception as err:  # noqa: BLE001 - report, never fail the jaxrb benchmark
            return {"error": repr(err)}
    code = (f"import json, sys; sys.path.insert(0, {str(HERE)!r}); import jax; "
            f"jax.config.update('jax_enable_x64', {x64!r}); import peers; "
            f"print('PEERS_JSON' + json.dumps(peers.run_all(small={quick!r})))")
    return json_from_python(peer_python, code, "PEERS_JSON")


def print_table(results):
    print(f"\n{'scene':<10} {'engine':<28} {'compile s':>9} {'steps/s 1':>11} {'env-steps/s N':>14}  accuracy")
    for scene, engines in results.items():
        for engine, r in engines.items():
            if "error" in r or "note" in r:
                print(f"{scene:<10} {engine:<28} {r.get('error', r.get('note'))[:80]}")
                continue
            many = next((v for k, v in r.items() if k.startswith("env_steps_per_s")), float("nan"))
            acc = {k: (round(v, 7) if isinstance(v, float) else v) for k, v in r.items()
                   if k in ("top_drift_m", "max_penetration_m", "penetration_end_m", "apex_rel_error",
                            "top_box_drift_m", "max_penetration_end_m", "apex1_rel_err", "apex2_rel_err",
                            "apex3_rel_err")}
            compile_s = r.get("compile_s", r.get("compile_s_1env", float("nan")))
            print(f"{scene:<10} {engine:<28} {compile_s:9.2f} "
                  f"{r.get('steps_per_s_1env', float('nan')):11.0f} {many:14.0f}  {acc}")


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, scene in zip(axes, results, strict=False):
        names, values = [], []
        for engine, r in results[scene].items():
            if "steps_per_s_1env" in r:
                names.append(engine)
                values.append(r["steps_per_s_1env"])
        ax.barh(names, values)
        ax.set_xscale("log")
        ax.set_xlabel("steps/s, one environment")
        ax.set_title(scene)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", type=int, default=1024)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--timing-steps", type=int, default=200,
                   help="the stack's first steps, also timed alone (one environment)")
    p.add_argument("--batch-steps", type=int, default=20, help="steps per timed call, --envs environments")
    p.add_argument("--x64", action="store_true")
    p.add_argument("--peer-python", default=None, help="interpreter with mujoco/mujoco-mjx/brax installed")
    p.add_argument("--no-peers", action="store_true")
    p.add_argument("--no-exact", action="store_true",
                   help="leave out the stack with the exact normal solve (a shorter run)")
    p.add_argument("--quick", action="store_true", help="tiny sizes, temp output dir (CI smoke run)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    header = record_header("contacts.py", argv)  # the load is the one at the start
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.float64 if args.x64 else jnp.float32
    if args.quick:
        args.envs, args.repeats, args.timing_steps, args.batch_steps = 4, 1, 5, 5
        args.out = args.out or Path(tempfile.mkdtemp(prefix="jaxrb_contacts_"))
    out = args.out or DEFAULT_OUT
    out.mkdir(parents=True, exist_ok=True)
    seconds = {"box_stack": 0.02 if args.quick else 2.0, "ball_drop": 0.05 if args.quick else 3.0}
    # The exact solve's dense Newton systems, vmapped over 1024 stacks, took over 15 min
    # here: its ensemble is measured at 64 environments (the JSON key says so).
    cases = {
        "box_stack": [("jaxrb pgs", box_stack, rb.ContactSettings(), args.envs),
                      ("jaxrb exact", box_stack, rb.ContactSettings(solver="exact"), min(args.envs, 64))],
        "ball_drop": [("jaxrb pgs + time of impact", ball_drop, rb.ContactSettings(), args.envs)],
    }
    if args.quick or args.no_exact:
        # The CI smoke run keeps every code path of this script but compiles fewer programs:
        # the exact solver's stack (its physics is tested in tests/test_contact.py) is left out,
        # as it is with --no-exact.
        cases["box_stack"] = cases["box_stack"][:1]
    results = {}
    for scene, runs in cases.items():
        results[scene] = {}
        for engine, make, settings, envs in runs:
            print(f"running {scene} / {engine} ...", flush=True)
            results[scene][engine] = run_jaxrb(scene, make, settings, seconds[scene], envs,
                                               args.repeats, args.timing_steps, args.batch_steps, dtype)
    if not args.no_peers:
        print("running the peers ...", flush=True)
        peers = run_peers(args.peer_python, args.quick, args.x64)
        for key, value in peers.items():
            scene = "box_stack" if "stack" in key else "ball_drop" if ("ball" in key or "drop" in key) else None
            if scene is None or not isinstance(value, dict):
                results.setdefault("peers", {})[key] = value if isinstance(value, dict) else {"note": str(value)}
            elif any("/" in k for k in value):  # brax: one entry per pipeline, "pipeline/key"
                shared = {k: v for k, v in value.items() if "/" not in k}
                for pipeline in sorted({k.split("/")[0] for k in value if "/" in k}):
                    own = {k.split("/", 1)[1]: v for k, v in value.items() if k.startswith(pipeline + "/")}
                    results[scene][f"{key.split('_')[0]} {pipeline}"] = {**shared, **own}
            else:
                results[scene][key.split("_")[0]] = value
    print_table(results)
    record = {**header, "jaxrb": rb.__version__, "backend": jax.default_backend(),
              "dtype": str(jnp.dtype(dtype)), "envs": args.envs, "results": results}
    write_results(out, "contacts", record,
                  lambda r, path: plot({k: v for k, v in r["results"].items() if k != "peers"}, path))
    return record


if __name__ == "__main__":
    main()
