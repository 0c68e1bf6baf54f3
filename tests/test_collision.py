"""Collision narrow phase against an independent support-function reference.

Reference (numpy/scipy only, nothing from jaxrb): for convex A, B and a unit direction
``n`` (from B to A), ``s(n) = -h_A(-n) - h_B(n)`` with the support function ``h``; the
signed distance is ``max_n s(n)`` (the distance when separated, minus the penetration depth
when overlapping) and the maximiser is the contact normal. Every shape here is centrally
symmetric, so ``s(n) = n.(c_a - c_b) - rho_a(n) - rho_b(n)`` with the projection radius
``rho`` (box: ``sum_i e_i |n.a_i|``; sphere: ``r``; capsule: ``l |n.axis| + r``). It is
maximised over 4000 Fibonacci directions, refined by a shrinking pattern search, then
polished by SLSQP on a smooth lift of the kinks (``t_j >= +-n.b_j``), which converges to
round-off even when the maximum sits on a kink ridge (a box face normal, a capsule side).
For the ground plane ``{n_p.x <= offset}``: ``sd = n_p.c_a - rho_a(n_p) - offset``.

Tolerances (float64, shapes and poses of order 1 m):

* gap vs reference signed distance: 1e-12 m for every pair. Both sides are a few
  float64 operations on O(1) coordinates (round-off ~1e-15); measured max 1e-15.
* ``s(normal)`` at our normal vs our gap: 1e-12 m (our normal attains our gap).
* normal vs the reference maximiser: 1e-6. ``s`` is quadratic about a smooth maximum, so
  a reference converged to ~1e-16 in value pins the direction only to ~sqrt(1e-16)=1e-8.
* surface points ``point +- gap/2 normal`` on each surface (independent signed distance
  functions): 1e-12 m.
"""

import functools

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.optimize import minimize, minimize_scalar  # noqa: E402

from jaxrb import collision  # noqa: E402
from jaxrb.shapes import Box, Capsule, Cone, Cylinder, Plane, Sphere  # noqa: E402

# ============================================================================ reference


def quat_matrix(q):
    """Rotation matrix of a (normalised) scalar-first quaternion."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def fibonacci_sphere(n):
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    rho = np.sqrt(1 - z * z)
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)


FIBONACCI = fibonacci_sphere(4000)
_GRID = np.stack(np.meshgrid(np.linspace(-1, 1, 11), np.linspace(-1, 1, 11)), -1).reshape(-1, 2)


def kinks(body):
    """``rho(n) = sum_j w_j |n.b_j| + C`` of a body ``(kind, size, centre, rotation)``: ``[(w_j, b_j)], C``."""
    kind, size, _, rot = body
    if kind == "sphere":
        return [], size[0]
    if kind == "box":
        return [(size[i], rot[:, i]) for i in range(3)], 0.0
    if kind == "capsule":
        return [(size[1], rot[:, 2])], size[0]
    raise ValueError(kind)


def projection_radius(body, n):
    if body[0] == "cylinder":  # h |n.a| + r |n - (n.a) a|: not of the kinks' form (planes only)
        r, half = body[1]
        axis = body[3][:, 2]  # |n x a|, not sqrt(1 - (n.a)^2): that is 1e-8 at round-off from upright
        return half * np.abs(n @ axis) + r * np.linalg.norm(np.cross(n, axis), axis=-1)
    terms, constant = kinks(body)
    return sum((w * np.abs(n @ b) for w, b in terms), np.full(n.shape[:-1], float(constant)))


def separation(n, a, b):
    """``s(n)`` for unit directions ``n`` of shape ``(m, 3)``."""
    return n @ (a[2] - b[2]) - projection_radius(a, n) - projection_radius(b, n)


def _pattern_search(f, n0, width, tol=1e-9):
    """Shrinking 11x11 grid of directions about ``n0``; moves without shrinking while the best is on the rim."""
    best, value = n0, f(n0[None])[0]
    while width > tol:
        t1 = np.cross(best, [1.0, 0, 0] if abs(best[0]) < 0.9 else [0, 1.0, 0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(best, t1)
        trial = best + width * (_GRID[:, :1] * t1 + _GRID[:, 1:] * t2)
        trial /= np.linalg.norm(trial, axis=1, keepdims=True)
        values = f(trial)
        i = np.argmax(values)
        if values[i] > value:
            best, value = trial[i], values[i]
            if np.max(np.abs(_GRID[i])) == 1:
                continue
        width *= 0.5
    return best


def _slsqp_polish(a, b, n0):
    """SLSQP on the smooth lift  max n.d - sum_j w_j t_j  s.t.  t_j >= +-n.b_j,  |n|^2 = 1."""
    terms = kinks(a)[0] + kinks(b)[0]
    w = np.array([t[0] for t in terms])
    basis = np.array([t[1] for t in terms]).reshape(-1, 3)
    d = a[2] - b[2]
    m = len(w)
    constraints = [
        dict(
            type="eq",
            fun=lambda x: np.array([x[:3] @ x[:3] - 1.0]),
            jac=lambda x: np.concatenate([2 * x[:3], np.zeros(m)])[None],
        )
    ]
    if m:
        lift = np.block([[-basis, np.eye(m)], [basis, np.eye(m)]])
        constraints.append(dict(type="ineq", fun=lambda x: lift @ x, jac=lambda x: lift))
    result = minimize(
        lambda x: -(x[:3] @ d - w @ x[3:]),
        np.concatenate([n0, np.abs(basis @ n0)]),
        jac=lambda x: -np.concatenate([d, -w]),
        constraints=constraints,
        method="SLSQP",
        options=dict(ftol=1e-16, maxiter=200),
    )
    return result.x[:3] / np.linalg.norm(result.x[:3])


def reference_signed_distance(a, b, starts=6):
    """``(sd, normal, unique)``: ``max_n s(n)``, its maximiser, and whether no other local maximum ties it."""

    def f(n):
        return separation(n, a, b)

    values = f(FIBONACCI)
    picked = []
    for i in np.argsort(-values):
        if all(np.linalg.norm(FIBONACCI[i] - FIBONACCI[j]) > 0.15 for j in picked):
            picked.append(i)
        if len(picked) == starts:
            break
    results = []
    for i in picked:
        n = _pattern_search(f, FIBONACCI[i], 0.05)
        polished = _slsqp_polish(a, b, n)
        # Keep whichever is better: each value is s at a true unit direction, a valid lower bound.
        results.append(max((f(n[None])[0], n), (f(polished[None])[0], polished), key=lambda r: r[0]))
    results.sort(key=lambda r: -r[0])
    best, normal = results[0]
    unique = all(np.linalg.norm(n - normal) < 1e-4 or v < best - 1e-7 for v, n in results[1:])
    return best, normal, unique


def surface_distance(body, x):
    """Independent signed distance function of a body at points ``x`` ``(m, 3)``."""
    kind, size, centre, rot = body
    local = (x - centre) @ rot
    if kind == "sphere":
        return np.linalg.norm(local, axis=-1) - size[0]
    if kind == "box":
        q = np.abs(local) - np.asarray(size)
        return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(axis=-1), 0)
    if kind == "capsule":
        r, half = size
        closest = np.stack([np.zeros(len(local)), np.zeros(len(local)), np.clip(local[:, 2], -half, half)], 1)
        return np.linalg.norm(local - closest, axis=-1) - r
    if kind == "cylinder":
        r, half = size
        q = np.stack([np.linalg.norm(local[:, :2], axis=-1) - r, np.abs(local[:, 2]) - half], -1)
        return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(axis=-1), 0)
    raise ValueError(kind)


# ============================================================================ shapes, poses

PLANE = Plane(normal=(0.2, -0.1, 1.0), offset=0.3)
PLANE_NORMAL = np.array(PLANE.normal)
MARGIN = 0.05
SHAPES = {
    "sphere": (Sphere(0.35), ("sphere", (0.35,))),
    "ball": (Sphere(0.5), ("sphere", (0.5,))),
    "box": (Box((0.3, 0.2, 0.2)), ("box", (0.3, 0.2, 0.2))),
    "crate": (Box((0.6, 0.5, 0.4)), ("box", (0.6, 0.5, 0.4))),
    "cube": (Box((0.4, 0.4, 0.4)), ("box", (0.4, 0.4, 0.4))),
    "capsule": (Capsule(0.15, 0.4), ("capsule", (0.15, 0.4))),
    "rod": (Capsule(0.25, 0.3), ("capsule", (0.25, 0.3))),
    "cylinder": (Cylinder(0.2, 0.35), ("cylinder", (0.2, 0.35))),
    "can": (Cylinder(0.15, 0.25), ("cylinder", (0.15, 0.25))),
    "plane": (PLANE, None),
}
# (A, B): every implemented pair, plus reversed orders served by the dispatch.
PAIRS = [
    ("sphere", "plane"),
    ("box", "plane"),
    ("capsule", "plane"),
    ("cylinder", "plane"),
    ("sphere", "ball"),
    ("sphere", "box"),
    ("sphere", "capsule"),
    ("sphere", "cylinder"),
    ("capsule", "rod"),
    ("box", "crate"),
    ("capsule", "box"),
    ("capsule", "cylinder"),
    ("box", "sphere"),
    ("capsule", "sphere"),
    ("box", "capsule"),
    ("cylinder", "sphere"),
    ("cylinder", "capsule"),
]
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
BATCH = 32  # every batch is padded to this size, so each pair compiles once


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def body(name, position, orientation):
    kind, size = SHAPES[name][1]
    return kind, size, np.asarray(position, float), quat_matrix(orientation)


def axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def quat_mul(p, q):
    """Hamilton product (apply q, then p)."""
    pw, pv, qw, qv = p[0], np.asarray(p[1:]), q[0], np.asarray(q[1:])
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def same_point_sets(x, y, atol):
    """Whether the rows of x and y are the same points, in any order."""
    x, y = np.asarray(x), np.asarray(y)
    return (
        len(x) == len(y)
        and all(np.min(np.linalg.norm(y - p, axis=1)) < atol for p in x)
        and all(np.min(np.linalg.norm(x - p, axis=1)) < atol for p in y)
    )


@functools.cache
def sampled_cases(a, b, count=16, seed=0):
    """Random poses, alternately separated within the margin and penetrating (up to 0.3 m).

    Returns ``(pa, qa, pb, qb)`` arrays and the reference ``(sd, normal, unique)`` per case.
    """
    rng = np.random.default_rng(seed)
    poses, refs = [], []
    while len(poses) < count:
        separated = len(poses) % 2 == 0
        qa, qb = random_quats(rng, 2)
        if b == "plane":
            target = rng.uniform(0, MARGIN) if separated else rng.uniform(-0.3, 0)
            shape_a = body(a, np.zeros(3), qa)
            pa = rng.uniform(-1, 1, 3)
            pa += (target + projection_radius(shape_a, PLANE_NORMAL[None])[0] + PLANE.offset - PLANE_NORMAL @ pa) * (
                PLANE_NORMAL
            )
            poses.append((pa, qa, np.zeros(3), IDENTITY))
            refs.append((target, PLANE_NORMAL, True))
            continue
        pa = rng.uniform(-0.9, 0.9, 3)
        pb = rng.uniform(-0.1, 0.1, 3)
        shape_a, shape_b = body(a, pa, qa), body(b, pb, qb)
        coarse = separation(FIBONACCI, shape_a, shape_b).max()  # a lower bound, to reject cheaply
        if not ((0 < coarse < MARGIN) if separated else (-0.3 < coarse < 0)):
            continue
        if "cylinder" in (a, b):  # the support function's polish has no cylinder term
            ref = _cylinder_reference(shape_a, shape_b)
            if "capsule" in (a, b) and _segment_enters_cylinder(shape_a, shape_b):
                continue  # capsule-cylinder's gap is exact only while the segment stays out
        else:
            ref = reference_signed_distance(shape_a, shape_b)
        if ref[0] < MARGIN - 1e-3:
            poses.append((pa, qa, pb, qb))
            refs.append(ref)
    return tuple(np.array(x) for x in zip(*poses, strict=True)), refs


def _cylinder_reference(a, b):
    """``(sd, normal, unique)`` of a sphere or a capsule and a cylinder (either order): the
    cylinder's signed distance function (:func:`surface_distance`) at the sphere's centre,
    or at the capsule's segment point where it is smallest (the function is convex along
    the segment: a grid, then scipy's bounded Brent search), less the radius; the normal
    from that function's central-difference gradient there (B to A); unique where the
    gradient has unit length (not on a kink of the function). For a capsule whose segment
    stays outside the cylinder this is the signed distance; where the segment enters it,
    the deepest segment point's (what capsule-cylinder documents)."""
    other, cylinder, sign = (a, b, 1.0) if b[0] == "cylinder" else (b, a, -1.0)
    point = _deepest_segment_point(other, cylinder) if other[0] == "capsule" else other[2]
    sd = surface_distance(cylinder, point[None])[0] - other[1][0]
    h = 1e-6
    steps = point[None, :] + h * np.concatenate([np.eye(3), -np.eye(3)])
    values = surface_distance(cylinder, steps)
    gradient = (values[:3] - values[3:]) / (2 * h)
    length = np.linalg.norm(gradient)  # 0 where the function is symmetric (the centre)
    return sd, sign * gradient / max(length, 1e-300), abs(length - 1.0) < 1e-6


def _deepest_segment_point(capsule, cylinder):
    """The point of a capsule's segment where the cylinder's signed distance is smallest."""
    _, (_, half), centre, rotation = capsule
    axis = rotation[:, 2]

    def distance(s):
        return surface_distance(cylinder, (centre + s * axis)[None])[0]

    grid = np.linspace(-half, half, 401)
    j = int(np.argmin([distance(s) for s in grid]))
    found = minimize_scalar(distance, bounds=(grid[max(j - 1, 0)], grid[min(j + 1, 400)]), method="bounded",
                            options=dict(xatol=1e-13))
    s = min((found.x, -half, half), key=distance)
    return centre + s * axis


