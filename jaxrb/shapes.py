"""Shapes: static, hashable geometry descriptions.

A shape is part of a scene's *static* structure: its sizes are Python floats, it is
hashable, and changing it recompiles. Everything a user may want to differentiate
(mass, inertia, ...) lives in :class:`jaxrb.Params` instead.

Frames. Every shape is described in its own frame, whose origin is the shape's centre
of mass (for a uniform density) and whose axes are the shape's symmetry axes. Axially
symmetric shapes (rod, disk, cylinder, capsule, cone) have their axis along **z**, as in
MuJoCo. Seed 001's inertia table puts the axis of the rod, cylinder and cone along x;
the moments are the same, permuted (see :mod:`jaxrb.inertia`). All sizes are in metres
and are *half* sizes (half extents, half lengths), as in MuJoCo.
"""

from __future__ import annotations

import dataclasses
import math

__all__ = [
    "Shape",
    "Sphere",
    "HollowSphere",
    "Box",
    "Capsule",
    "Cylinder",
    "EllipticalCylinder",
    "Cone",
    "Ellipsoid",
    "Rod",
    "Plate",
    "Disk",
    "Mesh",
    "Plane",
]


def not_text(value) -> None:
    """Raise TypeError for a string: ``float("0.1")`` and ``tuple("123")`` would pass as numbers."""
    if isinstance(value, (str, bytes)):
        raise TypeError(f"a string, {value!r}")


def _positive(owner: str, name: str, value: float) -> float:
    try:
        not_text(value)
        value = float(value)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{owner}.{name} must be a number, got {value!r}.") from err
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(
            f"{owner}.{name} must be a positive, finite length in metres, got {value}. "
            "Sizes are half sizes (radius, half extent, half length)."
        )
    return value


def _positive_tuple(owner: str, name: str, values, size: int) -> tuple[float, ...]:
    try:
        not_text(values)
        values = tuple(values)
    except TypeError as err:
        raise ValueError(f"{owner}.{name} must be a sequence of {size} numbers, got {values!r}.") from err
    if len(values) != size:
        raise ValueError(f"{owner}.{name} must have {size} entries, got {len(values)}: {values!r}.")
    return tuple(_positive(owner, f"{name}[{i}]", v) for i, v in enumerate(values))


class Shape:
    """Base class of all shapes. Subclasses are frozen dataclasses (hashable, static)."""

    #: True for shapes with zero volume (rod, plate, disk, thin shell): these need
    #: ``mass=``, because a volumetric density gives them no mass.
    thin: bool = False


@dataclasses.dataclass(frozen=True)
class Sphere(Shape):
    """Solid sphere of ``radius`` (m)."""

    radius: float

    def __post_init__(self):
        object.__setattr__(self, "radius", _positive("Sphere", "radius", self.radius))


@dataclasses.dataclass(frozen=True)
class HollowSphere(Shape):
    """Spherical shell of outer ``radius`` (m) and wall ``thickness`` (m).

    ``thickness=0`` (the default) is the thin shell, ``I = 2/3 m r^2``; it has no volume,
    so give its mass. ``0 < thickness < radius`` is a thick shell with a volume.
    """

    radius: float
    thickness: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "radius", _positive("HollowSphere", "radius", self.radius))
        t = float(self.thickness)
        if not (math.isfinite(t) and 0.0 <= t < self.radius):
            raise ValueError(
                f"HollowSphere.thickness must satisfy 0 <= thickness < radius = {self.radius}, "
                f"got {t}. Use Sphere for a solid ball."
            )
        object.__setattr__(self, "thickness", t)

    @property
    def thin(self) -> bool:  # type: ignore[override]
        return self.thickness == 0.0


@dataclasses.dataclass(frozen=True)
class Box(Shape):
    """Rectangular prism with ``half_extents = (a, b, c)`` (m) along x, y, z."""

    half_extents: tuple[float, float, float]

    def __post_init__(self):
        object.__setattr__(self, "half_extents", _positive_tuple("Box", "half_extents", self.half_extents, 3))


