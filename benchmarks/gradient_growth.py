"""Where does a rollout's gradient grow? A step-by-step reverse walk over resting scenes.

A whole rollout's gradient compiles slowly (minutes for a few boxes) and reports only its
final value. This script instead runs the rollout step by step, keeps every state, and walks
one jitted single-step VJP backwards from the cotangent of ``sum(final z)``. For each step it
records how much the state cotangent grew, so a blow-up (or the first NaN) is pinned to the
step and the state that made it; ``--jacobian K`` then compares that step's forward-mode
Jacobian with central differences of the float64 step at the same state.

In a resting scene each entry of ``d sum(z_final) / d z_initial`` is 1 or 0 (one-sided): a
cube pushed into its support by less than ``ContactSettings.correction_slop`` stays there,
one lifted falls back. Started exactly touching, rounding can leave a float64 scene on
either side of that kink from step to step, and the entries blend the two (``--lift=-1e-9``
starts every cube 1 nm in). A tower's bottom cube may reach the number of cubes in the
tower (pushed down, it takes those above with it). Entries far beyond that are wrong:
stops 94 and 95 found 5e10 and 3e7.

    python benchmarks/gradient_growth.py                 # all scenes, float32, 200 steps
    python benchmarks/gradient_growth.py grid_rot30 --steps 100 --jacobian 2
    JAX_ENABLE_X64=1 python benchmarks/gradient_growth.py tower3 --dtype float64

Prints one table row per scene (largest entry of the state gradient, the first non-finite
step walking back, the three steps with the largest growth) and writes
``gradient_growth.json`` and ``gradient_growth.png`` (the largest cotangent entry against the
step, walking back) to ``--out`` (default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxrb as rb

H = 0.05  # m, cube half extent


def _cubes(positions, angle=0.0):
    """Cubes of 1 kg at ``positions``, the whole set turned by ``angle`` about z."""
    c, s = math.cos(angle), math.sin(angle)
    turned = [(c * x - s * y, s * x + c * y, z) for x, y, z in positions]
    quat = [(math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2))] * len(positions)
    bodies = [rb.Body(f"b{i}", shape=rb.Box((H, H, H)), mass=1.0) for i in range(len(positions))]
    return bodies, dict(position=turned, orientation=quat)


def _scene(name):
    """``(bodies, initial pose)`` of a named resting scene."""
    if name == "two_cubes":
        return _cubes([(-H, 0, H), (H, 0, H)])
    if name == "tower3":
        return _cubes([(0, 0, H), (0, 0, 3 * H), (0, 0, 5 * H)])
    if name == "bridge":
        return _cubes([(-H, 0, H), (H, 0, H), (0, 0, 3 * H)])
    if name in ("grid", "grid_rot30"):
        angle = math.radians(30) if name == "grid_rot30" else 0.0
        return _cubes([(-H, -H, H), (H, -H, H), (-H, H, H), (H, H, H)], angle)
    if name == "row_rot30":
        return _cubes([(-H, 0, H), (H, 0, H)], math.radians(30))
    if name == "cube_rot30":
        return _cubes([(0, 0, H)], math.radians(30))
    raise ValueError(f"unknown scene {name!r}; choose from {SCENES}")


SCENES = ("two_cubes", "tower3", "bridge", "grid", "grid_rot30", "row_rot30", "cube_rot30")


def build(name, dtype, solver="pgs", lift=0.0):
    """``(step, params, prepared state)`` of a named scene; ``lift`` (m) is added to every
    initial height (negative: the cubes start that far into the ground and each other's
    planes stay flush)."""
    bodies, pose = _scene(name)
    pose["position"] = [(x, y, z + lift) for x, y, z in pose["position"]]
    scene = rb.Scene(bodies, ground=rb.Plane(), contacts="all")
    params = scene.params(friction=0.5, restitution=0.0, dtype=dtype)
    state = scene.state(params, **pose)
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), dt=1e-3,
                        contact=rb.ContactSettings(solver=solver))
    return step, params, step.prepare(state)


def _size(tree):
    """Largest absolute entry over a pytree's float leaves (NaN if any is NaN)."""
    leaves = [np.asarray(x) for x in jax.tree.leaves(tree) if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)]
    flat = np.concatenate([x.ravel() for x in leaves])
    return float(np.nan) if not np.all(np.isfinite(flat)) else float(np.max(np.abs(flat)))