def _segment_enters_cylinder(a, b):
    capsule, cylinder = (a, b) if a[0] == "capsule" else (b, a)
    return surface_distance(cylinder, _deepest_segment_point(capsule, cylinder)[None])[0] <= 0


def _pad(*arrays):
    n = len(arrays[0])
    size = -(-n // BATCH) * BATCH
    return n, [np.concatenate([x, np.repeat(x[-1:], size - n, 0)]) for x in arrays]


@functools.cache
def _batched(a, b):
    """``jit(vmap(collide))`` for one shape pair; the margin is a traced argument, so it does not recompile."""
    sa, sb = SHAPES[a][0], SHAPES[b][0]

    def one(pa, qa, pb, qb, margin):
        return collision.collide(sa, pa, qa, sb, pb, qb, margin)

    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, None)))


def run(a, b, pa, qa, pb, qb, margin=MARGIN, dtype=jnp.float64):
    """Batched, jitted ``collide`` returning numpy arrays (padded batches, one compile per pair and dtype)."""
    n, arrays = _pad(np.asarray(pa), np.asarray(qa), np.asarray(pb), np.asarray(qb))
    c = _batched(a, b)(*(jnp.asarray(x, dtype) for x in arrays), jnp.asarray(margin, dtype))
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[:n], c)


def turned(q, rotation):
    """``normalize((1, rotation/2)) * q``: a unit quaternion turned by a small world-frame rotation vector.

    Gradients and finite differences are taken in these 12 pose coordinates
    ``[pa, rotation_a, pb, rotation_b]`` at ``rotation = 0``, so that every perturbed
    orientation stays a unit quaternion, as in a simulation (the pair functions assume it).
    Works on numpy and jax arrays.
    """
    xp = jnp if isinstance(rotation, jax.Array) else np
    w = xp.concatenate([xp.ones(rotation.shape[:-1] + (1,)), 0.5 * rotation], axis=-1)
    w = w / xp.sqrt(xp.sum(w * w, axis=-1, keepdims=True))
    pw, pv, qw, qv = w[..., :1], w[..., 1:], q[..., :1], q[..., 1:]
    return xp.concatenate([pw * qw - xp.sum(pv * qv, axis=-1, keepdims=True), pw * qv + qw * pv + xp.cross(pv, qv)], -1)


@functools.cache
def _gradient(a, b):
    """``jit(value_and_grad)`` of one scalar w.r.t. the 12 pose coordinates of :func:`turned` (reverse mode).

    The scalar is ``sum(gap * active) + sum(W . point) + sum(V . normal)`` over the slots
    active at the base pose (``mask``), with fixed, distinct weights: a NaN or a wrong
    derivative in any of the three shows up in its gradient. Unbatched: reverse-mode
    box-box is the slowest thing to compile here, and vmap makes it slower still.
    """
    sa, sb = SHAPES[a][0], SHAPES[b][0]

    def scalar(x, q0, weights, mask):
        qa, qb = turned(q0[:4], x[3:6]), turned(q0[4:], x[9:])
        c = collision.collide(sa, x[:3], qa, sb, x[6:9], qb, MARGIN)
        weighted = weights[0] * c.point + weights[1] * c.normal
        return jnp.sum(jnp.where(c.active, c.gap, 0.0)) + jnp.sum(jnp.where(mask[:, None], weighted, 0.0))

    return jax.jit(jax.value_and_grad(scalar))


def gradient(a, b, pa, qa, pb, qb, mask):
    """``(value, gradient (12,), weights)`` of the scalar of :func:`_gradient` at one pose."""
    x = np.concatenate([pa, np.zeros(3), pb, np.zeros(3)])
    k = mask.shape[0]
    weights = np.linspace(0.3, 1.7, 2 * k * 3).reshape(2, k, 3)
    value, grad = _gradient(a, b)(jnp.asarray(x), jnp.asarray(np.concatenate([qa, qb])), weights, jnp.asarray(mask))
    return float(value), np.asarray(grad), weights


def min_active(c):
    """Per case: the index of the deepest active slot and its gap (inf if none)."""
    gaps = np.where(c.active, c.gap, np.inf)
    k = np.argmin(gaps, axis=1)
    return k, gaps[np.arange(len(k)), k]


# ============================================================================ accuracy


@pytest.mark.parametrize("pair", PAIRS, ids="-".join)
def test_gap_and_normal_match_the_support_function_reference(pair):
    """16 random poses per pair, 8 separated within the margin and 8 penetrating (to 0.3 m)."""
    a, b = pair
    (pa, qa, pb, qb), refs = sampled_cases(a, b)
    c = run(a, b, pa, qa, pb, qb)
    k, gap = min_active(c)
    sd = np.array([r[0] for r in refs])
    assert np.all(np.isfinite(gap)), "every case is within the margin, so one slot must be active"
    # 1e-12 m: see the module docstring.
    np.testing.assert_allclose(gap, sd, rtol=0, atol=1e-12)
    normals = c.normal[np.arange(len(k)), k]
    np.testing.assert_allclose(np.linalg.norm(c.normal, axis=-1), 1.0, atol=1e-14)
    for i, (_, n_ref, unique) in enumerate(refs):
        if b == "plane":
            np.testing.assert_allclose(normals[i], n_ref, atol=1e-15)
            continue
        shape_a, shape_b = body(a, pa[i], qa[i]), body(b, pb[i], qb[i])
        # Our normal attains our gap under the independent support functions...
        np.testing.assert_allclose(separation(normals[i][None], shape_a, shape_b)[0], gap[i], atol=1e-12)
        # ...and is the reference maximiser where that is unique.
        if unique:
            np.testing.assert_allclose(normals[i], n_ref, atol=1e-6)
    # Active means gap < margin; no active slot claims a deeper penetration than the true one.
    assert np.all(c.gap[c.active] < MARGIN)
    assert np.all(np.where(c.active, c.gap, np.inf) >= sd[:, None] - 1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_equal_boxes_resting_flat_keep_their_four_corners_in_the_same_slots(dtype):
    """A cube resting flat on an equal one, under tilts and shifts of round-off size (the
    poses of a settled stack): every pose's manifold holds the four corners of the face,
    each corner in the same slot in every pose. Clipping leaves points along the coincident
    edges, as deep as the corners to round-off. Before 2026-12-04 one of them could be
    taken as the deepest point instead of a corner (25 mm from it on a settled 5-box stack),
    and the deepest-first order put the corners in other slots from one pose to the next,
    where the solve's warm start then landed on the wrong corners."""
    with jax.enable_x64(dtype == jnp.float64):
        box = Box((0.1, 0.1, 0.1))
        rng = np.random.default_rng(3)
        tiny = 1e-6 if dtype == jnp.float32 else 1e-13
        n = 64
        axis = rng.normal(size=(n, 3))
        half_angle = 0.5 * tiny * rng.uniform(-1.0, 1.0, size=(n, 1))
        axis /= np.linalg.norm(axis, axis=1)[:, None]
        quat = np.concatenate([np.cos(half_angle), np.sin(half_angle) * axis], 1)
        top = np.array([0.0, 0.0, 0.2]) + tiny * 0.1 * rng.normal(size=(n, 3))
        identity = np.array([1.0, 0.0, 0.0, 0.0])
        contact = jax.jit(jax.vmap(lambda p, q: collision.collide(box, p, q, box, jnp.zeros(3, dtype),
                                                                   jnp.asarray(identity, dtype), margin=0.01)))(
            jnp.asarray(top, dtype), jnp.asarray(quat, dtype))
        assert np.all(np.asarray(contact.active))
        xy = np.asarray(contact.point, float)[..., :2]  # (n, 4, 2)
        corners = np.sign(xy) * 0.1
        np.testing.assert_allclose(xy, corners, atol=1e-5)  # a corner, not a point along an edge
        assert len({tuple(map(tuple, c)) for c in corners}) == 1, "a corner moved to another slot"
        assert len({tuple(c) for c in corners[0]}) == 4  # the four corners, each once


def test_box_box_separation_has_the_signed_distance_roots():
    """The separating-axis value the time-of-impact search uses: the signed distance where
    boxes overlap, a positive lower bound of it where they are apart, zero at touching."""
    from jaxrb.collision._box import box_box_separation

    box, crate = SHAPES["box"][0], SHAPES["crate"][0]
    sep = jax.jit(jax.vmap(lambda *x: box_box_separation(box, x[0], x[1], crate, x[2], x[3])))
    (pa, qa, pb, qb), refs = sampled_cases("box", "crate")
    sd = np.array([r[0] for r in refs])
    value = np.asarray(sep(pa, qa, pb, qb))
    inside = sd < 0
    np.testing.assert_allclose(value[inside], sd[inside], rtol=0, atol=1e-12)
    assert np.all((value[~inside] > 0) & (value[~inside] <= sd[~inside] + 1e-12))
    # Resting flat on the crate (depth 0), overlapping by 1 mm, and 1 mm above it.
    poses = [_box_on_crate(0.3, depth) for depth in (0.0, 1e-3, -1e-3)]
    flat = np.asarray(sep(*(np.array(x) for x in zip(*poses, strict=True)), np.zeros((3, 3)),
                          np.tile(IDENTITY, (3, 1))))
    np.testing.assert_allclose(flat, [0.0, -1e-3, 1e-3], rtol=0, atol=1e-12)


def test_capsule_box_separation_is_the_capsule_box_gap_until_the_segment_meets_the_box():
    """The value the time-of-impact search uses for capsule-box: on the sampled poses, the
    smallest gap of :func:`capsule_box` (1e-12 m; measured 1e-16) with its derivative (1e-6;
    measured 4e-8: the search places the point to ~1e-8 m), wherever the
    segment itself stays out of the box; where it meets the box, negative and no deeper
    than the separating axes' depth. Zero at touching."""
    from jaxrb.collision._capsule import capsule_box_separation

    capsule, box = SHAPES["capsule"][0], SHAPES["box"][0]

    def separation_and_gap(pa, qa, pb, qb, d):
        def both(pa):
            c = collision.capsule_box(capsule, pa, qa, box, pb, qb, margin=MARGIN)
            return capsule_box_separation(capsule, pa, qa, box, pb, qb), jnp.min(jnp.where(c.active, c.gap, jnp.inf))
        return jax.jvp(both, (pa,), (d,))

    run_both = jax.jit(jax.vmap(separation_and_gap))
    (pa, qa, pb, qb), _ = sampled_cases("capsule", "box")
    d = np.random.default_rng(3).normal(size=pa.shape)
    (sep, gap), (dsep, dgap) = (np.asarray(x) for x in np.asarray(run_both(pa, qa, pb, qb, d)))
    apart = gap > -capsule.radius  # the segment itself stays out of the box
    assert 8 <= apart.sum() < len(apart) and np.isfinite(gap).all()  # both kinds are sampled
    np.testing.assert_allclose(sep[apart], gap[apart], rtol=0, atol=1e-12)
    np.testing.assert_allclose(dsep[apart], dgap[apart], rtol=0, atol=1e-6)
    assert np.all((sep[~apart] < 0) & (sep[~apart] >= gap[~apart] - 1e-12))
    # Touching: a capsule lying flat on the box's top face (z = 0.2), and 1 mm into it.
    lying = axis_angle([0, 1, 0], np.pi / 2)
    for depth in (0.0, 1e-3):
        at = np.array([0.05, 0.0, 0.2 + capsule.radius - depth])
        value = capsule_box_separation(capsule, at, lying, box, np.zeros(3), IDENTITY)
        np.testing.assert_allclose(float(value), -depth, rtol=0, atol=1e-12)


def _check_on_surface(distance, deepest, kind):
    """On the surface (1e-12 m); a capsule's extra slot is an end sphere's point, which may lie inside the capsule."""
    if kind == "capsule":
        np.testing.assert_allclose(distance[deepest], 0.0, atol=1e-12)
        assert np.all(distance <= 1e-12)
    else:
        np.testing.assert_allclose(distance, 0.0, atol=1e-12)


@pytest.mark.parametrize("pair", PAIRS, ids="-".join)
def test_contact_points_lie_on_both_surfaces(pair):
    """``point +- gap/2 normal`` lie on A and B (independent signed distance functions).

    Exception, by design: capsule slots are end-sphere (capsule-plane) or overlap-end
    (capsule-capsule) contacts; for a tilted capsule that sphere's extreme point is buried
    in the capsule's cylinder, so only the deepest slot is required on the surface.
    """
    a, b = pair
    (pa, qa, pb, qb), _ = sampled_cases(a, b)
    c = run(a, b, pa, qa, pb, qb)
    k, _ = min_active(c)
    for i in range(len(pa)):
        act = c.active[i]
        deepest = np.flatnonzero(act) == k[i]
        on_a = c.point[i][act] + 0.5 * c.gap[i][act, None] * c.normal[i][act]
        on_b = c.point[i][act] - 0.5 * c.gap[i][act, None] * c.normal[i][act]
        _check_on_surface(surface_distance(body(a, pa[i], qa[i]), on_a), deepest, SHAPES[a][1][0])
        if b == "plane":
            np.testing.assert_allclose(on_b @ PLANE_NORMAL - PLANE.offset, 0.0, atol=1e-12)
        else:
            _check_on_surface(surface_distance(body(b, pb[i], qb[i]), on_b), deepest, SHAPES[b][1][0])


# ============================================================================ manifolds


def _rest_on_plane_pose(name, orientation, depth):
    """Position of a shape whose lowest point is ``depth`` below the (tilted) ground plane."""
    shape = body(name, np.zeros(3), orientation)
    height = projection_radius(shape, PLANE_NORMAL[None])[0] + PLANE.offset - depth
    lateral = np.array([0.3, -0.2, 0.0])
    return height * PLANE_NORMAL + lateral - (lateral @ PLANE_NORMAL) * PLANE_NORMAL


def _tilt_to_plane(spin):
    """Orientation turning body z onto the plane normal, after a spin about body z."""
    z = np.array([0.0, 0.0, 1.0])
    return quat_mul(axis_angle(np.cross(z, PLANE_NORMAL), np.arccos(PLANE_NORMAL @ z)), axis_angle(z, spin))


def test_box_resting_flat_edge_and_corner_on_plane():
    """On the tilted ground, 4 mm deep, margin 1 cm: flat -> 4 active corners, on an edge -> 2, on a corner -> 1."""
    depth = 0.004
    flat = _tilt_to_plane(0.7)
    edge = quat_mul(_tilt_to_plane(0.7), axis_angle([1, 0, 0], np.pi / 4))
    corner = quat_mul(_tilt_to_plane(0.2), quat_mul(axis_angle([1, 0, 0], 0.6), axis_angle([0, 1, 0], 0.5)))
    poses = [flat, edge, corner]
    pa = np.array([_rest_on_plane_pose("box", q, depth) for q in poses])
    c = run("box", "plane", pa, np.array(poses), np.zeros((3, 3)), np.tile(IDENTITY, (3, 1)), margin=0.01)
    assert list(c.active.sum(axis=1)) == [4, 2, 1]
    # Flat: the four bottom corners (body z = -half height), each at gap -depth.
    np.testing.assert_allclose(c.gap[0], -depth, atol=1e-14)
    on_box = c.point[0] + 0.5 * c.gap[0][:, None] * c.normal[0]
    assert same_point_sets(on_box, _box_bottom(pa[0], flat), 1e-13)
    np.testing.assert_allclose(c.normal[0], np.broadcast_to(PLANE_NORMAL, (4, 3)), atol=0)
    np.testing.assert_allclose(c.gap[1][c.active[1]], -depth, atol=1e-14)


def test_capsule_lying_on_plane_has_both_ends_active():
    q = quat_mul(_tilt_to_plane(0.4), axis_angle([0, 1, 0], np.pi / 2))  # axis in the plane
    pa = _rest_on_plane_pose("capsule", q, 0.003)
    c = run("capsule", "plane", pa[None], q[None], np.zeros((1, 3)), IDENTITY[None], margin=0.01)
    assert c.active.all()
    np.testing.assert_allclose(c.gap, -0.003, atol=1e-14)


def test_cylinder_on_plane_stands_on_its_rim_and_lies_on_a_line():
    """On the tilted ground, 3 mm deep, margin 1 cm. Standing on a cap: five slots at that
    depth, the cap's centre and four rim points 90 degrees apart, whose square holds the
    centre. Lying: both rims' lowest points (the contact line's ends), the other slots
    far above. Tilted by 0.3 rad onto its rim: one slot, at the exact depth."""
    depth, (r, half) = 0.003, SHAPES["cylinder"][1][1]
    standing = _tilt_to_plane(0.5)
    lying = quat_mul(_tilt_to_plane(0.5), axis_angle([1, 0, 0], np.pi / 2))
    tilted = quat_mul(_tilt_to_plane(0.5), axis_angle([1, 0.4, 0], 0.3))
    poses = [standing, lying, tilted]
    pa = np.array([_rest_on_plane_pose("cylinder", q, depth) for q in poses])
    c = run("cylinder", "plane", pa, np.array(poses), np.zeros((3, 3)), np.tile(IDENTITY, (3, 1)), margin=0.01)
    assert list(c.active.sum(axis=1)) == [5, 2, 1]
    on_cylinder = c.point + 0.5 * c.gap[..., None] * c.normal
    # Standing: the bottom cap's centre and four rim points, a square around it.
    np.testing.assert_allclose(c.gap[0], -depth, atol=1e-14)
    cap_centre = pa[0] - half * quat_matrix(standing)[:, 2]
    radial = np.linalg.norm(on_cylinder[0] - cap_centre, axis=1)
    np.testing.assert_allclose(np.sort(radial), [0.0, r, r, r, r], atol=1e-13)
    np.testing.assert_allclose(np.mean(on_cylinder[0][radial > r / 2], axis=0), cap_centre, atol=1e-13)
    # Lying: the two ends of the contact line, 2 h apart along the axis.
    active = on_cylinder[1][c.active[1]]
    np.testing.assert_allclose(c.gap[1][c.active[1]], -depth, atol=1e-14)
    np.testing.assert_allclose(np.abs((active[0] - active[1]) @ quat_matrix(lying)[:, 2]), 2 * half, atol=1e-13)
    assert np.all(c.gap[1][~c.active[1]] > 0.3 * r)
    # Tilted: the rim's lowest point, at the exact depth.
    np.testing.assert_allclose(c.gap[2][c.active[2]], -depth, atol=1e-14)


@pytest.mark.parametrize("name", ["cylinder", "box"])
def test_a_body_standing_on_the_ground_keeps_all_its_slots_on_its_base_under_jit(name):
    """400 poses standing on the ground, tilted by 1e-13 to 1e-3 rad (turned about the
    vertical at random), 1 um off touching: the jit-compiled, vmapped pair function equals
    the op-by-op one, and every slot is on the base (its gap under 0.1 mm) where the tilt
    is below 1e-4. The rank selection of the four deepest candidates, compiled with the
    candidates' heights in one fusion, had dropped a base point of 8 of these cylinders
    (then on a tripod of rim points) for a point of the top cap (gap 0.3 m), so the can
    stood on three points; op by op it kept all four."""
    rng = np.random.default_rng(0)
    n = 400
    shape = Cylinder(0.1, 0.15) if name == "cylinder" else Box((0.1, 0.1, 0.15))
    rotation = rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-13, -3, (n, 1))
    rotation[:, 2] = rng.uniform(-3, 3, n)
    q = np.array([axis_angle(r, np.linalg.norm(r)) for r in rotation])
    p = np.concatenate([rng.uniform(-1, 1, (n, 2)), 0.15 + rng.normal(size=(n, 1)) * 1e-6], 1)

    def slots(p, q):
        return collision.collide(shape, p, q, Plane(), margin=0.11)

    compiled, op_by_op = jax.jit(jax.vmap(slots))(p, q), jax.vmap(slots)(p, q)
    np.testing.assert_allclose(np.sort(compiled.gap, 1), np.sort(op_by_op.gap, 1), rtol=0, atol=1e-14)
    upright = np.linalg.norm(rotation[:, :2], axis=1) < 1e-4
    assert upright.sum() > 300 and np.all(np.asarray(compiled.gap)[upright] < 1e-4)