@dataclasses.dataclass(frozen=True)
class Capsule(Shape):
    """Cylinder of ``radius`` and ``half_length`` along z, capped by two hemispheres."""

    radius: float
    half_length: float

    def __post_init__(self):
        object.__setattr__(self, "radius", _positive("Capsule", "radius", self.radius))
        object.__setattr__(self, "half_length", _positive("Capsule", "half_length", self.half_length))


@dataclasses.dataclass(frozen=True)
class Cylinder(Shape):
    """Solid circular cylinder of ``radius`` and ``half_length``, axis along z."""

    radius: float
    half_length: float

    def __post_init__(self):
        object.__setattr__(self, "radius", _positive("Cylinder", "radius", self.radius))
        object.__setattr__(self, "half_length", _positive("Cylinder", "half_length", self.half_length))


@dataclasses.dataclass(frozen=True)
class EllipticalCylinder(Shape):
    """Solid cylinder with elliptical cross-section, axis along z.

    ``semi_axes = (a, b)`` are the ellipse's semi-axes along x and y.
    """

    semi_axes: tuple[float, float]
    half_length: float

    def __post_init__(self):
        object.__setattr__(
            self, "semi_axes", _positive_tuple("EllipticalCylinder", "semi_axes", self.semi_axes, 2)
        )
        object.__setattr__(
            self, "half_length", _positive("EllipticalCylinder", "half_length", self.half_length)
        )


@dataclasses.dataclass(frozen=True)
class Cone(Shape):
    """Solid circular cone, base ``radius``, ``height``, axis along +z (base to apex).

    The shape frame's origin is the centre of mass, a quarter of the height above the
    base: the base is at ``z = -height/4`` and the apex at ``z = 3 height/4``.
    """

    radius: float
    height: float

    def __post_init__(self):
        object.__setattr__(self, "radius", _positive("Cone", "radius", self.radius))
        object.__setattr__(self, "height", _positive("Cone", "height", self.height))


@dataclasses.dataclass(frozen=True)
class Ellipsoid(Shape):
    """Solid ellipsoid with ``semi_axes = (a, b, c)`` along x, y, z."""

    semi_axes: tuple[float, float, float]

    def __post_init__(self):
        object.__setattr__(self, "semi_axes", _positive_tuple("Ellipsoid", "semi_axes", self.semi_axes, 3))


@dataclasses.dataclass(frozen=True)
class Rod(Shape):
    """Slender rod of ``half_length`` along z, with no thickness (``I_z = 0``).

    Its inertia is singular, so it can describe a part of a body but not a whole
    simulated body: use a thin :class:`Cylinder` for that.
    """

    half_length: float
    thin = True

    def __post_init__(self):
        object.__setattr__(self, "half_length", _positive("Rod", "half_length", self.half_length))


@dataclasses.dataclass(frozen=True)
class Plate(Shape):
    """Thin rectangular plate in the x-y plane, ``half_extents = (a, b)``; normal along z."""

    half_extents: tuple[float, float]
    thin = True

    def __post_init__(self):
        object.__setattr__(self, "half_extents", _positive_tuple("Plate", "half_extents", self.half_extents, 2))


@dataclasses.dataclass(frozen=True)
class Disk(Shape):
    """Thin circular disk of ``radius`` in the x-y plane; normal along z."""

    radius: float
    thin = True

    def __post_init__(self):
        object.__setattr__(self, "radius", _positive("Disk", "radius", self.radius))


@dataclasses.dataclass(frozen=True)
class Mesh(Shape):
    """Closed, consistently oriented triangle mesh (outward normals, counter-clockwise).

    ``vertices``: ``(V, 3)`` positions in metres; ``faces``: ``(F, 3)`` vertex indices.
    Stored as nested tuples so the shape stays hashable; pass any array-like.
    Unlike the other shapes, the mesh frame is the frame the vertices are given in: its
    origin need not be the centre of mass (:func:`jaxrb.mass_properties` returns ``com``).
    """

    vertices: tuple[tuple[float, float, float], ...]
    faces: tuple[tuple[int, int, int], ...]

    def __post_init__(self):

        v, f = check_mesh(self.vertices, self.faces, "Mesh")
        object.__setattr__(self, "vertices", tuple(map(tuple, v.tolist())))
        object.__setattr__(self, "faces", tuple(map(tuple, f.astype(int).tolist())))


