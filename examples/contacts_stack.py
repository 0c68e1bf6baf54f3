"""Resting contact and simultaneous impacts: a stack of boxes and Newton's cradle.

* Five 1 kg cubes (half-extent 0.1 m) stacked on the ground should stay exactly where they
  are. The ``"exact"`` solver solves the normal impulses of all contacts as one LCP; PGS
  (20 sweeps) converges slowly down a stack, so the boxes sink into each other a little
  before the penetration correction holds them.
* Newton's cradle: five touching balls, e = 1, no friction, no gravity. k balls moving at
  1 m/s into the others leave k balls moving at 1 m/s out of the far end.
Run ``python examples/contacts_stack.py`` (2 s at dt = 1 ms; ``--quick`` for CI: 0.5 s at
dt = 10 ms, where both solvers drift more but differ just as clearly).
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxrb as rb  # noqa: E402

HALF, RADIUS, COUNT = 0.1, 0.1, 5


def stack(solver: str, dt: float, t_final: float) -> tuple[float, float, float]:
    """Largest sink (m), largest sideways drift (m) of any box over the run, and wall time (s)."""
    scene = rb.Scene([rb.Body(f"box{i}", shape=rb.Box((HALF,) * 3), mass=1.0) for i in range(COUNT)],
                     ground=rb.Plane(), contacts="all")
    params = scene.params(friction=0.5)
    start = np.array([(0.0, 0.0, HALF * (2 * i + 1)) for i in range(COUNT)])
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), dt=dt, contact=rb.ContactSettings(solver=solver))
    tic = time.perf_counter()
    _, traj = rb.rollout(step, params, scene.state(params, position=start), num_steps=round(t_final / dt))
    moved = np.asarray(traj.position) - start
    return -np.min(moved[..., 2]), np.max(np.linalg.norm(moved[..., :2], axis=-1)), time.perf_counter() - tic


def cradle(moving: int, steps: int = 3) -> np.ndarray:
    """x velocities (m/s) of the five balls after ``steps`` steps of 10 ms, ``moving`` launched."""
    scene = rb.Scene([rb.Body(f"ball{i}", shape=rb.Sphere(RADIUS), mass=1.0) for i in range(COUNT)],
                     contacts="all", gravity=None)
    params = scene.params(restitution=1.0, friction=0.0)
    velocity = np.zeros((COUNT, 3))
    velocity[:moving, 0] = 1.0
    position = np.array([(2 * RADIUS * i, 0.0, 0.0) for i in range(COUNT)])
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), dt=1e-2, contact=rb.ContactSettings())
    final, _ = rb.rollout(step, params, scene.state(params, position=position, velocity=velocity), num_steps=steps)
    return np.asarray(final.velocity[:, 0])


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="CI size: 0.5 s at dt = 10 ms")
    dt, t_final = (1e-2, 0.5) if parser.parse_args(argv).quick else (1e-3, 2.0)
    print(f"{COUNT}-box stack, {t_final} s at dt = {dt} s: largest displacement of any box")
    print(f"{'solver':<7} {'sink (m)':>10} {'sideways (m)':>13} {'wall (s, with compile)':>23}")
    out = {}
    for solver in ("exact", "pgs"):
        out[solver] = stack(solver, dt, t_final)
        print(f"{solver:<7} {out[solver][0]:10.1e} {out[solver][1]:13.1e} {out[solver][2]:23.1f}")

    print("\nNewton's cradle: x velocities (m/s) after 3 steps of 10 ms")
    for moving in (1, 2, 3):
        out[f"cradle_{moving}"] = v = cradle(moving)
        print(f"{moving} in: " + " ".join(f"{x + 0.0:6.3f}" for x in v.round(6))
              + f"   momentum {v.sum():.6f}, energy {0.5 * v @ v:.6f} J")
    return out


if __name__ == "__main__":
    main()