def test_a_nearly_upright_cylinder_has_bounded_contact_point_derivatives():
    """Tilted from upright by 1e-12 to 1e-6 rad, a cylinder's contact points move with the
    tilt at most ``r / TILT_RAMP`` (m/rad): the deepest rim point is ``e - r w / max(|w|,
    TILT_RAMP)``. With ``w / |w|`` it moves as ``r / tilt``, up to 2e11 here. The gap keeps
    the derivative of the plane's distance (at most ``r + h``)."""
    from jaxrb.collision._plane import TILT_RAMP

    shape, (r, half) = SHAPES["cylinder"][0], SHAPES["cylinder"][1][1]
    upright = _tilt_to_plane(0.5)
    position = _rest_on_plane_pose("cylinder", upright, 0.0)

    def slots(rotation, tilt):
        c = collision.collide(shape, jnp.asarray(position), turned(jnp.asarray(upright), rotation + tilt), PLANE,
                              margin=MARGIN)
        return jnp.concatenate([c.point.reshape(-1), c.gap])

    jacobian = jax.jit(jax.jacfwd(slots))
    for size in (1e-12, 1e-9, 1e-6):
        tilt = size * np.array([0.6, 0.8, 0.0])
        d = np.asarray(jacobian(jnp.zeros(3), jnp.asarray(tilt)))
        assert np.all(np.isfinite(d))
        assert np.max(np.abs(d[:15])) <= 1.01 * r / TILT_RAMP
        assert np.max(np.abs(d[15:])) <= 1.01 * (r + half)


# Box-box manifolds: the small "box" (0.3, 0.2, 0.2) on the big "crate" (0.6, 0.5, 0.4),
# whose top face is z = 0.4; equal cubes (0.4) for the octagon, the crossed edges and the corners.
BOX_HALF = np.array([0.3, 0.2, 0.2])


def _box_on_crate(spin, depth, tilt=0.0, offset=(0.1, -0.05)):
    q = quat_mul(axis_angle([0, 0, 1], spin), axis_angle([1, 0, 0], tilt))
    return np.array([offset[0], offset[1], 0.4 + 0.2 - depth]), q


def _box_bottom(pa, qa):
    return pa + np.array([[sx, sy, -1.0] for sx in (-1, 1) for sy in (-1, 1)]) * BOX_HALF @ quat_matrix(qa).T


def test_box_flat_on_bigger_box_gives_four_corners():
    """Face-face, turned 0.3 rad about z, penetrating by depth: A's four bottom corners, gap -depth.

    A's bottom face is the reference (SAT tie between A's and B's face normals, broken
    towards A); the crate as reference is covered by the random cases.
    """
    depth = 0.003
    pa, qa = _box_on_crate(0.3, depth)
    c = run("box", "crate", pa[None], qa[None], np.zeros((1, 3)), IDENTITY[None], margin=0.01)
    assert c.active[0].sum() == 4
    np.testing.assert_allclose(c.gap[0], -depth, atol=1e-14)
    np.testing.assert_allclose(c.normal[0], np.broadcast_to([0, 0, 1.0], (4, 3)), atol=1e-15)
    # The midpoints lie halfway between the box's bottom corners and the crate's top.
    np.testing.assert_allclose(c.point[0][:, 2], 0.4 - depth / 2, atol=1e-14)
    assert same_point_sets(c.point[0][:, :2], _box_bottom(pa, qa)[:, :2], 1e-13)


def test_box_overhanging_the_edge_gives_the_clipped_rectangle():
    """Zero relative rotation (SAT ties between A's and B's z axes), the box hanging over the
    crate's +x edge: the overlap rectangle, two of its corners cut by the crate's side plane."""
    depth = 0.002
    pa = np.array([0.45, 0.1, 0.6 - depth])
    c = run("box", "crate", pa[None], IDENTITY[None], np.zeros((1, 3)), IDENTITY[None], margin=0.01)
    assert c.active[0].sum() == 4
    np.testing.assert_allclose(c.gap[0], -depth, atol=1e-14)
    expected = np.array([[x, y] for x in (0.15, 0.6) for y in (-0.1, 0.3)])
    assert same_point_sets(c.point[0][:, :2], expected, 1e-13)
    np.testing.assert_allclose(c.normal[0], np.broadcast_to([0, 0, 1.0], (4, 3)), atol=0)


def test_rotated_square_on_square_keeps_a_well_spread_four_of_eight():
    """Two cubes, one turned 45 degrees about z: the clipped face is an octagon, reduced to 4 points."""
    depth = 0.001
    q = axis_angle([0, 0, 1], np.pi / 4)
    pa = np.array([0.0, 0.0, 0.8 - depth])
    c = run("cube", "cube", pa[None], q[None], np.zeros((1, 3)), IDENTITY[None], margin=0.01)
    assert c.active[0].sum() == 4
    np.testing.assert_allclose(c.gap[0], -depth, atol=1e-14)
    xy = c.point[0][:, :2]
    octagon_radius = 0.4 / np.cos(np.pi / 8)  # circumradius of the regular octagon
    np.testing.assert_allclose(np.linalg.norm(xy, axis=1), octagon_radius, atol=1e-13)
    # Well spread: the 4 picks cover at least 0.7 of the octagon's area (the best 4 of its
    # 8 vertices, a square, cover 1/sqrt(2) = 0.707; 4 adjacent ones only 0.5).
    order = np.argsort(np.arctan2(xy[:, 1], xy[:, 0]))
    x, y = xy[order].T
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    octagon_area = 2 * np.sqrt(2) * octagon_radius**2
    assert area >= 0.7 * octagon_area


