"""rb.viz: every drawn vertex on its shape's surface, at the body's pose; animations of a rollout."""

import gc

import matplotlib

matplotlib.use("Agg")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

import jaxrb as rb  # noqa: E402


def _radial(p):
    return np.hypot(p[:, 0], p[:, 1])


def _capsule_distance(p, radius, h):
    axis = np.stack([np.zeros(len(p)), np.zeros(len(p)), np.clip(p[:, 2], -h, h)], -1)
    return np.linalg.norm(p - axis, axis=-1) - radius


# Each shape with an independent signed distance-like function, zero exactly on its
# surface (negative inside), and its bounding box (lower, upper) in its own frame.
SURFACES = {
    "sphere": (rb.Sphere(0.3), lambda p: np.linalg.norm(p, axis=-1) - 0.3, (-0.3,) * 3, (0.3,) * 3),
    "hollow sphere": (rb.HollowSphere(0.2, 0.05), lambda p: np.linalg.norm(p, axis=-1) - 0.2, (-0.2,) * 3,
                      (0.2,) * 3),
    "ellipsoid": (rb.Ellipsoid((0.1, 0.2, 0.3)),
                  lambda p: np.linalg.norm(p / np.array([0.1, 0.2, 0.3]), axis=-1) - 1.0,
                  (-0.1, -0.2, -0.3), (0.1, 0.2, 0.3)),
    "box": (rb.Box((0.1, 0.2, 0.3)), lambda p: np.max(np.abs(p) / np.array([0.1, 0.2, 0.3]), axis=-1) - 1.0,
            (-0.1, -0.2, -0.3), (0.1, 0.2, 0.3)),
    "capsule": (rb.Capsule(0.1, 0.25), lambda p: _capsule_distance(p, 0.1, 0.25), (-0.1, -0.1, -0.35),
                (0.1, 0.1, 0.35)),
    "cylinder": (rb.Cylinder(0.15, 0.05), lambda p: np.maximum(_radial(p) - 0.15, np.abs(p[:, 2]) - 0.05),
                 (-0.15, -0.15, -0.05), (0.15, 0.15, 0.05)),
    "elliptical cylinder": (rb.EllipticalCylinder((0.2, 0.1), 0.3),
                            lambda p: np.maximum(np.hypot(p[:, 0] / 0.2, p[:, 1] / 0.1) - 1.0,
                                                 np.abs(p[:, 2]) / 0.3 - 1.0),
                            (-0.2, -0.1, -0.3), (0.2, 0.1, 0.3)),
    # Base radius 0.2 at z = -0.4/4, apex at z = 3 * 0.4 / 4.
    "cone": (rb.Cone(0.2, 0.4), lambda p: np.maximum(-(p[:, 2] + 0.1), _radial(p) - 0.2 * (0.3 - p[:, 2]) / 0.4),
             (-0.2, -0.2, -0.1), (0.2, 0.2, 0.3)),
    "plate": (rb.Plate((0.3, 0.1)), lambda p: np.abs(p[:, 2]) + np.abs(np.max(np.abs(p[:, :2]) / [0.3, 0.1], -1) - 1),
              (-0.3, -0.1, 0.0), (0.3, 0.1, 0.0)),
    "disk": (rb.Disk(0.25), lambda p: np.abs(p[:, 2]) + np.abs(_radial(p) - 0.25), (-0.25, -0.25, 0.0),
             (0.25, 0.25, 0.0)),
}


@pytest.mark.parametrize("name", list(SURFACES))
def test_every_drawn_vertex_lies_on_the_shapes_surface_and_they_span_it(name):
    shape, distance, lower, upper = SURFACES[name]
    for resolution in (16, 7):
        points = np.concatenate(rb.viz.shape_surface(shape, resolution))
        assert np.max(np.abs(distance(points))) < 1e-12, (name, resolution)
    # At 16 points around (angles of 90 degrees among them) the vertices reach the shape's
    # extent along every axis: a surface drawn only in part fails here.
    points = np.concatenate(rb.viz.shape_surface(shape, 16))
    np.testing.assert_allclose(points.min(0), lower, atol=1e-12)
    np.testing.assert_allclose(points.max(0), upper, atol=1e-12)


