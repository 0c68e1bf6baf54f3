"""Checks of static arguments: switches, counts and the step length fix a compiled
program's structure, so they are plain Python values, checked before anything is traced."""

from __future__ import annotations

import math
import numbers

import jax
import numpy as np

__all__ = ["positive_count", "static_step_length", "static_switch"]


def static_switch(name: str, value) -> bool:
    """``value`` as a Python bool, or a ``ValueError``: a static switch takes ``True`` or
    ``False`` (numpy's too), not any value Python would call true (``"no"`` is), nor a JAX
    array (it would be traced inside the rollout's jit)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False (a static switch), got {value!r}.")
    return bool(value)


def positive_count(name: str, value) -> int:
    """``value`` as a Python int: a whole number >= 1 of any integer type (``np.int64`` from a
    config array too; not a bool, not a float), at most ``2**31 - 1`` (the counts become loop
    lengths and int32 counters; 2**70 had passed here and failed later with an
    ``OverflowError`` naming no input), or a ``ValueError``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}.")
    if value > _LARGEST_COUNT:
        raise ValueError(f"{name} = {value!r} is too large: counts are at most 2**31 - 1 = {_LARGEST_COUNT}.")
    return int(value)


_LARGEST_COUNT = 2**31 - 1


def static_step_length(dt, where: str) -> float:
    """``dt`` (s) as a positive, finite Python float, or a ``ValueError`` that says what is wrong."""
    if isinstance(dt, jax.core.Tracer):
        raise ValueError("dt is static (a Python float): it cannot be traced or differentiated, and each "
                         f"new value compiles a new step. Call {where} outside jit/grad/vmap.")
    try:
        if isinstance(dt, (str, bytes)):  # float("0.01") would pass
            raise TypeError
        dt = float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}.") from None
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive, finite number of seconds, got {dt}.")
    return dt