def test_slightly_tilted_box_on_box_has_four_points_with_graded_gaps():
    pa, qa = _box_on_crate(0.3, 0.003, tilt=0.01)
    c = run("box", "crate", pa[None], qa[None], np.zeros((1, 3)), IDENTITY[None], margin=0.01)
    assert c.active[0].sum() == 4
    # Tilting by 0.01 rad about x raises one long edge by 2 * 0.2 * sin(0.01) = 4e-3 over the other.
    np.testing.assert_allclose(np.ptp(c.gap[0]), 0.4 * np.sin(0.01), rtol=1e-3)
    shape_a, shape_b = body("box", pa, qa), body("crate", np.zeros(3), IDENTITY)
    sd, _, _ = reference_signed_distance(shape_a, shape_b)
    np.testing.assert_allclose(c.gap[0].min(), sd, atol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_a_cube_resting_on_an_equal_cube_keeps_four_points_under_a_small_tilt(dtype):
    """Equal cubes stacked edge over edge, the top one tilted by 1e-6, 1e-4 or 3e-3 rad about
    10 random axes, its lowest corner 10 um into the lower one: four points each. Their edges
    lie over each other, so the axes of crossing edges beat the face normal by a hair; with
    a round-off tolerance alone, 12 of these 30 poses got the one-point edge contact in
    float64 (a 5-box stack then jolted to 0.023 m/s), none in float32, whose round-off
    (2.4e-5 m here) is larger than the depth. The deepest point is
    the exact depth to EDGE_PREFERENCE times the half-extent (0.4 mm here)."""
    from jaxrb.collision._box import EDGE_PREFERENCE

    rng = np.random.default_rng(3)
    depth, poses = 1e-5, []
    for tilt in (1e-6, 1e-4, 3e-3):
        for axis in rng.normal(size=(10, 3)):
            q = axis_angle(axis, tilt)
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * 0.4
            lowest = (corners @ quat_matrix(q).T)[:, 2].min()
            poses.append((np.array([0.0, 0.0, 0.4 - depth - lowest]), q))
    pa, qa = (np.array(x) for x in zip(*poses, strict=True))
    n = len(pa)
    c = run("cube", "cube", pa, qa, np.zeros((n, 3)), np.tile(IDENTITY, (n, 1)), margin=0.01, dtype=dtype)
    assert np.all(c.active.sum(axis=1) == 4)
    if dtype == jnp.float64:
        sd = np.array([reference_signed_distance(body("cube", pa[i], qa[i]), body("cube", np.zeros(3), IDENTITY))[0]
                       for i in range(n)])
        gap = np.where(c.active, c.gap, np.inf).min(axis=1)
        assert np.all((gap <= sd + 1e-12) & (gap >= sd - EDGE_PREFERENCE * 0.4 - 1e-12))


def test_crossed_edges_give_one_contact():
    """Two cubes on their edges, the edges crossed at right angles: one edge-edge point."""
    depth = 0.004
    qa = axis_angle([1, 0, 0], np.pi / 4)  # A's lowest edge along x
    qb = axis_angle([0, 1, 0], np.pi / 4)  # B's highest edge along y
    pa = np.array([0.01, -0.02, 2 * 0.4 * np.sqrt(2) - depth])
    c = run("cube", "cube", pa[None], qa[None], np.zeros((1, 3)), qb[None], margin=0.01)
    assert c.active[0].sum() == 1
    k = np.argmax(c.active[0])
    np.testing.assert_allclose(c.gap[0, k], -depth, atol=1e-14)
    np.testing.assert_allclose(c.normal[0, k], [0, 0, 1], atol=1e-14)
    # A's edge runs along x at y = -0.02, B's along y at x = 0: they cross at (0, -0.02).
    np.testing.assert_allclose(c.point[0, k], [0.0, -0.02, 0.4 * np.sqrt(2) - depth / 2], atol=1e-14)


def test_box_edge_on_face_gives_two_contacts():
    depth = 0.002
    qa = axis_angle([1, 0, 0], np.pi / 4)  # the lowest edge runs along x, (0.2 + 0.2)/sqrt(2) below the centre
    pa = np.array([0.0, 0.1, 0.4 + 0.4 / np.sqrt(2) - depth])
    c = run("box", "crate", pa[None], qa[None], np.zeros((1, 3)), IDENTITY[None], margin=0.01)
    assert c.active[0].sum() == 2
    np.testing.assert_allclose(c.gap[0][c.active[0]], -depth, atol=1e-14)
    np.testing.assert_allclose(np.sort(c.point[0][c.active[0], 0]), [-0.3, 0.3], atol=1e-14)


@pytest.mark.parametrize("spin_degrees", [0.0, 10.0, 20.0, 30.0])
def test_an_edge_parallel_to_a_face_within_the_margin_keeps_the_faces_distance(spin_degrees):
    """Separated boxes whose edges lie parallel to a face: edge axes tie with the face axis
    there, and the edge pair tried as the closest may not be. Slot 0 once took it over the
    face manifold's own exact pair: a plank across a block 1 cm above it, spun 20 degrees,
    got a slot at 0.30 m with a normal 70 degrees off +z; a box on its edge across a face,
    a second active slot at 0.04 m with a normal 45 degrees off."""
    spin = axis_angle([0, 0, 1], np.radians(spin_degrees))
    plank, block, clearance = Box((0.8, 0.1, 0.1)), Box((0.2, 0.5, 0.25)), 0.01
    c = collision.collide(plank, np.array([0.0, 0.0, 0.25 + 0.1 + clearance]), spin,
                          block, np.zeros(3), IDENTITY, margin=0.05)
    assert np.all(c.active)  # the plank's underside over the block's top: four corners of the overlap
    np.testing.assert_allclose(c.gap, clearance, atol=1e-12)
    np.testing.assert_allclose(c.normal, np.broadcast_to([0.0, 0.0, 1.0], (4, 3)), atol=1e-12)

    # A box on one of its edges, the edge across a larger box's top face, 2 cm above it.
    on_edge = quat_mul(spin, axis_angle([1, 0, 0], np.pi / 4))
    bar = Box((1.0, 0.2, 0.2))
    c = collision.collide(bar, np.array([0.0, 0.0, 0.3 + 0.02 + 0.2 * np.sqrt(2)]), on_edge,
                          Box((0.3, 0.3, 0.3)), np.zeros(3), IDENTITY, margin=0.05)
    assert int(np.sum(c.active)) == 2  # where the edge leaves the face, on both sides
    np.testing.assert_allclose(np.asarray(c.gap)[np.asarray(c.active)], 0.02, atol=1e-12)
    np.testing.assert_allclose(np.asarray(c.normal)[np.asarray(c.active)], [[0, 0, 1.0]] * 2, atol=1e-12)


def test_corner_facing_corner_within_margin_reports_the_diagonal_distance():
    """Separated boxes whose closest features are two corners: no face overlaps, and the
    separating axes underestimate the gap; the exact closest pair must be reported."""
    gap = 0.02
    pa = np.full(3, 0.8 + gap / np.sqrt(3))
    c = run("cube", "cube", pa[None], IDENTITY[None], np.zeros((1, 3)), IDENTITY[None], margin=0.05)
    assert c.active[0].sum() == 1
    k = np.argmax(c.active[0])
    np.testing.assert_allclose(c.gap[0, k], gap, atol=1e-14)
    np.testing.assert_allclose(c.normal[0, k], np.full(3, 1 / np.sqrt(3)), atol=1e-14)


def test_parallel_capsules_give_two_points_and_crossed_ones_one():
    depth = 0.002
    lying = axis_angle([0, 1, 0], np.pi / 2)  # axis along x
    # Parallel along x: A ("capsule", half length 0.4) spans [-0.3, 0.5], B ("rod", 0.3) [-0.3, 0.3].
    pa = np.array([0.1, 0.0, 0.15 + 0.25 - depth])
    parallel = (pa, lying, np.array([0.0, 0.0, 0.0]), lying)
    crossed = (pa, lying, np.zeros(3), axis_angle([1, 0, 0], np.pi / 2))  # B along y
    tee = (np.array([0.0, 0.0, 0.3 + 0.25 + 0.15 - depth]), lying, np.zeros(3), IDENTITY)  # on B's top end
    poses = [np.array(x) for x in zip(parallel, crossed, tee, strict=True)]
    c = run("capsule", "rod", *poses, margin=0.01)
    assert list(c.active.sum(axis=1)) == [2, 1, 1]
    np.testing.assert_allclose(c.gap[0], -depth, atol=1e-14)
    np.testing.assert_allclose(np.sort(c.point[0][:, 0]), [-0.3, 0.3], atol=1e-14)
    np.testing.assert_allclose(c.normal[0], [[0, 0, 1.0]] * 2, atol=1e-15)


def test_a_capsule_on_a_cylinder_lies_on_two_points_and_crosses_on_one():
    """The capsule (r 0.15, h 0.4) 2 mm into the cylinder (r 0.2, h 0.35), margin 1 cm.
    Lying across the top cap: the two ends of the part of its segment over the cap's disc,
    on the rim at x = -+0.2. Lying along the side: the ends of the part within the caps'
    slab, z = -0.3 and 0.35. Across the side, perpendicular to the axis: one point."""
    depth = 0.002
    lying = axis_angle([0, 1, 0], np.pi / 2)  # axis along x
    across = axis_angle([1, 0, 0], np.pi / 2)  # axis along y
    poses = [(np.array([0.05, 0.0, 0.5 - depth]), lying), (np.array([0.35 - depth, 0.0, 0.1]), IDENTITY),
             (np.array([0.35 - depth, 0.0, 0.0]), across)]
    pa, qa = (np.array(x) for x in zip(*poses, strict=True))
    c = run("capsule", "cylinder", pa, qa, np.zeros((3, 3)), np.tile(IDENTITY, (3, 1)), margin=0.01)
    assert list(c.active.sum(axis=1)) == [2, 2, 1]
    on_cylinder = c.point - 0.5 * c.gap[..., None] * c.normal
    np.testing.assert_allclose(c.gap[:2], -depth, atol=1e-14)
    np.testing.assert_allclose(np.sort(on_cylinder[0][:, 0]), [-0.2, 0.2], atol=1e-14)
    np.testing.assert_allclose(on_cylinder[0][:, 2], 0.35, atol=1e-14)
    np.testing.assert_allclose(c.normal[0], [[0, 0, 1.0]] * 2, atol=1e-15)
    np.testing.assert_allclose(np.sort(on_cylinder[1][:, 2]), [-0.3, 0.35], atol=1e-14)
    np.testing.assert_allclose(c.normal[1], [[1.0, 0, 0]] * 2, atol=1e-15)
    np.testing.assert_allclose(c.gap[2][c.active[2]], -depth, atol=1e-14)
    np.testing.assert_allclose(on_cylinder[2][c.active[2]], [[0.2, 0.0, 0.0]], atol=1e-8)


def test_capsule_cylinder_separation_is_the_smallest_capsule_cylinder_gap():
    """The value the time-of-impact search uses for capsule-cylinder: on the sampled poses
    (the segment outside the cylinder), the smallest gap of :func:`capsule_cylinder` and
    its derivative; zero when lying on the cap, -1 mm when 1 mm into it."""
    from jaxrb.collision._capsule import capsule_cylinder_separation

    capsule, cylinder = SHAPES["capsule"][0], SHAPES["cylinder"][0]

    def separation_and_gap(pa, qa, pb, qb, d):
        def both(pa):
            c = collision.capsule_cylinder(capsule, pa, qa, cylinder, pb, qb, margin=MARGIN)
            return (capsule_cylinder_separation(capsule, pa, qa, cylinder, pb, qb),
                    jnp.min(jnp.where(c.active, c.gap, jnp.inf)))
        return jax.jvp(both, (pa,), (d,))

    (pa, qa, pb, qb), _ = sampled_cases("capsule", "cylinder")
    d = np.random.default_rng(3).normal(size=pa.shape)
    (sep, gap), (dsep, dgap) = (np.asarray(x) for x in np.asarray(jax.jit(jax.vmap(separation_and_gap))(
        pa, qa, pb, qb, d)))
    assert np.isfinite(gap).all() and (gap < 0).sum() >= 4
    np.testing.assert_allclose(sep, gap, rtol=0, atol=1e-12)
    np.testing.assert_allclose(dsep, dgap, rtol=0, atol=1e-6)
    lying = axis_angle([0, 1, 0], np.pi / 2)
    for depth in (0.0, 1e-3):
        at = np.array([0.05, 0.0, 0.35 + capsule.radius - depth])
        value = capsule_cylinder_separation(capsule, at, lying, cylinder, np.zeros(3), IDENTITY)
        np.testing.assert_allclose(float(value), -depth, rtol=0, atol=1e-12)


def test_a_capsule_whose_segment_enters_a_cylinder_is_pushed_out_at_its_deepest_point():
    """Where the segment enters the cylinder, the documented gap: the cylinder's signed
    distance at the segment's deepest point less the radius (independent reference, 1e-9:
    the reference's Brent search stops at a kink), with that point's normal; never deeper
    than the true penetration (a lower bound of the signed distance over 4000 directions)."""
    rng = np.random.default_rng(5)
    poses, refs = [], []
    while len(poses) < 12:
        pa, (qa, qb) = rng.uniform(-0.4, 0.4, 3), random_quats(rng, 2)
        shape_a, shape_b = body("capsule", pa, qa), body("cylinder", np.zeros(3), qb)
        if _segment_enters_cylinder(shape_a, shape_b):
            poses.append((pa, qa, np.zeros(3), qb))
            refs.append((_cylinder_reference(shape_a, shape_b), separation(FIBONACCI, shape_a, shape_b).max()))
    pa, qa, pb, qb = (np.array(x) for x in zip(*poses, strict=True))
    c = run("capsule", "cylinder", pa, qa, pb, qb)
    k, gap = min_active(c)
    np.testing.assert_allclose(gap, [r[0][0] for r in refs], rtol=0, atol=1e-9)
    assert np.all(gap <= -SHAPES["capsule"][1][1][0])
    assert np.all(gap >= np.array([r[1] for r in refs]) - 1e-12)
    for i, ((_, normal, unique), _) in enumerate(refs):
        if unique:
            np.testing.assert_allclose(c.normal[i, k[i]], normal, atol=1e-6)


# ============================================================================ degenerate cases


def _degenerate_cases():
    """(name, A, B, poses (pa, qa, pb, qb), expected gap of the deepest slot or None)."""
    q = axis_angle([0.3, -0.5, 0.8], 0.9)
    z = np.zeros(3)
    lying = axis_angle([0, 1, 0], np.pi / 2)
    cases = [
        ("sphere touching plane", "sphere", "plane", (_rest_on_plane_pose("sphere", q, 0.0), q, z, IDENTITY), 0.0),
        (
            "box flat on plane",
            "box",
            "plane",
            (_rest_on_plane_pose("box", _tilt_to_plane(0.3), 0.0), _tilt_to_plane(0.3), z, IDENTITY),
            0.0,
        ),
        (
            "capsule lying on plane",
            "capsule",
            "plane",
            (
                _rest_on_plane_pose("capsule", quat_mul(_tilt_to_plane(0.1), lying), 0.0),
                quat_mul(_tilt_to_plane(0.1), lying),
                z,
                IDENTITY,
            ),
            0.0,
        ),
        # Exactly upright (tilt at round-off, inside the deepest rim point's ramp) and lying.
        ("cylinder standing on plane", "cylinder", "plane",
         (_rest_on_plane_pose("cylinder", _tilt_to_plane(0.3), 0.0), _tilt_to_plane(0.3), z, IDENTITY), 0.0),
        ("cylinder lying on plane", "cylinder", "plane",
         (_rest_on_plane_pose("cylinder", quat_mul(_tilt_to_plane(0.1), lying), 0.0),
          quat_mul(_tilt_to_plane(0.1), lying), z, IDENTITY), 0.0),
        ("coincident spheres", "sphere", "ball", (z, q, z, IDENTITY), -0.85),
        ("spheres touching", "sphere", "ball", (np.array([0.0, 0.85, 0.0]), q, z, q), 0.0),
        # The box (0.3, 0.2, 0.2): its centre is equally far from the y and z faces (a tie).
        ("sphere centre at box centre", "sphere", "box", (z, IDENTITY, z, IDENTITY), -0.55),
        ("sphere centre on a face", "sphere", "box", (np.array([0.1, 0.2, -0.1]), IDENTITY, z, IDENTITY), -0.35),
        ("sphere centre on an edge", "sphere", "box", (np.array([0.3, 0.2, 0.1]), IDENTITY, z, IDENTITY), -0.35),
        ("sphere centre on a corner", "sphere", "box", (np.array([0.3, 0.2, 0.2]), IDENTITY, z, IDENTITY), -0.35),
        ("sphere touching a face", "sphere", "box", (np.array([0.0, 0.0, 0.55]), IDENTITY, z, IDENTITY), 0.0),
        # The cylinder (r 0.2, h 0.35): from its centre the side is nearer than the caps.
        ("sphere centre at cylinder centre", "sphere", "cylinder", (z, IDENTITY, z, q), -0.55),
        ("sphere centre on cylinder axis", "sphere", "cylinder", (0.3 * quat_matrix(q)[:, 2], IDENTITY, z, q), -0.4),
        # Nearer the side: its radial direction is round-off, which jit rounded two ways
        # (a normal of length 1.15 before body x was taken within round-off of the axis).
        ("sphere centre on cylinder axis, side nearer", "sphere", "cylinder",
         (0.1 * quat_matrix(q)[:, 2], IDENTITY, z, q), -0.55),
        ("sphere centre on cylinder rim", "sphere", "cylinder", (np.array([0.2, 0.0, 0.35]), IDENTITY, z, IDENTITY),
         -0.35),
        ("sphere touching cylinder side", "sphere", "cylinder", (np.array([0.0, 0.55, 0.1]), IDENTITY, z, IDENTITY),
         0.0),
        # The capsule (r 0.15, h 0.4) against the cylinder: lying across the top cap, along
        # the side, and with its segment on the cylinder's axis (a flat minimum, -0.2 m
        # along 0.3 m of the segment).
        ("capsule lying across a cylinder cap", "capsule", "cylinder",
         (np.array([0.05, 0.0, 0.5]), lying, z, IDENTITY), 0.0),
        ("capsule along a cylinder side", "capsule", "cylinder", (np.array([0.35, 0.0, 0.1]), IDENTITY, z, IDENTITY),
         0.0),
        ("capsule segment on cylinder axis", "capsule", "cylinder", (z, q, z, q), -0.35),
        ("sphere centre on capsule axis", "sphere", "capsule", (z, IDENTITY, z, q), -0.5),
        ("sphere centre at capsule end", "sphere", "capsule", (np.array([0, 0, 0.4]), IDENTITY, z, IDENTITY), -0.5),
        ("parallel capsules touching", "capsule", "rod", (np.array([0.4, 0.0, 0.1]), IDENTITY, z, IDENTITY), 0.0),
        ("identical capsule poses", "capsule", "rod", (z, q, z, q), -0.4),
        ("crossing capsule axes", "capsule", "rod", (z, lying, z, IDENTITY), -0.4),
        ("identical box poses", "box", "crate", (z, q, z, q), -0.6),
        ("aligned boxes stacked", "box", "crate", (np.array([0.0, 0.0, 0.6]), IDENTITY, z, IDENTITY), 0.0),
        ("boxes, zero relative rotation, offset", "box", "crate", (np.array([0.2, 0.1, 0.5]), q, z, q), None),
        ("boxes corner to corner", "box", "crate", (np.array([0.9, 0.7, 0.6]), IDENTITY, z, IDENTITY), 0.0),
    ]
    return cases


DEGENERATE = _degenerate_cases()


@pytest.mark.parametrize("case", DEGENERATE, ids=[c[0] for c in DEGENERATE])
def test_degenerate_cases_have_finite_values_and_gradients(case):
    _, a, b, poses, expected = case
    poses = [np.asarray(p, float)[None] for p in poses]
    c = run(a, b, *poses)
    for leaf in (c.point, c.normal, c.gap):
        assert np.all(np.isfinite(leaf))
    np.testing.assert_allclose(np.linalg.norm(c.normal, axis=-1), 1.0, atol=1e-14)
    assert c.active.any()
    if expected is not None:
        np.testing.assert_allclose(min_active(c)[1], expected, atol=1e-14)
    if b != "plane":
        reference = _cylinder_reference if b == "cylinder" else reference_signed_distance
        ref, _, _ = reference(body(a, *[p[0] for p in poses[:2]]), body(b, *[p[0] for p in poses[2:]]))
        np.testing.assert_allclose(min_active(c)[1], ref, atol=1e-12)
    value, grad, _ = gradient(a, b, *(p[0] for p in poses), c.active[0])
    assert np.isfinite(value) and np.all(np.isfinite(grad))


def test_coincident_centres_use_the_documented_fallback_normals():
    z = np.zeros(3)
    q = axis_angle([0.3, -0.5, 0.8], 0.9)
    c = run("sphere", "ball", z[None], q[None], z[None], q[None])
    np.testing.assert_allclose(c.normal[0, 0], [0, 0, 1.0], atol=0)  # world +z
    c = run("sphere", "capsule", z[None], IDENTITY[None], z[None], q[None])
    np.testing.assert_allclose(c.normal[0, 0], quat_matrix(q)[:, 0], atol=1e-15)  # capsule body x


# ============================================================================ gradients


def _central_differences(a, b, pa, qa, pb, qb, weights, mask, h=1e-6):
    """Central differences of the scalar of :func:`gradient` in the 12 pose coordinates."""
    steps = np.concatenate([np.eye(12) * h, -np.eye(12) * h])
    c = run(a, b, pa + steps[:, :3], turned(qa, steps[:, 3:6]), pb + steps[:, 6:9], turned(qb, steps[:, 9:]))
    weighted = weights[0] * c.point + weights[1] * c.normal
    scalar = np.sum(np.where(c.active, c.gap, 0.0), axis=1) + np.sum(
        np.where(mask[None, :, None], weighted, 0.0), axis=(1, 2)
    )
    return (scalar[:12] - scalar[12:]) / (2 * h)


@pytest.mark.parametrize("pair", PAIRS[:12], ids="-".join)
def test_gradients_match_finite_differences(pair):
    """Reverse-mode gradient of gaps, points and normals vs central differences, h = 1e-6.

    On configurations away from any switch (the sampled poses), the truncation error is
    ~h^2 |f'''| ~ 1e-11 and the round-off ~eps/h ~ 1e-10: tolerance 1e-7. Reversed pairs
    are flips of these (tested in the API section).
    """
    a, b = pair
    (pa, qa, pb, qb), _ = sampled_cases(a, b)
    for j in (1, 2):  # one penetrating and one separated case
        c = run(a, b, pa[j : j + 1], qa[j : j + 1], pb[j : j + 1], qb[j : j + 1])
        _, grad, weights = gradient(a, b, pa[j], qa[j], pb[j], qb[j], c.active[0])
        fd = _central_differences(a, b, pa[j], qa[j], pb[j], qb[j], weights, c.active[0])
        np.testing.assert_allclose(grad, fd, rtol=0, atol=1e-7)
        assert np.abs(grad).max() > 0.1  # the outputs do depend on the pose


# ============================================================================ transforms


def test_jit_and_vmap_equal_eager_calls():
    """One pair (op-by-op eager execution compiles every primitive, which is slow for box-box)."""
    a, b = "sphere", "box"
    (pa, qa, pb, qb), _ = sampled_cases(a, b)
    batched = run(a, b, pa, qa, pb, qb)
    sa, sb = SHAPES[a][0], SHAPES[b][0]
    for i in (0, 1):
        eager = collision.collide(sa, pa[i], qa[i], sb, pb[i], qb[i], MARGIN)
        np.testing.assert_array_equal(eager.active, batched.active[i])
        np.testing.assert_allclose(eager.gap, batched.gap[i], rtol=0, atol=1e-14)
        np.testing.assert_allclose(eager.point, batched.point[i], rtol=0, atol=1e-14)
        np.testing.assert_allclose(eager.normal, batched.normal[i], rtol=0, atol=1e-14)


def test_changing_poses_does_not_retrace():
    traces = []

    @jax.jit
    def f(pa, qa, pb, qb):
        traces.append(None)
        return collision.collide(SHAPES["sphere"][0], pa, qa, SHAPES["box"][0], pb, qb, MARGIN)

    (pa, qa, pb, qb), _ = sampled_cases("sphere", "box")
    for i in range(3):
        f(pa[i], qa[i], pb[i], qb[i])
    assert len(traces) == 1


@pytest.mark.parametrize("pair", PAIRS, ids="-".join)
def test_float32_is_finite_and_close_to_float64(pair):
    """float32 keeps its dtype and stays finite; the deepest gap matches the reference to 1e-6 m.

    Rounding O(1) m poses to float32 moves the shapes by ~6e-8 m and each operation adds a
    few ulps; measured max 1.5e-7 m.
    """
    a, b = pair
    (pa, qa, pb, qb), refs = sampled_cases(a, b)
    c32 = run(a, b, pa, qa, pb, qb, dtype=jnp.float32)
    assert c32.gap.dtype == np.float32 and c32.point.dtype == np.float32
    for leaf in (c32.point, c32.normal, c32.gap):
        assert np.all(np.isfinite(leaf))
    _, gap32 = min_active(c32)
    sd = np.array([r[0] for r in refs])
    np.testing.assert_allclose(gap32[np.isfinite(gap32)], sd[np.isfinite(gap32)], atol=1e-6)
    assert np.isfinite(gap32).sum() >= len(sd) - 1  # at most one case slips past the margin by round-off


def test_capsule_over_a_box_edge_moves_its_contact_point_in_float32_as_in_float64():
    """Capsule-box's slot 0 at an interior point of the segment (a capsule skew over a box's
    edge): the point's derivative in the poses carries the implicit-function term of the
    refining Newton step in float32 too. The golden search places the point to about
    ``sqrt(eps)`` of the length; the step is taken up to ``64 sqrt(eps)`` of it. With a
    threshold of 1e-6 of the length, float32 skipped the step and its point's derivative
    was off by ~0.1 (the derivative of a point that does not slide along the segment)."""
    capsule, box = Capsule(0.05, 0.3), Box((0.2, 0.2, 0.2))
    rng = np.random.default_rng(7)
    n = 8
    # Beside the edge x = z = 0.2 (along y), the axis (a, 1, -a) skew to it: over the
    # segment the point stays in the edge's region (x, z > 0.2), and its distance to the
    # edge, sqrt(c^2 + 2 a^2 t^2), is smallest at the segment's middle (t = 0).
    clearance = rng.uniform(0.08, 0.12, n)
    position = np.stack([0.2 + clearance / np.sqrt(2), rng.uniform(-0.05, 0.05, n), 0.2 + clearance / np.sqrt(2)], 1)
    a = rng.uniform(0.1, 0.2, n) * rng.choice([-1, 1], n)
    axis = np.stack([a, np.ones(n), -a], 1)
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    # The quaternion turning z onto the axis.
    half_way = axis + np.array([0.0, 0.0, 1.0])
    half_way /= np.linalg.norm(half_way, axis=1, keepdims=True)
    orientation = np.concatenate([half_way[:, 2:], np.cross([0.0, 0.0, 1.0], half_way)], 1)
    box_orientation = np.tile(IDENTITY, (n, 1))
    direction = rng.normal(size=(n, 7))  # the capsule's position and orientation move

    def point_and_gap(pa, qa, pb, qb, dtype):
        c = collision.capsule_box(capsule, pa.astype(dtype), qa.astype(dtype), box, pb.astype(dtype),
                                  qb.astype(dtype), margin=0.1)
        return c.point[0], c.gap[0]

    @functools.partial(jax.jit, static_argnums=0)
    @functools.partial(jax.vmap, in_axes=(None, 0, 0, 0, 0, 0))
    def derivative(dtype, pa, qa, pb, qb, d):
        return jax.jvp(lambda pa, qa: point_and_gap(pa, qa, pb, qb, dtype),
                       (pa.astype(dtype), qa.astype(dtype)), (d[:3].astype(dtype), d[3:].astype(dtype)))

    args = (position, orientation, np.zeros((n, 3)), box_orientation, direction)
    (point64, gap64), (dpoint64, dgap64) = derivative(jnp.float64, *args)
    (point32, gap32), (dpoint32, dgap32) = derivative(jnp.float32, *args)
    along = np.einsum("ij,ij->i", np.asarray(point64) - position, axis)
    assert np.all(np.abs(along) < 0.1 * capsule.half_length)  # the segment's middle
    np.testing.assert_allclose(gap64, clearance - capsule.radius, rtol=0, atol=1e-12)
    assert np.max(np.linalg.norm(np.asarray(dpoint64), axis=1)) > 0.5  # the point does move
    np.testing.assert_allclose(point32, point64, rtol=0, atol=1e-5)
    np.testing.assert_allclose(dgap32, dgap64, rtol=0, atol=1e-4)
    np.testing.assert_allclose(dpoint32, dpoint64, rtol=0, atol=1e-3)


# ============================================================================ API


def test_reversed_order_is_the_flipped_contact():
    (pa, qa, pb, qb), _ = sampled_cases("sphere", "box")
    forward = collision.sphere_box(SHAPES["sphere"][0], pa[1], qa[1], SHAPES["box"][0], pb[1], qb[1], MARGIN)
    backward = collision.collide(SHAPES["box"][0], pb[1], qb[1], SHAPES["sphere"][0], pa[1], qa[1], MARGIN)
    np.testing.assert_array_equal(backward.normal, -forward.normal)
    np.testing.assert_array_equal(backward.point, forward.point)
    np.testing.assert_array_equal(backward.gap, forward.gap)
    plane_first = collision.collide(PLANE, None, None, SHAPES["sphere"][0], pa[1], qa[1], margin=1.0)
    plane_last = collision.sphere_plane(SHAPES["sphere"][0], pa[1], qa[1], PLANE, margin=1.0)
    np.testing.assert_array_equal(plane_first.normal, -plane_last.normal)


def test_max_contacts_and_unsupported_pairs():
    expected = {
        (Sphere, Plane): 1,
        (Box, Plane): 4,
        (Capsule, Plane): 2,
        (Cylinder, Plane): 5,
        (Sphere, Sphere): 1,
        (Sphere, Box): 1,
        (Sphere, Capsule): 1,
        (Sphere, Cylinder): 1,
        (Capsule, Capsule): 2,
        (Capsule, Box): 2,
        (Capsule, Cylinder): 2,
        (Cylinder, Box): 5,
        (Cylinder, Cylinder): 5,
        (Box, Box): 4,
    }
    for (ta, tb), k in expected.items():
        assert collision.max_contacts(ta, tb) == k == collision.max_contacts(tb, ta)
    assert collision.max_contacts(Box((1, 1, 1)), Sphere(1.0)) == 1
    with pytest.raises(ValueError, match="Supported pairs.*Sphere-Plane"):
        collision.collide(Cylinder(1.0, 1.0), np.zeros(3), IDENTITY, Cone(1.0, 1.0), np.zeros(3), IDENTITY)
    with pytest.raises(ValueError, match="Cone, Box"):
        collision.max_contacts(Cone, Box)


def test_bad_inputs_fail_early():
    sphere = Sphere(1.0)
    with pytest.raises(ValueError, match="position must have shape"):
        collision.collide(sphere, np.zeros((5, 3)), IDENTITY, sphere, np.zeros(3), IDENTITY)
    with pytest.raises(ValueError, match="orientation must have shape"):
        collision.collide(sphere, np.zeros(3), np.zeros(3), sphere, np.zeros(3), IDENTITY)
    with pytest.raises(ValueError, match="margin"):
        collision.collide(sphere, np.zeros(3), IDENTITY, sphere, np.zeros(3), IDENTITY, margin=-0.1)
    # The cylinder pairs (added on 2026-12-01) check the same, in either order.
    can, tilted = Cylinder(0.1, 0.2), np.array([1.0, 1.0, 0.0, 0.0])
    for other in (Box((0.1, 0.2, 0.3)), Cylinder(0.2, 0.1)):
        with pytest.raises(ValueError, match="position must have shape"):
            collision.collide(can, np.zeros(2), IDENTITY, other, np.ones(3), IDENTITY)
        with pytest.raises(ValueError, match="orientation_b is not a unit quaternion"):
            collision.collide(can, np.zeros(3), IDENTITY, other, np.ones(3), tilted)
        with pytest.raises(ValueError, match="orientation_a is not a unit quaternion"):
            collision.collide(other, np.ones(3), tilted, can, np.zeros(3), IDENTITY)
        with pytest.raises(ValueError, match="margin"):
            collision.collide(other, np.ones(3), IDENTITY, can, np.zeros(3), IDENTITY, margin=-1.0)


def test_a_non_unit_quaternion_is_refused():
    """The pair functions read a pose's rotation from a unit quaternion's formula. A box
    posed with ``(1, 1, 0, 0)`` had been stretched by sqrt(5) across two of its axes, and
    ``(0, 0, 0, 0)`` or ``(0.5, 0, 0, 0)`` taken as the identity, without a word."""
    box, plane = Box((0.1, 0.2, 0.3)), Plane()
    for q in ((1.0, 1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), (0.5, 0.0, 0.0, 0.0)):
        with pytest.raises(ValueError, match="orientation_a is not a unit quaternion"):
            collision.collide(box, np.zeros(3), np.asarray(q), plane)
        with pytest.raises(ValueError, match="orientation_b is not a unit quaternion"):
            collision.collide(plane, None, None, box, np.zeros(3), np.asarray(q))
    # Rounding passes (four decimals), and so does a traced pose, which cannot be checked.
    c = collision.collide(box, np.array([0.0, 0.0, 0.25]), np.array([0.7071, 0.7071, 0.0, 0.0]), plane)
    assert np.all(np.isfinite(c.gap))
    jax.jit(lambda q: collision.collide(box, np.zeros(3), q, plane).gap)(jnp.asarray(IDENTITY))


def test_flip_and_concatenate():
    (pa, qa, pb, qb), _ = sampled_cases("capsule", "rod")
    c1 = jax.tree_util.tree_map(lambda x: x[0], run("capsule", "rod", pa[:1], qa[:1], pb[:1], qb[:1]))
    c2 = jax.tree_util.tree_map(lambda x: x[0], run("capsule", "plane", pa[:1], qa[:1], pb[:1], qb[:1]))
    joined = collision.concatenate_contacts([c1, c2.flip()])
    assert joined.num_slots == 4
    np.testing.assert_array_equal(joined.normal[2:], -c2.normal)
    np.testing.assert_array_equal(joined.gap, np.concatenate([c1.gap, c2.gap]))
    # Batched contacts concatenate along the slot axis too.
    batched = jax.vmap(lambda p: collision.sphere_plane(SHAPES["sphere"][0], p, IDENTITY, PLANE))(jnp.zeros((3, 3)))
    assert collision.concatenate_contacts([batched, batched]).gap.shape == (3, 2)


def test_cores_within_round_off_take_the_fallback_normal_under_jit_and_vmap():
    """A sphere centred on a capsule's segment, and two capsules whose segments cross: the
    closest points coincide up to round-off, and the normal is the documented fallback (the
    capsule's body x axis, perpendicular to its segment; a_a x a_b). Compiled under jit and
    vmap the round-off difference had been normalised instead: normals of length 0.09 to 11
    along the segment, and for the crossing capsules A's own axis (0.75 to separate along
    it, against 0.25 along a_a x a_b)."""
    rng = np.random.default_rng(0)
    q = random_quats(rng, 300)
    axes = np.stack([quat_matrix(x)[:, 2] for x in q])
    identity = jnp.array([1.0, 0.0, 0.0, 0.0])
    on_segment = jax.jit(jax.vmap(lambda p, qb: collision.collide(
        Sphere(0.2), p, identity, Capsule(0.1, 0.5), jnp.zeros(3), qb)))(0.3 * axes, q)
    normal = np.asarray(on_segment.normal[:, 0])
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(normal * axes, axis=1), 0.0, atol=1e-12)
    np.testing.assert_allclose(on_segment.gap[:, 0], -0.3, atol=1e-12)
    turn = np.array([np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0])  # a quarter turn about y
    qa = np.stack([quat_mul(x, turn) for x in q])
    crossing = jax.jit(jax.vmap(lambda qa, qb: collision.collide(
        Capsule(0.1, 0.5), jnp.zeros(3), qa, Capsule(0.15, 0.3), jnp.zeros(3), qb)))(qa, q)
    across = np.cross(np.stack([quat_matrix(x)[:, 2] for x in qa]), axes)
    normal = np.asarray(crossing.normal[:, 0])
    np.testing.assert_allclose(np.abs(np.sum(normal * across, axis=1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(crossing.gap[:, 0], -0.25, atol=1e-12)


def test_cores_a_few_millimetres_apart_far_from_the_origin_keep_their_normal_in_float32():
    """At 1 km from the origin in float32 the coincidence bound of the cores was 64 eps of
    the coordinates, 7.6 mm: two 5 mm balls 5 mm apart along x were pushed apart along z,
    crossing capsules 5 mm apart along the common perpendicular were pushed into each other
    (A below B, normal +z), and a ball under a capsule sideways. Now the normal is the
    cores' direction there, as at the origin; and where cores do fall within the bound
    (0.5 mm apart), the fallback is turned to A's side."""
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)
    identity = f32([1.0, 0.0, 0.0, 0.0])
    along_x = f32([np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0])  # body z along world x
    along_y = f32([np.cos(np.pi / 4), -np.sin(np.pi / 4), 0.0, 0.0])  # body z along world y
    far = 1e3
    for offset in (0.0, far):
        at = lambda *p, offset=offset: f32(np.array(p) + offset)  # noqa: E731
        balls = collision.collide(Sphere(0.005), at(0.005, 0, 0), identity, Sphere(0.005), at(0, 0, 0), identity)
        np.testing.assert_allclose(balls.normal[0], [1.0, 0.0, 0.0], atol=1e-6)
        under = collision.collide(Sphere(0.01), at(0, 0, -0.005), identity, Capsule(0.01, 0.5), at(0, 0, 0), along_y)
        np.testing.assert_allclose(under.normal[0], [0.0, 0.0, -1.0], atol=1e-6)
        for dz in (0.005, -0.005, 0.0005, -0.0005):  # the last two inside the bound at 1 km
            crossing = collision.collide(Capsule(0.01, 0.5), at(0, 0, dz), along_x, Capsule(0.01, 0.5), at(0, 0, 0),
                                         along_y)
            np.testing.assert_allclose(crossing.normal[0], [0.0, 0.0, np.sign(dz)], atol=1e-6, err_msg=(offset, dz))
            assert abs(float(crossing.gap[0]) - (abs(dz) - 0.02)) < 2 * 6.2e-5 * (offset > 0) + 1e-7


def test_parallel_capsules_whose_segments_overlap_take_the_fallback_normal_under_jit():
    """Two capsules of one orientation whose segments overlap (coincident centres, or
    collinear and shifted along the axis). Under jit the equal axes came out apart by
    round-off, whose normalised cross product passed the parallel test: the normal was an
    arbitrary direction (0.56 along the axis), with derivatives of 2e16 in the attitudes.
    It is now the documented fallback, A's body x axis, as without jit."""
    q = np.concatenate([[np.cos(0.45)], np.sin(0.45) * np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])])
    body = quat_matrix(q)

    def turned(q, r):  # q turned by a small world rotation vector r
        w = jnp.concatenate([jnp.ones(1, r.dtype), 0.5 * r])
        w = w / jnp.sqrt(jnp.sum(w * w))
        return jnp.concatenate([jnp.stack([w[0] * q[0] - jnp.dot(w[1:], q[1:])]),
                                w[0] * q[1:] + q[0] * w[1:] + jnp.cross(w[1:], q[1:])])

    for dtype in (jnp.float64, jnp.float32):
        for shift in (0.0, 0.3):
            def normal(x, dtype=dtype, shift=shift):
                qq, centre = jnp.asarray(q, dtype), jnp.asarray(shift * body[:, 2], dtype)
                return collision.capsule_capsule(Capsule(0.1, 0.4), centre, turned(qq, x[:3]), Capsule(0.2, 0.3),
                                                 jnp.zeros(3, dtype), turned(qq, x[3:]), 0.1).normal[0]

            x0 = jnp.zeros(6, dtype)
            np.testing.assert_allclose(jax.jit(normal)(x0), body[:, 0], atol=1e-6)
            assert np.abs(np.asarray(jax.jit(jax.jacrev(normal))(x0))).max() < 10.0


