"""Tests for jaxrb.inertia, each against an independent reference.

References: numerical quadrature of the defining integrals (scipy), seed 001's table as
printed, seed 000's point-mass formula as an explicit NumPy loop, closed forms for
meshes and compositions, scipy's rotations, and finite differences.
"""

import math

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.integrate import cubature  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

import jaxrb.inertia as inertia  # noqa: E402
from jaxrb import shapes, spatial  # noqa: E402

TWO_PI = 2.0 * math.pi


# ----------------------------------------------------------------------------- helpers


def _raw_moments(to_cartesian, lower, upper):
    """Integrals of 1, x and x x^T (unit density) over a region in curvilinear coordinates.

    ``to_cartesian(u)`` maps coordinates ``u`` of shape ``(n, d)``, over the box
    ``lower <= u <= upper``, to ``(x, y, z, jacobian)``, each of shape ``(n,)``. Adaptive
    Gauss-Kronrod cubature integrates all 13 entries in one vectorised pass, to a
    relative 1e-12, far below the 1e-6 the tests ask for. The absolute floor 1e-14 only
    matters for entries that vanish by symmetry (odd moments, products of inertia).
    """

    def integrand(u):
        x, y, z, jac = to_cartesian(u)
        r = np.stack([x, y, z], axis=-1)
        second = (r[:, :, None] * r[:, None, :]).reshape(-1, 9)
        return jac[:, None] * np.concatenate([np.ones_like(x)[:, None], r, second], axis=-1)

    result = cubature(integrand, lower, upper, rtol=1e-12, atol=1e-14)
    assert result.status == "converged"
    moments = result.estimate
    return moments[0], moments[1:4], moments[4:].reshape(3, 3)


def _central(measure, first, second, mass):
    """(com, inertia about the com) of a uniform body of total ``mass`` from raw moments."""
    com = first / measure
    spread = second / measure - np.outer(com, com)
    return com, mass * (np.trace(spread) * np.eye(3) - spread)


def _integrated_properties(to_cartesian, lower, upper, mass):
    """(measure, com, inertia about the com) of a uniform body of total ``mass``."""
    measure, first, second = _raw_moments(to_cartesian, lower, upper)
    return (measure, *_central(measure, first, second, mass))


def _spherical(a=1.0, b=1.0, c=1.0, centre_z=0.0):
    """(rho, theta, phi) -> ellipsoidal coordinates with semi-axes a, b, c."""

    def to_cartesian(u):
        rho, theta, phi = u[:, 0], u[:, 1], u[:, 2]
        st = np.sin(theta)
        x = a * rho * st * np.cos(phi)
        y = b * rho * st * np.sin(phi)
        z = centre_z + c * rho * np.cos(theta)
        return x, y, z, a * b * c * rho**2 * st

    return to_cartesian


def _cylindrical(a=1.0, b=1.0, radius_at=None):
    """(z, s, phi) -> elliptic-cylindrical coordinates with semi-axes a, b.

    With ``radius_at(z)``, ``s`` in [0, 1] is a fraction of that radius (for the cone).
    """

    def to_cartesian(u):
        z, s, phi = u[:, 0], u[:, 1], u[:, 2]
        scale = np.ones_like(z) if radius_at is None else radius_at(z)
        rho = s * scale
        return a * rho * np.cos(phi), b * rho * np.sin(phi), z, a * b * rho * scale

    return to_cartesian


def _assert_inertia_close(actual, expected, rtol):
    """Full 3x3 check; off-diagonal zeros are compared against the largest entry."""
    expected = np.asarray(expected)
    scale = np.max(np.abs(expected))
    np.testing.assert_allclose(np.asarray(actual), expected, rtol=rtol, atol=rtol * scale)


def _random_rotation(rng):
    """A random rotation from scipy, as (quaternion scalar-first, matrix)."""
    rotation = Rotation.random(random_state=rng)
    x, y, z, w = rotation.as_quat()  # scipy is scalar-last
    return np.array([w, x, y, z]), rotation.as_matrix()


