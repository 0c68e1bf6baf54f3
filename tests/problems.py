"""Test problems shared by several test files (jaxrb scenes with their scipy-side definitions)."""

import jax.numpy as jnp
import numpy as np

import jaxrb as rb
from jaxrb import spatial


def forced_setup():
    """One body under time-dependent world force and torque (no gravity).

    Returns ``(scene, params, state, args)`` with ``args = (mass, inertia, force_np,
    torque_np, x0, v0, q0, l0)``, the inputs of ``reference.forced_body_world_frame``.
    """
    mass = 1.5
    inertia = np.array([[2.0, 0.3, 0.0], [0.3, 1.5, 0.1], [0.0, 0.1, 3.0]])

    def force_np(t):
        return np.array([np.sin(3 * t), np.cos(2 * t), 0.5 * t])

    def torque_np(t):
        return np.array([0.5 * np.cos(t), -0.3 * np.sin(2 * t), 0.2])

    def wrench(t, params, state):
        force = jnp.stack([jnp.sin(3 * t), jnp.cos(2 * t), 0.5 * t])[None]
        torque = jnp.stack([0.5 * jnp.cos(t), -0.3 * jnp.sin(2 * t), 0.2 + 0.0 * t])[None]
        return force, torque

    scene = rb.Scene([rb.Body("body", mass=mass, inertia=inertia)], gravity=None, forces=[rb.ExternalWrench(wrench)])
    params = scene.params()
    x0, v0, l0 = np.array([0.1, 0.2, 0.3]), np.array([1.0, 0.0, -0.5]), np.array([0.5, 2.0, -1.0])
    q0 = np.asarray(spatial.quat_from_axis_angle(jnp.array([1.0, -1.0, 0.5]), 0.8))
    state = scene.state(params, position=x0, velocity=v0, orientation=q0, angular_momentum=l0, time=0.0)
    return scene, params, state, (mass, inertia, force_np, torque_np, x0, v0, q0, l0)
