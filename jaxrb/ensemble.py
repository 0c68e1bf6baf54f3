"""Ensembles over several devices: split the ensemble axis with ``jax.sharding``.

A jaxrb ensemble is ``jax.vmap`` over params and/or state, whose arrays then carry a
leading ensemble axis of length ``E``. :func:`shard_ensemble` places those arrays so
that each device holds ``E / D`` of the environments; ``jax.jit`` then runs the
unchanged vmapped step or rollout on every device at once (SPMD). The environments are
independent, and a free body's step needs no communication between devices. A step that
can skip work (a contact scene's free branch, converged sweeps, the impact pass; an
implicit integrator's Newton iterations) skips it only where no member of the whole
ensemble needs it (``jaxrb/_branch.py``): that test is an all-reduce across the devices
at every step (68 in a sharded rollout of balls on the ground), and each device runs a
branch that a member on any device takes. The values are those of one device.

On a CPU, JAX shows one device by default and a compiled step runs on one core. To use
every core, ask for several CPU devices *before the first JAX computation*::

    jax.config.update("jax_num_cpu_devices", 2)   # or XLA_FLAGS=--xla_force_host_platform_device_count=2

jaxrb never changes this setting itself (as with ``jax_enable_x64``): it is a property
of the user's process. ``benchmarks/free_body.py --devices 2`` measures the gain.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["shard_ensemble"]

ENSEMBLE_AXIS = "ensemble"


def shard_ensemble(tree: Any, devices: Sequence[jax.Device] | None = None) -> Any:
    """Spread the leading (ensemble) axis of every array in ``tree`` over ``devices``.

    Args:
        tree: a pytree of arrays that all have the same leading ensemble axis ``E``,
            e.g. batched :class:`jaxrb.Params` and :class:`jaxrb.State`. ``None``
            leaves are kept.
        devices: the devices to use (a sequence, or one device); default
            ``jax.devices()`` (all of them). ``E`` must be a multiple of their number.

    Returns:
        The same pytree, with each array split along axis 0 into ``len(devices)``
        equal blocks, one per device. Values are unchanged; ``jax.jit(jax.vmap(f))``
        applied to it runs on all the devices and returns sharded results.
    """
    if isinstance(devices, jax.Device):  # one device given bare: 'Device' object is not iterable
        devices = [devices]
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("shard_ensemble needs at least one device.")
    leaves = jax.tree.leaves(tree)
    if not leaves:
        raise ValueError("shard_ensemble got a pytree with no arrays.")
    sizes = {np.shape(x)[0] if np.ndim(x) else None for x in leaves}
    if None in sizes:
        raise ValueError(
            "shard_ensemble needs every array to have a leading ensemble axis, but some are "
            "scalars. Batch params and state first, e.g. with jax.vmap or "
            "jax.tree.map(lambda x: jnp.broadcast_to(x, (E, *x.shape)), tree)."
        )
    if len(sizes) != 1:
        raise ValueError(
            f"shard_ensemble needs one ensemble size, but the leading axes are {sorted(sizes)}. "
            "Batch every array of params and state to the same number of environments."
        )
    (size,) = sizes
    if size % len(devices):
        raise ValueError(
            f"The ensemble has {size} environments, which does not split evenly over "
            f"{len(devices)} devices. Use a multiple of {len(devices)} environments."
        )
    mesh = Mesh(np.asarray(devices), (ENSEMBLE_AXIS,))
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec(ENSEMBLE_AXIS)))
