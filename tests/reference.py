"""Independent reference solutions (scipy, closed forms) for the dynamics tests.

Nothing here imports jaxrb: the references must not share code with what they check.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp


def _qmul(p, q):
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ])


def quat_to_matrix(q):
    q = np.asarray(q, dtype=float) / np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def torque_free_body_frame(inertia_diag, omega0_body, q0, times, rtol=1e-13, atol=1e-14):
    """Euler's equations ``I w' = -w x I w`` in the body frame with ``q' = q (0, w) / 2``.

    Integrated by scipy's DOP853 at tight tolerance. Returns ``(omega_body (T, 3),
    q (T, 4))`` at ``times``. This is the omega-form in the body frame, a different
    formulation from jaxrb's world-frame L-form, so agreement is a real check.
    """
    inertia = np.asarray(inertia_diag, dtype=float)

    def rhs(_, y):
        w = y[:3]
        q = y[3:]
        dw = -np.cross(w, inertia * w) / inertia
        dq = 0.5 * _qmul(q, np.concatenate([[0.0], w]))
        return np.concatenate([dw, dq])

    y0 = np.concatenate([np.asarray(omega0_body, float), np.asarray(q0, float)])
    sol = solve_ivp(rhs, (0.0, float(times[-1])), y0, method="DOP853", t_eval=times,
                    rtol=rtol, atol=atol)
    assert sol.success
    q = sol.y[3:].T
    return sol.y[:3].T, q / np.linalg.norm(q, axis=1, keepdims=True)


def symmetric_top_attitude(i_perp, i_axis, omega0_body, t):
    """Closed-form attitude of a torque-free symmetric top, ``I = diag(i_perp, i_perp, i_axis)``.

    Starting from the identity, the motion is a steady precession about the fixed
    angular momentum ``L`` at rate ``|L| / i_perp`` composed with a spin about the body
    symmetry axis at rate ``L3 (1/i_axis - 1/i_perp)``:
    ``R(t) = Rot(L/|L|, |L| t / i_perp) Rot(e3, L3 (1/i_axis - 1/i_perp) t)``.
    (Differentiate: ``R^T R' = I^-1 R^T L`` -- the body angular velocity.)
    """
    w = np.asarray(omega0_body, float)
    l_vec = np.array([i_perp * w[0], i_perp * w[1], i_axis * w[2]])
    l_norm = np.linalg.norm(l_vec)
    return _axis_angle_matrix(l_vec / l_norm, l_norm * t / i_perp) @ _axis_angle_matrix(
        np.array([0.0, 0.0, 1.0]), l_vec[2] * (1.0 / i_axis - 1.0 / i_perp) * t
    )


def _axis_angle_matrix(axis, angle):
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def rotation_angle(r_a, r_b):
    """atan2 form of the angle of ``R_a^T R_b`` (accurate for tiny angles)."""
    m = r_a.T @ r_b
    s = 0.5 * np.linalg.norm([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    c = 0.5 * (np.trace(m) - 1.0)
    return float(np.arctan2(s, c))


def first_sign_change(times, values):
    """Time of the first sign change of ``values``, by linear interpolation."""
    s = np.sign(values)
    idx = np.flatnonzero(s[1:] != s[:-1])[0]
    t0, t1, v0, v1 = times[idx], times[idx + 1], values[idx], values[idx + 1]
    return t0 - v0 * (t1 - t0) / (v1 - v0)


def forced_body_world_frame(mass, inertia_body, force_fn, torque_fn, x0, v0, q0, l0, times,
                            rtol=1e-13, atol=1e-14):
    """A body under time-dependent world force ``F(t)`` and torque ``tau(t)`` (about the com).

    ``x' = v``, ``v' = F/m``, ``L' = tau``, ``q' = (0, w) q / 2`` with
    ``w = R I_body^-1 R^T L``, by scipy's DOP853. Returns ``(x, v, q, L)`` at ``times``.
    """
    inertia_inv = np.linalg.inv(np.asarray(inertia_body, float))

    def rhs(t, y):
        v, q, l_world = y[3:6], y[6:10], y[10:]
        r = quat_to_matrix(q)
        omega = r @ inertia_inv @ r.T @ l_world
        dq = 0.5 * _qmul(np.concatenate([[0.0], omega]), q)
        return np.concatenate([v, force_fn(t) / mass, dq, torque_fn(t)])

    y0 = np.concatenate([x0, v0, q0, l0]).astype(float)
    sol = solve_ivp(rhs, (0.0, float(times[-1])), y0, method="DOP853", t_eval=times, rtol=rtol, atol=atol)
    assert sol.success
    y = sol.y.T
    return y[:, :3], y[:, 3:6], y[:, 6:10] / np.linalg.norm(y[:, 6:10], axis=1, keepdims=True), y[:, 10:]