@pytest.mark.parametrize(("capsule", "other", "height"), [(Capsule(0.1, 0.4), Box((0.6, 0.5, 0.4)), 0.5),
                                                          (Capsule(0.1, 0.1), Cylinder(0.3, 0.35), 0.45)],
                         ids=["box", "cylinder"])
def test_a_capsule_lying_on_a_face_has_finite_float32_gradients(capsule, other, height):
    """A capsule lying on a box's top face or a cylinder's cap, 64 random spins and offsets
    about the vertical, float32, jit and vmap: the gradient of the active gaps' sum in the
    capsule's position is (0, 0, 2) (two slots, each gap rising with its height). Along a
    face the gap is linear in the segment's parameter, and float32 left a curvature of
    round-off (3e-21) whose refused Newton step still had an infinite derivative: NaN in 14
    of 64 poses on either shape."""
    rng = np.random.default_rng(0)
    spin = rng.uniform(0, 2 * np.pi, 64)
    offset = rng.uniform(-0.3, 0.3, (64, 2)) * (1.0 if isinstance(other, Box) else 0.3)
    lying = np.array([np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0])
    qa = np.stack([quat_mul(np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)]), lying) for a in spin])
    pa = np.concatenate([offset, np.full((64, 1), height)], axis=1)

    def gaps(pa, qa):
        c = collision.collide(capsule, pa, qa, other, jnp.zeros(3, pa.dtype), jnp.array([1.0, 0, 0, 0], pa.dtype), 0.05)
        return jnp.sum(jnp.where(c.active, c.gap, 0.0))

    grad = jax.jit(jax.vmap(jax.grad(gaps)))(jnp.asarray(pa, jnp.float32), jnp.asarray(qa, jnp.float32))
    np.testing.assert_allclose(np.asarray(grad), np.tile([0.0, 0.0, 2.0], (64, 1)), atol=1e-5)


