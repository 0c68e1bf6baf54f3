# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 03 · Contacts: bouncing, sliding, rolling, stacking
#
# Bodies with shapes collide with each other and with a ground plane once the scene lists
# its contact pairs. This notebook checks the contact step against the closed forms of
# elementary mechanics:
#
# 1. how a step with contacts works (kick, solve, drift, kick; the time of impact);
# 2. a bouncing ball, whose apexes follow $e^{2n}$;
# 3. Coulomb friction: a sliding box, and a ball and a can that slip, then roll;
# 4. inclines: a tilted ground plane, and a sweep of slopes without recompiling;
# 5. Newton's cradle, with `rb.contact.resolve_impacts`;
# 6. a small stack: projected Gauss–Seidel against the exact normal solve.
#
# Every run is in float64. The constants in the first code cell set the sizes; CI runs
# this notebook exactly as it is, so they are small. Most of the time goes into compiling
# (each scene, time step or solver setting compiles a new step, several seconds each);
# the simulations themselves take milliseconds. `examples/contacts_*.py` print the same
# checks as tables, with longer runs.

# %%
import jax

jax.config.update("jax_enable_x64", True)  # jaxrb never flips this switch itself

import matplotlib.pyplot as plt
import numpy as np

import jaxrb as rb

G = 9.81  # m/s^2, the default Scene gravity
DT = 1e-2  # s, the step of every run below
T_BOUNCE = 4.0  # s, bouncing ball
T_FRICTION = 1.5  # s, sliding box, rolling ball, inclines
T_STACK = 0.5  # s, the stack
HEAVY, LIGHT = 10.0, 0.1  # kg, the two balls of the stack: top, bottom
SPLITTING = rb.integrators.SymplecticSplitting()


def vmap_states(f, params, traj):
    """Apply ``f(params, state)`` to every state of a trajectory (leading time axis)."""
    return np.asarray(jax.vmap(f, in_axes=(None, 0))(params, traj))


# %% [markdown]
# ## 1 · The contact step
#
# A scene gets contacts from three arguments: shapes on its bodies (`rb.Sphere`,
# `rb.Box`, ...), an optional static `ground=rb.Plane(normal, offset)` (the half-space
# below it is solid; a tilted normal makes an incline) and `contacts=`, either `"all"` or
# a list of pairs such as `[("ball", "ground"), ("b0", "b1")]`. The pairs are resolved
# when the scene is built; `scene.params(restitution=..., friction=...)` stores one
# coefficient of each kind per pair (a number, or a dict keyed by pair or body name), so
# they can be changed, or differentiated, without recompiling.
#
# `rb.make_step(scene, integrator, dt, contact=rb.ContactSettings(...))` then builds a
# step of length $h$ in four stages:
#
# 1. **Kick:** $\mathbf{v} \leftarrow \mathbf{v} + \tfrac{h}{2} \mathbf{F}/M$,
#    $\mathbf{L} \leftarrow \mathbf{L} + \tfrac{h}{2} \boldsymbol{\tau}$.
# 2. **Solve:** contacts are detected at the start pose, including pairs still up to a
#    margin apart ("speculative" contacts: they may close the gap during the step but not
#    pass it). Impulses are found so that every contact's normal velocity $u_n$ ends at
#    least at its target: $0$ for resting contact, $-e\,u_n^-$ at an impact (seed 000's
#    law; impacts slower than `restitution_threshold` = 0.25 m/s are plastic, so resting
#    bodies do not micro-bounce), with the friction impulse inside Coulomb's cone
#    $|\boldsymbol{\lambda}_t| \le \mu \lambda_n$.
# 3. **Drift:** the integrator advances the *force-free* motion with those velocities. A
#    penetration correction (split impulse) adds a pseudo-velocity to this drift only, so
#    it moves positions without adding kinetic energy.
# 4. **Kick:** the second half of the forces.
#
# Without contacts this is Störmer–Verlet, exact for constant gravity. Two consequences
# matter when reading the output below. The velocity stored *between* steps is leapfrog's
# staggered one: a body resting on the ground reports $v_z = -g h/2$, not 0. And the
# contact impulses act once per step, so a sample's tangential velocity is the mean over
# the step that just ended: it belongs to the time $t - h/2$.
#
# **Time of impact.** A pair that is apart at the start of a step but would meet during
# it is not bounced at the start pose. The step finds the first such instant $\tau h$ (a
# few regula-falsi iterations on the pair's distance along the free motion), moves
# everything there, applies the impact law *at contact*, and finishes the step. Bounce
# heights then do not depend on $h$, and `jax.grad` sees the dependence of $\tau$ on the
# parameters (implicit-function theorem).
#
# **Solvers.** `solver="pgs"` (the default) is projected Gauss–Seidel, or sequential
# impulses: it visits the contacts one at a time, `iterations` sweeps per step, and every
# update is capped so that it cannot add energy. `solver="exact"` solves the normal
# impulses of all contacts together as one linear complementarity problem (seed 000's
# LCP) by a semismooth Newton method, with friction by PGS sweeps in between. Section 6
# shows where the difference shows.

