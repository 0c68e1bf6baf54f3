"""jaxrb: differentiable rigid-body dynamics in JAX.

The public API is re-exported here; modules are named after the physics they hold.
"""

from . import collision as collision
from . import contact as contact
from . import dynamics as dynamics
from . import ensemble as ensemble
from . import exact as exact
from . import forces as forces
from . import identify as identify
from . import inertia as inertia
from . import integrators as integrators
from . import kinematics as kinematics
from . import ode as ode
from . import shapes as shapes
from . import spatial as spatial
from ._tradeoff import TradeoffResult as TradeoffResult
from ._tradeoff import comparison_times as comparison_times
from ._tradeoff import plot_tradeoff as plot_tradeoff
from ._tradeoff import reference_solution as reference_solution
from ._tradeoff import tradeoff as tradeoff
from .collision import Contact as Contact
from .collision import collide as collide
from .contact import ContactSettings as ContactSettings
from .ensemble import shard_ensemble as shard_ensemble
from .forces import AngularDamping as AngularDamping
from .forces import ExternalWrench as ExternalWrench
from .forces import Gravity as Gravity
from .forces import LinearDamping as LinearDamping
from .forces import PointForces as PointForces
from .inertia import MassProperties as MassProperties
from .inertia import mass_properties as mass_properties
from .inertia import principal_axes as principal_axes
from .scene import Body as Body
from .scene import Scene as Scene
from .shapes import Box as Box
from .shapes import Capsule as Capsule
from .shapes import Cone as Cone
from .shapes import Cylinder as Cylinder
from .shapes import Disk as Disk
from .shapes import Ellipsoid as Ellipsoid
from .shapes import EllipticalCylinder as EllipticalCylinder
from .shapes import HollowSphere as HollowSphere
from .shapes import Mesh as Mesh
from .shapes import Plane as Plane
from .shapes import Plate as Plate
from .shapes import Rod as Rod
from .shapes import Sphere as Sphere
from .simulate import Step as Step
from .simulate import make_step as make_step
from .simulate import rollout as rollout
from .state import Params as Params
from .state import State as State
from .state import angular_momentum_about as angular_momentum_about
from .state import angular_velocity as angular_velocity
from .state import body_angular_velocity as body_angular_velocity
from .state import kinetic_energy as kinetic_energy
from .state import linear_momentum as linear_momentum
from .state import potential_energy as potential_energy
from .state import rotation_matrix as rotation_matrix
from .state import rotational_kinetic_energy as rotational_kinetic_energy
from .state import total_energy as total_energy
from .state import translational_kinetic_energy as translational_kinetic_energy
from .state import world_inertia as world_inertia

__version__ = "0.1.0"