# ============================================================================ cylinder-box


def _closest_distance(cylinder, other):
    """The distance between a solid cylinder and a solid box or cylinder that are apart:
    SLSQP on the squared distance between a point of each (a cylinder's: ``x^2 + y^2 <= r^2``,
    ``|z| <= h``; a box's: bounds; each in its own frame), a convex problem with one
    minimum, from two starts."""
    (_, (r, h), ca, ra), (kind, size, cb, rb) = cylinder, other

    def difference(z):
        return ca + ra @ z[:3] - cb - rb @ z[3:]

    def jacobian(z):
        d = difference(z)
        return np.concatenate([2 * ra.T @ d, -2 * rb.T @ d])

    discs = [(r, 0)] + ([(size[0], 3)] if kind == "cylinder" else [])
    constraints = [dict(type="ineq", fun=(lambda z, w=w, i=i: np.array([w * w - z[i] ** 2 - z[i + 1] ** 2])),
                        jac=(lambda z, i=i: -2 * z * np.isin(np.arange(6), [i, i + 1]))) for w, i in discs]
    box_or_cylinder = [(-v, v) for v in size] if kind == "box" else [(-size[0], size[0])] * 2 + [(-size[1], size[1])]
    bounds = [(-r, r), (-r, r), (-h, h)] + box_or_cylinder
    best = np.inf
    for start in (np.zeros(6), np.array([0.5 * r, 0.0, 0.5 * h, 0.0, 0.0, 0.0])):
        found = minimize(lambda z: difference(z) @ difference(z), start, jac=jacobian, bounds=bounds,
                         constraints=constraints, method="SLSQP", options=dict(ftol=1e-20, maxiter=500))
        best = min(best, found.fun)
    return np.sqrt(best)