def _box_mesh(half_extents, rotation, position):
    """12-triangle mesh of a posed box, every triangle oriented outward."""
    a, b, c = half_extents
    corners = np.array(
        [[sx * a, sy * b, sz * c] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    )
    faces = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            quad = [i for i, p in enumerate(corners) if p[axis] * sign > 0]
            # Corners of a face in cyclic order around its centre, then orient outward.
            centre = corners[quad].mean(axis=0)
            u, v = [k for k in range(3) if k != axis]
            quad.sort(
                key=lambda i: math.atan2(corners[i][v] - centre[v], corners[i][u] - centre[u])
            )
            for tri in ([quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]):
                p0, p1, p2 = corners[tri]
                if np.dot(np.cross(p1 - p0, p2 - p0), centre) < 0:
                    tri = tri[::-1]
                faces.append(tri)
    vertices = corners @ rotation.T + position
    return vertices, np.array(faces)


def _edge_midpoint(vertices, midpoints, i, j):
    """Index of the edge (i, j)'s midpoint pushed out to the unit sphere, added once."""
    key = (min(i, j), max(i, j))
    if key not in midpoints:
        m = np.add(vertices[i], vertices[j])
        vertices.append(list(m / np.linalg.norm(m)))
        midpoints[key] = len(vertices) - 1
    return midpoints[key]


def _icosphere(subdivisions, radius):
    """Icosahedron subdivided ``subdivisions`` times, vertices on the sphere, outward faces."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    vertices = [
        [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
        [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
        [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1],
    ]  # fmt: skip
    vertices = [list(np.asarray(v, float) / np.linalg.norm(v)) for v in vertices]
    faces = [
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
        [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
        [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
        [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ]  # fmt: skip
    for _ in range(subdivisions):
        midpoints = {}  # edge (i, j), i < j -> index of its midpoint on the sphere
        refined = []
        for i, j, k in faces:
            a, b, c = (
                _edge_midpoint(vertices, midpoints, p, q) for p, q in ((i, j), (j, k), (k, i))
            )
            refined += [[i, a, c], [j, b, a], [k, c, b], [a, b, c]]
        faces = refined
    vertices = radius * np.asarray(vertices)
    faces = np.asarray(faces)
    normals = np.cross(
        vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]
    )
    outward = np.einsum("ij,ij->i", normals, vertices[faces].mean(axis=1)) > 0
    faces = np.where(outward[:, None], faces, faces[:, ::-1])
    return vertices, faces


def _point_mass_inertia_loop(masses, positions, about):
    """Independent NumPy loop: sum m_i (|r|^2 E - r r^T), r = x_i - about."""
    total = np.zeros((3, 3))
    for m, x in zip(masses, positions, strict=True):
        r = np.asarray(x) - about
        total += m * (np.dot(r, r) * np.eye(3) - np.outer(r, r))
    return total


# ------------------------------------------------- 1. primitives vs numerical integrals

MASS = 2.7  # kg, any non-trivial value

# (name, shape, primitive, coordinate map, lower corner, upper corner)
_SOLID_CASES = [
    (
        "sphere",
        shapes.Sphere(0.7),
        lambda: inertia.sphere(MASS, 0.7),
        _spherical(),
        [0.0, 0.0, 0.0],
        [0.7, math.pi, TWO_PI],
    ),
    (
        "hollow_thick",
        shapes.HollowSphere(0.9, 0.25),
        lambda: inertia.hollow_sphere(MASS, 0.9, 0.25),
        _spherical(),
        [0.65, 0.0, 0.0],
        [0.9, math.pi, TWO_PI],
    ),
    (
        "box",
        shapes.Box((0.3, 0.5, 1.1)),
        lambda: inertia.box(MASS, jnp.array([0.3, 0.5, 1.1])),
        lambda u: (u[:, 0], u[:, 1], u[:, 2], np.ones(len(u))),
        [-0.3, -0.5, -1.1],
        [0.3, 0.5, 1.1],
    ),
    (
        "cylinder",
        shapes.Cylinder(0.4, 0.9),
        lambda: inertia.cylinder(MASS, 0.4, 0.9),
        _cylindrical(),
        [-0.9, 0.0, 0.0],
        [0.9, 0.4, TWO_PI],
    ),
    (
        "elliptical_cylinder",
        shapes.EllipticalCylinder((0.3, 0.8), 0.6),
        lambda: inertia.elliptical_cylinder(MASS, jnp.array([0.3, 0.8]), 0.6),
        _cylindrical(0.3, 0.8),
        [-0.6, 0.0, 0.0],
        [0.6, 1.0, TWO_PI],
    ),
    (
        # The actual cone: base (radius 0.5) at z = -h/4, apex at z = 3h/4, h = 1.6.
        "cone",
        shapes.Cone(0.5, 1.6),
        lambda: inertia.cone(MASS, 0.5, 1.6),
        _cylindrical(radius_at=lambda z: 0.5 * (1.2 - z) / 1.6),
        [-0.4, 0.0, 0.0],
        [1.2, 1.0, TWO_PI],
    ),
    (
        "ellipsoid",
        shapes.Ellipsoid((0.3, 0.7, 1.2)),
        lambda: inertia.ellipsoid(MASS, jnp.array([0.3, 0.7, 1.2])),
        _spherical(0.3, 0.7, 1.2),
        [0.0, 0.0, 0.0],
        [1.0, math.pi, TWO_PI],
    ),
]


@pytest.mark.parametrize(
    "name, shape, primitive, to_cartesian, lower, upper",
    _SOLID_CASES,
    ids=[c[0] for c in _SOLID_CASES],
)
def test_solid_primitive_matches_quadrature(name, shape, primitive, to_cartesian, lower, upper):
    measure, com, inertia_ref = _integrated_properties(to_cartesian, lower, upper, MASS)
    mp = primitive()
    # 1e-6 relative is the brief; the quadrature itself is good to ~1e-12.
    _assert_inertia_close(mp.inertia, inertia_ref, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(mp.com), 0.0, atol=1e-12)
    np.testing.assert_allclose(com, 0.0, atol=1e-10)
    np.testing.assert_allclose(float(mp.mass), MASS, rtol=1e-15)
    np.testing.assert_allclose(inertia.volume(shape), measure, rtol=1e-10)
    by_density = inertia.mass_properties(shape, density=MASS / measure)
    np.testing.assert_allclose(float(by_density.mass), MASS, rtol=1e-10)
    _assert_inertia_close(by_density.inertia, inertia_ref, rtol=1e-6)


def test_capsule_matches_quadrature_of_its_three_pieces():
    r, h = 0.35, 0.8
    pieces = [
        (_cylindrical(), [-h, 0.0, 0.0], [h, r, TWO_PI]),
        (_spherical(centre_z=h), [0.0, 0.0, 0.0], [r, math.pi / 2, TWO_PI]),  # top cap
        (_spherical(centre_z=-h), [0.0, math.pi / 2, 0.0], [r, math.pi, TWO_PI]),  # bottom cap
    ]
    moments = [_raw_moments(*piece) for piece in pieces]
    measure, first, second = (sum(parts) for parts in zip(*moments, strict=True))
    com, inertia_ref = _central(measure, first, second, MASS)
    np.testing.assert_allclose(com, 0.0, atol=1e-10)
    _assert_inertia_close(inertia.capsule(MASS, r, h).inertia, inertia_ref, rtol=1e-6)
    _assert_inertia_close(
        inertia.mass_properties(shapes.Capsule(r, h), mass=MASS).inertia, inertia_ref, rtol=1e-6
    )
    np.testing.assert_allclose(inertia.volume(shapes.Capsule(r, h)), measure, rtol=1e-10)


def _thin_shell(u):
    theta, phi = u[:, 0], u[:, 1]
    st = np.sin(theta)
    return 0.8 * st * np.cos(phi), 0.8 * st * np.sin(phi), 0.8 * np.cos(theta), 0.64 * st


_THIN_CASES = [
    (
        "thin_shell",
        shapes.HollowSphere(0.8),
        lambda: inertia.hollow_sphere(MASS, 0.8),
        _thin_shell,
        [0.0, 0.0],
        [math.pi, TWO_PI],
    ),
    (
        "rod",
        shapes.Rod(0.9),
        lambda: inertia.rod(MASS, 0.9),
        lambda u: (np.zeros(len(u)), np.zeros(len(u)), u[:, 0], np.ones(len(u))),
        [-0.9],
        [0.9],
    ),
    (
        "plate",
        shapes.Plate((0.4, 1.3)),
        lambda: inertia.plate(MASS, jnp.array([0.4, 1.3])),
        lambda u: (u[:, 0], u[:, 1], np.zeros(len(u)), np.ones(len(u))),
        [-0.4, -1.3],
        [0.4, 1.3],
    ),
    (
        "disk",
        shapes.Disk(0.6),
        lambda: inertia.disk(MASS, 0.6),
        lambda u: (u[:, 0] * np.cos(u[:, 1]), u[:, 0] * np.sin(u[:, 1]), np.zeros(len(u)), u[:, 0]),
        [0.0, 0.0],
        [0.6, TWO_PI],
    ),
]


@pytest.mark.parametrize(
    "name, shape, primitive, to_cartesian, lower, upper",
    _THIN_CASES,
    ids=[c[0] for c in _THIN_CASES],
)
def test_thin_primitive_matches_quadrature(name, shape, primitive, to_cartesian, lower, upper):
    _, com, inertia_ref = _integrated_properties(to_cartesian, lower, upper, MASS)
    np.testing.assert_allclose(com, 0.0, atol=1e-10)
    _assert_inertia_close(primitive().inertia, inertia_ref, rtol=1e-6)
    _assert_inertia_close(inertia.mass_properties(shape, mass=MASS).inertia, inertia_ref, rtol=1e-6)


# ---------------------------------------------------------------- 2. seed 001's table


def test_seed_table_rows_as_printed():
    m = 1.9
    # Rectangular prism, full lengths a (x, depth), b (y, height), c (z, width).
    a, b, c = 0.6, 1.4, 2.2
    i = np.asarray(inertia.box(m, jnp.array([a, b, c]) / 2).inertia)
    np.testing.assert_allclose(i[0, 0], m * (b**2 + c**2) / 12, rtol=1e-14)
    np.testing.assert_allclose(
        np.diag(i),
        [m * (b**2 + c**2) / 12, m * (a**2 + c**2) / 12, m * (a**2 + b**2) / 12],
        rtol=1e-14,
    )
    # Sphere.
    r = 0.45
    np.testing.assert_allclose(np.diag(inertia.sphere(m, r).inertia), 0.4 * m * r**2, rtol=1e-14)
    # Ellipsoid with semi-axes a, b, c.
    np.testing.assert_allclose(
        np.diag(inertia.ellipsoid(m, jnp.array([a, b, c])).inertia),
        [m * (b**2 + c**2) / 5, m * (a**2 + c**2) / 5, m * (a**2 + b**2) / 5],
        rtol=1e-14,
    )
    # Slender rod of length l: 0 about its axis, m l^2 / 12 across.
    l = 1.7
    np.testing.assert_allclose(
        np.diag(inertia.rod(m, l / 2).inertia), [m * l**2 / 12, m * l**2 / 12, 0.0], rtol=1e-14
    )
    # Thin disk: 1/4 m r^2 about a diameter, 1/2 m r^2 about the normal.
    np.testing.assert_allclose(
        np.diag(inertia.disk(m, r).inertia), [m * r**2 / 4, m * r**2 / 4, m * r**2 / 2], rtol=1e-14
    )
    # Circular cylinder of length l: 1/12 m (3 r^2 + l^2) across.
    i = np.asarray(inertia.cylinder(m, r, l / 2).inertia)
    np.testing.assert_allclose([i[0, 0], i[1, 1]], m * (3 * r**2 + l**2) / 12, rtol=1e-14)
    # Rectangular plate, height b and width c (full lengths): 1/12 m (b^2 + c^2) about the
    # normal and 1/12 m b^2 about the axis along its width.
    i = np.asarray(inertia.plate(m, jnp.array([c, b]) / 2).inertia)  # width along x, height along y
    np.testing.assert_allclose(i[2, 2], m * (b**2 + c**2) / 12, rtol=1e-14)
    np.testing.assert_allclose(i[0, 0], m * b**2 / 12, rtol=1e-14)


def test_seed_elliptical_cylinder_with_its_axis_naming():
    # Seed: "l = length (x), b = height/2 (y), c = width/2 (z)"; its x, y, z are our z, x, y.
    m, l, b, c = 1.3, 2.4, 0.5, 0.9
    i = np.asarray(inertia.elliptical_cylinder(m, jnp.array([b, c]), l / 2).inertia)
    seed_i_x = m * (b**2 + c**2) / 4  # about the axis
    seed_i_y = m * (3 * c**2 + l**2) / 12
    seed_i_z = m * (3 * b**2 + l**2) / 12
    np.testing.assert_allclose(np.diag(i), [seed_i_y, seed_i_z, seed_i_x], rtol=1e-14)


def test_seed_cone_row_is_the_moment_about_the_apex():
    m, r, h = 1.1, 0.5, 1.6
    mp = inertia.cone(m, r, h)
    apex = jnp.array([0.0, 0.0, 0.75 * h])
    about_apex = np.asarray(mp.shifted_inertia(apex))
    # Seed's garbled "3/5 m (1/4 r^2 + 1/2)" read as 3/5 m (r^2/4 + h^2).
    np.testing.assert_allclose(about_apex[0, 0], 0.6 * m * (r**2 / 4 + h**2), rtol=1e-14)
    np.testing.assert_allclose(about_apex[1, 1], 0.6 * m * (r**2 / 4 + h**2), rtol=1e-14)
    np.testing.assert_allclose(about_apex[2, 2], 0.3 * m * r**2, rtol=1e-14)  # seed's 3/10 m r^2
    # ... and that row is not the moment about the com.
    assert abs(float(mp.inertia[0, 0]) - 0.6 * m * (r**2 / 4 + h**2)) > 0.1


# -------------------------------------------------------------------- 3. point masses


def test_from_point_masses_matches_numpy_loop():
    rng = np.random.default_rng(0)
    masses = rng.uniform(0.1, 2.0, size=17)
    positions = rng.normal(size=(17, 3)) + np.array([3.0, -1.0, 2.0])
    mp = inertia.from_point_masses(masses, positions)
    com = (masses[:, None] * positions).sum(axis=0) / masses.sum()
    np.testing.assert_allclose(float(mp.mass), masses.sum(), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(mp.com), com, rtol=1e-13)
    _assert_inertia_close(mp.inertia, _point_mass_inertia_loop(masses, positions, com), rtol=1e-12)


def test_eight_corner_masses():
    m, (a, b, c) = 3.2, (0.4, 0.9, 1.5)
    corners = [[sx * a, sy * b, sz * c] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    mp = inertia.from_point_masses(np.full(8, m / 8), np.asarray(corners))
    # Every corner is at distance^2 b^2 + c^2 from the x axis, etc.; products cancel.
    _assert_inertia_close(
        mp.inertia, m * np.diag([b**2 + c**2, a**2 + c**2, a**2 + b**2]), rtol=1e-14
    )


def test_dense_grid_of_point_masses_converges_to_box():
    m, half = 2.0, np.array([0.3, 0.5, 0.8])
    exact = np.asarray(inertia.box(m, jnp.asarray(half)).inertia)
    errors = []
    for n in (4, 8, 16, 32):
        cell = 2 * half / n
        axes = [-half[k] + cell[k] * (np.arange(n) + 0.5) for k in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        mp = inertia.from_point_masses(np.full(len(grid), m / len(grid)), grid)
        errors.append(np.max(np.abs(np.asarray(mp.inertia) - exact)) / np.max(exact))
        # Midpoint rule: each point mass misses its own cell's inertia about the cell centre.
        dx2, dy2, dz2 = cell**2
        cell_inertia = m / 12 * np.diag([dy2 + dz2, dx2 + dz2, dx2 + dy2])
        _assert_inertia_close(np.asarray(mp.inertia) + cell_inertia, exact, rtol=1e-12)
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    np.testing.assert_allclose(ratios, 4.0, rtol=1e-6)  # second order in the cell size


# ---------------------------------------------------------------------------- 4. meshes


def test_triangulated_box_equals_box_formula():
    rng = np.random.default_rng(1)
    half, m = np.array([0.35, 0.6, 1.2]), 4.5
    quat, rotation = _random_rotation(rng)
    position = np.array([1.7, -2.3, 0.9])
    vertices, faces = _box_mesh(half, rotation, position)
    expected = inertia.box(m, jnp.asarray(half)).transformed(position, quat)
    mp = inertia.from_mesh(vertices, faces, mass=m)
    np.testing.assert_allclose(np.asarray(mp.com), position, rtol=1e-12)
    _assert_inertia_close(mp.inertia, expected.inertia, rtol=1e-12)
    # Independent reference for the rotation: R I R^T with scipy's matrix.
    _assert_inertia_close(
        expected.inertia,
        rotation @ np.asarray(inertia.box(m, jnp.asarray(half)).inertia) @ rotation.T,
        rtol=1e-13,
    )
    by_density = inertia.from_mesh(vertices, faces, density=800.0)
    np.testing.assert_allclose(float(by_density.mass), 800.0 * 8 * np.prod(half), rtol=1e-12)
    mesh = shapes.Mesh(vertices, faces)
    np.testing.assert_allclose(inertia.volume(mesh), 8 * np.prod(half), rtol=1e-12)
    _assert_inertia_close(
        inertia.mass_properties(mesh, mass=m).inertia, expected.inertia, rtol=1e-12
    )


def test_icosphere_converges_to_sphere():
    radius, m = 0.8, 1.5
    exact = 0.4 * m * radius**2
    errors = []
    # The faces lie inside the sphere, so the error falls as the edge length squared
    # (x 1/4 per subdivision): 1.4e-3 after 4 subdivisions, 3.6e-4 after 5.
    for k in range(1, 6):
        vertices, faces = _icosphere(k, radius)
        mp = inertia.from_mesh(vertices, faces, mass=m)
        moments = np.linalg.eigvalsh(np.asarray(mp.inertia))
        errors.append(np.max(np.abs(moments - exact)) / exact)
        np.testing.assert_allclose(np.asarray(mp.com), 0.0, atol=1e-12)
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all((ratios > 3.5) & (ratios < 4.1)), errors  # monotone, second order
    assert errors[-1] < 1e-3, errors


def test_inside_out_mesh_raises():
    vertices, faces = _box_mesh(np.array([0.5, 0.5, 0.5]), np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="orientation"):
        inertia.from_mesh(vertices, faces[:, ::-1], mass=1.0)
    with pytest.raises(ValueError, match="orientation"):
        inertia.volume(shapes.Mesh(vertices, faces[:, ::-1]))
    with pytest.raises(ValueError, match="orientation"):
        inertia.mass_properties(shapes.Mesh(vertices, faces[:, ::-1]), density=1.0)


def test_meshes_and_point_masses_of_the_wrong_form_are_refused():
    """from_mesh had taken quad faces (their first three corners: a unit cube of 1000 kg/m^3
    came out 500 kg), wrapped a face index of -1 to the last vertex, and blamed a NaN
    vertex on the face orientation; from_point_masses had put the centre of mass at inf or
    NaN for masses summing to zero."""
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    quads = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
    with pytest.raises(ValueError, match=r"from_mesh: faces must have shape \(F>=4, 3\), triangles"):
        inertia.from_mesh(cube, quads, density=1000.0)
    triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    assert float(inertia.from_mesh(cube, triangles, density=1000.0).mass) == pytest.approx(1000.0, rel=1e-12)
    wrapped = triangles.copy()
    wrapped[wrapped == 7] = -1
    with pytest.raises(ValueError, match=r"integer indices in \[0, 8\)"):
        inertia.from_mesh(cube, wrapped, density=1000.0)
    with pytest.raises(ValueError, match="vertices contain NaN"):
        inertia.from_mesh(np.where(cube == 1, np.nan, cube), triangles, density=1000.0)
    with pytest.raises(ValueError, match=r"Mesh: vertices must have shape \(V>=4, 3\)"):
        shapes.Mesh(np.hstack([cube, cube[:, :1]]), triangles)
    for masses in ([1.0, -1.0], [0.0, 0.0], [1.0, np.nan]):
        with pytest.raises(ValueError, match="masses must be finite and >= 0 with a positive total"):
            inertia.from_point_masses(np.asarray(masses), np.eye(3)[:2])
    with pytest.raises(ValueError, match=r"masses must have shape \(n,\) and positions \(n, 3\)"):
        inertia.from_point_masses(np.ones(3), np.eye(3)[:2])
    # Traced masses pass the checks (a fit through them).
    assert jax.grad(lambda m: inertia.from_point_masses(m, np.eye(3)).com[0])(jnp.ones(3)).shape == (3,)


def test_a_mesh_part_wound_inward_is_refused_unless_it_is_a_cavity():
    """Two cubes, the second wound inward: each passes the edge test, the total volume is
    positive (8 - 1 = 7 instead of 9), and the centre of mass came out outside both. A part
    wound inward inside another is a cavity, and stays allowed."""
    cube, faces = _box_mesh(np.array([0.5, 0.5, 0.5]), np.eye(3), np.zeros(3))
    twice, n = np.vstack([2 * cube, cube + 10.0]), len(cube)
    assert float(inertia.volume(shapes.Mesh(twice, np.vstack([faces, faces + n])))) == pytest.approx(9.0)
    with pytest.raises(ValueError, match=r"part of the mesh \(12 faces\) is inside out: its volume is -1"):
        shapes.Mesh(twice, np.vstack([faces, faces[:, ::-1] + n]))
    with pytest.raises(ValueError, match="is inside out"):
        inertia.from_mesh(twice, np.vstack([faces, faces[:, ::-1] + n]), density=1.0)
    hollow = shapes.Mesh(np.vstack([4 * cube, cube]), np.vstack([faces, faces[:, ::-1] + n]))
    assert float(inertia.volume(hollow)) == pytest.approx(64.0 - 1.0)


def test_a_float32_mesh_far_from_its_origin_keeps_its_inertia():
    """A stored Mesh's vertices were cast to the mass's dtype before the apex was
    subtracted: in float32 a 10 x 6 x 4 cm box 1000 m from its frame's origin lost 4e-4 of
    its inertia. Now about their mean in float64 first: float32's own rounding."""
    half = np.array([0.05, 0.03, 0.02])
    turn = Rotation.from_rotvec([0.4, -0.3, 0.8]).as_matrix()
    expected = inertia.box(8 * np.prod(half), half).inertia
    expected = turn @ np.asarray(expected) @ turn.T
    for offset in (0.0, 1e3):
        where = offset * np.array([1.0, 0.5, 0.2])
        vertices, faces = _box_mesh(half, turn, where)
        props = inertia.mass_properties(shapes.Mesh(vertices, faces), mass=jnp.float32(8 * np.prod(half)))
        assert props.inertia.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(props.inertia), expected, rtol=0, atol=1e-6 * np.abs(expected).max())
        np.testing.assert_allclose(np.asarray(props.com), where, rtol=1e-7, atol=1e-7)