def test_a_mesh_is_drawn_as_its_own_triangles():
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    drawn = rb.viz.shape_surface(rb.Mesh(vertices, faces))
    np.testing.assert_array_equal(np.stack(drawn), vertices[faces])


def _pose_scene():
    # A tetrahedron mesh's centre of mass is off its origin: its shape offset is not zero.
    vertices = np.array([[0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.2]])
    faces = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=2.0),
                      rb.Body("mesh", shape=rb.Mesh(vertices, faces), density=500.0),
                      rb.Body("point", mass=1.0, inertia=(1.0, 1.0, 1.0))])
    return scene, vertices, faces


def test_bodies_are_drawn_at_their_pose_with_their_shape_offset():
    scene, vertices, faces = _pose_scene()
    rng = np.random.default_rng(3)
    quats = rng.normal(size=(3, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    positions = rng.normal(size=(3, 3))
    params = scene.params(dtype=jnp.float64)
    state = scene.state(params, position=dict(zip(scene.body_names, positions, strict=True)),
                        orientation=dict(zip(scene.body_names, quats, strict=True)))
    drawing = rb.viz.draw(scene, state)
    assert set(drawing.surfaces) == {"box", "mesh"}  # the shapeless body has nothing to draw
    # The reference rotation: SciPy's, from the quaternion in its scalar-last order.
    rot = Rotation.from_quat(quats[:, [1, 2, 3, 0]]).as_matrix()
    corners = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.2, 0.2) for z in (-0.3, 0.3)])
    drawn_box = np.unique(np.round(np.concatenate(drawing.surfaces["box"]), 12), axis=0)
    expected_box = np.unique(np.round(positions[0] + corners @ rot[0].T, 12), axis=0)
    np.testing.assert_allclose(drawn_box, expected_box, atol=1e-12)
    # The mesh's vertices sit at x + A (p - com): its centre of mass at the body's position.
    com = np.asarray(rb.mass_properties(rb.Mesh(vertices, faces), density=500.0).com)
    expected_mesh = positions[1] + (vertices[np.asarray(faces)] - com) @ rot[1].T
    np.testing.assert_allclose(np.stack(drawing.surfaces["mesh"]), expected_mesh, atol=1e-12)
    plt.close("all")


def test_a_carried_rotation_matrix_is_what_is_drawn():
    # ExplicitEuler (seed 000's algorithm) carries A in State.rotation; the drawing follows
    # rb.state.rotation_matrix, which reads it, as the step's collisions would.
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=2.0)])
    params = scene.params(dtype=jnp.float64)
    state = rb.make_step(scene, rb.integrators.ExplicitEuler(), 1e-3).prepare(scene.state(params))
    assert state.rotation is not None
    turned = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    drawing = rb.viz.draw(scene, state.replace(rotation=jnp.asarray(turned)[None]))
    expected = np.stack(rb.viz.shape_surface(rb.Box((0.1, 0.2, 0.3)))) @ turned.T
    np.testing.assert_allclose(np.stack(drawing.surfaces["box"]), expected, atol=1e-12)
    plt.close("all")


def _tumbling_box(steps=40):
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=2.0),
                      rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(offset=-1.0))
    params = scene.params(dtype=jnp.float64)
    state = scene.state(params, position={"ball": (1.0, 0.0, 0.5)}, velocity={"ball": (0.0, 2.0, 3.0)},
                        angular_velocity={"box": (0.1, 5.0, 0.1)})
    step = rb.make_step(scene, rb.integrators.SemiImplicitEuler(), 1e-2)
    return scene, state, rb.rollout(step, params, state, steps)[1]