# %% [markdown]
# ## 2 · A bouncing ball
#
# A 1 kg ball of radius 0.1 m is dropped from 1 m above the ground with restitution
# $e = 0.8$. It hits the ground at $v_1 = \sqrt{2 g h_0}$ and leaves at $e v_1$, so it
# rises to $e^2 h_0$; the $n$-th apex is at $e^{2n} h_0$. The apex is read from energy,
# $z + v_z^2 / 2g - r$, at the last sample before $v_z$ turns negative. We run the same
# drop with and without the time of impact.

# %%
E, DROP, R = 0.8, 1.0, 0.1
ball_scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(R), mass=1.0)], ground=rb.Plane(), contacts="all")
ball_params = ball_scene.params(restitution=E, friction=0.5)
ball_state = ball_scene.state(ball_params, position=(0.0, 0.0, R + DROP))

bounces = {}
for toi in (True, False):
    step = rb.make_step(ball_scene, SPLITTING, dt=DT, contact=rb.ContactSettings(time_of_impact=toi))
    _, traj = rb.rollout(step, ball_params, ball_state, num_steps=round(T_BOUNCE / DT))
    z, vz = np.asarray(traj.position[:, 0, 2]), np.asarray(traj.velocity[:, 0, 2])
    k = np.flatnonzero((vz[:-1] > 0) & (vz[1:] <= 0))
    bounces[toi] = (np.asarray(traj.time), z - R, z[k] + vz[k] ** 2 / (2 * G) - R)

n_shown = 8
theory = E ** (2 * np.arange(1, n_shown + 1)) * DROP
print(f" n   e^(2n) (m)   time of impact   without    (apex clearance, dt = {DT} s)")
for n in range(n_shown):
    print(f"{n + 1:2d}   {theory[n]:10.6f}   {bounces[True][2][n]:14.6f}   {bounces[False][2][n]:8.6f}")
for toi in (True, False):
    error = np.max(np.abs(bounces[toi][2][:n_shown] - theory))
    print(f"time_of_impact={toi}: max |apex - e^(2n)| over {n_shown} bounces = {error:.1e} m")

# %%
fig, ax = plt.subplots(figsize=(8, 4))
for toi, label in [(True, "with time of impact"), (False, "without")]:
    t, height, _ = bounces[toi]
    ax.plot(t, height, lw=1.2, label=label)
for h in theory:
    ax.axhline(h, color="0.6", lw=0.7, ls=":")
ax.set_xlabel("time (s)")
ax.set_ylabel("clearance above the ground (m)")
ax.set_title(f"ball dropped from {DROP} m, e = {E}, dt = {DT} s; dotted: $e^{{2n}}$ m")
ax.legend()
plt.show()