def check_mesh(vertices, faces, what: str):
    """``(vertices, faces)`` as NumPy arrays, or a ``ValueError``: ``(V >= 4, 3)`` finite
    vertices, ``(F >= 4, 3)`` integer faces indexing them (a quad face, read as its first
    three corners, had halved a cube's volume; a face index of -1 wrapped to the last
    vertex), and a closed, consistently oriented surface."""
    import numpy as np

    given = np.asarray(vertices)
    # The rounding of the vertices as given (float32's from a float32 array), for the
    # volume test of _check_parts_outward.
    precision = float(np.finfo(given.dtype if np.issubdtype(given.dtype, np.floating) else np.float64).eps)
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4:
        raise ValueError(f"{what}: vertices must have shape (V>=4, 3), got {v.shape}.")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{what}: vertices contain NaN or infinite values.")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
        raise ValueError(f"{what}: faces must have shape (F>=4, 3), triangles, got {f.shape}. Split polygons "
                         f"into triangles (a quad (a, b, c, d) into (a, b, c) and (a, c, d)).")
    if not np.issubdtype(f.dtype, np.integer) or f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"{what}: faces must be integer indices in [0, {len(v)}).")
    _check_closed_and_oriented(v, f, precision)
    return v, f


def _check_closed_and_oriented(vertices, faces, precision: float) -> None:
    """Raise unless every edge of the mesh is traversed as often in each direction by its
    faces (once, or more where solids touch along it): the surface is closed, and its
    faces agree on the orientation (the volume
    integrals of :func:`jaxrb.inertia.from_mesh` are wrong otherwise, silently: an open
    unit cube missing one face gave 833 kg at a density of 1000). Vertices at the same
    position count as one, so a triangle soup (as STL files store a mesh) passes."""
    import numpy as np

    unique, same = np.unique(vertices, axis=0, return_inverse=True)
    corners = same.reshape(-1)[faces]
    edges = np.stack([corners, np.roll(corners, -1, axis=1)], -1).reshape(-1, 2).astype(np.int64)
    code = edges[:, 0] * len(vertices) + edges[:, 1]
    codes, counts = np.unique(code, return_counts=True)
    # An edge may be shared by more than two faces (two cubes touching along an edge: a
    # valid solid, refused until stop 90) as long as it is traversed as often each way.
    reverse = (codes % len(vertices)) * len(vertices) + codes // len(vertices)
    where = np.minimum(np.searchsorted(codes, reverse), len(codes) - 1)
    reverse_counts = np.where(codes[where] == reverse, counts[where], 0)
    twice = int(np.sum(counts > np.maximum(reverse_counts, 1)))
    opposite = edges[:, 1] * len(vertices) + edges[:, 0]
    open_edges = int(np.sum(~np.isin(opposite, codes)))
    if twice or open_edges:
        raise ValueError(
            f"Mesh must be a closed, consistently oriented surface (each edge traversed by its faces as often in "
            f"one direction as in the other), but {open_edges} edges have no opposite (the surface is open there) "
            f"and {twice} are traversed twice the same way, more often than the other way (a face flipped or given "
            "twice). Its volume and inertia would be wrong: close the surface and orient every face "
            "counter-clockwise seen from outside.")
    _check_parts_outward(unique, corners, precision)