def walk(name, dtype, steps, solver="pgs", lift=0.0):
    """Forward step by step, then the reverse walk. Returns a result dict and the states."""
    step, params, state = build(name, dtype, solver, lift)
    one = jax.jit(step)
    states = [state]
    for _ in range(steps):
        states.append(one(params, states[-1]))

    @jax.jit
    def back(p, s, ct):
        return jax.vjp(step, p, s)[1](ct)

    final = states[-1]
    ct = jax.tree.map(jnp.zeros_like, final)
    ct = ct.replace(position=ct.position.at[:, 2].set(1.0))
    growth, sizes, first_bad = [], [], None
    gp = jax.tree.map(jnp.zeros_like, params)
    for k in range(steps - 1, -1, -1):
        before = _size(ct)
        dp, ct = back(params, states[k], ct)
        gp = jax.tree.map(jnp.add, gp, dp)
        after = _size(ct)
        if math.isnan(after) and first_bad is None:
            first_bad = k
        growth.append((k, after / before if before > 0 else float("nan")))
        sizes.append(after)
        if first_bad is not None:
            break
    top = sorted((g for g in growth if math.isfinite(g[1])), key=lambda g: -g[1])[:3]
    drift = float(np.max(np.abs(np.asarray(final.position - states[0].position))))
    return dict(
        scene=name, dtype=str(jnp.dtype(dtype)), solver=solver, steps=steps, lift=lift,
        largest_state_gradient=_size(ct), largest_param_gradient=_size(gp),
        dz0=np.asarray(ct.position[:, 2]).tolist(),
        first_nonfinite_step=first_bad, top_growth=[(k, round(g, 3)) for k, g in top],
        forward_drift_m=drift, cotangent_size=sizes,
    ), states, (step, params)


def jacobian_check(name, states, k, eps=1e-7):
    """Step ``k``'s Jacobian d(position, velocity, L)_out / d(position, velocity, L)_in:
    forward mode at the stored (float32) state and at the same state in float64, and float64
    central differences. Prints the largest entries and their disagreements."""
    fields = ("position", "velocity", "angular_momentum")
    out = {}
    for dtype in (jnp.float32, jnp.float64):
        step, params, _ = build(name, dtype)
        s = jax.tree.map(lambda x, d=dtype: x.astype(d) if jnp.issubdtype(x.dtype, jnp.floating) else x, states[k])

        def f(flat, s=s, step=step, params=params):
            parts = jnp.split(flat, 3)
            s2 = s.replace(**{n: p.reshape(-1, 3) for n, p in zip(fields, parts, strict=True)})
            o = step(params, s2)
            return jnp.concatenate([getattr(o, n).ravel() for n in fields])

        x0 = jnp.concatenate([getattr(s, n).ravel() for n in fields])
        out[str(jnp.dtype(dtype))] = np.asarray(jax.jit(jax.jacfwd(f))(x0))
        if dtype == jnp.float64:
            fj = jax.jit(f)
            cols = [(np.asarray(fj(x0.at[i].add(eps))) - np.asarray(fj(x0.at[i].add(-eps)))) / (2 * eps)
                    for i in range(x0.size)]
            out["central64"] = np.stack(cols, axis=1)
    j32, j64, fd = out["float32"], out["float64"], out["central64"]
    n = j32.shape[0] // 3
    label = [f"{f[:3]}[{b},{'xyz'[c]}]" for f in fields for b in range(n // 3) for c in range(3)]
    print(f"step {k}: max|J32| {np.max(np.abs(j32)):.3g}  max|J64| {np.max(np.abs(j64)):.3g}  "
          f"max|FD64| {np.max(np.abs(fd)):.3g}")
    for tag, a, b in (("J32 - J64", j32, j64), ("J64 - FD64", j64, fd)):
        d = np.abs(a - b)
        i, j = np.unravel_index(np.argmax(d), d.shape)
        print(f"  {tag}: largest {d[i, j]:.3g} at d {label[i]} / d {label[j]} ({a[i, j]:.4g} vs {b[i, j]:.4g})")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    ap.add_argument("--solver", default="pgs")
    ap.add_argument("--lift", type=float, default=0.0, help="m added to every initial height")
    ap.add_argument("--jacobian", type=int, default=None, help="compare this step's Jacobian (needs x64)")
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path(__file__).parent / "results")
    args = ap.parse_args(argv)
    if args.jacobian is not None:
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.dtype(args.dtype)
    rows = []
    print(f"{'scene':12s} {'dtype':8s} {'max|dL/ds0|':>12s} {'first NaN':>9s}  largest growth (step, x)   dz0")
    for name in args.scenes:
        t = time.perf_counter()
        r, states, _ = walk(name, dtype, args.steps, args.solver, args.lift)
        r["seconds"] = round(time.perf_counter() - t, 1)
        rows.append(r)
        print(f"{name:12s} {r['dtype']:8s} {r['largest_state_gradient']:12.4g} "
              f"{str(r['first_nonfinite_step']):>9s}  {r['top_growth']}  "
              f"{np.round(r['dz0'], 3).tolist()}", flush=True)
        if args.jacobian is not None:
            jacobian_check(name, states, args.jacobian)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "gradient_growth.json").write_text(json.dumps(rows, indent=1))
    plot(rows, args.out / "gradient_growth.png")
    print(f"wrote {args.out / 'gradient_growth.json'} and .png")
    return rows


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for r in rows:
        steps = np.arange(r["steps"] - 1, r["steps"] - 1 - len(r["cotangent_size"]), -1)
        ax.semilogy(steps, r["cotangent_size"], label=f"{r['scene']} ({r['dtype']})")
    finite = [v for r in rows for v in r["cotangent_size"] if np.isfinite(v) and v > 0]
    if finite:  # at least a decade either side of 1, so that a flat 1.0 reads as one
        ax.set_ylim(min(0.1, min(finite) / 2), max(10.0, 2 * max(finite)))
    ax.set_xlabel("step k (walking back from the last)")
    ax.set_ylabel("largest entry of d sum(z_final) / d state_k")
    ax.invert_xaxis()
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