# %% [markdown]
# With the time of impact the apexes are $e^{2n}$ m to round-off (the first is 0.640000).
# `examples/contacts_bounce.py` repeats the drop at $h$ = 1/60 s and gets the same
# numbers. Without it, the impact is applied at the start of the step in which the ball
# would reach the ground, while it is still up to $v h$ above it, so the ball turns back
# early and every apex comes out too high, by $(1 - e^2)$ times that height: here the
# last sample before the first impact is at $t$ = 0.45 s, 6.7 mm up, and the first apex
# is 0.6424 m. (0.45 s is a whole number of steps at 10, 5 and 2.5 ms alike, so those
# three step sizes give the same first apex; the later ones differ.) With the time of
# impact, after thirteen bounces the impact speed falls below the 0.25 m/s restitution
# threshold, below which impacts are plastic, and the ball is at rest on the ground
# 3.87 s after the drop.

# %% [markdown]
# ## 3 · Coulomb friction: a sliding box, a rolling ball and a rolling can
#
# Three experiments share one scene, each with its own friction coefficient on its own
# contact pair (the bodies are 1 m apart and never meet):
#
# * a 1 kg cube of half-extent 0.1 m launched at $v_0$ = 5 m/s with $\mu$ = 0.5. Kinetic
#   friction $\mu m g$ decelerates it uniformly: it stops after $t = v_0 / \mu g$ =
#   1.019 s and $d = v_0^2 / 2 \mu g$ = 2.548 m;
# * a solid ball ($I = \tfrac25 m r^2$) launched at $v_0$ = 2 m/s with no spin and
#   $\mu$ = 0.2. Friction slows it, $v = v_0 - \mu g t$, and spins it up, $r\omega =
#   \tfrac52 \mu g t$, until the contact point stops slipping at $t = 2 v_0 / 7 \mu g$ =
#   0.291 s. From then on it rolls at $\tfrac57 v_0$ = 1.429 m/s with no friction at all;
# * a solid cylinder ($I = \tfrac12 m r^2$ about its axis, r = 0.1 m) lying on its side,
#   launched the same way. Its spin grows faster, $r\omega = 2 \mu g t$: it rolls from
#   $t = v_0 / 3 \mu g$ = 0.340 s at $\tfrac23 v_0$ = 1.333 m/s, touching the ground
#   at the lowest points of its two rims.

# %%
V_BOX, MU_BOX, V_BALL, MU_BALL, HALF = 5.0, 0.5, 2.0, 0.2, 0.1
flat_scene = rb.Scene(
    [rb.Body("box", shape=rb.Box((HALF, HALF, HALF)), mass=1.0), rb.Body("ball", shape=rb.Sphere(R), mass=1.0),
     rb.Body("can", shape=rb.Cylinder(R, 0.15), mass=1.0)],
    ground=rb.Plane(),
    contacts=[("box", "ground"), ("ball", "ground"), ("can", "ground")],
)
FRICTION = {("box", "ground"): MU_BOX, ("ball", "ground"): MU_BALL, ("can", "ground"): MU_BALL}
flat_params = flat_scene.params(friction=FRICTION)
print("friction per pair:", dict(zip(flat_scene.contacts, np.asarray(flat_params.friction).tolist(), strict=True)))
LYING = (np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0)  # the can's axis (body z) along world y
UPRIGHT = (1.0, 0.0, 0.0, 0.0)
flat_state = flat_scene.state(flat_params, position=[(0, 0, HALF), (0, 1, R), (0, 2, R)],
                              orientation=[UPRIGHT, UPRIGHT, LYING],
                              velocity=[(V_BOX, 0, 0), (V_BALL, 0, 0), (V_BALL, 0, 0)])
flat_step = rb.make_step(flat_scene, SPLITTING, dt=DT, contact=rb.ContactSettings())
flat_steps = round(T_FRICTION / DT)
_, traj = rb.rollout(flat_step, flat_params, flat_state, num_steps=flat_steps)

t_mid = np.asarray(traj.time) - DT / 2  # tangential velocities are step means
v_box, v_ball, v_can = (np.asarray(traj.velocity[:, i, 0]) for i in range(3))
r_omega, r_omega_can = (R * vmap_states(rb.angular_velocity, flat_params, traj)[:, i, 1] for i in (1, 2))


