"""Reproduction of an open bug: a NaN gradient through four cubes touching in a 2x2 grid.

Four 0.1 m cubes of 1 kg on the ground, faces flush, meeting at one vertical edge (so the
diagonal pairs touch along that edge only), friction 0.5, float32, ``SymplecticSplitting``,
PGS, dt = 1 ms. The forward rollout is finite and the cubes rest. The gradient of the sum
of the final heights with respect to params and the initial state is finite after 1 step
and all NaN after 100 (found by stop 93's review; compiled in 523 s on a loaded 2-core
machine). The same grid 1e-4 m apart gives finite gradients (0, 0, 1 per body), as do the
diagonal pair alone and three cubes in a row. Removing the box-box manifold's duplicate
slots (the diagonal pairs' edge contact gives the same point twice) does not remove the
NaN, so that is not its cause. Not yet found: bisect the step count, then the step's
pieces (``jax.config.update("jax_debug_nans", True)`` on the gradient).

    python benchmarks/repro/grid_gradient_nan.py [steps]   # default 100; prints finiteness
"""

import sys

import jax
import jax.numpy as jnp
import numpy as np

import jaxrb as rb

H = 0.05  # m, half extent


def main(steps: int = 100) -> bool:
    box = rb.Box((H, H, H))
    scene = rb.Scene([rb.Body(f"b{i}", shape=box, mass=1.0) for i in range(4)], ground=rb.Plane(), contacts="all")
    params = scene.params(friction=0.5, restitution=0.0, dtype=jnp.float32)
    state = scene.state(params, position=[(-H, -H, H), (H, -H, H), (-H, H, H), (H, H, H)])
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), dt=1e-3)
    state = step.prepare(state)

    def loss(p, s):
        final, _ = rb.rollout(step, p, s, steps)
        return jnp.sum(final.position[:, 2])

    forward = jax.jit(loss)(params, state)
    grads = jax.jit(jax.grad(loss, argnums=(0, 1)))(params, state)
    finite = {name: bool(np.all(np.isfinite(np.asarray(leaf))))
              for name, leaf in zip(("params", "state"), (jax.tree.leaves(grads[0]), jax.tree.leaves(grads[1])),
                                    strict=True)
              for leaf in [np.concatenate([np.ravel(x) for x in leaf])]}
    print(f"{steps} steps: forward {float(forward):.6f} (finite {bool(np.isfinite(forward))}); "
          f"gradient finite: {finite}")
    return all(finite.values())


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 100)
