"""Pictures of a scene with matplotlib: one state drawn in 3D, a trajectory animated.

Each body is drawn as its shape's surface (polygons), where the collision code sees it:
a point ``p`` of the shape's frame is at ``x + A (offset + p)`` in the world, with ``x``
the centre of mass, ``A`` the body-to-world rotation (:func:`jaxrb.state.rotation_matrix`:
the quaternion's, or the matrix that :class:`jaxrb.integrators.ExplicitEuler` carries: the
collisions read the quaternion, which agrees with that matrix unless Gram-Schmidt is off,
``ExplicitEuler(reorthonormalize=False)``, where the drawing shows the matrix's drift) and
``offset`` the shape's origin in the body frame (``Body.shape_offset``, non-zero for a mesh
whose centre of mass is off its origin). Static planes are drawn as translucent squares
under the bodies. Everything here runs in NumPy on concrete arrays, outside ``jit``.

In a notebook::

    from IPython.display import HTML
    final, traj = rb.rollout(step, params, state, 2000, save_every=40)
    HTML(rb.viz.animate(scene, traj).to_jshtml())
"""

from __future__ import annotations

import math

import numpy as np

from . import shapes as _shapes
from .state import State, rotation_matrix

#: Colours of the bodies, in turn (matplotlib's default cycle).
_COLOURS = ("C0", "C1", "C2", "C3", "C4", "C5", "C6", "C7", "C8", "C9")


def _ring(radius_x, radius_y, z, n):
    """``(n, 3)``: ``n`` points of an ellipse at height ``z``."""
    angle = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.stack([radius_x * np.cos(angle), radius_y * np.sin(angle), np.full(n, float(z))], -1)


def _band(lower, upper):
    """Quads joining two rings of the same length, ``(n, 4, 3)``."""
    following = np.roll(np.arange(len(lower)), -1)
    return np.stack([lower, lower[following], upper[following], upper], 1)


def _prism(semi_x, semi_y, bottom, top, n, *, apex=False):
    """The sides and caps of an elliptical cylinder (or, with ``apex``, a cone whose
    apex is at ``top``): a list of polygons."""
    lower = _ring(semi_x, semi_y, bottom, n)
    upper = _ring(0.0, 0.0, top, n) if apex else _ring(semi_x, semi_y, top, n)
    polygons = list(_band(lower, upper)) + [lower[::-1]]
    return polygons if apex else polygons + [upper]