def zero_crossing(t, y):
    """Where a linearly falling y (then ~0) reaches 0, from its last two clearly positive samples."""
    k = np.flatnonzero(y > 1e-6 * y[0])[-1]
    return t[k] + y[k] * (t[k] - t[k - 1]) / (y[k - 1] - y[k])


stop_time, stop_distance = zero_crossing(t_mid, v_box), float(traj.position[-1, 0, 0])
roll_time, roll_speed = zero_crossing(t_mid, v_ball - r_omega), v_ball[-1]
can_time, can_speed = zero_crossing(t_mid, v_can - r_omega_can), v_can[-1]
print(f"box stops after {stop_time:.6f} s (closed form {V_BOX / (MU_BOX * G):.6f} s) "
      f"and {stop_distance:.6f} m (closed form {V_BOX**2 / (2 * MU_BOX * G):.6f} m)")
print(f"ball rolls from {roll_time:.6f} s (closed form {2 * V_BALL / (7 * MU_BALL * G):.6f} s) "
      f"at {roll_speed:.6f} m/s (closed form 5 v0 / 7 = {5 * V_BALL / 7:.6f} m/s)")
print(f"can rolls from {can_time:.6f} s (closed form {V_BALL / (3 * MU_BALL * G):.6f} s) "
      f"at {can_speed:.6f} m/s (closed form 2 v0 / 3 = {2 * V_BALL / 3:.6f} m/s)")

# %%
t = np.linspace(0, T_FRICTION, 301)
fig, (left, right, can) = plt.subplots(1, 3, figsize=(15, 4))
left.plot(t_mid, v_box, "o", ms=3, label="jaxrb")
left.plot(t, np.maximum(V_BOX - MU_BOX * G * t, 0), "k:", label=r"$\max(v_0 - \mu g t, 0)$")
left.set(xlabel="time (s)", ylabel="box velocity (m/s)", title=f"sliding box, mu = {MU_BOX}")
left.legend()


def slip_then_roll(ax, v, r_omega, spin_rate, rolling_speed, body):
    """A body launched at V_BALL without spin: v = v0 - mu g t, r omega = spin_rate mu g t,
    until both reach the rolling speed."""
    t_roll = (V_BALL - rolling_speed) / (MU_BALL * G)
    ax.plot(t_mid, v, "o", ms=3, label=r"$v$")
    ax.plot(t_mid, r_omega, "s", ms=3, label=r"$r \omega$")
    ax.plot(t, np.where(t < t_roll, V_BALL - MU_BALL * G * t, rolling_speed), "k:", lw=1, label="closed form")
    ax.plot(t, np.where(t < t_roll, spin_rate * MU_BALL * G * t, rolling_speed), "k:", lw=1)
    ax.set(xlabel="time (s)", ylabel="m/s", title=f"{body} launched without spin, mu = {MU_BALL}")
    ax.legend()


slip_then_roll(right, v_ball, r_omega, 2.5, 5 * V_BALL / 7, "ball")
slip_then_roll(can, v_can, r_omega_can, 2.0, 2 * V_BALL / 3, "can")
plt.show()

# %% [markdown]
# `rb.viz` draws a scene's bodies as their shapes, at the poses the collisions see
# (`rb.viz.draw(scene, state)` for one state), and animates a trajectory. The ball's and
# the can's facets turn as they start to roll; the box slides without turning.

# %%
from IPython.display import HTML  # noqa: E402

animation = rb.viz.animate(flat_scene, traj, every=5)  # one frame every 50 ms of the 1.5 s
plt.close(animation.drawing.ax.figure)  # shown once, as the animation below, not also as a still
HTML(animation.to_jshtml())