def _check_parts_outward(vertices, corners, precision: float) -> None:
    """Raise unless the connected parts of a closed mesh nest as the boundary of one solid:
    each part wound outward (positive volume) lies outside the solid the other parts bound,
    and each part wound inward (a cavity) lies inside it. Each part passes the edge test on
    its own, and the mesh's total volume can still be positive:

    - two cubes, one wound inward, had come out with volume 7 instead of 9, its centre of
      mass outside both;
    - a cavity wound outward (the commonest export mistake: the inner shell of a hollow
      body wound like an outer one) added its volume instead of removing it (a 2 m cube with
      a 1 m cavity: 9 instead of 7), and a cavity inside a cavity removed material twice
      (6.875), both silently (stop 96's review).

    The test takes points just behind up to eight faces spread over each part, on their
    material side, and the winding number of all other parts' faces about each: 0 for an
    outward part, 1 for a cavity. An outward part is refused where one of those points lies
    inside the others' solid, a cavity where none does: two outward parts that overlap are
    refused when one of the points tested lies inside the other, not always.
    ``vertices``: the distinct positions; ``corners``: ``(F, 3)`` face corners indexing them;
    ``precision``: the relative rounding of the vertices as given (their dtype's eps)."""
    import numpy as np

    labels = np.arange(len(vertices))
    while True:  # connected parts: each vertex takes the smallest label of any face it is on
        face_min = labels[corners].min(axis=1)
        new = labels.copy()
        np.minimum.at(new, corners.ravel(), np.repeat(face_min, 3))
        new = new[new]
        if np.array_equal(new, labels):
            break
        labels = new
    part = labels[corners[:, 0]]
    # About each part's own vertex mean, in float64: the signed volumes of a part far from
    # that point cancel, and the rounding bound below grows with the distances from it (a
    # 2 cm cube 10 km from a 1 m one in the same mesh was refused as flat).
    vertices = np.asarray(vertices, np.float64)
    counts = np.maximum(np.bincount(labels, minlength=len(vertices)), 1)
    means = np.stack([np.bincount(labels, weights=vertices[:, i], minlength=len(vertices)) for i in range(3)], -1)
    centred = vertices - (means / counts[:, None])[labels]
    a, b, c = (centred[corners[:, k]] for k in range(3))
    terms = np.einsum("fi,fi->f", a, np.cross(b, c)) / 6.0
    volume = np.bincount(part, weights=terms)
    # A part whose volume is within the rounding of its terms encloses none (all its
    # vertices in a plane): its sign is the rounding's, and the mesh was accepted or called
    # inside out by where it was placed, an accepted flat tetrahedron given moments from
    # noise (stop 90's review). Each term's own rounding is eps |a| |b| |c|, not eps
    # |term| (a flat part's terms are each near 0, their apex lying in its plane). The
    # vertices' rounding as given, ``precision |x|_max`` each, moves a term by at most that
    # times |b x c| + |c x a| + |a x b| (its gradient in a, b and c), to first order.
    # With products of norms for those, and a factor 64, float32 cubes of 3 cm and less
    # 1000 m from the origin were refused as flat (real rounding about 1% of their volume).
    na, nb, nc = np.linalg.norm(np.stack([a, b, c]), axis=-1)
    far = precision * np.max(np.abs(vertices))
    spread = sum(np.linalg.norm(np.cross(x, y), axis=-1) for x, y in ((b, c), (c, a), (a, b)))
    sizes = (np.finfo(np.float64).eps * na * nb * nc + far * spread) / 6.0
    rounding = 8 * np.bincount(part, weights=sizes)
    for k in np.flatnonzero((np.abs(volume) <= rounding) & (np.bincount(part) > 0)):
        raise ValueError(
            f"A connected part of the mesh ({int(np.sum(part == k))} faces) encloses no volume ({volume[k]:.3g} "
            f"m^3, within rounding): its faces lie in a plane or fold onto each other. A solid needs a closed "
            "surface around a volume; model a thin part as a thin solid (a box of small thickness).")
    parts = np.flatnonzero(np.bincount(part) > 0)
    if len(parts) < 2:
        return
    normals = np.cross(b - a, c - a)
    twice_area = np.linalg.norm(normals, axis=-1)
    area = np.bincount(part, weights=twice_area / 2)
    for k in parts:
        own = np.flatnonzero((part == k) & (twice_area > 0))
        chosen = own[np.linspace(0, len(own) - 1, min(8, len(own))).astype(int)]
        # Just behind each chosen face, on its material side (inside an outward part, in the
        # solid around a cavity): by a thousandth of the part's mean thickness, so a point
        # is neither on its own surface nor on that of a part it touches (a vertex on
        # another part's face had counted 0 or 1 there, by the rounding of a zero solid angle).
        depth = 1e-3 * abs(volume[k]) / area[k]
        # (In the mesh's own coordinates: each part's centred ones have their own origin.)
        points = vertices[corners[chosen]].mean(axis=1) - depth * normals[chosen] / twice_area[chosen, None]
        others = [vertices[corners[part != k, j]] for j in range(3)]
        inside = max(_winding_number(point, *others) for point in points)
        size = int(np.sum(part == k))
        if volume[k] < 0 and inside < 0.5:
            raise ValueError(
                f"A connected part of the mesh ({size} faces) is inside out: its volume is {volume[k]:.4g} m^3 and "
                f"it is not a cavity inside another part, so its volume and inertia would be subtracted. Check the "
                f"face orientation: reverse the vertex order of that part's faces (counter-clockwise seen from "
                f"outside).")
        if volume[k] > 0 and inside > 0.5:
            raise ValueError(
                f"A connected part of the mesh ({size} faces, volume {volume[k]:.4g} m^3) is wound outward but lies "
                f"inside the solid of the other parts, so its volume and inertia would be counted twice. If it is "
                f"a cavity, reverse the vertex order of its faces (a cavity's faces are counter-clockwise seen from "
                f"inside it, so that its normals point into the cavity); if it is a separate solid, it must not "
                f"overlap the others.")