def test_solids_touching_along_an_edge_make_one_valid_mesh():
    """Two cubes sharing one edge: each direction of that edge is traversed twice. A valid
    solid, but it was refused as "traversed twice the same way (a face flipped or given
    twice)"; now its volume and inertia are the two cubes'. A face given twice is still
    refused (its edges run twice one way, once the other)."""
    cube, faces = _box_mesh(np.array([0.5, 0.5, 0.5]), np.eye(3), np.zeros(3))
    other = cube + np.array([1.0, 1.0, 0.0])  # shares the edge x = y = 0.5
    vertices, both = np.vstack([cube, other]), np.vstack([faces, faces + len(cube)])
    solid = inertia.mass_properties(shapes.Mesh(vertices, both), density=1.0)
    parts = [inertia.box(1.0, jnp.asarray([0.5, 0.5, 0.5])).transformed(jnp.asarray(c))
             for c in ([0.0, 0.0, 0.0], [1.0, 1.0, 0.0])]
    expected = inertia.compose(parts)
    np.testing.assert_allclose(float(solid.mass), 2.0, rtol=1e-12)
    np.testing.assert_allclose(solid.com, expected.com, atol=1e-12)
    _assert_inertia_close(solid.inertia, expected.inertia, rtol=1e-12)
    with pytest.raises(ValueError, match="3 are traversed twice the same way"):
        shapes.Mesh(vertices, np.vstack([both, both[:1]]))