# %% [markdown]
# All three match the closed forms to about $10^{-6}$, at a step of 10 ms: a stop at
# 1.019368 s after 2.548419 m; the ball rolling from 0.291248 s at 1.428571 m/s, the can
# from 0.339789 s at 1.333333 m/s. (The times are
# read at $t - h/2$, as section 1 explains; read at $t$ they would be late by $h/2$.)
#
# ## 4 · Inclines
#
# A ground plane with normal $(-\sin\theta, 0, \cos\theta)$ is an incline of angle
# $\theta$ that rises towards $+x$. A box resting on it stays put while
# $\tan\theta \le \mu$ and otherwise slides down at $g(\sin\theta - \mu\cos\theta)$: at
# 30° with $\mu$ = 0.5 that is 0.6571 m/s². The box starts flush with the plane: its
# centre at $0.1\,\mathbf{n}$, turned by $-\theta$ about $y$.

# %%
theta = np.radians(30.0)
normal = np.array([-np.sin(theta), 0.0, np.cos(theta)])
downhill = np.array([-np.cos(theta), 0.0, -np.sin(theta)])
incline_scene = rb.Scene([rb.Body("box", shape=rb.Box((HALF, HALF, HALF)), mass=1.0)],
                         ground=rb.Plane(normal=tuple(normal)), contacts="all")
incline_params = incline_scene.params(friction=MU_BOX)
tilt = rb.spatial.quat_from_axis_angle(np.array([0.0, 1.0, 0.0]), -theta)
incline_state = incline_scene.state(incline_params, position=HALF * normal, orientation=tilt)
step = rb.make_step(incline_scene, SPLITTING, dt=DT, contact=rb.ContactSettings())
_, traj = rb.rollout(step, incline_params, incline_state, num_steps=flat_steps)
s = (np.asarray(traj.position[:, 0]) - HALF * normal) @ downhill  # distance slid down the slope
incline_accel = 2 * np.polyfit(np.asarray(traj.time), s, 2)[0]
print(f"30 deg incline, mu = {MU_BOX}: acceleration {incline_accel:.6f} m/s^2 "
      f"(closed form {G * (np.sin(theta) - MU_BOX * np.cos(theta)):.6f} m/s^2)")

# %% [markdown]
# The plane is part of the `Scene`, so each angle would compile its own step. An
# incline is also a flat ground under tilted gravity, and gravity lives in `Params`: the
# step compiled for section 3 can sweep the slope with no new compilation. On a slope,
# the box sticks up to the friction angle $\arctan\mu$ = 26.6°. The ball, released at
# rest, rolls without slipping at $\tfrac57 g\sin\theta$ as long as the friction this
# needs, $\tfrac27 m g \sin\theta$, is within $\mu m g\cos\theta$, i.e. up to
# $\tan\theta = \tfrac72\mu$ (35° for $\mu$ = 0.2); beyond that it slips, at
# $g(\sin\theta - \mu\cos\theta)$. The can rolls more slowly, at $\tfrac23
# g\sin\theta$ (more of its mass is far from its axis), and needs more friction,
# $\tfrac13 m g \sin\theta$: it slips beyond $\tan\theta = 3\mu$ (31°).

# %%
angles = np.arange(0.0, 45.1, 2.5)
accels = []
for degrees in angles:
    th = np.radians(degrees)
    params = flat_scene.params(friction=FRICTION, gravity=(G * np.sin(th), 0.0, -G * np.cos(th)))
    state = flat_scene.state(params, position=[(0, 0, HALF), (0, 1, R), (0, 2, R)],
                             orientation=[UPRIGHT, UPRIGHT, LYING])
    _, traj = rb.rollout(flat_step, params, state, num_steps=flat_steps)  # compiled in section 3
    x = np.asarray(traj.position[:, :, 0])
    accels.append(2 * np.polyfit(np.asarray(traj.time), x, 2)[0])  # (box, ball, can)
box_accel, ball_accel, can_accel = np.transpose(accels)

