"""Collision narrow phase: one function per shape pair, returning fixed-size masked contacts.

Every pair function takes ``(shape_a, position_a, orientation_a, shape_b, position_b,
orientation_b, margin)`` for ONE pair (``jax.vmap`` for batches); the ground plane is
always B and takes no pose. The result is a :class:`Contact` with a static number ``K`` of
slots (:func:`max_contacts`), normals from B towards A, signed gaps, midpoints, and an
``active`` mask. :func:`collide` dispatches on the shape types, in either order.

=================  ===  ==========================================================
pair               K    slots
=================  ===  ==========================================================
sphere-plane       1    the sphere's lowest point
box-plane          4    the four deepest corners
capsule-plane      2    the two end spheres
cylinder-plane     5    the five deepest of: each rim's deepest point, and four
                        rim points per cap fixed in the body, a square (to stand
                        and slide upright on a cap)
sphere-sphere      1    along the line of centres (coincident: world +z)
sphere-box         1    closest box point, or nearest face from inside
sphere-capsule     1    closest segment point (on the segment: capsule's body x)
sphere-cylinder    1    closest point of the solid, or nearest face from inside
capsule-capsule    2    closest pair + the other end of the overlap
capsule-box        2    closest segment point (SAT where the segment meets the box)
                        + the other end of the segment's overlap with that face
capsule-cylinder   2    closest segment point + the other end of its overlap with
                        the cap's disc or the side's slab (see its docstring for a
                        segment that enters the cylinder)
box-box            4    SAT; clipped face manifold reduced to 4, or one edge-edge
cylinder-box       5    the deepest of the box's corners and edge points and the
                        cylinder's rim square and side lines, each against the
                        other solid or held on a face; spread by farthest points
                        (overlapping: slot 0 pushes along the best direction)
cylinder-cylinder  5    the same from both: rim squares, each rim's point closest
                        to the other (sampled, then searched), the side point
                        facing the other's axis, the line over the other's cap
=================  ===  ==========================================================
"""

from ._box import box_box as box_box
from ._capsule import capsule_box as capsule_box
from ._capsule import capsule_capsule as capsule_capsule
from ._capsule import capsule_cylinder as capsule_cylinder
from ._contact import Contact as Contact
from ._contact import concatenate_contacts as concatenate_contacts
from ._cylinder import cylinder_box as cylinder_box
from ._cylinder import cylinder_cylinder as cylinder_cylinder
from ._dispatch import collide as collide
from ._dispatch import max_contacts as max_contacts
from ._dispatch import supported_pairs as supported_pairs
from ._plane import box_plane as box_plane
from ._plane import capsule_plane as capsule_plane
from ._plane import cylinder_plane as cylinder_plane
from ._plane import sphere_plane as sphere_plane
from ._sphere import sphere_box as sphere_box
from ._sphere import sphere_capsule as sphere_capsule
from ._sphere import sphere_cylinder as sphere_cylinder
from ._sphere import sphere_sphere as sphere_sphere