def _sphere_quads(semi_axes, n, *, z_shift=(0.0, 0.0)):
    """Latitude-longitude quads of an ellipsoid, with the equator among the rings, so that
    each band lies in one hemisphere; with ``z_shift = (s_low, s_high)`` the lower and
    upper hemispheres are moved along z by those (a capsule's caps)."""
    quarter = max(1, n // 4)
    polar = np.concatenate([np.linspace(0.0, np.pi / 2, quarter + 1), np.linspace(np.pi / 2, np.pi, quarter + 1)[1:]])
    rings = [_ring(semi_axes[0] * np.sin(a), semi_axes[1] * np.sin(a), semi_axes[2] * np.cos(a), n) for a in polar]
    quads = []
    for k, (upper, lower) in enumerate(zip(rings[:-1], rings[1:], strict=True)):
        shift = np.array([0.0, 0.0, z_shift[1] if k < quarter else z_shift[0]])
        quads.extend(_band(lower + shift, upper + shift))
    return quads


def shape_surface(shape: _shapes.Shape, resolution: int = 16) -> list[np.ndarray]:
    """The surface of ``shape`` as polygons in its own frame (m): a list of ``(k, 3)``
    vertex arrays (quads, triangles, or a cap's ``resolution``-gon).

    Curved surfaces are sampled at ``resolution`` points around (and half that from pole
    to pole); every vertex lies on the shape's surface. A :class:`jaxrb.Rod` has no
    thickness and is drawn as a thin cylinder of radius ``half_length / 50``, for
    visibility only. A :class:`jaxrb.Plane` has no finite surface: see :func:`draw`.
    """
    if not isinstance(resolution, int | np.integer) or isinstance(resolution, bool) or resolution < 3:
        raise ValueError(f"resolution must be an int >= 3 (points around a curved surface), got {resolution!r}.")
    n = int(resolution)
    if isinstance(shape, _shapes.Box):
        a, b, c = shape.half_extents
        corners = np.array([[x, y, z] for x in (-a, a) for y in (-b, b) for z in (-c, c)])
        faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        return [corners[list(f)] for f in faces]
    if isinstance(shape, _shapes.Sphere | _shapes.HollowSphere):
        return _sphere_quads((shape.radius,) * 3, n)
    if isinstance(shape, _shapes.Ellipsoid):
        return _sphere_quads(shape.semi_axes, n)
    if isinstance(shape, _shapes.Capsule):
        h = shape.half_length
        caps = _sphere_quads((shape.radius,) * 3, n, z_shift=(-h, h))
        return caps + list(_band(_ring(shape.radius, shape.radius, -h, n), _ring(shape.radius, shape.radius, h, n)))
    if isinstance(shape, _shapes.Cylinder):
        return _prism(shape.radius, shape.radius, -shape.half_length, shape.half_length, n)
    if isinstance(shape, _shapes.EllipticalCylinder):
        return _prism(*shape.semi_axes, -shape.half_length, shape.half_length, n)
    if isinstance(shape, _shapes.Cone):
        return _prism(shape.radius, shape.radius, -shape.height / 4, 3 * shape.height / 4, n, apex=True)
    if isinstance(shape, _shapes.Rod):
        width = shape.half_length / 50
        return _prism(width, width, -shape.half_length, shape.half_length, n)
    if isinstance(shape, _shapes.Plate):
        a, b = shape.half_extents
        return [np.array([[-a, -b, 0.0], [a, -b, 0.0], [a, b, 0.0], [-a, b, 0.0]])]
    if isinstance(shape, _shapes.Disk):
        return [_ring(shape.radius, shape.radius, 0.0, n)]
    if isinstance(shape, _shapes.Mesh):
        vertices, faces = np.asarray(shape.vertices, float), np.asarray(shape.faces, int)
        return list(vertices[faces])
    if isinstance(shape, _shapes.Plane):
        raise ValueError("A Plane is unbounded and has no surface to draw by itself: rb.viz.draw(scene, state) "
                         "draws the scene's planes as squares under its bodies.")
    raise ValueError(f"No surface for shape {type(shape).__name__}: draw() can show rb.Box, rb.Sphere, "
                     "rb.HollowSphere, rb.Ellipsoid, rb.Capsule, rb.Cylinder, rb.EllipticalCylinder, rb.Cone, "
                     "rb.Rod, rb.Plate, rb.Disk and rb.Mesh.")


def _frames(scene, states, where: str):
    """Centres ``(T, N, 3)`` and rotations ``(T, N, 3, 3)`` of ``states`` as NumPy arrays,
    with ``T = 1`` for one state, and the times ``(T,)``; or a ``ValueError``."""
    if not isinstance(states, State):
        raise ValueError(f"{where}: expected an rb.State (scene.state(...), or the trajectory rb.rollout returns), "
                         f"got {type(states).__name__}.")
    n = scene.num_bodies
    shape = np.shape(states.position)
    if len(shape) < 2 or shape[-2:] != (n, 3):
        raise ValueError(f"{where}: State.position has shape {shape}; this scene of {n} bodies needs ({n}, 3) for "
                         f"one state, or (T, {n}, 3) for a trajectory.")
    if len(shape) > 3:
        raise ValueError(f"{where}: State.position has shape {shape}, an ensemble of trajectories; draw one member: "
                         f"jax.tree.map(lambda x: x[i], traj).")
    centres = np.asarray(states.position, float).reshape(-1, n, 3)
    rotations = np.asarray(rotation_matrix(states), float).reshape(-1, n, 3, 3)
    times = np.asarray(states.time, float).reshape(-1)
    if not (np.all(np.isfinite(centres)) and np.all(np.isfinite(rotations))):
        bad = sorted({scene.body_names[i] for i in np.nonzero(~np.isfinite(centres).all(-1))[1]}
                     | {scene.body_names[i] for i in np.nonzero(~np.isfinite(rotations).all((-1, -2)))[1]})
        raise ValueError(f"{where}: the state has non-finite positions or orientations (bodies {bad}): "
                         "nothing to draw there. Find where the simulation diverged first.")
    return centres, rotations, times


class _Bodies:
    """Every body's surface in its shape frame, moved to world poses in one product."""

    def __init__(self, scene, resolution):
        self.names = [b.name for b in scene.bodies if b.shape is not None]
        self.polygons = []  # per body: list of (k, 3) in the body frame
        for body in scene.bodies:
            if body.shape is not None:
                offset = np.asarray(body.shape_offset, float)
                self.polygons.append([p + offset for p in shape_surface(body.shape, resolution)])
        self.index = [scene.index(name) for name in self.names]

    def world(self, centre, rotation) -> dict[str, list[np.ndarray]]:
        """``{name: [(k, 3), ...]}`` in the world frame (m), for one state's ``(N, 3)``
        centres and ``(N, 3, 3)`` rotations."""
        return {name: [centre[i] + p @ rotation[i].T for p in polygons]
                for name, i, polygons in zip(self.names, self.index, self.polygons, strict=True)}


def _on_plane(plane, x):
    """The point of ``plane`` nearest to ``x`` (m)."""
    n = np.asarray(plane.normal, float)
    return x - (n @ x - plane.offset) * n


def _plane_square(plane, middle, half_width):
    """A square of the plane, centred at ``middle``'s projection on it."""
    n = np.asarray(plane.normal, float)
    centre = _on_plane(plane, middle)
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    return np.stack([centre + half_width * (su * u + sv * v) for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))])