def _winding_number(point, a, b, c) -> float:
    """How many times the triangles ``(a, b, c)`` (each ``(F, 3)``) wind around ``point``:
    their solid angles (Van Oosterom and Strackee) over ``4 pi``; 1 inside a closed,
    outward surface, 0 outside."""
    import numpy as np

    x, y, z = a - point, b - point, c - point
    lx, ly, lz = (np.linalg.norm(v, axis=1) for v in (x, y, z))
    numerator = np.einsum("fi,fi->f", x, np.cross(y, z))
    denominator = (lx * ly * lz + np.einsum("fi,fi->f", x, y) * lz + np.einsum("fi,fi->f", y, z) * lx
                   + np.einsum("fi,fi->f", z, x) * ly)
    return float(np.sum(2.0 * np.arctan2(numerator, denominator)) / (4.0 * np.pi))


@dataclasses.dataclass(frozen=True)
class Plane(Shape):
    """Static half-space ``{x : n . x <= offset}``, ``n = normal / |normal|``, e.g. the
    ground. Has no mass and no pose.

    ``normal`` is normalised on construction (the stored one is unit), and ``offset`` (m)
    is the plane's signed distance from the origin along that unit normal: ``Plane((0, 0,
    2), 1.0)`` is the plane ``z = 1``, not ``2 z = 1``."""

    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    offset: float = 0.0

    def __post_init__(self):
        try:
            for x in (self.normal, *self.normal):
                not_text(x)
            n = tuple(float(x) for x in self.normal)
        except (TypeError, ValueError):
            n = ()
        # hypot, not the square root of the sum of squares, which under- and overflowed:
        # (0, 0, 1e-170) was refused as zero and (3e-160, 0, 4e-160) stored (0.6000033, 0, 0.8000045).
        norm = math.hypot(*n)
        if len(n) != 3 or not norm > 0 or not math.isfinite(norm):
            raise ValueError(f"Plane.normal must be a non-zero 3-vector, got {self.normal!r}.")
        try:
            not_text(self.offset)
            offset = float(self.offset)
        except (TypeError, ValueError):
            offset = math.nan
        if not math.isfinite(offset):
            raise ValueError(f"Plane.offset must be a finite number (m), got {self.offset!r}.")
        object.__setattr__(self, "normal", tuple(x / norm for x in n))
        object.__setattr__(self, "offset", offset)