def test_an_animation_shows_every_kth_state_inside_its_limits():
    scene, _, traj = _tumbling_box()
    animation = rb.viz.animate(scene, traj, every=3)
    shown = np.arange(0, 40, 3)
    assert len(list(animation.new_frame_seq())) == len(shown)
    assert animation._interval == pytest.approx(30.0)  # 3 steps of 10 ms: real time
    animation.to_jshtml()  # runs every frame, in order
    drawing = animation.drawing
    last = shown[-1]
    rot = Rotation.from_quat(np.asarray(traj.orientation[last])[:, [1, 2, 3, 0]]).as_matrix()
    box = np.stack(rb.viz.shape_surface(rb.Box((0.1, 0.2, 0.3)))) @ rot[0].T + np.asarray(traj.position[last, 0])
    np.testing.assert_allclose(np.stack(drawing.surfaces["box"]), box, atol=1e-12)
    assert drawing.ax.get_title() == f"t = {float(traj.time[last]):.3f} s"
    # The limits hold every shown frame's bodies (the ball flies 1.2 m), with equal scales.
    limits = np.array([drawing.ax.get_xlim(), drawing.ax.get_ylim(), drawing.ax.get_zlim()])
    for k in shown:
        for name, body in (("box", 0), ("ball", 1)):
            centre = np.asarray(traj.position[k, body])
            assert np.all(limits[:, 0] < centre) and np.all(centre < limits[:, 1]), (k, name)
    widths = limits[:, 1] - limits[:, 0]
    np.testing.assert_allclose(widths, widths[0], rtol=1e-12)
    plt.close("all")


def test_the_ground_is_in_view_and_behind_the_bodies_on_it():
    # A ball 2 m up: the limits had held the ball alone, and the ground's square was off the
    # axes. A box resting on the ground: the translucent square reaching past it was drawn
    # over it (matplotlib orders collections by their nearest vertex).
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0), rb.Body("box", shape=rb.Box((0.1,) * 3),
                                                                                  mass=1.0),
                      rb.Body("point", mass=1.0, inertia=(1.0, 1.0, 1.0))],
                     ground=rb.Plane(), walls={"wall": rb.Plane((-1.0, 0.0, 0.0), -1.5)})
    params = scene.params(dtype=jnp.float64)
    state = scene.state(params, position={"ball": (0.0, 0.0, 2.0), "box": (0.5, 0.0, 0.1), "point": (0.2, 0.3, 0.4)})
    drawing = rb.viz.draw(scene, state)
    limits = np.array([drawing.ax.get_xlim(), drawing.ax.get_ylim(), drawing.ax.get_zlim()])
    for name, square in drawing.planes.items():
        plane = scene.planes[name]
        np.testing.assert_allclose(square @ np.asarray(plane.normal), plane.offset, atol=1e-12)
        inside = (limits[:, 0] - 1e-9 <= square) & (square <= limits[:, 1] + 1e-9)
        assert inside.all(axis=1).sum() >= 2, name  # the square reaches into the view from a side at least
    assert limits[2, 0] <= 0.0 and limits[0, 1] >= 1.5  # the ground's and the wall's nearest points
    drawing.ax.figure.canvas.draw()
    planes = [c for c in drawing.ax.collections if c not in drawing.collections.values()]
    assert len(planes) == 2
    assert max(c.get_zorder() for c in planes) < min(c.get_zorder() for c in drawing.collections.values())
    # The shapeless body is a dot at its centre of mass.
    (dot,) = drawing.ax.get_lines()
    np.testing.assert_allclose(np.ravel(dot.get_data_3d()), [0.2, 0.3, 0.4])
    plt.close("all")


