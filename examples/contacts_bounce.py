"""A bouncing ball returns to e^(2n) of its drop height, whatever the time step.

A 1 kg ball of radius 0.1 m falls 1 m onto the ground with restitution e = 0.8. Each
impact multiplies the rebound speed by e, so the n-th apex is at e^(2n) m (0.64, 0.41,
0.26, ...). The contact step finds the time of impact inside the step and bounces there,
so the apexes do not depend on dt (the full run adds dt = 0.01 s without it). Apex: z +
vz^2 / 2g - r at the last sample before vz turns negative. Run ``python
examples/contacts_bounce.py`` (``--quick`` for CI; ``--out DIR`` also saves a plot).
"""

from __future__ import annotations

import argparse
import pathlib

import jax

jax.config.update("jax_enable_x64", True)  # the apexes are compared to 1e-12

import numpy as np  # noqa: E402

import jaxrb as rb  # noqa: E402

RADIUS, DROP, RESTITUTION, G = 0.1, 1.0, 0.8, 9.81


def bounce(dt: float, t_final: float, time_of_impact: bool = True):
    """Times, heights above the ground (m) and apex clearances (m) of one drop."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(RADIUS), mass=1.0)], ground=rb.Plane(), contacts="all")
    params = scene.params(restitution=RESTITUTION, friction=0.5)
    state = scene.state(params, position=(0.0, 0.0, RADIUS + DROP))
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), dt=dt,
                        contact=rb.ContactSettings(time_of_impact=time_of_impact))
    _, traj = rb.rollout(step, params, state, num_steps=round(t_final / dt))
    z, vz = np.asarray(traj.position[:, 0, 2]), np.asarray(traj.velocity[:, 0, 2])
    k = np.flatnonzero((vz[:-1] > 0) & (vz[1:] <= 0))
    return np.asarray(traj.time), z - RADIUS, z[k] + vz[k] ** 2 / (2 * G) - RADIUS


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="CI size: 4 bounces, no run without time of impact")
    parser.add_argument("--out", type=pathlib.Path, help="save contacts_bounce.png in this directory")
    args = parser.parse_args(argv)
    bounces, t_final = (4, 2.5) if args.quick else (8, 4.0)
    runs = {"dt=0.01": (1e-2, True), "dt=1/60": (1 / 60, True)}
    if not args.quick:
        runs["dt=0.01 no TOI"] = (1e-2, False)
    results = {name: bounce(dt, t_final, toi) for name, (dt, toi) in runs.items()}
    theory = RESTITUTION ** (2 * np.arange(1, bounces + 1)) * DROP

    print(f"apex clearance (m) after n bounces, e = {RESTITUTION}, dropped from {DROP} m")
    print(f"{'n':>2} {'e^(2n)':>10} " + " ".join(f"{name:>15}" for name in results))
    for n, h in enumerate(theory):
        row = " ".join(f"{r[2][n]:15.6f}" if n < len(r[2]) else f"{'-':>15}" for r in results.values())
        print(f"{n + 1:2d} {h:10.6f} {row}")
    for name, (_, _, apex) in results.items():
        m = min(bounces, len(apex))
        print(f"{name:<15} max |apex - e^(2n)| over {m} bounces = {np.max(np.abs(apex[:m] - theory[:m])):.1e} m")

    if args.out is not None:
        from matplotlib.figure import Figure  # Agg, no pyplot state

        fig = Figure(figsize=(8, 4), layout="constrained")
        ax = fig.subplots()
        for name, (t, height, _) in results.items():
            ax.plot(t, height, lw=1, label=name)
        for h in theory:
            ax.axhline(h, color="0.6", lw=0.6, ls=":")
        ax.set(xlabel="time (s)", ylabel="clearance (m)", title="dotted: e^(2n) m"), ax.legend()
        args.out.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.out / "contacts_bounce.png", dpi=120)
        print(f"plot saved to {args.out / 'contacts_bounce.png'}")
    return {"theory": theory, **{name: r[2] for name, r in results.items()}}


if __name__ == "__main__":
    main()