def test_a_closed_mesh_that_encloses_no_volume_is_refused_wherever_it_is_placed():
    """Four coplanar vertices, four faces: closed and consistently oriented, but flat. Its
    signed volume is rounding, so it had been accepted or called inside out by where it was
    placed (1 of 12 rigid placements accepted, with moments from noise that differed 1.5%
    between placements, and a mass of 4.6e-15 kg at a density of 1000). A thin solid stays
    accepted, far from the origin too."""
    flat = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.3, 0.3, 0.0]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]])
    rng = np.random.default_rng(5)
    for _ in range(12):
        turn = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        for offset, dtype in ((0.0, np.float64), (3.0, np.float64), (1e3, np.float64), (3.0, np.float32)):
            placed = (flat @ turn.T + offset * rng.normal(size=3)).astype(dtype)
            with pytest.raises(ValueError, match=r"\(4 faces\) encloses no volume"):
                inertia.from_mesh(placed, faces, mass=1.0)
            with pytest.raises(ValueError, match="encloses no volume"):
                shapes.Mesh(placed, faces)
    for thickness in (1e-3, 1e-9):
        half = np.array([0.5, 0.5, thickness])
        vertices, box_faces = _box_mesh(half, turn, np.full(3, 1e3))
        thin = inertia.from_mesh(vertices, box_faces, density=1.0)
        np.testing.assert_allclose(float(thin.mass), 8 * np.prod(half), rtol=1e-4)


def test_open_or_inconsistently_oriented_meshes_are_refused():
    """The volume integrals need a closed surface whose faces agree on the orientation;
    an open cube missing one face gave 833 kg at a density of 1000, silently."""
    vertices, faces = _box_mesh(np.array([0.5, 0.5, 0.5]), np.eye(3), np.zeros(3))
    flipped = faces.copy()
    flipped[0] = flipped[0][::-1]
    for bad, why in ((faces[2:], "4 edges have no opposite"), (flipped, "3 are traversed twice"),
                     (np.vstack([faces, faces[:1]]), "3 are traversed twice")):
        with pytest.raises(ValueError, match=f"closed, consistently oriented.*{why}"):
            shapes.Mesh(vertices, bad)
        with pytest.raises(ValueError, match="closed, consistently oriented"):
            inertia.from_mesh(vertices, bad, mass=1.0)
    # A triangle soup (each face its own three vertices, as STL stores a mesh) is closed:
    # vertices at the same position are one.
    soup_vertices, soup_faces = vertices[faces].reshape(-1, 3), np.arange(3 * len(faces)).reshape(-1, 3)
    soup = inertia.mass_properties(shapes.Mesh(soup_vertices, soup_faces), density=1000.0)
    np.testing.assert_allclose(float(soup.mass), 1000.0, rtol=1e-12)
    _assert_inertia_close(soup.inertia, inertia.box(1000.0, jnp.asarray([0.5, 0.5, 0.5])).inertia, rtol=1e-12)


def test_inside_out_mesh_fails_at_run_time_under_jit():
    # Traced vertices: the volume's sign is unknown at trace time, so eqx.error_if reports it.
    vertices, faces = _box_mesh(np.array([0.5, 0.5, 0.5]), np.eye(3), np.zeros(3))
    from_mesh = jax.jit(lambda v, f: inertia.from_mesh(v, f, mass=1.0).inertia)
    np.testing.assert_allclose(np.asarray(from_mesh(vertices, faces)), np.eye(3) / 6, rtol=1e-12)
    with pytest.raises(Exception, match="check the face orientation"):
        jax.block_until_ready(from_mesh(vertices, faces[:, ::-1]))