@pytest.mark.filterwarnings("ignore:Animation was deleted without rendering")  # frames drawn one by one here
def test_colours_titles_and_frames_on_request():
    scene, state, traj = _tumbling_box(12)
    drawing = rb.viz.draw(scene, state, colours={"ball": "red"})
    assert matplotlib.colors.to_hex(drawing.collections["ball"].get_facecolor()[0], keep_alpha=False) == "#ff0000"
    drawing = rb.viz.draw(scene, state, colours="black")
    assert all(matplotlib.colors.to_hex(c.get_facecolor()[0], keep_alpha=False) == "#000000"
               for c in drawing.collections.values())
    # Frames 0.2 ms apart: every title differs (three decimals had shown 0.000 s twice).
    fine = traj.replace(time=traj.time * 0.02)
    animation = rb.viz.animate(scene, fine)
    titles = []
    for k in range(12):
        animation.show_frame(k)
        titles.append(animation.drawing.ax.get_title())
        np.testing.assert_allclose(np.stack(animation.drawing.surfaces["ball"]).mean((0, 1)),
                                   np.asarray(traj.position[k, 1]), atol=1e-12)  # frame k shows state k
    assert len(set(titles)) == 12, titles
    plt.close("all")
    del animation
    gc.collect()  # its "deleted without rendering" warning here, inside this test's filter


def test_every_shape_renders():
    shapes = [s for s, *_ in SURFACES.values()]
    bodies = [rb.Body(f"b{k}", shape=s, mass=1.0, inertia=(1.0, 1.0, 1.0)) for k, s in enumerate(shapes)]
    scene = rb.Scene(bodies, ground=rb.Plane(), walls={"wall": rb.Plane((-1.0, 0.0, 0.0), -3.0)})
    params = scene.params(dtype=jnp.float64)
    state = scene.state(params, position={f"b{k}": (0.5 * k, 0.0, 0.5) for k in range(len(shapes))})
    drawing = rb.viz.draw(scene, state, resolution=8)
    drawing.ax.figure.canvas.draw()
    assert len(drawing.ax.collections) == len(shapes) + 2  # and the two planes
    plt.close("all")


def test_bad_input_is_refused_with_what_to_do():
    scene, state, traj = _tumbling_box(5)
    with pytest.raises(ValueError, match="expected an rb.State"):
        rb.viz.draw(scene, {"position": state.position})
    with pytest.raises(ValueError, match="use rb.viz.animate"):
        rb.viz.draw(scene, traj)
    with pytest.raises(ValueError, match="got one state: use rb.viz.draw"):
        rb.viz.animate(scene, state)
    ensemble = traj.replace(position=jnp.stack([traj.position] * 2))
    with pytest.raises(ValueError, match="ensemble of trajectories; draw one member"):
        rb.viz.animate(scene, ensemble)
    other = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=2.0)])
    with pytest.raises(ValueError, match="scene of 1 bodies needs"):
        rb.viz.draw(other, state)
    for every in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="every must be a positive int"):
            rb.viz.animate(scene, traj, every=every)
    for resolution in (2, 8.0):
        with pytest.raises(ValueError, match="resolution must be an int >= 3"):
            rb.viz.draw(scene, state, resolution=resolution)
    with pytest.raises(ValueError, match="3D matplotlib Axes"):
        rb.viz.draw(scene, state, ax=plt.figure().add_subplot())
    with pytest.raises(ValueError, match="one per body with a shape"):
        rb.viz.draw(scene, state, colours=["C0"])
    with pytest.raises(ValueError, match=r"no body with a shape is named \['bal'\]"):
        rb.viz.draw(scene, state, colours={"bal": "red"})
    for interval in (0, -5.0, float("nan"), "fast"):
        with pytest.raises(ValueError, match="interval_ms must be a positive number"):
            rb.viz.animate(scene, traj, interval_ms=interval)
    with pytest.raises(ValueError, match="the trajectory has no states"):
        rb.viz.animate(scene, jax.tree.map(lambda x: x[:0], traj))
    with pytest.raises(ValueError, match=r"non-finite .*\['ball'\]"):
        rb.viz.draw(scene, state.replace(position=state.position.at[1, 0].set(jnp.nan)))
    with pytest.raises(ValueError, match="has no surface to draw by itself"):
        rb.viz.shape_surface(rb.Plane())
    with pytest.raises(ValueError, match="one state"):
        rb.viz.draw(scene, state).update(traj)
    plt.close("all")
