"""A fixed bug, kept as a check: a NaN gradient through four cubes touching in a 2x2 grid.

Four 0.1 m cubes of 1 kg on the ground, faces flush, meeting at one vertical edge (so the
diagonal pairs touch along that edge only), friction 0.5, float32, ``SymplecticSplitting``,
PGS, dt = 1 ms. The forward rollout is finite and the cubes rest. The gradient of the sum
of the final heights with respect to params and the initial state was finite after 1 step
and all NaN after 100 (found by stop 93's review).

Cause (stop 94): the PGS friction step projects the wanted tangential impulse ``w`` onto
the disk ``|w| <= mu lambda_n`` by ``r / sqrt(|w|^2)``. At a slot that touches without
pushing (``lambda_n = 0``, so ``r = 0``) with a tiny ``w`` (1e-14 N s), JAX's derivative of
the reciprocal square root, ``-q^(-3/2)/2``, overflowed in float32 and was multiplied by
``r = 0``: NaN in the sweep's Jacobian, and (through a NaN that the frozen derivative's
contraction test let through) in the whole gradient. Found by running the rollout step by
step with each step's VJP, then ``jax.experimental.checkify`` on the first bad step. Fixed
by a derivative rule for the projection whose factors are all bounded
(``jaxrb.contact._solver._onto_disk``), and a frozen Jacobian must now be finite.
Tests: ``tests/test_contact.py::test_a_slot_touching_without_pushing_has_a_finite_solve_derivative``
and ``::test_friction_projection_has_a_bounded_derivative``. This scene's gradient compiles
in about 2 minutes on an idle 2-core machine, too slow for the suite.

    python benchmarks/repro/grid_gradient_nan.py [steps]   # default 100; exit status 1 on a NaN
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
    sys.exit(0 if main(int(sys.argv[1]) if len(sys.argv) > 1 else 100) else 1)