def _cylinder_overlap(cylinder, other):
    """``max_n s(n)`` for a cylinder and a box or a cylinder that overlap (minus the
    penetration depth): the best Fibonacci directions, the pattern search, then SLSQP on a
    smooth lift of the kinks (``t_j >= +-n.b_j`` for a box's faces, ``t >= +-n.a`` for each
    cylinder's caps; a side's ``r |n x a|`` is smooth away from its axis). The largest is
    kept: each is ``s`` at a true direction, a lower bound of the signed distance."""
    (_, (r, h), ca, ra), (kind, size, cb, rb) = cylinder, other
    axis, d = ra[:, 2], ca - cb
    kinked = [(h, axis)] + ([(size[i], rb[:, i]) for i in range(3)] if kind == "box" else [(size[1], rb[:, 2])])
    smooth = [(r, axis)] + ([(size[0], rb[:, 2])] if kind == "cylinder" else [])
    weights, basis = np.array([w for w, _ in kinked]), np.array([b for _, b in kinked])
    m = len(weights)

    def f(n):
        return separation(n, cylinder, other)

    def lifted(x):
        n, t = x[:3], x[3:]
        sides = sum(w * np.sqrt(max(n @ n - (n @ b) ** 2, 1e-300)) for w, b in smooth)
        return -(n @ d - weights @ t - sides)

    lift = np.block([[-basis, np.eye(m)], [basis, np.eye(m)]])
    constraints = [dict(type="eq", fun=lambda x: np.array([x[:3] @ x[:3] - 1.0])),
                   dict(type="ineq", fun=lambda x: lift @ x, jac=lambda x: lift)]
    values = f(FIBONACCI)
    best = -np.inf
    for i in np.argsort(-values)[:6]:
        n = _pattern_search(f, FIBONACCI[i], 0.05)
        x = minimize(lifted, np.concatenate([n, np.abs(basis @ n)]), constraints=constraints, method="SLSQP",
                     options=dict(ftol=1e-16, maxiter=300)).x
        polished = x[:3] / np.linalg.norm(x[:3])
        best = max(best, f(n[None])[0], f(polished[None])[0])
    return best


@functools.cache
def _cylinder_cases(other):
    """Random poses of SHAPES' cylinder against ``other`` ("box" or "can"): 12 apart within
    the margin, 8 a little overlapping (to 1 cm) and 4 more (1 to 5 cm). Each is placed along
    a random direction by bisection on the coarse (Fibonacci) separation, given its
    reference (the distance, :func:`_closest_distance`, or ``max_n s(n)``,
    :func:`_cylinder_overlap`), and drawn again if the reference falls outside its range (the
    coarse separation is a lower bound, off by up to a few mm)."""
    rng = np.random.default_rng(7)
    poses, refs = [], []
    for low_sd, high_sd, count in ((1e-4, MARGIN - 1e-3, 12), (-0.01, -1e-4, 8), (-0.05, -0.01, 4)):
        while sum(low_sd < r < high_sd for r in refs) < count:
            target = rng.uniform(low_sd, high_sd)
            qa, qb = random_quats(rng, 2)
            pb = rng.uniform(-0.1, 0.1, 3)
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            near, far = 0.0, 2.0  # overlapping with the centres together, far apart at 2 m
            for _ in range(50):
                mid = (near + far) / 2
                coarse = separation(FIBONACCI, body("cylinder", pb + mid * direction, qa), body(other, pb, qb)).max()
                near, far = (mid, far) if coarse < target else (near, mid)
            pa = pb + far * direction
            cylinder, shape_b = body("cylinder", pa, qa), body(other, pb, qb)
            ref = _closest_distance(cylinder, shape_b) if target > 0 else _cylinder_overlap(cylinder, shape_b)
            if low_sd < ref < high_sd:
                poses.append((pa, qa, pb, qb))
                refs.append(ref)
    return tuple(np.array(x) for x in zip(*poses, strict=True)), np.array(refs)


@pytest.mark.parametrize("other", ["box", "can"])
def test_a_cylinder_is_the_exact_distance_apart_and_the_push_that_frees_it_when_overlapping(other):
    """Cylinder-box and cylinder-cylinder. Apart (or touching), slot 0 is a point of each
    surface at the shapes' distance (SLSQP reference to 1e-9 m; the support functions at its
    normal give its gap, 1e-12 m). Once they overlap, slot 0's gap is the overlap along its
    normal (the support functions' separation there, 1e-12 m), within 2e-5 m of the true
    signed distance below 1 cm of overlap and 1e-4 m below 5 cm (measured 3.5e-6 and 4.8e-5
    against a box, 1.5e-5 and 5.8e-5 against a cylinder; the reference itself, a search over
    directions, is good to about 1e-6). The push is the best of a finite set of directions,
    so where none is the true one it is deeper than the truth: two rims crossing take the
    direction across them at the searched rim points, not at the crossing (the 1.5e-5 m, at
    4.6 mm of overlap). Every other active slot is a point of each surface."""
    (pa, qa, pb, qb), refs = _cylinder_cases(other)
    c = run("cylinder", other, pa, qa, pb, qb)
    assert np.all(c.active[:, 0]) and np.all(np.isfinite(c.gap))
    np.testing.assert_allclose(np.linalg.norm(c.normal, axis=-1), 1.0, atol=1e-14)
    apart = refs > 0
    gap = c.gap[:, 0]
    np.testing.assert_allclose(gap[apart], refs[apart], rtol=0, atol=1e-9)
    shallow, deeper = (refs < 0) & (refs > -0.01), refs <= -0.01
    assert shallow.sum() == 8 and deeper.sum() == 4
    np.testing.assert_allclose(gap[shallow], refs[shallow], rtol=0, atol=2e-5)
    np.testing.assert_allclose(gap[deeper], refs[deeper], rtol=0, atol=1e-4)
    for i in range(len(pa)):
        cylinder, shape_b = body("cylinder", pa[i], qa[i]), body(other, pb[i], qb[i])
        np.testing.assert_allclose(separation(c.normal[i, :1], cylinder, shape_b)[0], gap[i], atol=1e-12)
        on_surfaces = c.active[i] & ((np.arange(5) > 0) | apart[i])
        on_a = c.point[i][on_surfaces] + 0.5 * c.gap[i][on_surfaces, None] * c.normal[i][on_surfaces]
        on_b = c.point[i][on_surfaces] - 0.5 * c.gap[i][on_surfaces, None] * c.normal[i][on_surfaces]
        np.testing.assert_allclose(surface_distance(cylinder, on_a), 0.0, atol=1e-12)
        np.testing.assert_allclose(surface_distance(shape_b, on_b), 0.0, atol=1e-12)


@pytest.mark.parametrize("other", ["box", "cylinder"])
def test_a_cylinder_overlapping_a_shape_through_its_centre_is_pushed_out(other):
    """Deep overlaps where the candidate points of one shape lie on the other's surface: a
    cylinder (r = 0.2 m, half length 0.35 m) coaxial with an equal one (same centre, 1e-6,
    0.2 and 0.3 m apart along the axis: every rim point on the other's side), one crossing
    it at one centre, a box at the cylinder's centre (1e-6 off, and turned). Each centre is
    inside the other shape, so slot 0 is the push along the best direction, within 1e-4 m
    of the support-function reference's signed distance (the coaxial pairs' exact 2r = 0.4
    m to 1e-12). Until 2026-12-04 the candidates'
    gaps of 0 made these count as touching: no active slot, and two cans stacked 0.2 m into
    each other stayed so (found by a fuzz)."""
    along_x = axis_angle([1.0, 0.0, 0.0], np.pi / 2)
    if other == "cylinder":
        pa = [[0.0, 0.0, 0.0], [0.0, 0.0, 1e-6], [0.0, 0.0, 0.2], [0.0, 0.0, 0.3], [0.0, 0.0, 0.0]]
        qa = [IDENTITY] * 4 + [along_x]
    else:
        pa = [[1e-6, 0.0, 0.0], [0.0, 1e-6, 0.0], [0.0, 0.0, 1e-6]]
        qa = [IDENTITY, along_x, axis_angle([1.0, 2.0, 3.0], 0.7)]
    pb, qb = np.zeros((len(pa), 3)), np.tile(IDENTITY, (len(pa), 1))
    c = run("cylinder", other, pa, qa, pb, qb)
    assert np.all(c.active[:, 0]) and np.all(np.isfinite(c.gap))
    refs = np.array([_cylinder_overlap(body("cylinder", pa[i], qa[i]), body(other, pb[i], qb[i]))
                     for i in range(len(pa))])
    assert np.all(refs < -0.1), refs
    np.testing.assert_allclose(c.gap[:, 0], refs, rtol=0, atol=1e-4)
    if other == "cylinder":
        np.testing.assert_allclose(c.gap[:4, 0], -0.4, rtol=0, atol=1e-12)


def _cylinder_contact(cylinder, pa, qa, other, pb, qb, margin=0.01):
    c = collision.collide(cylinder, jnp.asarray(pa, float), jnp.asarray(qa, float), other, jnp.asarray(pb, float),
                          jnp.asarray(qb, float), margin)
    return jax.tree_util.tree_map(np.asarray, c)


def test_a_can_stands_on_a_box_on_its_cap_and_the_square_and_lies_on_the_two_ends_of_its_line():
    """Upright, 1 mm into a table's top and turned 0.3 rad: the cap's centre and the four
    square points, all at -1 mm along +z. Lying along x: the two ends of its line. Lying
    across a beam narrower than the can: the line clipped to the beam's top, its two edges."""
    can, table, beam = Cylinder(0.05, 0.1), Box((0.3, 0.3, 0.05)), Box((0.3, 0.02, 0.05))
    up = np.array([0.0, 0.0, 1.0])
    c = _cylinder_contact(can, [0.01, 0.02, 0.05 + 0.1 - 1e-3], axis_angle(up, 0.3), table, np.zeros(3), IDENTITY)
    assert c.active.all()
    np.testing.assert_allclose(c.gap, -1e-3, atol=1e-15)
    np.testing.assert_allclose(c.normal, np.broadcast_to(up, (5, 3)), atol=1e-15)
    turned_square = [[0.01 + 0.05 * np.cos(0.3 + k * np.pi / 2), 0.02 + 0.05 * np.sin(0.3 + k * np.pi / 2)]
                     for k in range(4)]
    assert same_point_sets(c.point[:, :2], [[0.01, 0.02], *turned_square], atol=1e-12)
    lying = axis_angle([0.0, 1.0, 0.0], np.pi / 2)  # the can's axis along x
    c = _cylinder_contact(can, [0.0, 0.0, 0.05 + 0.05 + 1e-4], lying, table, np.zeros(3), IDENTITY)
    assert c.active.sum() == 2
    np.testing.assert_allclose(c.gap[c.active], 1e-4, atol=1e-15)
    assert same_point_sets(c.point[c.active][:, :2], [[-0.1, 0.0], [0.1, 0.0]], atol=1e-12)
    across = axis_angle([1.0, 0.0, 0.0], np.pi / 2)  # the can's axis along y, the beam's along x
    c = _cylinder_contact(can, [0.0, 0.0, 0.05 + 0.05 + 1e-4], across, beam, np.zeros(3), IDENTITY)
    assert c.active.sum() == 2
    np.testing.assert_allclose(c.gap[c.active], 1e-4, atol=1e-15)
    assert same_point_sets(c.point[c.active][:, :2], [[0.0, -0.02], [0.0, 0.02]], atol=1e-12)


def test_a_box_on_a_cans_cap_rests_on_its_corners_or_on_the_rim_under_it():
    """A small lid (inside the cap) on the can's top: its four corners are slots, at the
    depth, along the can's axis. A lid larger than the cap: the four rim points of the
    cap's square (the lid's corners are off the can)."""
    can, up = Cylinder(0.05, 0.1), np.array([0.0, 0.0, 1.0])
    small, large = Box((0.02, 0.03, 0.02)), Box((0.2, 0.2, 0.02))
    spin = axis_angle(up, 0.4)
    centre = np.array([0.01, 0.0, 0.1 + 0.02 - 1e-4])
    c = _cylinder_contact(can, np.zeros(3), IDENTITY, small, centre, spin)
    assert c.active.all()
    np.testing.assert_allclose(c.gap, -1e-4, atol=1e-15)
    np.testing.assert_allclose(c.normal, np.broadcast_to(-up, (5, 3)), atol=1e-15)  # box (B) to can (A)
    corners = [centre[:2] + quat_matrix(spin)[:2, :2] @ [sx * 0.02, sy * 0.03] for sx in (-1, 1) for sy in (-1, 1)]
    assert all(np.min(np.linalg.norm(c.point[:, :2] - p, axis=1)) < 1e-12 for p in corners)
    c = _cylinder_contact(can, np.zeros(3), IDENTITY, large, centre, spin)
    rim = [[0.05 * np.cos(k * np.pi / 2), 0.05 * np.sin(k * np.pi / 2)] for k in range(4)]
    assert all(np.min(np.linalg.norm(c.point[c.active][:, :2] - p, axis=1)) < 1e-12 for p in rim)
    np.testing.assert_allclose(c.gap[c.active], -1e-4, atol=1e-15)


