"""Closed-form reference motions for validating integrators (float64 numpy + scipy).

Two classical exact solutions of rigid-body dynamics:

- :func:`torque_free_top`: the free asymmetric body (Euler–Poinsot), with ω(t) from
  Jacobi elliptic functions and the attitude from one smooth scalar quadrature.
- :func:`heavy_symmetric_top`: the Lagrange top on a fixed pivot, with cos θ(t) from
  Jacobi elliptic functions and φ(t), ψ(t) from smooth scalar quadratures.

This module deliberately imports nothing from jaxrb: a reference must not share code
with what it checks. It needs scipy, which jax itself requires (``import jaxrb``
imports this module as ``rb.exact``); without it, importing this module says so.
Conventions: SI units; quaternions scalar first ``(w, x, y, z)`` mapping
body to world; rotation matrices hold the body axes as columns (``v_world = R v_body``).

References: L. D. Landau & E. M. Lifshitz, *Mechanics*, §§35–37 (Euler's equations,
elliptic solution, Euler angles of the free top); H. Goldstein, *Classical Mechanics*,
3rd ed., §5.7 (heavy symmetric top, the cubic f(u)); DLMF §22 (Jacobi functions).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

try:
    from scipy.special import ellipj, ellipk, ellipkinc, ellipkm1
except ImportError as err:  # jax requires scipy, so this is for an unusual install
    raise ImportError("jaxrb.exact needs scipy: pip install scipy") from err

# 16-point Gauss–Legendre on panels at most 0.5 wide in the elliptic argument τ: the
# integrands below are analytic in a strip of half-width >= 0.5 around the real τ axis
# (poles at ±iK' with K' >= π/2, or at the estimated distance for the heavy top), so the
# panel error is below 1e-20 relative and the result is limited by rounding alone.
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(16)
_MAX_PANEL_TAU = 0.5


class TorqueFreeMotion(NamedTuple):
    """Exact torque-free motion sampled at ``times`` (T,)."""

    omega_body: np.ndarray  # (T, 3) angular velocity in the body frame, rad/s
    orientation: np.ndarray  # (T, 4) unit quaternions (w, x, y, z), body -> world
    rotation: np.ndarray  # (T, 3, 3) rotation matrices, body axes as columns
    angular_momentum_world: np.ndarray  # (3,) constant angular momentum, world frame, kg m^2/s
    energy: float  # kinetic energy, J


class HeavyTopMotion(NamedTuple):
    """Exact heavy-symmetric-top motion sampled at ``times`` (T,); angles in rad."""

    theta: np.ndarray  # (T,) nutation angle between symmetry axis and world +z
    cos_theta: np.ndarray  # (T,)
    phi: np.ndarray  # (T,) precession angle (not wrapped)
    psi: np.ndarray  # (T,) spin angle (not wrapped)
    rotation: np.ndarray  # (T, 3, 3) R = Rz(phi) Rx(theta) Rz(psi), body -> world
    omega_body: np.ndarray  # (T, 3) angular velocity in the body frame, rad/s
    nutation_period: float  # period of theta(t), s
    energy: float  # kinetic + potential (zero at the pivot height), J
    L_z: float  # angular momentum about the pivot along world z, kg m^2/s
    L_3: float  # angular momentum along the symmetry axis, kg m^2/s


def _as_times(times):
    t = np.asarray(times, dtype=np.float64)
    if t.ndim != 1 or not np.all(np.isfinite(t)):
        raise ValueError(f"times must be a finite 1-D array, got shape {t.shape}")
    return t


def _cumulative_integral(integrand, times, max_panel, breakpoints=()):
    """``∫_0^t integrand(s) ds`` for every t in ``times``, shape ``(C, T)``.

    ``integrand`` maps an array of times ``(P, n)`` to ``(C, P, n)``. Every gap between
    consecutive sorted output times, ``breakpoints`` (panel ends only) and 0 is cut into
    equal panels no wider than ``max_panel`` and integrated by Gauss–Legendre, then the
    gaps are summed in order.
    """
    knots = np.unique(np.concatenate([[0.0], times, np.asarray(breakpoints, np.float64)]))
    gaps = np.diff(knots)
    counts = np.maximum(1, np.ceil(gaps / max_panel)).astype(int)
    width = np.repeat(gaps / counts, counts)
    first = np.cumsum(counts) - counts
    index_in_gap = np.arange(counts.sum()) - np.repeat(first, counts)
    left = np.repeat(knots[:-1], counts) + index_in_gap * width
    nodes = left[:, None] + 0.5 * width[:, None] * (_GL_NODES + 1.0)
    panels = 0.5 * width * (integrand(nodes) @ _GL_WEIGHTS)  # (C, P)
    per_gap = np.add.reduceat(panels, first, axis=-1) if gaps.size else panels[..., :0]
    # Kahan-compensated running sum: thousands of gaps would otherwise lose ~sqrt(N) ulps.
    total = np.zeros((per_gap.shape[0], knots.size))
    running, carry = np.zeros(per_gap.shape[0]), np.zeros(per_gap.shape[0])
    for g in range(gaps.size):
        y = per_gap[:, g] - carry
        new = running + y
        carry = (new - running) - y
        running = new
        total[:, g + 1] = running
    total -= total[:, np.searchsorted(knots, 0.0)][:, None]
    return total[:, np.searchsorted(knots, times)]


def _quat_mul(p, q):
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack([pw * qw - px * qx - py * qy - pz * qz,
                     pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx,
                     pw * qz + px * qy - py * qx + pz * qw], axis=-1)


def _quat_to_matrix(q):
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def _axis_angle_quat(axis, angle):
    """Rotation by ``angle`` (T,) about the fixed unit ``axis`` (3,)."""
    half = 0.5 * np.asarray(angle)
    return np.concatenate([np.cos(half)[..., None], np.sin(half)[..., None] * axis], axis=-1)


def _align_quat(a, b):
    """Minimal rotation taking unit vectors ``a`` (..., 3) onto ``b``; needs a·b > -1."""
    q = np.concatenate([1.0 + np.sum(a * b, axis=-1, keepdims=True), np.cross(a, b)], axis=-1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def torque_free_top(inertia, omega0_body, times, orientation0=None) -> TorqueFreeMotion:
    """Exact motion of a free rigid body (no forces, no torques) in its principal frame.

    Args:
      inertia: ``(3,)`` principal moments ``(I1, I2, I3)``, kg m², any order, positive;
        equal moments (symmetric or spherical bodies) are handled exactly.
      omega0_body: ``(3,)`` initial angular velocity in the body frame, rad/s.
      times: ``(T,)`` sample times, s; the initial state is at t = 0.
      orientation0: ``(4,)`` initial unit quaternion (w, x, y, z), body -> world;
        identity by default.

    Returns:
      :class:`TorqueFreeMotion`.

    **Angular velocity** (Landau–Lifshitz §37). Sort the axes into j, m, k where m is the
    middle moment and k the axis the polhode circulates around (k = max axis when
    ``L² > 2E I_m``, k = min axis when ``L² < 2E I_m``). With ``P = 2E I_k − L²`` and
    ``Q = L² − 2E I_j`` (evaluated as sums of same-sign terms, free of cancellation)::

        ω_j = a_j cn τ,   ω_m = a_m sn τ,   ω_k = a_k dn τ,   τ = λ t + τ0,
        a_j² = P / (I_j (I_k − I_j)),  a_m² = P / (I_m (I_k − I_m)),  a_k² = Q / (I_k (I_k − I_j)),
        λ² = (I_k − I_m) Q / (I_j I_m I_k),  m = (I_m − I_j) P / ((I_k − I_m) Q)   (parameter m = k²).

    The sign of a_k is that of ω_k(0) (dn > 0 never changes it), a_j >= 0, and
    ``sign a_m = sign((I_p − I_q) a_k)`` with (m, p, q) cyclic, as Euler's equation
    ``I_m ω̇_m = (I_p − I_q) ω_p ω_q`` requires. The phase is ``τ0 = F(φ0 | m)``,
    ``φ0 = atan2(ω_m(0)/a_m, ω_j(0)/a_j)`` (scipy's ``ellipkinc`` is valid for any φ0).
    Two equal moments give m = 0 (cn, sn, dn = cos, sin, 1: the symmetric top). The
    separatrix ``L² = 2E I_m`` raises ValueError unless the motion is a steady rotation.

    **Attitude.** L_world = R0 I ω(0) is fixed, and R(t) I ω(t) = L_world. Write
    ``n = I ω / |L|`` (body) and ``e = sign(ω_k) ê_k``, so n·e > 0 always. Let S(n) be the
    minimal rotation taking n to e, and ``R(t) = Rot(L̂_world, ψ(t)) R0 S(n0)ᵀ S(n(t))``.
    Matching ω_body = ψ̇ n + vee(SᵀṠ) and using ṅ = n × ω gives, in closed form::

        ψ̇ = (2E + |L| |ω_k|) / (|L| + I_k |ω_k|),

    a smooth, bounded function of dn τ alone, integrated from 0 by composite
    Gauss–Legendre (rounding-limited: 1.2e-14 rad after 100 s against a 25-digit Taylor solve of
    the full ODE for I = (1, 2, 3), ω0 = (−0.3, 0.9, −0.5)). R(0) = R0 by construction.
    """
    inertia = np.asarray(inertia, dtype=np.float64)
    omega0 = np.asarray(omega0_body, dtype=np.float64)
    t = _as_times(times)
    q0 = np.array([1.0, 0.0, 0.0, 0.0]) if orientation0 is None else np.asarray(orientation0, dtype=np.float64)
    if inertia.shape != (3,) or not np.all(np.isfinite(inertia)) or np.any(inertia <= 0):
        raise ValueError(f"inertia must be 3 positive principal moments, got {inertia}")
    if omega0.shape != (3,) or not np.all(np.isfinite(omega0)):
        raise ValueError(f"omega0_body must be a finite (3,) vector, got {omega0}")
    if q0.shape != (4,) or not np.all(np.isfinite(q0)) or np.linalg.norm(q0) == 0:
        raise ValueError(f"orientation0 must be a nonzero (4,) quaternion (w, x, y, z), got {q0}")
    q0 = q0 / np.linalg.norm(q0)
    momentum0 = inertia * omega0
    L = float(np.linalg.norm(momentum0))
    two_e = float(np.sum(inertia * omega0**2))
    L_world = _quat_to_matrix(q0) @ momentum0
    lo, mid, hi = np.argsort(inertia, kind="stable")
    separatrix = float(np.sum(inertia * (inertia - inertia[mid]) * omega0**2))  # L² − 2E I_mid

    spun = omega0 != 0.0
    if not spun.any() or np.ptp(inertia[spun]) == 0.0:
        # ω0 is an eigenvector of the inertia (a principal axis, or rest): ω stays constant, parallel to L.
        speed = float(np.linalg.norm(omega0))
        axis = L_world / L if L > 0 else np.array([0.0, 0.0, 1.0])
        q = _quat_mul(_axis_angle_quat(axis, speed * t), q0)
        return TorqueFreeMotion(np.tile(omega0, (t.size, 1)), q, _quat_to_matrix(q), L_world, 0.5 * two_e)
    if separatrix == 0.0:
        raise ValueError("omega0_body lies on the separatrix L² = 2E I_mid (period infinite); "
                         "perturb it slightly to get a closed-form elliptic solution")

    k, j = (hi, lo) if separatrix > 0 else (lo, hi)
    I_j, I_m, I_k = inertia[j], inertia[mid], inertia[k]
    P = float(np.sum(inertia * (I_k - inertia) * omega0**2))  # 2E I_k − L²
    Q = float(np.sum(inertia * (inertia - I_j) * omega0**2))  # L² − 2E I_j
    a_j = np.sqrt(P / (I_j * (I_k - I_j)))
    a_k = np.copysign(np.sqrt(Q / (I_k * (I_k - I_j))), omega0[k])
    c_m = inertia[(mid + 1) % 3] - inertia[(mid + 2) % 3]
    a_m = np.copysign(np.sqrt(P / (I_m * (I_k - I_m))), c_m * a_k)
    lam = np.sqrt((I_k - I_m) * Q / (I_j * I_m * I_k))
    m = min(1.0, (I_m - I_j) * P / ((I_k - I_m) * Q))  # guards rounding just above 1 near the separatrix
    m1 = (I_k - I_j) * separatrix / ((I_k - I_m) * Q)  # 1 − m without the cancellation of 1 − m
    if m == 1.0:
        # scipy's elliptic functions take m, not 1 − m: F(φ0 | 1) is infinite at φ0 = π/2,
        # and the motion came out NaN (ω0 = (1e-8, 1, 0) about I = (1, 2, 3)). 1 − m of
        # 1e-14 (a relative 1e-7 off the intermediate axis) is still resolved, to ~1e-9.
        raise ValueError(f"omega0_body is within rounding of the separatrix L² = 2E I_mid (1 − m = {m1:.2g} rounds "
                         f"m to 1, which the elliptic functions cannot resolve); perturb it by more (1 − m of "
                         f"1e-14 or more is accurate)")
    period = 4.0 * ellipkm1(m1)  # 4 K(m), accurate even when m rounds to within ulps of 1
    tau0 = ellipkinc(np.arctan2(omega0[mid] / a_m, omega0[j] / a_j), m)  # P > 0 here, so a_j, a_m > 0

    def jacobi(s):
        # Near the separatrix the float m fixes ellipj's own period only to ~ulp/(1 − m); reducing τ with
        # the accurate period stops that phase error from growing period after period (Dzhanibekov case).
        tau = lam * s + tau0
        return _jacobi_reduced(tau - period * np.round(tau / period), m, m1, period / 4.0)

    sn, cn, dn = jacobi(t)
    omega = np.empty((t.size, 3))
    omega[:, j], omega[:, mid], omega[:, k] = a_j * cn, a_m * sn, a_k * dn

    def psi_rate(s):
        abs_omega_k = abs(a_k) * jacobi(s)[2]
        return ((two_e + L * abs_omega_k) / (L + I_k * abs_omega_k))[None]

    psi = _cumulative_integral(psi_rate, t, _MAX_PANEL_TAU / lam)[0]
    e_k = np.zeros(3)
    e_k[k] = np.sign(a_k)
    to_e = _align_quat(inertia * omega / np.linalg.norm(inertia * omega, axis=-1, keepdims=True), e_k)
    from_e0 = _align_quat(momentum0 / L, e_k) * np.array([1.0, -1.0, -1.0, -1.0])  # conjugate: e -> n0
    q = _quat_mul(_quat_mul(_axis_angle_quat(L_world / L, psi), _quat_mul(q0, from_e0)), to_e)
    return TorqueFreeMotion(omega, q, _quat_to_matrix(q), L_world, 0.5 * two_e)


#: How near a turning point of the heavy top's axis must come to a vertical (in ``1 ∓ u``)
#: to count as reaching it, where ``a = ±b`` makes the vertical a root of ``f``: the root
#: finder leaves it ~1e-16 off, and another root that close would be a double root.
_POLE = 1e-12


def _jacobi_reduced(u, m, m1, quarter):
    """``sn, cn, dn (u | m)`` for ``|u| <= 2K``, from ``ellipj`` at ``|u| <= K/2`` only.

    For ``1 − m`` below 1e-10 scipy's ``ellipj`` switches to an expansion about ``m = 1``
    that holds for small ``u`` only: at ``1 − m = 1e-12``, ``cn(2K)`` came out −2 and
    ``cn(3K)`` −8e6, and the free top's ``|I ω|`` drifted from ``L`` by 120% after 13 s
    (stop 96's review). Half periods (``sn(u ± 2K) = −sn u``, ``cn(u ± 2K) = −cn u``) bring
    ``u`` into ``[−K, K]``, and the reflection about the quarter period (``sn(K − v) = cn v /
    dn v``, ``cn(K − v) = sqrt(1 − m) sn v / dn v``, ``dn(K − v) = sqrt(1 − m) / dn v``) into
    ``|v| <= K/2``, where the expansion's error is about ``16 (1 − m)`` relative. ``dn`` is
    taken as ``sqrt(cn² + (1 − m) sn²)``, free of the cancellation of ``1 − m sn²``.
    ``m1``: ``1 − m`` computed without cancellation; ``quarter``: ``K(m)``."""
    u = np.asarray(u, dtype=float)
    flip = np.abs(u) > quarter
    u = np.where(flip, u - np.copysign(2.0 * quarter, u), u)
    sign = np.where(flip, -1.0, 1.0)
    reflect = np.abs(u) > quarter / 2.0
    v = np.where(reflect, quarter - np.abs(u), u)
    sn_v, cn_v, _, _ = ellipj(v, m)
    dn_v = np.sqrt(cn_v * cn_v + m1 * sn_v * sn_v)
    root = np.sqrt(m1)
    sn = np.where(reflect, np.copysign(1.0, u) * cn_v / dn_v, sn_v)
    cn = np.where(reflect, root * sn_v / dn_v, cn_v)
    dn = np.where(reflect, root / dn_v, dn_v)
    return sign * sn, sign * cn, dn


def _shifted_cubic_roots(beta, f2, f1, f0):
    """Real roots x1 <= x2 <= x3 of ``β x³ + f2 x² + f1 x + f0`` with f0 >= 0 (x = u − u0)."""
    if f0 == 0.0:  # u0 is a turning point: deflate exactly and solve the quadratic stably
        disc = np.sqrt(max(f2 * f2 - 4.0 * beta * f1, 0.0))
        q = -0.5 * (f2 + np.copysign(disc, f2))
        others = [q / beta, f1 / q] if q != 0.0 else [0.0, 0.0]
        return np.sort([0.0, *others])
    coeffs = np.array([beta, f2, f1, f0])
    x = np.sort(np.roots(coeffs).real)
    slope = np.polyval(np.polyder(coeffs), x)
    for _ in range(2):  # Newton polish; the roots are simple here because f(u0) > 0
        x = x - np.polyval(coeffs, x) / np.where(slope != 0.0, slope, np.inf)
        slope = np.polyval(np.polyder(coeffs), x)
    return x


def _polish_pole_distance(p, rest, gap, b, beta, scale):
    """The root near ``p >= 0`` of ``p (2 - p) (rest - beta p) - (gap - b p)^2`` (a turning
    point's distance to a vertical, see :func:`heavy_symmetric_top`), by Newton's method
    from ``p`` (under 0.1); ``p`` itself where the root is not within the rounding
    ``64 eps scale`` of ``p`` or not found."""
    bound = 64 * np.finfo(np.float64).eps * scale
    if not 0.0 < p < 0.1:  # (farther, the rounding is below ~1e-14 of it)
        return p
    x = p
    for _ in range(6):
        g = x * (2.0 - x) * (rest - beta * x) - (gap - b * x) ** 2
        slope = (2.0 - 2.0 * x) * (rest - beta * x) - beta * x * (2.0 - x) + 2.0 * b * (gap - b * x)
        if not slope > 0.0:
            return p
        x = x - g / slope
    return x if np.isfinite(x) and x > 0.0 and abs(x - p) <= bound else p


def heavy_symmetric_top(i_perp, i_axis, mgl, omega3, theta0, times, theta_dot0=0.0, phi_dot0=0.0) -> HeavyTopMotion:
    """Exact motion of the heavy symmetric (Lagrange) top on a fixed pivot.

    Args:
      i_perp: moment of inertia about a transverse axis through the PIVOT, kg m².
      i_axis: moment of inertia about the symmetry axis, kg m².
      mgl: M g l > 0, weight times pivot-to-centre-of-mass distance, N m.
      omega3: constant angular-velocity component along the symmetry axis, rad/s.
      theta0: initial angle between the symmetry axis and world +z (up), rad, in (0, π).
      times: ``(T,)`` sample times, s; the initial state is at t = 0 with φ = ψ = 0.
      theta_dot0, phi_dot0: initial nutation and precession rates, rad/s.

    Returns:
      :class:`HeavyTopMotion`. Euler angles are z-x-z, ``R = Rz(φ) Rx(θ) Rz(ψ)`` (body z =
      symmetry axis, body -> world), so ``ω_body = (φ̇ sθ sψ + θ̇ cψ, φ̇ sθ cψ − θ̇ sψ, φ̇ cθ + ψ̇)``.

    **Nutation** (Goldstein §5.7). L_3 = i_axis ω3, L_z = i_perp φ̇ sin²θ + L_3 cos θ and
    E = ½ i_perp (θ̇² + φ̇² sin²θ) + ½ i_axis ω3² + mgl cos θ are conserved. With
    u = cos θ, a = L_z/i_perp, b = L_3/i_perp, β = 2 mgl/i_perp, α = (2E − i_axis ω3²)/i_perp::

        u̇² = f(u) = (1 − u²)(α − β u) − (a − b u)² = β (u − u1)(u − u2)(u − u3),
        u(t) = u1 + (u2 − u1) sn²(λ t + τ0 | m),   λ = ½ √(β (u3 − u1)),   m = (u2 − u1)/(u3 − u1),

    with −1 <= u1 <= u2 <= 1 <= u3 (roots found in x = u − u0 so that u0 − u1 and u2 − u0 are
    accurate), nutation period ``2 K(m) / λ``, and τ0 = F(φ0 | m) where sin φ0 = ±√((u0 − u1)/(u2 − u1)),
    the sign of u̇(0) = −sin θ0 θ̇0 (so θ̇0 = 0 starts exactly at a turning point, τ0 ∈ {0, K}).

    **Precession and spin** by partial fractions, which stay well conditioned near the poles::

        φ̇ = (a − b u)/(1 − u²) = ½ [(a − b)/(1 − u) + (a + b)/(1 + u)],
        ψ̇ = L_3/i_axis − u φ̇ = (ω3 − b) − ½ [(a − b)/(1 − u) − (a + b)/(1 + u)],

    with ∫dt/(1 ∓ u) by composite Gauss–Legendre; around each passage near a vertical the panels
    are graded to the estimated distance of the pole u = ±1 from the real τ axis (a few dozen
    more panels a passage, however close), and a turning point near a vertical is polished from
    its own equation (its distance to the vertical sets how far φ and ψ turn there). Accuracy
    is ~1e-12 rad over 5 s for ordinary tops; against DOP853, 9e-12 to 2e-8 rad for axes that
    pass 1e-5 to 1e-9 rad from a vertical, or start 1e-5 rad from it
    (``tests/test_exact.py::test_heavy_top_passing_close_to_a_vertical``).
    """
    i_perp, i_axis, mgl, omega3, theta0 = (float(v) for v in (i_perp, i_axis, mgl, omega3, theta0))
    theta_dot0, phi_dot0 = float(theta_dot0), float(phi_dot0)
    t = _as_times(times)
    if not (i_perp > 0 and i_axis > 0 and mgl > 0):
        raise ValueError(f"need i_perp > 0, i_axis > 0, mgl > 0; got {i_perp}, {i_axis}, {mgl}")
    if not 0.0 < theta0 < np.pi:
        raise ValueError(f"theta0 must lie in (0, pi) (Euler angles are singular at the vertical), got {theta0}")
    if not np.all(np.isfinite([omega3, theta_dot0, phi_dot0])):
        raise ValueError("omega3, theta_dot0 and phi_dot0 must be finite")
    u0, s0 = np.cos(theta0), np.sin(theta0)
    L_3 = i_axis * omega3
    L_z = i_perp * phi_dot0 * s0**2 + L_3 * u0
    energy = 0.5 * i_perp * (theta_dot0**2 + (phi_dot0 * s0) ** 2) + 0.5 * i_axis * omega3**2 + mgl * u0
    a, b, beta = L_z / i_perp, L_3 / i_perp, 2.0 * mgl / i_perp
    # Taylor coefficients of f about u0, written with α − β u0 = w² and a − b u0 = φ̇0 sin²θ0.
    w2 = theta_dot0**2 + (phi_dot0 * s0) ** 2
    f0 = (s0 * theta_dot0) ** 2
    f1 = -2.0 * u0 * w2 - beta * s0**2 + 2.0 * b * phi_dot0 * s0**2
    f2 = -w2 + 2.0 * beta * u0 - b * b
    x1, x2, x3 = _shifted_cubic_roots(beta, f2, f1, f0)
    x1, x2 = min(x1, 0.0), max(x2, 0.0)  # u0 lies between the turning points
    span = x2 - x1  # u2 − u1
    lam = 0.5 * np.sqrt(beta * (x3 - x1))
    m = span / (x3 - x1)
    nutation_period = 2.0 * ellipk(m) / lam
    # 1 − u = (1 − u2) + (u2 − u1) cn² and 1 + u = (1 + u1) + (u2 − u1) sn²: sums of non-negative terms, so
    # 1/(1 ∓ u) keeps full relative accuracy when the axis passes close to the vertical (1 − u0 = 2 sin²(θ0/2)).
    half_up, half_down = 2.0 * np.sin(0.5 * theta0) ** 2, 2.0 * np.cos(0.5 * theta0) ** 2  # 1 - u0, 1 + u0
    one_minus_u2 = max(half_up - x2, 0.0)  # rounding must not push u2 past 1
    one_plus_u1 = max(half_down + x1, 0.0)  # (its NaN square root gave wrong values)
    # These cancel down to ~eps absolute, and a passage near a vertical turns φ and ψ by an
    # amount set by a ± b against sqrt(1 ± u): at 1 + u1 = 2e-14 its 2% rounding put them
    # 4e-3 rad off after a pendulum's swing through the bottom, and at 2e-18 (a spin of 1e-8
    # rad/s) 3 rad. So a small one is polished against f(∓1 ± p) = 0 by Newton's method,
    # p (2 - p) (α ± β ∓ β p) = (a ± b ∓ b p)^2 (α ± β written without cancellation), the
    # step kept only within the rounding it corrects.
    one_plus_u1 = _polish_pole_distance(one_plus_u1, w2 + beta * half_down, a + b, b, beta, half_down)
    one_minus_u2 = _polish_pole_distance(one_minus_u2, w2 - beta * half_up, a - b, -b, -beta, half_up)
    sn0 = np.sqrt(-x1 / span) if span > 0 else 0.0
    cn0 = np.sqrt(x2 / span) if span > 0 else 1.0
    tau0 = ellipkinc(np.arctan2(sn0 if theta_dot0 <= 0 else -sn0, cn0), m)  # sign of sn·cn = sign of u̇(0)

    def one_minus_plus_u(s):
        sn, cn, _, _ = ellipj(lam * s + tau0, m)
        return one_minus_u2 + span * cn * cn, one_plus_u1 + span * sn * sn

    def inverse_factors(s):
        minus, plus = one_minus_plus_u(s)
        return np.stack([1.0 / minus, 1.0 / plus])

    # An axis whose turning point is within _POLE of a vertical, with a ∓ b zero up to its
    # rounding, passes through it (see the crossings below): the same top given a rate one ulp
    # away had come out 3 rad off. Its term is then the jump alone. (A turning point on the
    # vertical needs a ∓ b = 0: f(±1) = -(a ∓ b)^2.) Any other passage, however close, is
    # integrated (graded panels, below).
    rounding = 64 * np.finfo(np.float64).eps * (abs(a) + abs(b))
    through_top = one_minus_u2 <= _POLE and (abs(a - b) <= rounding or one_minus_u2 == 0.0)
    through_bottom = one_plus_u1 <= _POLE and (abs(a + b) <= rounding or one_plus_u1 == 0.0)
    # Leading-order distance in τ from the real axis to the poles u = ±1 (τ ≈ K + i d₋, i d₊):
    # 1/(1 ∓ u) is a Lorentzian of that width around each passage. Uniform panels that
    # narrow had made a close passage cost ~1/d panels (14 GiB at d ~ 1e-7, and seconds at
    # 1e-4); the panels are graded instead, each as wide as half its distance from the
    # passage (about 2 log(1/d) / log(1.5) more panels a passage, accurate at any d > 0).
    quarter = ellipk(m)
    tau = lam * t + tau0
    breakpoints = []
    for d, first in ((np.sqrt(one_minus_u2 / (span * (1.0 - m))) if not through_top else np.inf, quarter),
                     (np.sqrt(one_plus_u1 / span) if not through_bottom else np.inf, 0.0)):
        if d < _MAX_PANEL_TAU:
            # Passages at τ = first + 2kK within the sampled range (and one beyond each end).
            low, high = min(tau0, tau.min()), max(tau0, tau.max())
            k = np.arange(np.floor((low - first) / (2 * quarter)) - 1, np.ceil((high - first) / (2 * quarter)) + 2)
            grade = d * np.concatenate([[0.0, 0.5], 1.5 ** np.arange(int(np.ceil(np.log(_MAX_PANEL_TAU / d)
                                                                                    / np.log(1.5))) + 1)])
            offsets = np.concatenate([-grade[::-1], grade])
            breakpoints.append(((first + 2 * quarter * k)[:, None] + offsets[None, :]).ravel())
    breakpoints = (np.concatenate(breakpoints) - tau0) / lam if breakpoints else ()
    j_minus, j_plus = _cumulative_integral(inverse_factors, t, _MAX_PANEL_TAU / lam, breakpoints)
    a_minus_b = 0.0 if through_top else a - b
    a_plus_b = 0.0 if through_bottom else a + b
    phi = 0.5 * (a_minus_b * j_minus + a_plus_b * j_plus)
    psi = (omega3 - b) * t - 0.5 * (a_minus_b * j_minus - a_plus_b * j_plus)
    # With a = -b (a = b) the downward (upward) vertical is a root of f: an axis that reaches
    # it passes through the pole, e.g. a top released without spin swings through the bottom
    # as a pendulum. There θ turns back in [0, π] while the axis goes on, so φ and ψ each
    # jump by π (Rx(π + ε) = Rz(π) Rx(π − ε) Rz(π)), which the integrals above cannot give.
    # The axis is at u = −1 where sn = 0 (τ = 2kK) and at u = 1 where cn = 0 (τ = (2k+1)K).
    crossings = np.zeros_like(t)
    if through_bottom:
        crossings += np.floor(tau / (2 * quarter)) - np.floor(tau0 / (2 * quarter))
    if through_top:
        crossings += np.floor((tau - quarter) / (2 * quarter)) - np.floor((tau0 - quarter) / (2 * quarter))
    phi, psi = phi + np.pi * crossings, psi + np.pi * crossings

    sn, cn, dn, _ = ellipj(lam * t + tau0, m)
    minus, plus = one_minus_plus_u(t)
    cos_theta = 1.0 - minus
    sin_theta = np.sqrt(minus * plus)
    theta = np.arctan2(sin_theta, cos_theta)
    theta_dot = -2.0 * span * lam * sn * cn * dn / sin_theta  # θ̇ = −u̇ / sin θ
    with np.errstate(divide="ignore", invalid="ignore"):  # 0/0 on a vertical: that term's share is 0
        phi_dot = 0.5 * (np.where(minus > 0, (a - b) / minus, 0.0) + np.where(plus > 0, (a + b) / plus, 0.0))
    rotation = _quat_to_matrix(_quat_mul(_quat_mul(
        _axis_angle_quat(np.array([0.0, 0.0, 1.0]), phi), _axis_angle_quat(np.array([1.0, 0.0, 0.0]), theta)),
        _axis_angle_quat(np.array([0.0, 0.0, 1.0]), psi)))
    omega_body = np.stack([phi_dot * sin_theta * np.sin(psi) + theta_dot * np.cos(psi),
                           phi_dot * sin_theta * np.cos(psi) - theta_dot * np.sin(psi),
                           np.full_like(t, omega3)], axis=-1)  # φ̇ cos θ + ψ̇ = ω3 exactly
    return HeavyTopMotion(theta, cos_theta, phi, psi, rotation, omega_body, float(nutation_period),
                          float(energy), float(L_z), float(L_3))
