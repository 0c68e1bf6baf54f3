"""Static tables and gathers by static indices, with no captured array constant.

``x[np.array([...])]`` or ``jnp.asarray(table)`` captures an array constant in the jaxpr. Inside a
differentiated ``lax.cond`` (the contact step's branches, a rollout's free-or-contact
chunks) every constant the backward pass needs becomes a residual: JAX's partial
evaluation of ``cond`` does not forward its operands, so the forward ``cond`` outputs a
copy of each, and a rollout's loop stacks those copies at every iteration. A slice with
static bounds carries no constant, nor does a stack of scalars (each a literal).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["literal_array", "take_rows"]


def take_rows(x: jax.Array, indices: Sequence[int] | np.ndarray) -> jax.Array:
    """``x[indices]`` along the leading axis, for static ``0 <= indices < len(x)`` (1-D).

    Built from static slices: a run of consecutive rows is one slice, a repeated row one
    broadcast, and the runs are concatenated. Meant for the short, structured index lists
    of a scene's contact layout (a few runs); a long irregular list would make one slice
    per row.
    """
    idx = [int(i) for i in np.asarray(indices).reshape(-1)]
    n = x.shape[0]
    if any(not 0 <= i < n for i in idx):
        raise IndexError(f"take_rows: indices {idx} out of range for {n} rows.")
    pieces, start = [], 0
    while start < len(idx):
        stop = start + 1
        if stop < len(idx) and idx[stop] == idx[start]:  # a repeated row
            while stop < len(idx) and idx[stop] == idx[start]:
                stop += 1
            pieces.append(jnp.broadcast_to(x[idx[start]:idx[start] + 1], (stop - start, *x.shape[1:])))
        else:  # consecutive rows
            while stop < len(idx) and idx[stop] == idx[stop - 1] + 1:
                stop += 1
            pieces.append(x[idx[start]:idx[stop - 1] + 1])
        start = stop
    if not pieces:
        return x[:0]
    return pieces[0] if len(pieces) == 1 else jnp.concatenate(pieces)


def literal_array(values, dtype=jnp.int32) -> jax.Array:
    """The array of static ``values`` (any shape) as ``dtype``, built from scalars so that no
    array constant is captured: each scalar is a literal of the jaxpr, and XLA folds the
    stack back into one constant. For the small fixed tables of the contact code (a
    layout's indices, a box's half extents and corner signs, a plane's normal)."""
    array = np.asarray(values)
    if array.size == 0:
        return jnp.zeros(array.shape, dtype)
    return jnp.stack([jnp.asarray(v.item(), dtype) for v in array.reshape(-1)]).reshape(array.shape)