def test_mesh_is_differentiable_in_its_vertices():
    # Scaling all vertices by s scales a box's inertia by s^2 at fixed mass.
    vertices, faces = _box_mesh(np.array([0.3, 0.4, 0.5]), np.eye(3), np.array([0.2, 0.0, -0.1]))

    def trace(s):
        return jnp.trace(inertia.from_mesh(s * jnp.asarray(vertices), faces, mass=2.0).inertia)

    t0 = float(trace(1.0))
    np.testing.assert_allclose(float(jax.grad(trace)(1.0)), 2.0 * t0, rtol=1e-12)
    np.testing.assert_allclose(float(jax.jit(trace)(1.0)), t0, rtol=1e-14)


# ------------------------------------------------------------- 5. composition, frames


def test_compose_posed_point_clouds_equals_the_union():
    rng = np.random.default_rng(2)
    masses = rng.uniform(0.2, 1.5, size=30)
    positions = rng.normal(size=(30, 3)) * np.array([1.0, 2.0, 0.5])
    parts = []
    for idx in np.array_split(np.arange(30), 3):
        quat, rotation = _random_rotation(rng)
        origin = rng.normal(size=3)
        local = (positions[idx] - origin) @ rotation  # R^T (x - origin), row-wise
        parts.append(inertia.from_point_masses(masses[idx], local).transformed(origin, quat))
    composed = inertia.compose(parts)
    union = inertia.from_point_masses(masses, positions)
    np.testing.assert_allclose(float(composed.mass), float(union.mass), rtol=1e-14)
    np.testing.assert_allclose(
        np.asarray(composed.com), np.asarray(union.com), rtol=1e-12, atol=1e-12
    )
    _assert_inertia_close(composed.inertia, union.inertia, rtol=1e-12)


def test_dumbbell_by_hand():
    m_ball, r_ball, d = 1.2, 0.15, 0.6  # two balls at x = +-d
    m_bar, r_bar, h_bar = 0.4, 0.02, 0.45  # bar along x
    to_x = Rotation.from_rotvec([0.0, math.pi / 2, 0.0])  # z axis -> x axis
    x, y, z, w = to_x.as_quat()
    bar = inertia.cylinder(m_bar, r_bar, h_bar).transformed(jnp.zeros(3), jnp.array([w, x, y, z]))
    balls = [
        inertia.sphere(m_ball, r_ball).transformed(jnp.array([s * d, 0.0, 0.0])) for s in (-1, 1)
    ]
    composed = inertia.compose([balls[0], bar, balls[1]])
    i_along = 2 * 0.4 * m_ball * r_ball**2 + 0.5 * m_bar * r_bar**2
    length = 2 * h_bar
    i_across = (
        2 * (0.4 * m_ball * r_ball**2 + m_ball * d**2) + m_bar * (3 * r_bar**2 + length**2) / 12
    )
    _assert_inertia_close(composed.inertia, np.diag([i_along, i_across, i_across]), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(composed.com), 0.0, atol=1e-15)
    np.testing.assert_allclose(float(composed.mass), 2 * m_ball + m_bar, rtol=1e-15)


def test_a_rotated_float32_part_is_symmetric_and_a_body_accepts_it():
    # R I R^T rounded in float32 was asymmetric at ~1e-8 relative, and Body's check (1e-9)
    # refused jaxrb's own compose of a rotated box.
    import jaxrb as rb

    q = spatial.quat_exp(jnp.array([0.3, -0.5, 1.0], jnp.float32))
    part = inertia.box(jnp.float32(2.0), jnp.array([0.1, 0.2, 0.3], jnp.float32)).transformed(
        jnp.zeros(3, jnp.float32), q)
    assert part.inertia.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(part.inertia), np.asarray(part.inertia).T)
    scene = rb.Scene(bodies=[rb.Body("b", mass_properties=inertia.compose([part]))])
    np.testing.assert_allclose(np.asarray(scene.params(dtype=jnp.float64).inertia[0]),
                               np.asarray(part.inertia, np.float64), rtol=1e-6)


def test_transformed_rotates_and_translates():
    rng = np.random.default_rng(3)
    quat, rotation = _random_rotation(rng)
    body = inertia.from_point_masses(rng.uniform(0.5, 1.0, 6), rng.normal(size=(6, 3)))
    position = np.array([0.3, -0.2, 1.1])
    moved = body.transformed(position, quat)
    np.testing.assert_allclose(
        np.asarray(moved.com), position + rotation @ np.asarray(body.com), rtol=1e-13
    )
    _assert_inertia_close(
        moved.inertia, rotation @ np.asarray(body.inertia) @ rotation.T, rtol=1e-13
    )
    np.testing.assert_allclose(float(moved.mass), float(body.mass))