def test_a_rim_across_a_box_edge_keeps_its_normal_through_touching():
    """A tilted can's rim across the table's top edge (the normal perpendicular to the edge
    and to the rim there, between the top's and the side's normals), moved along that
    normal by d: apart, the gap is d to 1e-15 m (touching: 1e-11 m, see below); overlapping, slot 0 pushes
    along within 1e-3 degrees of it by d to 1e-12 m at d = -1e-7, and within 0.5 degrees by
    d to 1e-6 m at d = -1e-4 (six random tilts; measured 0.28 degrees, 1.5e-7 m). A
    deepest point's own face would have taken the top's or the side's normal: a jump of up
    to 45 degrees as the rim touches."""
    can, table = Cylinder(0.05, 0.1), Box((0.3, 0.3, 0.05))
    rng = np.random.default_rng(3)
    tried = 0
    while tried < 6:
        q = random_quats(rng, 1)[0]
        rotation = quat_matrix(q)
        phi = rng.uniform(0, 2 * np.pi)
        rim_point = np.array([0.05 * np.cos(phi), 0.05 * np.sin(phi), -0.1])
        outward = rotation @ np.array([np.cos(phi), np.sin(phi), 0.0])
        normal = np.cross([0.0, 1.0, 0.0], rotation @ np.array([-np.sin(phi), np.cos(phi), 0.0]))
        normal /= np.linalg.norm(normal)
        normal *= np.sign(normal[0] + normal[2])
        # The can touches the edge there only if -normal is in the rim's cone (outward, -axis).
        weights = np.linalg.lstsq(np.stack([outward, -rotation[:, 2]], 1), -normal, rcond=None)[0]
        if not (normal[0] > 0.2 and normal[2] > 0.2 and np.all(weights > 0.1)):
            continue
        tried += 1
        edge = np.array([0.3, rng.uniform(-0.1, 0.1), 0.05])
        # At d = 0 the edge's distance to the rim has a kink at its minimum (0), which the
        # golden-section search places to ~1e-10 of the edge's length: 1e-11 m.
        for d, angle, atol in ((1e-3, 1e-6, 1e-15), (0.0, 1e-6, 1e-11), (-1e-7, 1e-3, 1e-12), (-1e-4, 0.5, 1e-6)):
            c = _cylinder_contact(can, edge + d * normal - rotation @ rim_point, q, table, np.zeros(3), IDENTITY)
            k = np.argmin(np.where(c.active, c.gap, np.inf))
            np.testing.assert_allclose(c.gap[k], d, rtol=0, atol=atol)
            assert np.degrees(np.arccos(min(c.normal[k] @ normal, 1.0))) < angle


@pytest.mark.parametrize("other", ["box", "can"])
def test_cylinder_gradients_match_finite_differences(other):
    """As test_gradients_match_finite_differences: an apart and an overlapping pose, 1e-7."""
    (pa, qa, pb, qb), _ = _cylinder_cases(other)
    for j in (0, 13):
        c = run("cylinder", other, pa[j : j + 1], qa[j : j + 1], pb[j : j + 1], qb[j : j + 1])
        _, grad, weights = gradient("cylinder", other, pa[j], qa[j], pb[j], qb[j], c.active[0])
        fd = _central_differences("cylinder", other, pa[j], qa[j], pb[j], qb[j], weights, c.active[0])
        np.testing.assert_allclose(grad, fd, rtol=0, atol=1e-7)
        assert np.abs(grad).max() > 0.1


@pytest.mark.parametrize("other", ["box", "can"])
def test_cylinder_pairs_in_float32_and_in_either_order(other):
    """float32 stays finite and within 1e-5 m of float64's slot 0 (the overlap's push by its
    directions' round-off too). The other shape first: for a box, the flipped contact; for
    a cylinder (the same function with the roles swapped), slot 0 of separated shapes is the
    same closest pair (gap to 1e-12 m, normal negated to 1e-9)."""
    (pa, qa, pb, qb), refs = _cylinder_cases(other)
    c64, c32 = run("cylinder", other, pa, qa, pb, qb), run("cylinder", other, pa, qa, pb, qb, dtype=jnp.float32)
    assert c32.gap.dtype == np.float32 and all(np.all(np.isfinite(x)) for x in (c32.point, c32.normal, c32.gap))
    np.testing.assert_allclose(c32.gap[:, 0], c64.gap[:, 0], atol=1e-5)
    flipped = run(other, "cylinder", pb, qb, pa, qa)
    if other == "box":
        np.testing.assert_array_equal(flipped.active, c64.active)
        np.testing.assert_allclose(flipped.normal, -c64.normal, atol=1e-15)
        np.testing.assert_allclose(flipped.gap, c64.gap, atol=1e-15)
    else:
        apart = refs > 0
        np.testing.assert_allclose(flipped.gap[apart, 0], c64.gap[apart, 0], atol=1e-12)
        np.testing.assert_allclose(flipped.normal[apart, 0], -c64.normal[apart, 0], atol=1e-9)


def test_cans_stand_lie_and_cross_on_each_other():
    """A small can standing 1 mm into a bigger can's top, turned: its cap's centre and
    square, all at -1 mm along +z; a big can on a small one's top: the small cap's centre
    and square under it. Two lying cans side by side: the ends of the overlap of their lines
    (and points between), at the gap. Crossed: one point. A thin can lying on a cap: the
    ends of its line over the disc."""
    small, big, up = Cylinder(0.04, 0.05), Cylinder(0.06, 0.08), np.array([0.0, 0.0, 1.0])
    turn = axis_angle(up, 0.3)
    c = _cylinder_contact(small, [0.01, 0.005, 0.08 + 0.05 - 1e-3], turn, big, np.zeros(3), IDENTITY)
    assert c.active.all()
    np.testing.assert_allclose(c.gap, -1e-3, atol=1e-15)
    np.testing.assert_allclose(c.normal, np.broadcast_to(up, (5, 3)), atol=1e-15)
    square = [[0.01 + 0.04 * np.cos(0.3 + k * np.pi / 2), 0.005 + 0.04 * np.sin(0.3 + k * np.pi / 2)] for k in range(4)]
    assert same_point_sets(c.point[:, :2], [[0.01, 0.005], *square], atol=1e-12)
    c = _cylinder_contact(big, [0.0, 0.0, 0.05 + 0.08 - 1e-3], turn, small, np.zeros(3), IDENTITY)
    assert c.active.all()
    np.testing.assert_allclose(c.gap, -1e-3, atol=1e-15)
    radius = np.linalg.norm(c.point[:, :2], axis=1)
    assert np.sum(radius < 1e-12) == 1 and np.allclose(radius[radius > 1e-12], 0.04, atol=1e-12)
    angles = np.sort(np.arctan2(c.point[radius > 1e-12, 1], c.point[radius > 1e-12, 0]))
    assert np.max(np.diff(np.concatenate([angles, angles[:1] + 2 * np.pi]))) < np.radians(135)  # around the centre
    along_x, along_y = axis_angle([0.0, 1.0, 0.0], np.pi / 2), axis_angle([1.0, 0.0, 0.0], np.pi / 2)
    c = _cylinder_contact(Cylinder(0.05, 0.1), [0.03, 0.0, 0.1 + 1e-4], along_x, Cylinder(0.05, 0.15),
                              np.zeros(3), along_x)
    np.testing.assert_allclose(c.gap[c.active], 1e-4, atol=1e-15)
    np.testing.assert_allclose(c.point[c.active][:, 1:], [[0.0, 0.05 + 5e-5]] * c.active.sum(), atol=1e-12)
    assert np.min(c.point[c.active][:, 0]) == pytest.approx(-0.07, abs=1e-12)
    assert np.max(c.point[c.active][:, 0]) == pytest.approx(0.13, abs=1e-12)
    c = _cylinder_contact(Cylinder(0.05, 0.1), [0.0, 0.0, 0.1 + 1e-4], along_y, Cylinder(0.05, 0.15),
                              np.zeros(3), along_x)
    assert c.active.sum() == 1
    np.testing.assert_allclose(c.gap[c.active], 1e-4, atol=1e-15)
    np.testing.assert_allclose(c.point[c.active], [[0.0, 0.0, 0.05 + 5e-5]], atol=1e-12)
    c = _cylinder_contact(Cylinder(0.03, 0.1), [0.0, 0.0, 0.08 + 0.03 + 1e-4], along_x, big, np.zeros(3),
                              IDENTITY)
    np.testing.assert_allclose(c.gap[c.active], 1e-4, atol=1e-15)
    assert np.min(c.point[c.active][:, 0]) == pytest.approx(-0.06, abs=1e-12)
    assert np.max(c.point[c.active][:, 0]) == pytest.approx(0.06, abs=1e-12)


def test_an_edge_lying_in_a_clip_plane_has_a_bounded_derivative():
    """float32: a square's edge lies in the clip plane to rounding, its ends one ulp either
    side of it (as where two cube faces have the same footprint). It crosses anywhere, so
    the crossing point is kept where rounding puts it, and it moves with the edge: the
    derivative of the clipped polygon with respect to the square's vertices is bounded
    (at most 1 here). Before, it moved along the edge at 1/(d_a - d_b), 1e8 per m, and a
    3-cube float32 tower's gradient grew to 5e10 over 200 steps. A genuinely crossing edge
    keeps its derivative (against central differences in float64)."""
    from jaxrb.collision._box import _clip

    f32 = jnp.float32
    offset = jnp.asarray(0.05, f32)
    above, below = np.nextafter(np.float32(0.05), np.float32(1)), np.nextafter(np.float32(0.05), np.float32(0))
    square = np.zeros((8, 3), np.float32)
    square[:4] = [[below, -0.05, 0.1], [above, 0.05, 0.1], [-0.05, 0.05, 0.1], [-0.05, -0.05, 0.1]]
    normal = jnp.asarray([1.0, 0.0, 0.0], f32)

    def clipped(polygon):
        return _clip(polygon, jnp.asarray(4), normal, offset, jnp.asarray(0.1, f32))[0]

    points, count = _clip(jnp.asarray(square), jnp.asarray(4), normal, offset, jnp.asarray(0.1, f32))
    assert np.asarray(points[:int(count)])[:, 0].max() <= 0.05 + 1e-8
    jacobian = np.asarray(jax.jacfwd(clipped)(jnp.asarray(square)))
    assert np.all(np.isfinite(jacobian))
    assert np.abs(jacobian).max() <= 1.0 + 1e-6

    tilted = np.array(square, np.float64)
    tilted[0, 0], tilted[1, 0] = 0.04, 0.06  # the edge crosses x = 0.05 at its middle

    def clipped64(polygon):
        return _clip(polygon, jnp.asarray(4), jnp.asarray([1.0, 0.0, 0.0]), jnp.asarray(0.05), jnp.asarray(0.1))[0]

    jacobian = np.asarray(jax.jacfwd(clipped64)(jnp.asarray(tilted)))
    h = 1e-7
    for vertex, axis in ((0, 0), (1, 0), (1, 1)):
        e = np.zeros_like(tilted)
        e[vertex, axis] = h
        fd = (np.asarray(clipped64(jnp.asarray(tilted + e))) - np.asarray(clipped64(jnp.asarray(tilted - e)))) / (2 * h)
        np.testing.assert_allclose(jacobian[..., vertex, axis], fd, atol=1e-6)
    assert np.abs(jacobian).max() > 0.4  # the crossing point slides along the edge


def _largest_point_derivative_of_diagonal_cubes(jitter, samples=8):
    """Two 0.05 m cubes of a 2x2 grid turned by 30, 45 and 60 degrees about z, diagonal
    neighbours touching along the vertical edge on the z axis, each pose moved by
    ``jitter(rng, pa, pb, quat) -> (pa, pb, qa, qb)``. Returns ``{degrees: the largest
    |d contact point / d positions|}`` over ``samples`` jittered poses."""
    box = Box((0.05, 0.05, 0.05))

    def points(x, qa, qb):
        contact = collision.box_box(box, x[:3], qa, box, x[3:], qb, margin=1e-3)
        return jnp.where(contact.active[:, None], contact.point, 0.0), contact.active

    jacobian_of = jax.jit(jax.jacfwd(lambda *a: points(*a)[0]))
    rng = np.random.default_rng(0)
    worst = {}
    for degrees in (30.0, 45.0, 60.0):
        angle = np.radians(degrees)
        turn = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        quat = np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)])
        worst[degrees] = 0.0
        for _ in range(samples):
            pa, pb, qa, qb = jitter(rng, turn @ [0.05, -0.05, 0.05], turn @ [-0.05, 0.05, 0.05], quat)
            x = jnp.asarray(np.concatenate([pa, pb]))
            assert bool(jnp.any(points(x, qa, qb)[1]))
            jacobian = np.asarray(jacobian_of(x, qa, qb))
            assert np.all(np.isfinite(jacobian))
            worst[degrees] = max(worst[degrees], float(np.abs(jacobian).max()))
    return worst


def test_diagonal_cubes_sharing_an_edge_at_the_origin_have_bounded_point_derivatives():
    """float32: the diagonal neighbours' face manifold is their shared edge; the clipped
    points lie at the origin, where the clip distances cancel to 1e-9 and below, far under
    the round-off of the 0.05 m coordinates they come from. Jittered by a few ulps, as a
    step leaves them, the contact points' derivatives with respect to the positions stay
    of order 1. Before, the clipping judged round-off by the cancelled distances, let a
    4e-9 m edge lying in a side plane cross it, and slot 0 moved at 2e8 m per m (the
    turned grid's float32 gradient grew to 3e7 over 100 steps). On the old code these
    poses gave 3.4e6, 2.6e6 and 6.8e6 at 30, 45 and 60 degrees."""

    def jitter(rng, pa, pb, quat):
        ulps = np.float32(1e-8)  # about two ulps of 0.05

        def near(x, size):
            return x.astype(np.float32) + np.float32(size) * rng.integers(-2, 3, x.shape).astype(np.float32)

        return near(pa, ulps), near(pb, ulps), near(quat, 3e-8), near(quat, 3e-8)

    worst = _largest_point_derivative_of_diagonal_cubes(jitter)
    assert max(worst.values()) <= 2.0, worst


def test_cubes_touching_along_an_edge_tilted_by_a_hair_have_bounded_point_derivatives():
    """float64: the same diagonal neighbours, one tilted against the other by about 1e-11
    rad and both moved by 1e-12 m, as a float64 rollout leaves them. The shared edge then
    genuinely crosses the other cube's side plane, at a slope of 1e-11, and the crossing
    point slides along it 1e11 times faster than the cubes move. Clipping holds such a
    crossing (``PARALLEL_SLOPE``), so the points' derivatives stay of order 1. On the
    old code the 30 degree poses gave 9.6e10."""
    from jaxrb.collision._box import PARALLEL_SLOPE

    assert PARALLEL_SLOPE <= 1e-3

    def jitter(rng, pa, pb, quat):
        qb = quat + np.concatenate([[0.0], 0.5e-11 * rng.standard_normal(3)])
        pa, pb = pa + 1e-12 * rng.standard_normal(3), pb + 1e-12 * rng.standard_normal(3)
        return pa, pb, quat, qb / np.linalg.norm(qb)

    worst = _largest_point_derivative_of_diagonal_cubes(jitter)
    assert max(worst.values()) <= 2.0, worst