th = np.radians(angles)
box_theory = np.maximum(G * (np.sin(th) - MU_BOX * np.cos(th)), 0.0)
ball_theory = np.where(np.tan(th) <= 3.5 * MU_BALL, 5 / 7 * G * np.sin(th), G * (np.sin(th) - MU_BALL * np.cos(th)))
can_theory = np.where(np.tan(th) <= 3 * MU_BALL, 2 / 3 * G * np.sin(th), G * (np.sin(th) - MU_BALL * np.cos(th)))
print(f"gravity sweep over {len(angles)} slopes: max |a - closed form| box {np.max(np.abs(box_accel - box_theory)):.1e}"
      f" m/s^2, ball {np.max(np.abs(ball_accel - ball_theory)):.1e} m/s^2, "
      f"can {np.max(np.abs(can_accel - can_theory)):.1e} m/s^2")

# %%
fine = np.radians(np.linspace(0, 45, 451))
fig, ax = plt.subplots(figsize=(7, 4.5))
ax.plot(angles, box_accel, "o", label=f"box, mu = {MU_BOX} (tilted gravity)")
ax.plot(angles, ball_accel, "s", label=f"ball, mu = {MU_BALL} (tilted gravity)")
ax.plot(angles, can_accel, "^", label=f"can, mu = {MU_BALL} (tilted gravity)")
ax.plot([30], [incline_accel], "k*", ms=12, label="box on a tilted plane")
ax.plot(np.degrees(fine), np.maximum(G * (np.sin(fine) - MU_BOX * np.cos(fine)), 0), "k:", lw=1, label="closed forms")
ax.plot(np.degrees(fine), np.where(np.tan(fine) <= 3.5 * MU_BALL, 5 / 7 * G * np.sin(fine),
                                   G * (np.sin(fine) - MU_BALL * np.cos(fine))), "k:", lw=1)
ax.plot(np.degrees(fine), np.where(np.tan(fine) <= 3 * MU_BALL, 2 / 3 * G * np.sin(fine),
                                   G * (np.sin(fine) - MU_BALL * np.cos(fine))), "k:", lw=1)
ax.axvline(np.degrees(np.arctan(MU_BOX)), color="0.6", lw=0.7)
ax.axvline(np.degrees(np.arctan(3.5 * MU_BALL)), color="0.6", lw=0.7)
ax.set(xlabel="slope (deg)", ylabel="acceleration down the slope (m/s²)",
       title="sticking, sliding, rolling and slipping")
ax.legend()
plt.show()

# %% [markdown]
# The box stays put below the friction angle and then follows $g(\sin\theta -
# \mu\cos\theta)$; the tilted plane at 30° and the tilted gravity agree. The ball rolls
# at $\tfrac57 g \sin\theta$ and switches to slipping at 35°, where the two curves meet;
# the can at $\tfrac23 g \sin\theta$, until it slips from 31°.
#
# ## 5 · Newton's cradle
#
# Five touching steel-like balls, $e = 1$, no friction, no gravity (`gravity=None`
# compiles no gravity at all). Launch $k$ of them at 1 m/s into the others: $k$ balls
# leave the far end at 1 m/s and the rest stay still. Solving all contacts as one
# simultaneous impact would not give this: momentum and energy alone allow other
# outcomes, and a simultaneous solve spreads the momentum over the row. jaxrb resolves
# impacts as a sequence of binary collisions, each from the current velocities, which is
# the classic explanation of the cradle (the shock travels through the row faster than
# the balls move).
#
# `rb.contact.resolve_impacts(scene, params, state)` applies this impact law at an
# instant, without a time step: positions stay, velocities jump.

# %%
cradle = rb.Scene([rb.Body(f"b{i}", shape=rb.Sphere(R), mass=1.0) for i in range(5)], contacts="all", gravity=None)
row = np.array([(2 * R * i, 0.0, 0.0) for i in range(5)])
impact = jax.jit(lambda params, state: rb.contact.resolve_impacts(cradle, params, state))
for e, moving in [(1.0, 1), (1.0, 2), (1.0, 3), (0.9, 1)]:
    params = cradle.params(restitution=e, friction=0.0)
    velocity = np.zeros((5, 3))
    velocity[:moving, 0] = 1.0
    after = np.asarray(impact(params, cradle.state(params, position=row, velocity=velocity)).velocity[:, 0])
    print(f"e = {e}, {moving} in:  after = [" + ", ".join(f"{v + 0.0:.4f}" for v in after.round(4))
          + f"]  momentum {after.sum():.6f}  energy {0.5 * after @ after:.6f} J")