def test_transformed_refuses_a_non_unit_quaternion():
    """R comes from the unit quaternion's formula: (1, 0, 0, 1), meant as 90 degrees about z,
    had given a sphere the moments (0.02, 0.02, 0.004) for 0.004 each, silently; (0, 0, 0,
    0) had meant no rotation. Rounded decimals pass, and so does a traced quaternion."""
    sphere = inertia.mass_properties(shapes.Sphere(0.1), mass=1.0)
    for q in [(1.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.3)]:
        with pytest.raises(ValueError, match="not a unit quaternion"):
            sphere.transformed((0.0, 0.0, 0.0), q)
    turned = sphere.transformed((0.0, 0.0, 0.0), (0.7071, 0.0, 0.0, 0.7071))
    np.testing.assert_allclose(np.diag(np.asarray(turned.inertia)), 0.004, rtol=1e-4)
    traced = jax.jit(lambda q: sphere.transformed((0.0, 0.0, 0.0), q).inertia)(jnp.array([1.0, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(np.asarray(traced), np.asarray(sphere.inertia))


def test_shifted_inertia_matches_point_mass_loop():
    rng = np.random.default_rng(4)
    masses, positions = rng.uniform(0.5, 1.0, 9), rng.normal(size=(9, 3))
    point = np.array([0.7, -1.2, 0.4])
    shifted = inertia.from_point_masses(masses, positions).shifted_inertia(point)
    _assert_inertia_close(shifted, _point_mass_inertia_loop(masses, positions, point), rtol=1e-12)


# ------------------------------------------------------------------- 6. principal axes


def test_principal_axes_reconstruct_random_inertia():
    rng = np.random.default_rng(5)
    for _ in range(10):
        quat, rotation = _random_rotation(rng)
        moments = np.sort(rng.uniform(1.0, 2.0, size=3))  # 1 + 1 >= 2: triangle holds
        tensor = rotation @ np.diag(moments) @ rotation.T
        found, axes = inertia.principal_axes(jnp.asarray(tensor))
        found, axes = np.asarray(found), np.asarray(axes)
        np.testing.assert_allclose(found, moments, rtol=1e-12)
        assert np.all(np.diff(found) > 0)
        np.testing.assert_allclose(np.linalg.det(axes), 1.0, rtol=1e-12)
        np.testing.assert_allclose(axes @ np.diag(found) @ axes.T, tensor, rtol=1e-12, atol=1e-12)
        # Each axis equals scipy's up to sign.
        np.testing.assert_allclose(np.abs(np.sum(axes * rotation, axis=0)), 1.0, rtol=1e-10)


def _rotated(tensor_fn, quat):
    rotation = jnp.asarray(Rotation.from_quat(np.roll(quat, -1)).as_matrix())
    return lambda *args: rotation @ tensor_fn(*args) @ rotation.T


def test_principal_axes_gradients_finite_for_repeated_moments():
    rng = np.random.default_rng(6)
    quat, _ = _random_rotation(rng)
    weights = jnp.asarray(rng.normal(size=(3, 3)))

    def loss(tensor):
        moments, axes = inertia.principal_axes(tensor)
        return jnp.sum(moments) + jnp.sum(weights * axes) + jnp.sum(moments**2)

    m = 2.0
    cube = _rotated(lambda he: inertia.box(m, he).inertia, quat)
    he = jnp.array([0.5, 0.5, 0.5])
    grad_he = jax.jit(jax.grad(lambda he: loss(cube(he))))(he)
    assert np.all(np.isfinite(np.asarray(grad_he)))
    grad_tensor = jax.jit(jax.grad(loss))(cube(he))
    assert np.all(np.isfinite(np.asarray(grad_tensor)))
    # The moments' part is exact even though all three are equal: trace = 2m/3 |he|^2.
    grad_trace = jax.jit(jax.grad(lambda he: jnp.sum(inertia.principal_axes(cube(he))[0])))(he)
    np.testing.assert_allclose(np.asarray(grad_trace), 4 * m / 3 * np.asarray(he), rtol=1e-10)

    # Rotated thin cylinder: moments (axial, transverse, transverse), the last two equal.
    cyl = _rotated(lambda r, h: inertia.cylinder(m, r, h).inertia, quat)
    r, h = 0.1, 1.0
    jac = jax.jit(jax.jacobian(lambda r, h: inertia.principal_axes(cyl(r, h))[0], argnums=(0, 1)))(
        r, h
    )
    np.testing.assert_allclose(np.asarray(jac[0]), [m * r, m * r / 2, m * r / 2], rtol=1e-10)
    np.testing.assert_allclose(
        np.asarray(jac[1]), [0.0, 2 * m * h / 3, 2 * m * h / 3], rtol=1e-10, atol=1e-12
    )
    grad_axes = jax.jit(jax.grad(lambda r, h: loss(cyl(r, h)), argnums=(0, 1)))(r, h)
    assert np.all(np.isfinite(np.asarray(grad_axes)))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_principal_axes_gradient_finite_in_both_precisions(dtype):
    he = jnp.array([0.5, 0.5, 0.5], dtype=dtype)
    quat = jnp.array([0.9, 0.3, -0.2, 0.1], dtype=dtype)
    quat = quat / jnp.linalg.norm(quat)

    def loss(he):
        tensor = (
            inertia.box(jnp.asarray(1.0, dtype), he).transformed(jnp.zeros(3, dtype), quat).inertia
        )
        moments, axes = inertia.principal_axes(tensor)
        return jnp.sum(moments) + jnp.sum(axes[:, 0] * jnp.arange(3, dtype=dtype))

    grad = jax.jit(jax.grad(loss))(he)
    assert grad.dtype == dtype
    assert np.all(np.isfinite(np.asarray(grad)))


def test_principal_axes_derivatives_match_finite_differences():
    rng = np.random.default_rng(7)
    quat, rotation = _random_rotation(rng)
    base = rotation @ np.diag([1.0, 1.6, 2.1]) @ rotation.T
    direction = rng.normal(size=(3, 3))
    direction = direction + direction.T

    def along(t):
        return inertia.principal_axes(jnp.asarray(base) + t * jnp.asarray(direction))

    step = 1e-6
    (moments_plus, axes_plus), (moments_minus, axes_minus) = along(step), along(-step)
    _, (d_moments, d_axes) = jax.jvp(along, (0.0,), (1.0,))
    # Central differences: O(step^2) truncation plus round-off ~1e-16/1e-6.
    np.testing.assert_allclose(
        np.asarray(d_moments), np.asarray(moments_plus - moments_minus) / (2 * step), rtol=1e-7
    )
    np.testing.assert_allclose(
        np.asarray(d_axes), np.asarray(axes_plus - axes_minus) / (2 * step), atol=1e-7
    )
    # Reverse mode agrees with forward mode (the custom JVP transposes).
    weights = jnp.asarray(rng.normal(size=3))
    grad = jax.grad(lambda t: jnp.sum(weights * along(t)[0]))(0.0)
    np.testing.assert_allclose(float(grad), float(jnp.sum(weights * d_moments)), rtol=1e-12)


# ---------------------------------------------------------------- 7. density vs mass


def test_density_or_mass():
    shape = shapes.Box((0.5, 1.0, 1.5))
    mp = inertia.mass_properties(shape, density=1000.0)
    np.testing.assert_allclose(float(mp.mass), 1000.0 * inertia.volume(shape), rtol=1e-15)
    np.testing.assert_allclose(float(mp.mass), 1000.0 * 8 * 0.5 * 1.0 * 1.5, rtol=1e-15)
    with pytest.raises(ValueError, match="exactly one of density"):
        inertia.mass_properties(shape, density=1000.0, mass=2.0)
    with pytest.raises(ValueError, match="exactly one of density"):
        inertia.mass_properties(shape)
    with pytest.raises(ValueError, match="exactly one of density"):
        inertia.from_mesh(*_box_mesh(np.ones(3), np.eye(3), np.zeros(3)))


@pytest.mark.parametrize(
    "shape", [shapes.Rod(1.0), shapes.Plate((1.0, 2.0)), shapes.Disk(0.5), shapes.HollowSphere(1.0)]
)
def test_thin_shapes_need_mass(shape):
    with pytest.raises(ValueError, match="has no volume.*give mass="):
        inertia.mass_properties(shape, density=1000.0)
    with pytest.raises(ValueError, match="no volume"):
        inertia.volume(shape)
    assert float(inertia.mass_properties(shape, mass=2.0).mass) == 2.0


def test_plane_has_no_mass():
    with pytest.raises(ValueError, match="Plane"):
        inertia.mass_properties(shapes.Plane(), mass=1.0)


# --------------------------------------------------------- 8. check_mass_properties

_GOOD = np.diag([1.0, 2.0, 2.5])


@pytest.mark.parametrize(
    "mass, tensor, pattern",
    [
        (0.0, _GOOD, "mass must be positive"),
        (-1.0, _GOOD, "mass must be positive"),
        (float("nan"), _GOOD, "mass must be positive and finite"),
        (1.0, _GOOD + np.triu(np.full((3, 3), 0.1), 1), "must be symmetric"),
        (1.0, np.diag([1.0, 2.0, -0.5]), "positive definite"),
        (1.0, np.diag([1.0, 1.0, 3.0]), "triangle inequality I1 \\+ I2 >= I3"),
        (1.0, np.eye(2), "3x3"),
        (1.0, np.full((3, 3), np.nan), "NaN"),
    ],
    ids=[
        "zero-mass",
        "negative-mass",
        "nan-mass",
        "asymmetric",
        "indefinite",
        "triangle",
        "shape",
        "nan-inertia",
    ],
)
def test_check_mass_properties_rejects(mass, tensor, pattern):
    with pytest.raises(ValueError, match=f"wheel.*{pattern}"):
        inertia.check_mass_properties(mass, tensor, name="wheel")


def test_check_mass_properties_accepts_valid_and_boundary_cases():
    rng = np.random.default_rng(8)
    _, rotation = _random_rotation(rng)
    inertia.check_mass_properties(2.0, rotation @ _GOOD @ rotation.T)
    plate = inertia.plate(2.0, jnp.array([0.3, 0.7])).transformed(
        jnp.zeros(3), jnp.array([0.8, 0.2, -0.5, 0.26]) / np.linalg.norm([0.8, 0.2, -0.5, 0.26])
    )
    inertia.check_mass_properties(plate.mass, plate.inertia, name="plate")  # I1 + I2 = I3 exactly
    rod = inertia.rod(2.0, 0.5)
    with pytest.raises(ValueError, match="rod.*positive definite.*Cylinder"):
        inertia.check_mass_properties(rod.mass, rod.inertia, name="rod")


def test_flat_bodies_pass_in_float32():
    """A plate has I1 + I2 = I3 exactly; rounding the moments to float32 broke that by ~1e-8 of
    the trace, and the fixed 1e-9 allowance refused 27 of 76 random plates with x64 off (and
    scene.params(dtype=float32) refused them with x64 on). A real violation still fails."""
    import jaxrb as rb

    rng = np.random.default_rng(11)
    for a, b in rng.uniform(0.05, 1.0, (40, 2)):
        scene = rb.Scene([rb.Body("p", shape=shapes.Plate((a, b)), mass=1.3)])
        scene.params(dtype=jnp.float32)
        moments = np.array([a, b, a + b], np.float32)
        inertia.check_mass_properties(np.float32(1.0), np.diag(moments), name="flat")
    with pytest.raises(ValueError, match="triangle inequality"):
        inertia.check_mass_properties(np.float32(1.0), np.diag(np.float32([1.0, 1.0, 2.001])), name="flat")


# ----------------------------------------------------------- 9. jit and gradients

_ALL_SHAPES = [
    shapes.Sphere(0.3),
    shapes.HollowSphere(0.5, 0.1),
    shapes.HollowSphere(0.5),
    shapes.Box((0.1, 0.2, 0.3)),
    shapes.Capsule(0.1, 0.4),
    shapes.Cylinder(0.2, 0.5),
    shapes.EllipticalCylinder((0.2, 0.3), 0.4),
    shapes.Cone(0.3, 0.9),
    shapes.Ellipsoid((0.2, 0.3, 0.4)),
    shapes.Rod(0.5),
    shapes.Plate((0.2, 0.3)),
    shapes.Disk(0.25),
]


@pytest.mark.parametrize("shape", _ALL_SHAPES, ids=lambda s: type(s).__name__)
def test_jit_equals_eager(shape):
    eager = inertia.mass_properties(shape, mass=1.7)
    jitted = jax.jit(lambda m: inertia.mass_properties(shape, mass=m))(jnp.asarray(1.7))
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-15, atol=0.0)


@pytest.mark.parametrize("shape", _ALL_SHAPES, ids=lambda s: type(s).__name__)
def test_float32_matches_float64(shape):
    single = inertia.mass_properties(shape, mass=jnp.asarray(1.7, jnp.float32))
    double = inertia.mass_properties(shape, mass=jnp.asarray(1.7, jnp.float64))
    assert single.inertia.dtype == jnp.float32 and single.com.dtype == jnp.float32
    # float32 round-off (eps 1.2e-7) over a handful of operations.
    _assert_inertia_close(single.inertia, double.inertia, rtol=1e-6)


def test_vmap_equals_loop():
    rng = np.random.default_rng(9)
    masses = jnp.asarray(rng.uniform(0.5, 2.0, 5))
    half_extents = jnp.asarray(rng.uniform(0.1, 1.0, (5, 3)))
    batched = jax.vmap(inertia.box)(masses, half_extents)
    for k in range(5):
        single = inertia.box(masses[k], half_extents[k])
        np.testing.assert_allclose(
            np.asarray(batched.inertia[k]), np.asarray(single.inertia), rtol=1e-15
        )
    moments, axes = jax.vmap(inertia.principal_axes)(batched.inertia)
    for k in range(5):
        m_k, r_k = inertia.principal_axes(batched.inertia[k])
        np.testing.assert_allclose(np.asarray(moments[k]), np.asarray(m_k), rtol=1e-14)
        np.testing.assert_allclose(np.asarray(axes[k]), np.asarray(r_k), atol=1e-14)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_primitives_keep_dtype(dtype):
    mp = inertia.box(jnp.asarray(2.0, dtype), jnp.asarray([0.1, 0.2, 0.3], dtype))
    assert mp.inertia.dtype == dtype and mp.com.dtype == dtype
    mp = inertia.principal_axes(mp.inertia)
    assert mp[0].dtype == dtype and mp[1].dtype == dtype


def test_box_inertia_gradient_matches_finite_differences():
    half = np.array([0.3, 0.5, 0.8])
    weights = jnp.asarray(np.arange(9.0).reshape(3, 3) + 1.0)

    def f(he):
        return jnp.sum(weights * inertia.box(2.5, he).inertia)

    grad = np.asarray(jax.grad(f)(jnp.asarray(half)))
    step = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = step
        fd = (float(f(jnp.asarray(half + e))) - float(f(jnp.asarray(half - e)))) / (2 * step)
        np.testing.assert_allclose(
            grad[k], fd, rtol=1e-8
        )  # f is quadratic: FD exact up to round-off


def test_hollow_sphere_gradient_at_zero_thickness():
    # d/dt [2/5 m (r^5 - s^5)/(r^3 - s^3)] at s = r - t, t = 0 is -2/3 m r.
    m, r = 1.4, 0.6
    grad = jax.grad(lambda t: inertia.hollow_sphere(m, r, t).inertia[0, 0])(0.0)
    np.testing.assert_allclose(float(grad), -2.0 / 3.0 * m * r, rtol=1e-12)
    fd = (
        float(inertia.hollow_sphere(m, r, 2e-6).inertia[0, 0])
        - float(inertia.hollow_sphere(m, r, 0.0).inertia[0, 0])
    ) / 2e-6
    np.testing.assert_allclose(float(grad), fd, rtol=1e-5)  # one-sided FD: O(step) error


def test_density_gradient_through_mass_properties():
    shape = shapes.Cylinder(0.2, 0.5)
    grad = jax.grad(lambda rho: inertia.mass_properties(shape, density=rho).inertia[2, 2])(1000.0)
    np.testing.assert_allclose(float(grad), 0.5 * inertia.volume(shape) * 0.2**2, rtol=1e-14)


def test_principal_frame_round_trip():
    """A composed, non-diagonal part re-expressed in its principal frame, and back."""
    rod = inertia.cylinder(2.0, 0.1, 0.5)
    tilted = inertia.box(1.0, jnp.array([0.3, 0.1, 0.2])).transformed(
        jnp.array([0.2, -0.1, 0.4]), spatial.quat_from_axis_angle(jnp.array([1.0, 1.0, 0.0]), 0.7))
    part = inertia.compose([rod, tilted])
    principal, orientation = part.principal()
    assert float(jnp.max(jnp.abs(principal.inertia - jnp.diag(jnp.diagonal(principal.inertia))))) == 0.0
    assert bool(jnp.all(jnp.diff(jnp.diagonal(principal.inertia)) >= 0))
    back = principal.transformed(part.com, orientation)
    np.testing.assert_allclose(back.inertia, part.inertia, atol=1e-12)
    np.testing.assert_allclose(back.com, part.com, atol=1e-15)


@pytest.mark.parametrize("dtype, tolerance", [(jnp.float64, 1e-13), (jnp.float32, 5e-6)])
def test_principal_axes_batched_jacobi_matches_numpy(dtype, tolerance):
    """The element-wise Jacobi eigensolver behind principal_axes, vmapped and jitted.

    Random symmetric matrices plus the degenerate and ill-scaled ones (cube, cylinder,
    thin rod, zero), and some of each at 1e-30 to 1e30 kg m^2. Tolerances: measured 3.6e-15
    (float64) and 1.2e-6 (float32) relative to the largest entry; float32 under jit once
    failed here (tau^2 overflow), and at 1e-20 or 1e20 (a 10 um steel box, a 2 km rock) its
    moments were 10-36% off (squares under- or overflowing in the rotations).
    """
    rng = np.random.default_rng(0)
    matrices = rng.normal(size=(2000, 3, 3))
    matrices = matrices + np.swapaxes(matrices, 1, 2)
    turn = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    special = [np.diag([1.0, 1.0, 2.0]), np.eye(3), np.diag([3.0, 2.0, 1.0]), np.diag([1e-4, 1.0, 1.0 + 5e-5]),
               np.zeros((3, 3))]
    special += [turn @ m @ turn.T for m in special]
    matrices = np.concatenate([matrices, np.stack(special)])
    matrices = np.concatenate([matrices] + [size * matrices[-60:] for size in (1e-30, 1e-20, 1e20, 1e30)])
    moments, axes = jax.jit(jax.vmap(inertia.principal_axes))(jnp.asarray(matrices, dtype=dtype))
    assert moments.dtype == dtype
    moments, axes = np.asarray(moments, dtype=float), np.asarray(axes, dtype=float)
    scale = np.maximum(np.abs(matrices).max(axis=(1, 2)), 1e-300)[:, None]
    np.testing.assert_array_less(np.abs(moments - np.linalg.eigvalsh(matrices)) / scale, tolerance)
    rebuilt = np.einsum("nij,nj,nkj->nik", axes, moments, axes)
    np.testing.assert_array_less(np.abs(rebuilt - matrices).max(axis=2) / scale, tolerance)
    np.testing.assert_allclose(np.linalg.det(axes), 1.0, atol=tolerance)  # rotations
    assert np.all(np.diff(moments, axis=1) >= -tolerance * scale)  # ascending


def test_the_primitives_refuse_impossible_sizes_and_masses():
    """The shape classes check their sizes, but the functions behind them had taken a wall
    thicker than the radius, a negative one, negative sizes or masses, and a composition
    of total mass 0 (com [inf, nan, nan]) without a word; mass_properties refused mass=-1.0
    but not mass=[-1.0]. Traced values are not checked (they pass under grad and vmap)."""
    cases = [
        (lambda: inertia.hollow_sphere(1.0, 1.0, 1.5), "thickness 1.5 must be less than the radius"),
        (lambda: inertia.hollow_sphere(1.0, 1.0, -0.5), "thickness must be finite and >= 0"),
        (lambda: inertia.cone(1.0, -1.0, 2.0), "cone: radius must be finite and > 0"),
        (lambda: inertia.sphere(-1.0, 1.0), "sphere: mass must be finite and > 0"),
        (lambda: inertia.box(1.0, (0.1, 0.0, 0.1)), "box: half_extents must be finite and > 0"),
        (lambda: inertia.capsule(1.0, 0.1, np.nan), "capsule: half_length must be finite and >= 0"),
        (lambda: inertia.cylinder(1.0, jnp.array([0.1, -0.1]), 0.2), "cylinder: radius"),
        (lambda: inertia.compose([inertia.sphere(1.0, 1.0), inertia.MassProperties(
            jnp.asarray(-1.0), jnp.asarray([1.0, 0.0, 0.0]), jnp.eye(3))]), "total mass must be finite and > 0"),
        (lambda: inertia.mass_properties(shapes.Sphere(0.1), mass=[-1.0]), "mass must be positive and finite"),
    ]
    for build, message in cases:
        with pytest.raises(ValueError, match=message):
            build()
    # The limits that are bodies: a thin shell, a capsule that is a sphere, a hole cut out.
    np.testing.assert_allclose(inertia.hollow_sphere(1.0, 1.0, 0.0).inertia[0, 0], 2.0 / 3.0, rtol=1e-6)
    np.testing.assert_allclose(inertia.capsule(1.0, 0.1, 0.0).inertia, inertia.sphere(1.0, 0.1).inertia, rtol=1e-6)
    core = inertia.sphere(1.0, 1.0)
    hole = inertia.compose([inertia.sphere(8.0, 2.0), inertia.MassProperties(-core.mass, core.com, -core.inertia)])
    np.testing.assert_allclose(hole.mass, 7.0)
    np.testing.assert_allclose(hole.inertia[0, 0], 0.4 * (8.0 * 4.0 - 1.0), rtol=1e-6)  # a thick shell
    # Traced sizes and masses pass the checks.
    np.testing.assert_allclose(jax.grad(lambda r: inertia.sphere(2.0, r).inertia[0, 0])(1.0), 1.6, rtol=1e-6)
    assert jax.vmap(lambda r: inertia.cylinder(1.0, r, 1.0).inertia[2, 2])(jnp.array([1.0, 2.0])).shape == (2,)


def test_mesh_parts_must_nest_as_one_solid():
    """A cavity wound outward (the inner shell of a hollow body wound like an outer one) had
    added its volume instead of removing it, and a cavity inside a cavity removed material
    twice, both silently (stop 96's review): a 2 m cube with a 1 m cavity came out 9 and
    6.875 m^3 instead of 7. Both are refused now; an island inside a cavity, two cavities
    side by side and separate solids stay valid."""
    cube, faces = _box_mesh(np.array([0.5, 0.5, 0.5]), np.eye(3), np.zeros(3))
    n = len(cube)

    def mesh(*parts):  # (scale, offset, inward) per part
        vertices = np.vstack([s * cube + np.asarray(o, float) for s, o, _ in parts])
        tris = np.vstack([(faces[:, ::-1] if inward else faces) + k * n for k, (_, _, inward) in enumerate(parts)])
        return vertices, tris

    hollow = mesh((2, 0, False), (1, 0, True))
    assert float(inertia.volume(shapes.Mesh(*hollow))) == pytest.approx(7.0)
    # The hollow cube's inertia is the solid one's less the cavity's.
    solid, cavity = inertia.box(8.0, jnp.ones(3)), inertia.box(1.0, jnp.full(3, 0.5))
    expected = np.asarray(solid.inertia) - np.asarray(cavity.inertia)
    np.testing.assert_allclose(np.asarray(inertia.from_mesh(*hollow, density=1.0).inertia), expected, rtol=1e-12)
    outward_cavity = mesh((2, 0, False), (1, 0, False))
    for build in (lambda: shapes.Mesh(*outward_cavity), lambda: inertia.from_mesh(*outward_cavity, density=1.0)):
        with pytest.raises(ValueError, match=r"\(12 faces, volume 1 m\^3\) is wound outward but lies inside"):
            build()
    with pytest.raises(ValueError, match="is inside out"):
        shapes.Mesh(*mesh((4, 0, False), (2, 0, True), (1, 0, True)))  # a cavity inside a cavity
    with pytest.raises(ValueError, match="wound outward but lies inside"):
        shapes.Mesh(*mesh((2, 0, False), (2, (0.5, 0.5, 0.5), False)))  # two solids overlapping
    for parts, volume in ((((4, 0, False), (2, 0, True), (1, 0, False)), 64 - 8 + 1),  # an island in a cavity
                          (((4, 0, False), (1, (-1, 0, 0), True), (1, (1, 0, 0), True)), 64 - 2),
                          (((1, 0, False), (1, (3, 0, 0), False)), 2),
                          (((1, 0, False), (0.5, (0.75, 0, 0), False)), 1.125)):  # touching face to face
        assert float(inertia.volume(shapes.Mesh(*mesh(*parts)))) == pytest.approx(volume, rel=1e-12)


def test_small_float32_meshes_far_from_the_origin_are_not_called_flat():
    """The flat-part test bounded each part's rounding by products of vertex distances times
    64, from the whole mesh's vertex mean: float32 cubes of 3 cm and less 1000 m from the
    origin were refused as enclosing no volume (their rounding is about 1% of it), and so
    was a 2 cm cube 10 km from a 1 m cube in a float64 mesh (stop 96's review)."""
    for side in (0.03, 0.01, 0.005):
        vertices, faces = _box_mesh(np.full(3, side / 2), np.eye(3), np.full(3, 1e3))
        mass = inertia.from_mesh(vertices.astype(np.float32), faces, density=1.0).mass
        assert float(mass) == pytest.approx(side**3, rel=0.05)
    big, faces = _box_mesh(np.full(3, 0.5), np.eye(3), np.zeros(3))
    small, _ = _box_mesh(np.full(3, 0.01), np.eye(3), np.array([1e4, 0.0, 0.0]))
    both = inertia.from_mesh(np.vstack([big, small]), np.vstack([faces, faces + len(big)]), density=1.0)
    assert float(both.mass) == pytest.approx(1.0 + 0.02**3, rel=1e-9)


def test_non_finite_positions_and_parts_are_refused():
    """from_point_masses checked only the masses (a NaN position gave a NaN inertia, an
    infinite one a com of [inf, 0, 0]), and compose only the total mass."""
    for bad in (np.nan, np.inf):
        positions = np.eye(3).copy()
        positions[1, 2] = bad
        with pytest.raises(ValueError, match=r"positions must be finite \(m\); rows \[1\] are not"):
            inertia.from_point_masses(np.ones(3), positions)
    part = inertia.box(1.0, jnp.full(3, 0.5))
    for broken in (MassProperties_with(part, com=jnp.array([0.0, jnp.nan, 0.0])),
                   MassProperties_with(part, inertia=part.inertia.at[0, 0].set(jnp.inf))):
        with pytest.raises(ValueError, match=r"compose: every part's (com|inertia) must be finite; parts \[1\]"):
            inertia.compose([part, broken])


def MassProperties_with(part, **changes):  # noqa: N802
    fields = {"mass": part.mass, "com": part.com, "inertia": part.inertia, **changes}
    return inertia.MassProperties(fields["mass"], fields["com"], fields["inertia"])
