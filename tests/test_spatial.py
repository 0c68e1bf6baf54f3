"""Spatial algebra against independent references (numpy/scipy) and identities."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxrb import spatial

RNG = np.random.default_rng(0)


def random_quats(n):
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def scipy_matrix(q):
    # scipy is scalar-last.
    return Rotation.from_quat(np.concatenate([q[..., 1:], q[..., :1]], axis=-1)).as_matrix()


def test_skew_is_the_cross_product_matrix():
    w, x = RNG.normal(size=(2, 10, 3))
    np.testing.assert_allclose(spatial.matvec(spatial.skew(w), x), np.cross(w, x), atol=1e-15)
    np.testing.assert_allclose(spatial.vee(spatial.skew(w)), w, atol=0)
    # The seed's layout, entry by entry.
    s = np.asarray(spatial.skew(jnp.array([1.0, 2.0, 3.0])))
    np.testing.assert_array_equal(s, [[0, -3, 2], [3, 0, -1], [-2, 1, 0]])


def test_quat_to_matrix_matches_scipy_and_rotate():
    q = random_quats(50)
    np.testing.assert_allclose(spatial.quat_to_matrix(q), scipy_matrix(q), atol=1e-14)
    v = RNG.normal(size=(50, 3))
    expected = np.einsum("nij,nj->ni", scipy_matrix(q), v)
    np.testing.assert_allclose(spatial.quat_rotate(q, v), expected, atol=1e-14)
    # Rot(v) = q (0, v) q^-1, as in seed 000.
    pure = np.concatenate([np.zeros((50, 1)), v], axis=1)
    sandwich = spatial.quat_multiply(spatial.quat_multiply(q, pure), spatial.quat_conjugate(q))
    np.testing.assert_allclose(sandwich[:, 1:], expected, atol=1e-14)
    np.testing.assert_allclose(spatial.quat_rotate_inverse(q, expected), v, atol=1e-14)


def test_quat_product_composes_rotations():
    p, q = random_quats(20), random_quats(20)
    np.testing.assert_allclose(
        spatial.quat_to_matrix(spatial.quat_multiply(p, q)),
        scipy_matrix(p) @ scipy_matrix(q),
        atol=1e-14,
    )


@pytest.mark.parametrize("angle", [0.0, 1e-9, 0.3, np.pi / 2, np.pi - 1e-9, np.pi])
def test_matrix_to_quat_round_trip_including_half_turns(angle):
    axes = RNG.normal(size=(8, 3))
    q = spatial.quat_from_axis_angle(axes, jnp.full(8, angle))
    r = spatial.quat_to_matrix(q)
    q_back = spatial.matrix_to_quat(r)
    # q and -q are the same rotation: compare matrices and |<q, q_back>| = 1.
    np.testing.assert_allclose(spatial.quat_to_matrix(q_back), r, atol=1e-14)
    np.testing.assert_allclose(np.abs(np.sum(np.asarray(q) * np.asarray(q_back), -1)), 1.0, atol=1e-14)


def test_axis_angle_matches_scipy_rotvec():
    axis = RNG.normal(size=(10, 3))
    angle = RNG.uniform(-3, 3, size=10)
    unit = axis / np.linalg.norm(axis, axis=1, keepdims=True)
    expected = Rotation.from_rotvec(unit * angle[:, None]).as_matrix()
    q = spatial.quat_from_axis_angle(axis, angle)
    np.testing.assert_allclose(spatial.quat_to_matrix(q), expected, atol=1e-14)
    np.testing.assert_allclose(spatial.quat_to_matrix(spatial.quat_exp(unit * angle[:, None])), expected, atol=1e-14)
    np.testing.assert_allclose(spatial.rotation_matrix_exp(unit * angle[:, None]), expected, atol=1e-14)


def test_axis_angle_broadcasts_axes_and_angles_and_refuses_a_zero_axis():
    axes = RNG.normal(size=(4, 3))
    unit = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    # Many axes, one angle (this failed: the (1,) half angle did not broadcast with (4, 3)).
    np.testing.assert_allclose(spatial.quat_to_matrix(spatial.quat_from_axis_angle(axes, 0.7)),
                               Rotation.from_rotvec(0.7 * unit).as_matrix(), atol=1e-14)
    # One axis, many angles; and a (2, 1) batch of angles against (4,) axes: (2, 4).
    angles = np.array([0.1, -2.0, 3.0])
    np.testing.assert_allclose(spatial.quat_to_matrix(spatial.quat_from_axis_angle(axes[0], angles)),
                               Rotation.from_rotvec(angles[:, None] * unit[0]).as_matrix(), atol=1e-14)
    assert spatial.quat_from_axis_angle(axes, np.ones((2, 1))).shape == (2, 4, 4)
    # A zero axis names no rotation: refused when concrete (it returned (cos, 0, 0, 0), not
    # a unit quaternion), the identity under jit, where it cannot be refused.
    with pytest.raises(ValueError, match="axis is zero"):
        spatial.quat_from_axis_angle(np.zeros(3), 1.0)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3\)"):
        spatial.quat_from_axis_angle(np.ones(2), 1.0)
    traced = jax.jit(spatial.quat_from_axis_angle)(jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]]), jnp.pi)
    np.testing.assert_allclose(traced, [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]], atol=1e-15)
    assert np.all(np.isfinite(jax.jacfwd(lambda a: jax.jit(spatial.quat_from_axis_angle)(a, 1.0))(jnp.zeros(3))))


def test_exp_log_round_trip_and_small_angles():
    r = RNG.normal(size=(20, 3))
    r = r / np.linalg.norm(r, axis=1, keepdims=True) * RNG.uniform(0, np.pi - 1e-6, size=(20, 1))
    np.testing.assert_allclose(spatial.quat_log(spatial.quat_exp(r)), r, atol=1e-13)
    for scale in [1e-3, 1e-6, 1e-9, 0.0]:
        tiny = r * scale
        np.testing.assert_allclose(spatial.quat_log(spatial.quat_exp(tiny)), tiny, atol=1e-18, rtol=1e-13)
    # log picks the short way round: -q gives the same rotation vector.
    q = spatial.quat_exp(r)
    np.testing.assert_allclose(spatial.quat_log(-q), r, atol=1e-13)


def test_exp_and_log_gradients_are_finite_and_right_at_zero():
    # At r = 0, d exp(r) / dr = [0; I/2]: the quaternion's vector part is r/2 to first order.
    jac = jax.jacfwd(spatial.quat_exp)(jnp.zeros(3))
    np.testing.assert_allclose(jac, np.vstack([np.zeros(3), 0.5 * np.eye(3)]), atol=1e-15)
    jac_rev = jax.jacrev(spatial.quat_exp)(jnp.zeros(3))
    np.testing.assert_allclose(jac_rev, jac, atol=1e-15)
    jac_log = jax.jacfwd(spatial.quat_log)(jnp.array([1.0, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(jac_log[:, 1:], 2.0 * np.eye(3), atol=1e-15)
    # Away from zero, against central differences.
    r0 = jnp.array([0.3, -0.2, 0.5])
    jac = jax.jacfwd(spatial.quat_exp)(r0)
    eps = 1e-6
    fd = np.stack([(spatial.quat_exp(r0 + eps * e) - spatial.quat_exp(r0 - eps * e)) / (2 * eps)
                   for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(jac, fd, atol=1e-9)


def test_safe_norm_gradient_is_per_element():
    x = jnp.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]])
    g = jax.grad(lambda x: jnp.sum(spatial.safe_norm(x)))(x)
    # One zero row must not poison the other (the MJX/brax allclose pitfall).
    np.testing.assert_allclose(g, [[0, 0, 0], [0.6, 0.8, 0]], atol=1e-15)
    g = jax.grad(lambda x: jnp.sum(spatial.safe_normalize(x)))(x)
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(spatial.safe_normalize(x), [[0, 0, 0], [0.6, 0.8, 0]], atol=1e-15)
    np.testing.assert_allclose(spatial.quat_normalize(jnp.zeros(4)), [1, 0, 0, 0])


def test_quat_normalize_has_the_projection_as_its_derivative():
    """Its hand-written tangent against the derivative of ``q / |q|`` written plainly (jvp,
    vjp, Hessian), against central differences, in float32, and at q = 0 (zero, finite)."""
    q = jnp.asarray(RNG.normal(size=(6, 4)) * RNG.uniform(0.2, 3.0, size=(6, 1)))
    q = q.at[0].set(random_quats(1)[0] * (1 + 1e-9))  # near the unit sphere, as in the integrators
    plain = lambda q: q / jnp.linalg.norm(q, axis=-1, keepdims=True)  # noqa: E731
    dq = jnp.asarray(RNG.normal(size=(6, 4)))
    value, tangent = jax.jvp(spatial.quat_normalize, (q,), (dq,))
    value_ref, tangent_ref = jax.jvp(plain, (q,), (dq,))
    np.testing.assert_array_equal(value, spatial.quat_normalize(q))
    np.testing.assert_allclose(value, value_ref, rtol=1e-15, atol=1e-16)
    np.testing.assert_allclose(tangent, tangent_ref, rtol=1e-13, atol=1e-15)
    weights = jnp.array([1.0, -2.0, 3.0, 0.5])
    loss = lambda f: lambda q: jnp.sum(jnp.sin(f(q)) * jnp.broadcast_to(weights, q.shape))  # noqa: E731
    np.testing.assert_allclose(jax.grad(loss(spatial.quat_normalize))(q), jax.grad(loss(plain))(q),
                               rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(jax.hessian(loss(spatial.quat_normalize))(q[1:2]), jax.hessian(loss(plain))(q[1:2]),
                               rtol=1e-12, atol=1e-14)
    eps = 1e-6
    for i in range(4):
        e = jnp.zeros(4).at[i].set(eps)
        fd = (spatial.quat_normalize(q[2] + e) - spatial.quat_normalize(q[2] - e)) / (2 * eps)
        np.testing.assert_allclose(jax.jacfwd(spatial.quat_normalize)(q[2])[:, i], fd, rtol=1e-8, atol=1e-9)
    # Float32 and vmapped, against the float64 derivative.
    g32 = jax.vmap(jax.grad(loss(spatial.quat_normalize)))(q.astype(jnp.float32))
    assert g32.dtype == jnp.float32
    np.testing.assert_allclose(g32, jax.vmap(jax.grad(loss(plain)))(q), rtol=1e-5, atol=1e-5)
    # At zero: the identity, with a zero (finite) derivative; a NaN stays NaN.
    zero = jnp.zeros((2, 4))
    np.testing.assert_array_equal(jax.grad(loss(spatial.quat_normalize))(zero), 0.0)
    assert np.all(np.isnan(spatial.quat_normalize(jnp.full(4, jnp.nan))))


def test_euler_angles_round_trip_and_order_matters():
    rpy = np.stack([RNG.uniform(-3, 3, 20), RNG.uniform(-1.5, 1.5, 20), RNG.uniform(-3, 3, 20)], 1)
    r = spatial.euler_to_matrix(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    # R = Rz(yaw) Ry(pitch) Rx(roll) is scipy's intrinsic "ZYX" with angles (yaw, pitch, roll).
    expected = Rotation.from_euler("ZYX", rpy[:, ::-1]).as_matrix()
    np.testing.assert_allclose(r, expected, atol=1e-14)
    np.testing.assert_allclose(spatial.matrix_to_euler(r), rpy, atol=1e-12)
    np.testing.assert_allclose(spatial.quat_to_euler(spatial.euler_to_quat(*rpy.T)), rpy, atol=1e-12)
    # Seed 000: Euler angles depend on the order of application.
    a, b = 0.4, 0.7
    rx_then_ry = spatial.euler_to_matrix(a, b, 0.0)  # roll first, then pitch
    ry_then_rx = np.asarray(spatial.euler_to_matrix(a, 0.0, 0.0)) @ np.asarray(spatial.euler_to_matrix(0.0, b, 0.0))
    assert np.max(np.abs(np.asarray(rx_then_ry) - ry_then_rx)) > 0.1


def test_euler_gimbal_lock_still_encodes_the_rotation():
    r = spatial.euler_to_matrix(0.3, np.pi / 2, -0.2)
    rpy = spatial.matrix_to_euler(r)
    np.testing.assert_allclose(spatial.euler_to_matrix(*rpy), r, atol=1e-7)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_euler_angles_encode_the_rotation_at_and_near_the_lock_in_both_precisions(dtype):
    # In float32 cos(pitch) at the lock is round-off (~1e-7), not 0: a fixed lock threshold
    # of 1e-9 read roll and yaw from round-off, and the angles encoded a rotation up to 2
    # off in its entries (0.39 at pitch = pi/2).
    eps = float(jnp.finfo(dtype).eps)
    for pitch in (np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-6, np.pi / 2 - 1e-4, 1.2, -0.4):
        for roll, yaw in ((0.3, -0.2), (2.9, 1.1), (-1.7, -3.0)):
            r = spatial.euler_to_matrix(jnp.asarray(roll, dtype), jnp.asarray(pitch, dtype), jnp.asarray(yaw, dtype))
            rpy = spatial.matrix_to_euler(r)
            assert rpy.dtype == dtype
            assert np.max(np.abs(np.asarray(spatial.euler_to_matrix(*rpy)) - np.asarray(r))) < 20 * eps


def test_gram_schmidt_is_the_seed_algorithm():
    a = scipy_matrix(random_quats(10)) + 0.05 * RNG.normal(size=(10, 3, 3))
    b = np.asarray(spatial.gram_schmidt(a))
    # The seed's formulas, written out independently.
    for ai, bi in zip(a, b, strict=True):
        a1, a2, a3 = ai.T
        b1 = a1 / np.linalg.norm(a1)
        b2 = a2 - (b1 @ a2) * b1
        b2 /= np.linalg.norm(b2)
        np.testing.assert_allclose(bi[:, 0], b1, atol=1e-15)
        np.testing.assert_allclose(bi[:, 1], b2, atol=1e-15)
        np.testing.assert_allclose(bi[:, 2], np.cross(b1, b2), atol=1e-15)
        b3 = a3 - (b1 @ a3) * b1 - (b2 @ a3) * b2
        np.testing.assert_allclose(np.asarray(spatial.gram_schmidt(ai, cross_third=False))[:, 2],
                                   b3 / np.linalg.norm(b3), atol=1e-14)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", b, b), np.broadcast_to(np.eye(3), b.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(b), 1.0, atol=1e-14)


def test_polar_orthonormalize_matches_svd():
    a = scipy_matrix(random_quats(10)) + 0.2 * RNG.normal(size=(10, 3, 3))
    u, _, vt = np.linalg.svd(a)
    np.testing.assert_allclose(spatial.polar_orthonormalize(a), u @ vt, atol=1e-13)
    # Gradients are finite exactly at a rotation, where all singular values coincide.
    g = jax.grad(lambda m: jnp.sum(spatial.polar_orthonormalize(m) ** 3))(jnp.eye(3))
    assert np.all(np.isfinite(g))


def test_rotation_angle_is_accurate_for_tiny_angles():
    for angle in [1e-12, 1e-9, 1e-4, 1.0, 3.0]:
        r = spatial.rotation_matrix_exp(jnp.array([angle, 0.0, 0.0]))
        np.testing.assert_allclose(spatial.rotation_angle(jnp.eye(3), r), angle, rtol=1e-12)


def test_inverse3_and_matmul_match_numpy():
    m = RNG.normal(size=(10, 3, 3)) + 3 * np.eye(3)
    np.testing.assert_allclose(spatial.inverse3(m), np.linalg.inv(m), rtol=1e-12, atol=1e-14)
    n = RNG.normal(size=(10, 3, 3))
    np.testing.assert_allclose(spatial.matmul(m, n), m @ n, atol=1e-14)
    np.testing.assert_allclose(spatial.cross(m[:, 0], n[:, 0]), np.cross(m[:, 0], n[:, 0]), atol=1e-14)


def test_inverse3_of_tiny_and_huge_inertias_in_float32():
    # det is cubic in M: unscaled, a 0.1 mm grain's inertia (4e-15 kg m^2) gave an inf
    # inverse in float32 and a 1000 m body's (4e17) a zero one.
    for moment in (4e-15, 4e-18, 4e17):
        m = jnp.asarray(moment * np.array([[1.0, 0.1, 0.0], [0.1, 2.0, 0.3], [0.0, 0.3, 1.5]]), jnp.float32)
        inv = spatial.inverse3(m)
        assert inv.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(inv)))
        np.testing.assert_allclose(np.asarray(inv, np.float64), np.linalg.inv(np.asarray(m, np.float64)), rtol=1e-5)
    # The derivative is the inverse's, -M^-1 dM M^-1, scale or not.
    m = RNG.normal(size=(3, 3)) + 3 * np.eye(3)
    dm = RNG.normal(size=(3, 3))
    _, tangent = jax.jvp(spatial.inverse3, (m,), (dm,))
    inv = np.linalg.inv(m)
    np.testing.assert_allclose(tangent, -inv @ dm @ inv, rtol=1e-12, atol=1e-14)


def test_float32_stays_float32():
    q = jnp.asarray(random_quats(4), dtype=jnp.float32)
    for out in [spatial.quat_to_matrix(q), spatial.quat_exp(q[:, 1:]), spatial.quat_log(q),
                spatial.matrix_to_quat(spatial.quat_to_matrix(q))]:
        assert out.dtype == jnp.float32