def _extent(world_polygons, centres, planes):
    """The bounding box (lower, upper) of the drawn bodies over every frame, of the centres
    of mass (bodies without a shape), and of each plane's point nearest to them (a ground
    under a ball dropped from 2 m had been left out of the view)."""
    points = [centres.reshape(-1, 3)] + [p for frame in world_polygons for polygons in frame.values() for p in polygons]
    points = np.concatenate(points)
    middle = 0.5 * (points.min(0) + points.max(0))
    points = np.concatenate([points, *(_on_plane(plane, middle)[None] for plane in planes)])
    return points.min(0), points.max(0)


def _backdrop(polygons, **style):
    """A ``Poly3DCollection`` always drawn behind the others: matplotlib orders collections
    by their nearest vertex, and a translucent ground square reaching past the bodies on it
    was drawn over them (they looked sunk into it). Seen from under a plane's solid side the
    bodies are still drawn over it."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    class Backdrop(Poly3DCollection):
        def do_3d_projection(self):
            super().do_3d_projection()
            return np.inf

    return Backdrop(polygons, **style)


def _colour_list(colours, names):
    """One colour per body with a shape, from ``None``, one colour, a list, or ``{name: colour}``."""
    default = [_COLOURS[k % len(_COLOURS)] for k in range(len(names))]
    if colours is None:
        return default
    from matplotlib.colors import is_color_like

    if not isinstance(colours, dict | list) and is_color_like(colours):
        return [colours] * len(names)  # one colour for all: "red", "C3", (0.1, 0.2, 0.3)
    if isinstance(colours, dict):
        unknown = sorted(set(colours) - set(names))
        if unknown:
            raise ValueError(f"colours: no body with a shape is named {unknown}; the bodies drawn are {names}.")
        return [colours.get(name, d) for name, d in zip(names, default, strict=True)]
    colours = list(colours)
    if len(colours) != len(names):
        raise ValueError(f"colours: one per body with a shape ({len(names)}: {names}), a dict {{name: colour}}, or "
                         f"one colour for all; got {len(colours)}.")
    return colours


def _axes(ax):
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(subplot_kw={"projection": "3d"}, figsize=(6, 6))
    elif getattr(ax, "name", None) != "3d":
        raise ValueError("ax must be a 3D matplotlib Axes: fig.add_subplot(projection='3d') "
                         "(or leave ax out and one is made).")
    return ax


class Drawing:
    """What :func:`draw` put on an Axes: ``ax``, the bodies' ``Poly3DCollection`` by body
    name (``collections``), the world polygons last set (``surfaces``, m), the planes'
    squares by name (``planes``, ``(4, 3)`` m), and :meth:`update` to move the bodies to
    another state of the same scene."""

    def __init__(self, scene, ax, bodies: _Bodies, collections, planes, title: bool, points=None, decimals: int = 3):
        self.scene, self.ax, self._bodies, self.collections, self._title = scene, ax, bodies, collections, title
        self.planes, self._points, self._decimals = planes, points, decimals
        self.surfaces: dict[str, list[np.ndarray]] = {}

    def update(self, state: State) -> list:
        """Move every body to ``state`` (one state of this scene); returns the changed artists."""
        centres, rotations, times = _frames(self.scene, state, "Drawing.update")
        if centres.shape[0] != 1:
            raise ValueError("Drawing.update takes one state; for a trajectory use rb.viz.animate.")
        return self._show(centres[0], rotations[0], times[0])

    def _show(self, centre, rotation, time):
        self.surfaces = self._bodies.world(centre, rotation)
        for name, polygons in self.surfaces.items():
            self.collections[name].set_verts(polygons)
        changed = list(self.collections.values())
        if self._points is not None:
            shapeless = [i for i, b in enumerate(self.scene.bodies) if b.shape is None]
            self._points.set_data_3d(*centre[shapeless].T)
            changed.append(self._points)
        if self._title:
            self.ax.set_title(f"t = {time:.{self._decimals}f} s")
        return changed


def draw(scene, state: State, ax=None, *, resolution: int = 16, planes: bool = True, alpha: float = 0.9,
         colours=None, title: bool = True) -> Drawing:
    """Draw ``scene``'s bodies at ``state`` (one state) on a 3D matplotlib Axes.

    Args:
        scene: the :class:`jaxrb.Scene` the state belongs to.
        state: one :class:`jaxrb.State` (``position (N, 3)``); a body without a shape is not drawn.
        ax: a 3D Axes (``fig.add_subplot(projection="3d")``); ``None`` makes a new figure.
        resolution: points around curved surfaces (:func:`shape_surface`).
        planes: draw the ground and walls as translucent squares around the bodies.
        alpha: the bodies' opacity.
        colours: ``None`` (matplotlib's cycle), one colour for all, one per body with a
            shape, or ``{name: colour}`` (the others from the cycle).
        title: show the state's time (s) as the title.

    Returns:
        A :class:`Drawing` (its ``ax``, the bodies' collections, and ``update(state)``).
        The axes have equal scales in x, y and z (m), so that shapes are not distorted, and
        hold the bodies and each plane's point nearest to them. Bodies without a shape are
        drawn as black dots at their centres of mass. Set the view afterwards with
        ``drawing.ax.set_xlim(...)`` or ``drawing.ax.view_init(elev, azim)``.
    """
    centres, rotations, times = _frames(scene, state, "rb.viz.draw")
    if np.ndim(state.position) != 2:
        raise ValueError(f"rb.viz.draw takes one state, got a trajectory of {centres.shape[0]}: use rb.viz.animate, "
                         "or pick one: jax.tree.map(lambda x: x[k], traj).")
    bodies = _Bodies(scene, resolution)
    return _draw(scene, bodies, centres, rotations, times, [bodies.world(centres[0], rotations[0])], ax,
                 planes=planes, alpha=alpha, colours=colours, title=title)


def _draw(scene, bodies, centres, rotations, times, shown_polygons, ax, *, planes, alpha, colours, title,
          decimals=3) -> Drawing:
    """:func:`draw` at the first of ``centres``/``rotations`` (``(T, N, ...)``), with the
    axes' limits around ``shown_polygons`` (every frame's world polygons), ``centres`` and
    the planes."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    ax = _axes(ax)
    colours = _colour_list(colours, bodies.names)
    shown_planes = list(scene.planes.values()) if planes else []  # (in the order of scene.planes)
    lower, upper = _extent(shown_polygons, centres, shown_planes)
    middle, half = 0.5 * (lower + upper), 0.5 * float(np.max(upper - lower))
    # A floor for a view of one point: 1 mm beside shapes (a 1 mm body stays visible), 0.5 m
    # for point masses alone.
    half = max(half, 1e-3 if bodies.names else 0.5) * 1.15
    squares = {name: _plane_square(plane, middle, half) for name, plane in scene.planes.items() if planes}
    for square in squares.values():
        ax.add_collection3d(_backdrop([square], facecolor="0.6", edgecolor="0.4", alpha=0.25))
    points = None
    if any(b.shape is None for b in scene.bodies):
        (points,) = ax.plot([], [], [], "k.", markersize=8)
    collections = {}
    for name, colour in zip(bodies.names, colours, strict=True):
        collection = Poly3DCollection([], facecolor=colour, edgecolor="k", linewidth=0.2, alpha=alpha)
        ax.add_collection3d(collection)
        collections[name] = collection
    for set_limits, mid in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), middle, strict=True):
        set_limits(mid - half, mid + half)
    ax.set_box_aspect((1.0, 1.0, 1.0))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    drawing = Drawing(scene, ax, bodies, collections, squares, title, points, decimals)
    drawing._show(centres[0], rotations[0], times[0])
    return drawing


