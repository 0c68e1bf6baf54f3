"""Static options of the contact stage of a step."""

from __future__ import annotations

import dataclasses
import math
import numbers

import numpy as np

from .._static import positive_count, static_switch

__all__ = ["ContactSettings"]

#: m/s: the approach speed the default margin covers in one step.
DEFAULT_MARGIN_SPEED = 10.0
#: Metres: the least difference of overlap within a pair that the split impulse levels
#: (``ContactSettings.correction_slop``). A difference of 1 nm across a 0.1 m face is a
#: tilt of 1e-8 rad: a normal force leaning by that moves a frictionless box on another
#: by 0.02 mm in 2 s under a 100:1 load (an acceleration of 1e-8 g times the mass ratio).
LEVEL_TOLERANCE = 1e-9
#: m; slots this close count as touching for the impact law at the time of impact.
TOUCHING = 1e-4


def _check(name: str, value, *, unit: bool = False):
    """A real number >= 0 (at most 1 where ``unit``), or a ``ValueError`` naming the setting."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
    ok = ok and math.isfinite(value) and value >= 0
    if unit:
        ok = ok and value <= 1
    if not ok:
        kind = "a number in [0, 1]" if unit else "a number >= 0"
        raise ValueError(f"ContactSettings.{name} must be {kind}, got {value!r}.")


@dataclasses.dataclass(frozen=True)
class ContactSettings:
    """How a step resolves contacts (static: changing it recompiles). Pass to :func:`jaxrb.make_step`.

    Attributes:
        solver: ``"pgs"``, projected Gauss-Seidel (sequential impulses) for friction and
            normals; or ``"exact"``, which solves the normal impulses of all contacts
            together as one LCP by a semismooth Newton method (exact to round-off for the
            small contact sets it is meant for, e.g. a heavy body on a light one, where PGS
            contracts only by ``M/(M+m)`` per sweep) and friction by PGS sweeps between.
        iterations: PGS sweeps per solve, at most (``"exact"``: outer normal/friction
            alternations, always all of them). Sweeps that stop at this cap unconverged
            keep part of their warm start; since 2026-12-05 the warm start is scaled so
            that it adds no kinetic energy (before, with ``iterations=1`` a box landing flat
            at 0.13 m/s with e = 0 came back up at 0.018 m/s, and three boxes dropped onto
            one another gained up to 1.7e-2 J in a step with the default 20 sweeps, 0.36 J
            with 8). With one sweep a box landing flat still tilts and rises by 0.03 mm
            (without gaining energy), where the default settles it in place.
        tolerance: the PGS sweeps (and the split impulse's) stop after the first sweep that
            changes no impulse by more than ``tolerance`` times the largest impulse. ``None``
            (default): the square root of the state's machine epsilon (1.5e-8 in float64,
            3.5e-4 in float32), the level at which the derivative takes the sweeps as
            converged. ``0``: the sweeps stop only once one changes nothing. The float32
            5-box stack of ``benchmarks/contacts.py`` ran 4.7 of its 20 sweeps a step on
            average over its first 200 steps and 1.0 over the last 1000 of 2 s (float64:
            20 and 1.0; counted 2026-12-04). Under ``vmap`` a sweep is skipped only once every member has
            converged.
        impact_iterations: sweeps of sequential collisions per impact; momentum crosses
            one contact per sweep in the worst slot order (a row of ``n`` touching balls
            needs ``n - 1``).
        newton_iterations: ``"exact"`` only: Newton steps per normal solve (a value other
            than the default with ``"pgs"`` is refused: it would be ignored).
        warm_start: start each step's solve from the previous step's impulses (kept in
            ``State.contact_impulse``).
        restitution_threshold: m/s. Impacts at or below this speed are plastic (``e = 0``), so a
            resting body does not micro-bounce on the velocity gravity gives it in one step.
            A slot that the last step's solve held is compared without the velocity a
            resting body reports between steps (``dt/2`` of the forces: leapfrog's stagger,
            0.049 m/s at dt = 10 ms): a threshold under that velocity bounces no resting
            body (tested down to 0: a 5-box stack, a box dropped on a resting table).
        margin: m. In a contact step, slots closer than this are solved ahead of contact
            ("speculative" contacts, which may approach by ``gap`` in the step but not
            pass). With ``time_of_impact``, a step is a contact step only where a pair
            touches at its start (within 0.1 mm, or twice ``penetration_slop``) or closes
            during its free flight; without it, wherever a pair is within the margin, which
            must then exceed the largest approach speed times ``dt``. Default ``None``:
            ``0.01 m + (10 m/s) dt``. At least the touching distance (0.1 mm, or twice
            ``penetration_slop``): the narrow phase reports slots within the margin only,
            and with ``margin=0`` a touching ball had passed through the ground.
        time_of_impact: locate the first new impact inside each step: advance to it,
            apply the impulse, finish the step. Bounce heights then do not depend on ``dt``.
        toi_iterations: root-finding iterations for the time of impact (with
            ``time_of_impact`` only, as ``located_impacts``: another value without it is
            refused, since it would be ignored).
        located_impacts: with ``time_of_impact``, the impacts located inside one step, the
            earliest first; the step is split at each (at most ``located_impacts + 1``
            parts). A later impact in the same step is applied at the instant of the last
            located one, before it touches (an error of up to its approach speed times the
            rest of the step). Located impacts after the first are those of pairs whose
            bodies move as predicted until then: none struck earlier in the step, nor
            touching (through a chain of contacts) a body that was. A second ball landing
            elsewhere, or on a table resting elsewhere, is located; a body's second impact
            after its first is not. With 1, a ball landing 0.45 dt after another in the
            same step bounced 1.1% too high at dt = 10 ms (0.11% at 1 ms); with 2, exactly.
            Above 1, the compiled step holds a loop of searches and one more evaluation of
            the pairs' separations (run only in steps that locate an impact), where some
            two pairs have their moving bodies apart (not a ball with the ground and
            walls): the 5-box stack's 200-step program grew
            from 18,478 to 19,474 lines of StableHLO, and compiled in 11.8-12.4 s against
            10.3-11.6 s (one machine, alternating processes), with the same states.
        position_iterations: PGS sweeps of the split-impulse penetration correction.
        position_correction: fraction of the penetration (beyond ``correction_slop``)
            removed per step. The correction moves positions only, never velocities, so it
            adds no kinetic energy (split impulse; not Baumgarte on velocity). It keeps
            neither the bodies' centre of mass nor their total angular momentum about a
            fixed point: its shifts and turns are those of pseudo-impulses, and the moved
            positions change ``r x p``. The change is first order in the overlap removed:
            two free boxes (1 and 6 kg) sliding in contact after an oblique hit with spin,
            overlapping by up to 5.45 mm at dt = 5 ms, changed their total angular
            momentum by 0.9% (1.0e-3 at dt = 1 ms, 7.9e-5 at 0.2 ms); the impulses
            themselves keep it to round-off.
        penetration_slop: m, penetration left alone by the time-of-impact search (keeps
            resting contacts in contact); a pair within twice it (or 0.1 mm) at a step's
            start touches.
        skin: m. In the resting solve, a slot whose gap is under ``skin`` counts as touching
            (target ``u_n >= 0``: it may not approach); beyond it the speculative target is
            ``-(gap - skin)/h``, so a body arriving comes to rest ``skin`` above the surface.
            Its job is round-off: without it, a resting corner's gap wanders by the
            rounding of the poses (about 6e-8 m at 1 m in float32), which moves its
            speculative target by that over ``h`` (6e-5 m/s at h = 1 ms) and with it the
            impulses of every box above, more than the sweeps' tolerance. The float32 5-box
            stack of ``benchmarks/contacts.py`` then ran 2.7 sweeps a step over its last
            1000 steps of 2 s, 43 of them at the 20-sweep cap, where with the default skin
            it runs one (tested). Default ``None``: 16 machine epsilons in metres (float32:
            1.9e-6 m, 30 times that rounding near 1 m; float64: 3.6e-15 m). Far from the
            origin the rounding grows with the coordinates (near 10 m, about 5e-7 m a coordinate
            in float32): a scene there may need a larger skin (not measured).
        correction_slop: m, penetration the split impulse leaves alone. Below it, the
            overlap a resting solve leaves (its own error, about 2e-4 m in a PGS stack of
            a 100 kg box on a 1 kg one) is left to that solve: correcting it every step,
            the split impulse's few unconverged sweeps tilted the boxes, and the 5-box PGS
            stack drifted 2.5 cm in 2 s (6e-5 m with the correction idle) and the 100:1
            stack fell through (``position_iterations``: 8). Deeper overlaps (bodies
            started overlapping, or driven in) are removed down to it. Within the slop,
            every pair of several slots (all but the sphere pairs) is levelled where it
            touches at every active slot: a slot's overlap beyond the shallowest of its
            pair's slots is removed (where the difference exceeds the skin, and
            :data:`LEVEL_TOLERANCE`). So a box resting tilted on its face, as
            the first sweeps of a heavy-on-light stack leave it, is turned flat: left
            tilted by 1.4e-4 rad, its leaning face normal pushed a frictionless 1 kg box
            under a 100 kg one 0.16 m sideways in 2 s (levelled: 2.1 mm); a can left
            tilted on its cap, or on a box, stayed so. A body resting on some of its slots
            and apart at others (a can rocking on its rim) is left to its dynamics (see
            ``jaxrb.contact._layout._Group.levelled``).
    """

    solver: str = "pgs"
    iterations: int = 20
    tolerance: float | None = None
    impact_iterations: int = 8
    newton_iterations: int = 8
    warm_start: bool = True
    restitution_threshold: float = 0.25
    margin: float | None = None
    time_of_impact: bool = True
    toi_iterations: int = 14
    located_impacts: int = 2
    position_iterations: int = 8
    position_correction: float = 0.8
    penetration_slop: float = 1e-5
    correction_slop: float = 1e-3
    skin: float | None = None

    def __post_init__(self):
        if self.solver not in ("pgs", "exact"):
            raise ValueError(f"ContactSettings.solver must be 'pgs' or 'exact', got {self.solver!r}.")
        for name in ("iterations", "impact_iterations", "newton_iterations", "toi_iterations", "located_impacts",
                     "position_iterations"):
            # np.int64(8) too, and at most 2**31 - 1: a static loop length
            object.__setattr__(self, name, positive_count(f"ContactSettings.{name}", getattr(self, name)))
        for name in ("restitution_threshold", "penetration_slop", "correction_slop", "margin", "skin", "tolerance",
                     "position_correction"):
            value = getattr(self, name)
            if value is None and name in ("margin", "skin", "tolerance"):
                continue
            _check(name, value, unit=name == "position_correction")
            # As a Python float: a Fraction passed the check and failed inside the step.
            object.__setattr__(self, name, float(value))
        for name in ("warm_start", "time_of_impact"):  # np.True_ too, stored as a Python bool
            object.__setattr__(self, name, static_switch(f"ContactSettings.{name}", getattr(self, name)))
        floor = max(TOUCHING, 2.0 * self.penetration_slop)
        if self.margin is not None and self.margin < floor:
            # The narrow phase reports a slot only within the margin, and the impact law
            # takes slots within TOUCHING as touching: at margin = 0 a touching ball passed
            # through the ground, and a dropped one sank 2 cm into it.
            raise ValueError(f"ContactSettings.margin must be at least {floor:g} m (the touching distance, "
                             f"max(1e-4, 2 penetration_slop)), got {self.margin!r}.")
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        unused = [("newton_iterations", "solver='pgs'")] if self.solver == "pgs" else []
        if not self.time_of_impact:
            unused += [(name, "time_of_impact=False") for name in ("toi_iterations", "located_impacts")]
        for name, why in unused:
            if getattr(self, name) != defaults[name]:
                raise ValueError(f"ContactSettings.{name}={getattr(self, name)!r} would be ignored with {why}: "
                                 f"leave it at its default ({defaults[name]!r}).")

    def tolerance_for(self, dtype) -> float:
        """The sweeps' relative tolerance for states of ``dtype``."""
        return self.tolerance if self.tolerance is not None else float(np.sqrt(np.finfo(dtype).eps))

    def skin_for(self, dtype) -> float:
        """The resting solve's skin (m) for states of ``dtype``."""
        return self.skin if self.skin is not None else 16.0 * float(np.finfo(dtype).eps)

    def level_tolerance_for(self, dtype) -> float:
        """Metres: the least difference of overlap within a pair that the split impulse
        levels (see ``correction_slop``). The skin, and at least :data:`LEVEL_TOLERANCE`,
        so that the rounding of a settled stack's gaps (1e-12 m apart in float64, 6e-8 m in
        float32) does not run the correction at every step."""
        return max(self.skin_for(dtype), LEVEL_TOLERANCE)

    def margin_for(self, dt: float) -> float:
        """The detection margin (m) used with time step ``dt``."""
        return self.margin if self.margin is not None else 0.01 + DEFAULT_MARGIN_SPEED * dt
