"""The cost of gradients: time against the forward rollout, and memory with checkpointing.

What it measures
    * ``bounce``: a ball (r = 0.1 m, 1 kg) dropped from 1 m clearance, e = 0.8, mu = 0.5,
      h = 1 ms, 1000 steps (two impacts, time of impact located inside steps). The loss is
      the sum of the heights over the trajectory. Times: the jitted forward rollout, the
      reverse-mode gradient with respect to everything in ``Params`` and the initial
      ``State`` (``jax.grad``), and the forward-mode Jacobian with respect to
      ``(e, mu, mass)`` (``jax.jacfwd``), with their compile times. Each program is timed
      hot, as a user's loop calls it and as ``peers.py`` times the peers (best of
      consecutive calls): in blocks of 10 consecutive calls, the programs' blocks taken in
      turn, 40 calls each after a warm-up. The ratio of the minima (and, beside it, of the
      medians) gradient / forward is the figure of merit. The same calls interleaved one
      by one (forward, reverse, Jacobian, forward, ...), this script's protocol until
      2026-12-04, are recorded beside it (``interleaved``): there each call follows another
      program's, and the forward, a small program, runs up to 1.5x slower cold.
    * ``bounce`` also splits that cost, in blocks of its own: the same two compiled
      programs from a start high enough that no step of the rollout comes near the ground
      (every step is free flight), and the same ball in a scene that declares no contacts
      (its step is the bare integrator step) from that start, with the loss as it is (XLA
      then drops the attitude, which the heights do not need) and with the attitude kept
      (``0 *`` its sum added). Where the gradient's time goes: into the impacts, or into
      the free steps of a program that can collide.
    * ``bounce_one_thread_pool``: the headline forward and gradient again, timed alike, in a
      fresh interpreter whose XLA:CPU thread pool has one thread, as the peers' runs have
      (``peers.single_thread_xla_pool``, their deadlock workaround): jaxrb's ratio beside
      theirs measured the same way. The headline stays on the default pool.
    * ``free_body_long``: a tumbling box under gravity, h = 1 ms, ``--long-steps`` steps
      (default 1e5), the gradient of the final pose with respect to the inertia and the
      initial state, through ``rollout(..., checkpoint=True, save_every=k)`` with
      ``k ~ sqrt(steps)``, and without checkpointing for comparison. Memory: XLA's own
      buffer assignment for the compiled gradient (``memory_analysis()``: arguments +
      outputs + temporaries, which is the peak the program needs), and the peak resident
      set (``VmHWM``, ``_machine.peak_rss_bytes``) of a fresh process that runs only this
      measurement. That is the process's high-water mark since it started: Python, jaxlib
      and the compiles included, so it bounds the run's peak from above but does not
      measure it. It is read before and after each variant's timed calls; the checkpointed
      variant runs first, and the plain one's figure is set by its own compile (the rise
      across its calls was 0 in stop 92's check). Compare the variants by XLA's figures.

    Peers (``benchmarks/peers.py``, MJX and Brax) run in another interpreter given by
    ``--peer-python``: the same gradient/forward ratio on their ball drop.

How to run (from the repository root)
    python benchmarks/gradients.py                      # float64, full sizes
    python benchmarks/gradients.py --peer-python /path/to/venv/bin/python
    python benchmarks/gradients.py --quick              # CI smoke run, temp dir

It prints a table and writes ``gradients.json`` and ``gradients.png`` to ``--out``
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
from _machine import json_from_python, peak_rss_bytes, record_header, timed, write_results  # noqa: E402

HERE = Path(__file__).resolve().parent
DEFAULT_OUT = HERE / "results"


def progress(message: str) -> None:
    """One line on stderr as the run goes (a run takes minutes; on a GPU, longer)."""
    print(f"[gradients.py {time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def compiled(fn, *args, name: str = "a program"):
    t0 = time.perf_counter()
    exe = jax.jit(fn).lower(*args).compile()
    seconds = time.perf_counter() - t0
    progress(f"compiled {name} in {seconds:.1f} s")
    return exe, seconds


def memory_bytes(exe) -> int | None:
    analysis = exe.memory_analysis()
    if analysis is None:
        return None
    return int(analysis.argument_size_in_bytes + analysis.output_size_in_bytes + analysis.temp_size_in_bytes
               - analysis.alias_size_in_bytes)


#: The ball's programs take milliseconds, and one process's calls of the same program vary
#: by up to 2x on the 2-core machine (bursts of slow calls), so a best of three sequential
#: calls made the committed ratio swing between 4x and 7x from run to run. So each program
#: is called this many times, in blocks taken in turn: a slow spell of the machine falls
#: on all the programs alike.
BOUNCE_ROUNDS = 40
#: Consecutive calls of one program in a block. A call right after another program's runs
#: cold: the 1000-step ball's forward took 0.55-0.61 ms by minima interleaved call by call
#: with its gradient, and 0.38-0.40 ms in blocks of 10 or called alone; its gradient
#: 2.3-3.0 ms either way (2026-12-04, Intel Xeon, benchmarks/README.md, "How the ratio is
#: timed"). The peers are timed hot (``peers.py``: best of consecutive calls).
HOT_BLOCK = 10


def interleaved(programs: dict, rounds: int, block: int = 1) -> dict[str, np.ndarray]:
    """Wall times (s) of ``rounds`` calls of each ``name: (fn, args)``, after one warm-up
    call each: ``block`` consecutive calls of one program, then of the next, in turn, until
    each has had ``rounds``. With ``block = 1`` every call follows another program's."""
    for fn, args in programs.values():
        jax.block_until_ready(fn(*args))
    times = {name: [] for name in programs}
    for _ in range(max(1, rounds // block)):
        for name, (fn, args) in programs.items():
            for _ in range(block):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(*args))
                times[name].append(time.perf_counter() - t0)
    return {name: np.asarray(t) for name, t in times.items()}


def ball(steps, dtype):
    """The bouncing ball: ``(scene, step, params, state, loss)``, the loss the sum of the
    centre's heights over a ``steps``-step rollout."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
    params = scene.params(restitution=0.8, friction=0.5, dtype=dtype)
    state = step.prepare(scene.state(params, position=(0.0, 0.0, 1.1), velocity=(0.3, 0.0, 0.0),
                                     angular_velocity=(0.0, 2.0, 0.0)))

    def loss(p, s):
        _, traj = rb.rollout(step, p, s, steps)
        return jnp.sum(traj.position[:, 0, 2])

    return scene, step, params, state, loss


def bounce_ratio(steps, dtype, xla_cpu_pool: str) -> dict:
    """The headline figure alone: the ball's forward and gradient (as in :func:`bounce`),
    timed hot in blocks as there, in a process whose XLA:CPU pool ``xla_cpu_pool`` says
    (recorded). For :func:`bounce_in_one_thread_pool`."""
    _, _, params, state, loss = ball(steps, dtype)
    forward, _ = compiled(loss, params, state, name="the ball's forward rollout")
    reverse, _ = compiled(jax.grad(loss, argnums=(0, 1)), params, state, name="its gradient")
    times = interleaved({"forward": (forward, (params, state)), "reverse": (reverse, (params, state))},
                        BOUNCE_ROUNDS, HOT_BLOCK)
    t_fwd, t_rev = float(np.min(times["forward"])), float(np.min(times["reverse"]))
    m_fwd, m_rev = float(np.median(times["forward"])), float(np.median(times["reverse"]))
    return {"forward_s": t_fwd, "reverse_grad_s": t_rev, "ratio_reverse_over_forward": t_rev / t_fwd,
            "median_ratio_reverse_over_forward": m_rev / m_fwd, "xla_cpu_pool": xla_cpu_pool}


def bounce_in_one_thread_pool(args) -> dict:
    """:func:`bounce_ratio` in a new interpreter whose XLA:CPU pool has one thread, as the
    peers' (``peers.single_thread_xla_pool``, their deadlock workaround): the ratio beside
    theirs measured alike. On two cores the ball's reverse pass hands work to the pool's
    other thread (benchmarks/README.md, stop 81), which costs it more than the forward."""
    return in_fresh_process(args, f"bounce_ratio({args.steps}, dtype, pool)", "the one-thread-pool measurement",
                            first="import peers; pool = peers.single_thread_xla_pool(); ")


def bounce(steps, repeats, dtype):
    scene, step, params, state, loss = ball(steps, dtype)

    def coefficients(x):
        return loss(params.replace(restitution=x[:1], friction=x[1:2], mass=x[2:3]), state)

    x = jnp.asarray([0.8, 0.5, 1.0], dtype)
    forward, c_fwd = compiled(loss, params, state, name="the ball's forward rollout")
    reverse, c_rev = compiled(jax.grad(loss, argnums=(0, 1)), params, state, name="its gradient")
    jacfwd, c_jf = compiled(jax.jacfwd(coefficients), x, name="its forward-mode Jacobian")

    # The cost split: flight only, in this program and in one without contacts.
    fall = 0.5 * 9.81 * (steps * 1e-3) ** 2
    high = step.prepare(scene.state(params, position=(0.0, 0.0, 1.1 + fall), velocity=(0.3, 0.0, 0.0),
                                    angular_velocity=(0.0, 2.0, 0.0)))
    bare_scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    bare_step = rb.make_step(bare_scene, rb.integrators.SymplecticSplitting(), 1e-3)
    bare_params = bare_scene.params(dtype=dtype)
    bare_state = bare_step.prepare(bare_scene.state(bare_params, position=high.position, velocity=high.velocity,
                                                    angular_velocity=(0.0, 2.0, 0.0)))

    def bare_loss(p, s):
        _, traj = rb.rollout(bare_step, p, s, steps)
        return jnp.sum(traj.position[:, 0, 2])

    def bare_loss_attitude_kept(p, s):
        # The same value. Without contacts the heights do not depend on the attitude, and
        # XLA removes its whole update (forward and derivative) from bare_loss's programs;
        # the contact program keeps it (a contact could need it). ``0 * x`` is not folded
        # away, so these programs do the free step's whole work.
        _, traj = rb.rollout(bare_step, p, s, steps)
        return jnp.sum(traj.position[:, 0, 2]) + 0.0 * jnp.sum(traj.orientation)

    bare_forward, _ = compiled(bare_loss, bare_params, bare_state)
    bare_reverse, _ = compiled(jax.grad(bare_loss, argnums=(0, 1)), bare_params, bare_state)
    kept_forward, _ = compiled(bare_loss_attitude_kept, bare_params, bare_state)
    kept_reverse, _ = compiled(jax.grad(bare_loss_attitude_kept, argnums=(0, 1)), bare_params, bare_state)
    lowest = float(jnp.min(rb.rollout(step, params, high, steps)[1].position[:, 0, 2]))
    if lowest < 1.0:  # radius 0.1 m, the contact margin 0.02 m at h = 1 ms: far above both
        raise RuntimeError(f"the flight-only start reaches {lowest:.3f} m: it must stay far from the ground")
    # Flight only, the two programs' gradients must be those of the same free motion.
    g_flight, g_bare = reverse(params, high), bare_reverse(bare_params, bare_state)
    flight_mismatch = max(
        float(np.max(np.abs(np.asarray(getattr(g_flight[1], f)) - np.asarray(getattr(g_bare[1], f)))))
        for f in ("position", "velocity", "orientation", "angular_momentum"))

    rounds = max(repeats, BOUNCE_ROUNDS)
    block = min(HOT_BLOCK, rounds)
    progress(f"timing the bouncing ball: {rounds} calls each in blocks of {block}, then one by one, then the split")
    headline = {"forward": (forward, (params, state)), "reverse": (reverse, (params, state)), "jacfwd": (jacfwd, (x,))}
    times = interleaved(headline, rounds, block)
    one_by_one = interleaved(headline, rounds)
    # The split in blocks of its own (the headline ratio's stay as they were), with the
    # bouncing start again beside the others.
    split_times = interleaved({"forward_bounce": (forward, (params, state)),
                               "reverse_bounce": (reverse, (params, state)),
                               "forward_flight": (forward, (params, high)), "reverse_flight": (reverse, (params, high)),
                               "forward_no_contacts": (bare_forward, (bare_params, bare_state)),
                               "reverse_no_contacts": (bare_reverse, (bare_params, bare_state)),
                               "forward_no_contacts_attitude_kept": (kept_forward, (bare_params, bare_state)),
                               "reverse_no_contacts_attitude_kept": (kept_reverse, (bare_params, bare_state))},
                              rounds, block)
    t_fwd, t_rev, t_jf = (float(np.min(times[k])) for k in ("forward", "reverse", "jacfwd"))
    lone_fwd, lone_rev = (float(np.min(one_by_one[k])) for k in ("forward", "reverse"))
    median = {k: float(np.median(v)) for k, v in times.items()}
    grads = reverse(params, state)
    finite = all(bool(np.all(np.isfinite(np.asarray(g)))) for g in jax.tree.leaves(grads))
    split = {k: float(np.min(v)) for k, v in split_times.items()}
    return {
        "cost_split_s": split, "flight_state_gradient_max_abs_difference": flight_mismatch,
        "steps": steps, "forward_s": t_fwd, "reverse_grad_s": t_rev, "forward_jacobian_3_params_s": t_jf,
        "ratio_reverse_over_forward": t_rev / t_fwd, "ratio_jacfwd3_over_forward": t_jf / t_fwd,
        "timing_rounds": rounds, "median_forward_s": median["forward"], "median_reverse_grad_s": median["reverse"],
        "median_ratio_reverse_over_forward": median["reverse"] / median["forward"],
        "timing_block": block,
        "interleaved": {"forward_s": lone_fwd, "reverse_grad_s": lone_rev,
                        "ratio_reverse_over_forward": lone_rev / lone_fwd,
                        "median_ratio_reverse_over_forward": float(np.median(one_by_one["reverse"])
                                                                   / np.median(one_by_one["forward"]))},
        "compile_forward_s": c_fwd, "compile_reverse_s": c_rev, "compile_jacfwd_s": c_jf,
        "reverse_memory_bytes": memory_bytes(reverse), "forward_memory_bytes": memory_bytes(forward),
        "gradient_finite": finite,
    }


def free_body_long(steps, repeats, dtype, plain_too: bool):
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=2.0)])
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
    params = scene.params(dtype=dtype)
    state = scene.state(params, velocity=(1.0, 0.0, 5.0), angular_velocity=(0.3, 4.0, 0.1))
    every = max(d for d in range(1, int(math.isqrt(steps)) + 1) if steps % d == 0)

    def loss(p, s, checkpoint):
        end, _ = rb.rollout(step, p, s, steps, save_every=every, checkpoint=checkpoint)
        return jnp.sum(end.position**2) + jnp.sum(end.orientation * jnp.asarray([1.0, 2.0, 3.0, 4.0], dtype))

    out = {"steps": steps, "save_every": every}
    forward, c_fwd = compiled(lambda p, s: loss(p, s, True), params, state)
    t_fwd = timed(forward, (params, state), repeats)
    variants = [("checkpointed", True)] + ([("plain", False)] if plain_too else [])
    for name, checkpoint in variants:
        grad = jax.grad(lambda p, s, c=checkpoint: loss(p, s, c), argnums=(0, 1))
        exe, c_grad = compiled(grad, params, state)
        rss0 = peak_rss_bytes()
        t_grad = timed(exe, (params, state), repeats)
        g = exe(params, state)
        out[name] = {
            "grad_s": t_grad, "compile_s": c_grad, "ratio_grad_over_forward": t_grad / t_fwd,
            "xla_memory_bytes": memory_bytes(exe),
            "process_peak_rss_bytes": peak_rss_bytes(),
            "peak_rss_before_run_bytes": rss0,
            "gradient_finite": all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree.leaves(g)),
        }
    out["forward_s"] = t_fwd
    out["compile_forward_s"] = c_fwd
    return out


def long_in_fresh_process(args):
    """``free_body_long`` in a new interpreter, so that its peak RSS is its own."""
    return in_fresh_process(args, f"free_body_long({args.long_steps}, {args.repeats}, dtype, {not args.no_plain!r})",
                            "the long-rollout measurement")


def in_fresh_process(args, call: str, what: str, first: str = "") -> dict:
    """``gradients.<call>`` (an expression in which ``dtype`` is the run's dtype) evaluated in
    a new interpreter, after the statements ``first`` (run before JAX starts); its result,
    a JSON-able dict."""
    code = (f"import json, sys; sys.path.insert(0, {str(HERE)!r}); {first}import jax; "
            f"jax.config.update('jax_enable_x64', {not args.float32!r}); import jax.numpy as jnp; "
            f"dtype = jnp.{'float32' if args.float32 else 'float64'}; import gradients as g; "
            f"print('RESULT_JSON' + json.dumps(g.{call}))")
    result = json_from_python(sys.executable, code, "RESULT_JSON")
    if "error" in result:
        raise RuntimeError(f"{what} failed:\n{result['error']}")
    return result


def run_peers(peer_python, steps, repeats):
    code = (f"import json, sys; sys.path.insert(0, {str(HERE)!r}); import peers; "
            f"print('PEERS_JSON' + json.dumps(peers.gradient_ratios(steps={steps}, repeats={repeats})))")
    return json_from_python(peer_python, code, "PEERS_JSON")


def print_table(record):
    b = record["bounce"]
    print(f"\nbounce, {b['steps']} steps: forward {b['forward_s'] * 1e3:.1f} ms, reverse gradient "
          f"{b['reverse_grad_s'] * 1e3:.1f} ms (x{b['ratio_reverse_over_forward']:.2f}; medians "
          f"{b['median_forward_s'] * 1e3:.1f} / {b['median_reverse_grad_s'] * 1e3:.1f} ms, "
          f"x{b['median_ratio_reverse_over_forward']:.2f}), forward Jacobian (3 params) "
          f"{b['forward_jacobian_3_params_s'] * 1e3:.1f} ms (x{b['ratio_jacfwd3_over_forward']:.2f}); compile "
          f"{b['compile_forward_s']:.1f} / {b['compile_reverse_s']:.1f} / {b['compile_jacfwd_s']:.1f} s; "
          f"each timed hot, in blocks of {b['timing_block']} calls")
    i = b["interleaved"]
    print(f"  the same calls one by one, each after another program's: forward {i['forward_s'] * 1e3:.2f} ms, "
          f"gradient {i['reverse_grad_s'] * 1e3:.2f} ms (x{i['ratio_reverse_over_forward']:.2f}; medians "
          f"x{i['median_ratio_reverse_over_forward']:.2f})")
    c = b.get("cost_split_s")
    if c:
        print(f"  split (blocks of its own): bouncing as above: forward {c['forward_bounce'] * 1e3:.2f} ms, "
              f"gradient {c['reverse_bounce'] * 1e3:.2f} ms (x{c['reverse_bounce'] / c['forward_bounce']:.2f})")
        print(f"  the same programs, flight only (no step near the ground): forward "
              f"{c['forward_flight'] * 1e3:.2f} ms, gradient {c['reverse_flight'] * 1e3:.2f} ms "
              f"(x{c['reverse_flight'] / c['forward_flight']:.2f})")
        print(f"  the same flight, scene without contacts: forward {c['forward_no_contacts'] * 1e3:.3f} ms, "
              f"gradient {c['reverse_no_contacts'] * 1e3:.3f} ms "
              f"(x{c['reverse_no_contacts'] / c['forward_no_contacts']:.2f}; XLA drops the attitude, which the "
              f"heights do not need); state gradients agree to {b['flight_state_gradient_max_abs_difference']:.1e}")
        print(f"  the same, attitude kept (0 * its sum added to the loss): forward "
              f"{c['forward_no_contacts_attitude_kept'] * 1e3:.3f} ms, gradient "
              f"{c['reverse_no_contacts_attitude_kept'] * 1e3:.3f} ms "
              f"(x{c['reverse_no_contacts_attitude_kept'] / c['forward_no_contacts_attitude_kept']:.2f})")
    o = record.get("bounce_one_thread_pool")
    if o:
        print(f"  the same forward and gradient in a fresh process with a one-thread XLA pool "
              f"({o['xla_cpu_pool']}, as the peers): {o['forward_s'] * 1e3:.2f} / {o['reverse_grad_s'] * 1e3:.2f} ms "
              f"(x{o['ratio_reverse_over_forward']:.2f}; medians x{o['median_ratio_reverse_over_forward']:.2f})")
    f = record["free_body_long"]
    for name in ("checkpointed", "plain"):
        if name in f:
            r = f[name]
            mem = r["xla_memory_bytes"]
            print(f"free body, {f['steps']} steps, {name:<12}: gradient {r['grad_s']:.2f} s "
                  f"(x{r['ratio_grad_over_forward']:.2f} forward), XLA memory "
                  f"{(mem or float('nan')) / 2**20:.1f} MiB, "
                  f"process peak RSS {r['process_peak_rss_bytes'] / 2**20:.0f} MiB")
    peers = record.get("peers", {})
    for engine in ("mjx", "mjx_iterations1", "brax_generalized", "brax_positional"):
        r = peers.get(engine)
        if not isinstance(r, dict):
            continue
        if "error" in r:
            print(f"peer {engine:<18}: gradient fails: {str(r['error'])[:100]}")
        else:
            print(f"peer {engine:<18}: gradient/forward x{r.get('grad_over_forward', float('nan')):.2f}, "
                  f"finite {r.get('grad_finite')}, gradient {r.get('grad')} vs local finite difference "
                  f"{r.get('grad_fd_local')}")


def plot(record, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names, ratios = ["jaxrb reverse", "jaxrb jacfwd(3)"], [record["bounce"]["ratio_reverse_over_forward"],
                                                           record["bounce"]["ratio_jacfwd3_over_forward"]]
    if "bounce_one_thread_pool" in record:
        names.append("jaxrb reverse, one-thread pool")
        ratios.append(record["bounce_one_thread_pool"]["ratio_reverse_over_forward"])
    for engine, r in record.get("peers", {}).items():
        if isinstance(r, dict) and "error" not in r and r.get("grad_finite"):
            ratio = r.get("grad_over_forward")
            if isinstance(ratio, (int, float)):
                names.append(engine)
                ratios.append(ratio)
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.barh(names, ratios)
    ax.axvline(4.0, color="k", ls="--", lw=0.8, label="target 4x")
    ax.set_xlabel("gradient time / forward time, ball drop")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=1000, help="bouncing-ball rollout length")
    p.add_argument("--long-steps", type=int, default=100_000, help="checkpointed free-body rollout length")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-plain", action="store_true", help="skip the un-checkpointed long gradient")
    p.add_argument("--float32", action="store_true")
    p.add_argument("--peer-python", default=None)
    p.add_argument("--quick", action="store_true", help="tiny sizes, temp output dir (CI smoke run)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.float32 if args.float32 else jnp.float64
    if args.quick:
        args.steps, args.long_steps, args.repeats = 50, 400, 1
    out = args.out or (Path(tempfile.mkdtemp()) if args.quick else DEFAULT_OUT)
    out.mkdir(parents=True, exist_ok=True)
    record = {
        **record_header("gradients.py", argv),
        "dtype": str(jnp.dtype(dtype)),
    }
    record["bounce"] = bounce(args.steps, args.repeats, dtype)
    progress("the ball's ratio again, in a fresh process with the peers' one-thread XLA pool")
    record["bounce_one_thread_pool"] = bounce_in_one_thread_pool(args)
    progress(f"the free body's {args.long_steps}-step gradient, in a fresh process")
    record["free_body_long"] = long_in_fresh_process(args)
    if args.peer_python:
        progress("the peers, in their interpreter")
        record["peers"] = run_peers(args.peer_python, args.steps, args.repeats)
    print_table(record)
    write_results(out, "gradients", record, plot)
    return record


if __name__ == "__main__":
    main()