def animate(scene, trajectory: State, ax=None, *, every: int = 1, interval_ms: float | None = None,
            resolution: int = 12, planes: bool = True, alpha: float = 0.9, colours=None, title: bool = True):
    """Animate a trajectory: a ``matplotlib.animation.FuncAnimation``.

    Args:
        scene: the :class:`jaxrb.Scene`.
        trajectory: the stacked states ``rb.rollout`` returns (``position (T, N, 3)``).
        ax: a 3D Axes, or ``None`` for a new figure.
        every: show every ``every``-th state (a positive int).
        interval_ms: time between frames (ms, positive); ``None``: the trajectory's own
            time between shown states (real time), at least 20 ms.
        resolution, planes, alpha, colours, title: as in :func:`draw`; the title shows
            enough decimals to tell the frames' times apart.

    Returns:
        The animation, with its :class:`Drawing` as ``animation.drawing`` and
        ``animation.show_frame(k)`` to draw the k-th shown state (e.g. for a slider:
        ``ipywidgets.interact(animation.show_frame, k=(0, n - 1))``). The axes' limits cover
        every frame. In a notebook ``HTML(animation.to_jshtml())`` shows it
        (about 0.1 MB and 0.1 s a frame at the default size: matplotlib stops embedding at
        ``matplotlib.rcParams["animation.embed_limit"]``, 20 MB, so pick ``every`` for
        about 100-150 frames); ``animation.save("out.gif")`` writes it (with a matplotlib
        writer installed).
    """
    from matplotlib.animation import FuncAnimation

    if not isinstance(every, int | np.integer) or isinstance(every, bool) or every < 1:
        raise ValueError(f"every must be a positive int (show every k-th state), got {every!r}.")
    if interval_ms is not None and not (isinstance(interval_ms, int | float | np.integer | np.floating)
                                        and math.isfinite(interval_ms) and interval_ms > 0):
        raise ValueError(f"interval_ms must be a positive number of milliseconds (or None for real time), "
                         f"got {interval_ms!r}.")
    centres, rotations, times = _frames(scene, trajectory, "rb.viz.animate")
    if np.ndim(trajectory.position) != 3:
        raise ValueError("rb.viz.animate needs a trajectory (position (T, N, 3)), got one state: use rb.viz.draw.")
    if centres.shape[0] == 0:
        raise ValueError("rb.viz.animate: the trajectory has no states (position of shape "
                         f"{np.shape(trajectory.position)}).")
    shown = np.arange(0, centres.shape[0], every)
    centres, rotations, times = centres[shown], rotations[shown], times[shown]
    bodies = _Bodies(scene, resolution)
    everywhere = [bodies.world(c, r) for c, r in zip(centres, rotations, strict=True)]
    gap = float(np.median(np.diff(times))) if len(times) > 1 else 0.0
    # Decimals enough to tell the frames apart (3 had printed 0.2 ms steps as t = 0.001 s twice).
    decimals = max(3, math.ceil(-math.log10(gap)) + 1) if math.isfinite(gap) and gap > 0 else 3
    drawing = _draw(scene, bodies, centres, rotations, times, everywhere, ax, planes=planes, alpha=alpha,
                    colours=colours, title=title, decimals=min(decimals, 9))
    if interval_ms is None:
        interval_ms = max(20.0, 1e3 * gap) if math.isfinite(gap) else 20.0

    def frame(k):
        return drawing._show(centres[k], rotations[k], times[k])

    animation = FuncAnimation(drawing.ax.figure, frame, frames=len(times), interval=interval_ms, blit=False)
    animation.drawing = drawing
    animation.show_frame = frame
    return animation