# %% [markdown]
# With $e = 1$, one, two and three balls in give one, two and three balls out, with
# momentum and energy kept. With $e = 0.9$ every binary collision leaves a little
# velocity behind, and the momentum spreads along the row. A time step does the same
# (the example `examples/contacts_stack.py` runs the cradle with `rb.rollout`).
#
# ## 6 · A small stack: PGS against the exact normal solve
#
# Bodies stacked on the ground should stay exactly where they are. Every body's weight
# reaches the ground through every contact below it, so the normal impulses are coupled
# along the whole stack. Projected Gauss–Seidel passes the load on one contact at a time;
# with a fixed number of sweeps per step it under-resolves it, the bodies sink into each
# other a little each step, and the penetration correction pushes them back out: the
# stack settles low. The worst case is a heavy body on a light one, where each sweep
# removes only a fraction $m / (M + m)$ of the error. The `"exact"` solver finds all the
# normal impulses at once (a few Newton steps on the LCP), whatever the mass ratio.
#
# The smallest such stack is a 10 kg ball resting on a 0.1 kg ball on the ground, one
# exactly above the other (an unstable balance, but a symmetric one: nothing pushes the
# balls sideways, so they stay aligned). Balls keep this cell quick to compile; the
# example `examples/contacts_stack.py` stacks five boxes.

# %%
column = rb.Scene([rb.Body("light", shape=rb.Sphere(R), mass=LIGHT), rb.Body("heavy", shape=rb.Sphere(R), mass=HEAVY)],
                  ground=rb.Plane(), contacts="all")
column_params = column.params(friction=0.5)
start = np.array([(0.0, 0.0, R), (0.0, 0.0, 3 * R)])
column_state = column.state(column_params, position=start)
fig, ax = plt.subplots(figsize=(7, 4))
for solver in ("exact", "pgs"):
    step = rb.make_step(column, SPLITTING, dt=DT, contact=rb.ContactSettings(solver=solver))
    _, traj = rb.rollout(step, column_params, column_state, num_steps=round(T_STACK / DT))
    sink = -(np.asarray(traj.position[:, :, 2]) - start[:, 2])
    print(f"{solver:<5}: the heavy ball sinks up to {np.max(sink[:, 1]):.1e} m ({sink[-1, 1]:.1e} m at the end), "
          f"the light one {np.max(sink[:, 0]):.1e} m ({HEAVY:g} kg on {LIGHT:g} kg, {T_STACK} s at dt = {DT} s)")
    ax.plot(traj.time, -sink[:, 1] * 1e3, label=f"{solver}: heavy ball")
ax.set(xlabel="time (s)", ylabel="height change (mm)", title=f"{HEAVY:g} kg ball resting on a {LIGHT:g} kg ball")
ax.legend()
plt.show()

# %% [markdown]
# The exact solve holds the stack to round-off ($10^{-11}$ m); PGS with its default 20
# sweeps lets the heavy ball sag by 6 mm and stand 2.2 mm low at the end of the 0.5 s (it
# settles 2.0 mm low by 1.5 s). Boxes behave the same way, less strongly at 1 kg each:
# `examples/contacts_stack.py` runs five 1 kg cubes for 2 s at 1 ms, and the largest
# displacement of any box is $2 \times 10^{-10}$ m down and $4 \times 10^{-7}$ m sideways
# with `"exact"`, against $3 \times 10^{-6}$ m and $6 \times 10^{-6}$ m with PGS (at a 10 ms
# step PGS sinks 0.3 mm). PGS is cheaper per step; for stacks, mass ratios and precise
# resting loads, use
# `ContactSettings(solver="exact")`.
#
# **Next:** `examples/contacts_bounce.py`, `contacts_friction.py` and `contacts_stack.py`
# print these checks as tables, with longer runs.
