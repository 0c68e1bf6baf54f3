"""Reproduction of a fixed bug: a member of a vmapped float32 step turned NaN.

Two members of ``benchmarks/fuzz_contacts.py``'s box-box-can pen (float32, seed 1, cases
20 and 25 of 32), at the states a 4-member ensemble reached after 355 steps
(``vmap_forward_nan_bby.npz``, saved 2026-12-06). Until stop 86, member 1 stepped alone
was finite, and in any batch of two (beside member 0, or beside itself) its next state
was NaN: the batched compilation rounded one sliding slot's approach to -4.6e-22 m/s
(a rounding: the unbatched step stayed finite), and the Coulomb search of the impact
law bracketed its multiplier at 1.5e21, whose square overflowed (see ``jaxrb.contact._coulomb.coulomb_impulse`` and
``tests/test_contact.py::test_an_approach_below_rounding_gives_no_impulse_and_no_nan``).
Prints each member's finiteness, alone and together: all ``True`` since the fix (before
it, ``[True]``, ``[True]``, ``[True, False]``).

    python benchmarks/repro/vmap_forward_nan_bby.py
"""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrb as rb

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # benchmarks/ is not a package
from fuzz_contacts import pen  # noqa: E402


def load(step, scene):
    """The saved params and states, stacked over the two members."""
    saved = np.load(HERE / "vmap_forward_nan_bby.npz")
    params = scene.params(dtype=jnp.float32)
    state = step.prepare(scene.state(params, dtype=jnp.float32))
    trees = []
    for prefix, tree in (("params", params), ("state", state)):
        paths, treedef = jax.tree_util.tree_flatten_with_path(tree)
        leaves = [jnp.asarray(saved[prefix + jax.tree_util.keystr(path)]) for path, _ in paths]
        trees.append(jax.tree_util.tree_unflatten(treedef, leaves))
    return trees


def main() -> dict:
    scene = pen("bby")
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3, contact=rb.ContactSettings())
    params, state = load(step, scene)
    vstep = jax.jit(jax.vmap(step))
    finite = {}
    for members in ((1,), (0,), (0, 1)):
        index = np.asarray(members)
        out = vstep(*jax.tree.map(lambda x, index=index: x[index], (params, state)))
        finite[members] = np.isfinite(np.asarray(out.position)).all(axis=(1, 2)).tolist()
        print(f"members {members}: next position finite {finite[members]}")
    return finite


if __name__ == "__main__":
    main()
