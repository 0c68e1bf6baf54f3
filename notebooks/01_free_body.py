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
# # 01 · A free rigid body, from mass properties to gradients
#
# This notebook is a tour of jaxrb on the simplest rigid body there is: one body, no
# gravity, no contacts. It shows
#
# 1. mass properties of primitive shapes and of a body composed from them;
# 2. a `Scene` (static structure), its `Params` and its `State` (arrays);
# 3. the three integrators on the torque-free asymmetric top, with their order of
#    convergence measured;
# 4. why seed 000's rotation-matrix update needs Gram–Schmidt;
# 5. an ensemble of spins with `jax.vmap`;
# 6. the derivative of a final pose with respect to the inertia with `jax.grad`.
#
# The formulas come from the two lecture notes jaxrb is built on: "seed 000" (rigid-body
# dynamics with the rotation matrix and angular momentum as state, Gram–Schmidt) and
# "seed 001" (systems of particles, inertia of primitive shapes, Newton–Euler).
#
# `T_FINAL` sets the simulated time of every experiment (a multiple of 0.1 s, the largest step
# below); CI runs this notebook as it is.

# %%
import jax

# Accuracy checks need float64. jaxrb never flips this switch itself: it is the user's.
jax.config.update("jax_enable_x64", True)

import equinox as eqx
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jaxrb as rb

T_FINAL = 5.0  # s, simulated time of each experiment; keep it small for CI

# %% [markdown]
# ## 1 · Mass properties
#
# A rigid body's mass distribution enters the dynamics through three numbers and a
# matrix: the mass $M = \sum m_i$, the centre of mass
# $\mathbf{x}_{CM} = \sum m_i \mathbf{x}_i / M$, and the inertia tensor about it,
# $\bar{\mathbf{I}} = \sum -m_i \tilde{\mathbf{r}}_i \tilde{\mathbf{r}}_i$ (seed 000),
# where $\tilde{\mathbf{r}}$ is the cross-product matrix.
#
# For primitive shapes the integrals have closed forms (seed 001's table). jaxrb puts
# every primitive's frame at its centre of mass with its symmetry axis along $z$, and
# takes **half** sizes. Here is a steel cylinder, checked against the table's
# $\tfrac{1}{12} m (3 r^2 + l^2)$ for the transverse moments and $\tfrac12 m r^2$ about
# the axis:

# %%
radius, length = 0.02, 0.10  # m
cylinder = rb.mass_properties(rb.Cylinder(radius=radius, half_length=length / 2), density=7850.0)
m = float(cylinder.mass)
print(f"mass {m:.4f} kg")
print("inertia (kg m^2):\n", np.asarray(cylinder.inertia))
print("seed 001 table:  ", m * (3 * radius**2 + length**2) / 12, "and", m * radius**2 / 2)

# %% [markdown]
# A body made of several parts is *composed*: each part is placed in a common frame
# (`MassProperties.transformed(position, orientation)`), and `rb.inertia.compose` adds the
# masses, finds the common centre of mass, and moves each inertia to it with the
# parallel-axis theorem $\mathbf{I} = \bar{\mathbf{I}}_k + m_k (|\mathbf{d}_k|^2 E -
# \mathbf{d}_k \mathbf{d}_k^T)$.
#
# A hammer: a wooden handle along $z$ and a steel head across it, along $x$.

# %%
handle = rb.inertia.cylinder(mass=0.25, radius=0.015, half_length=0.15)
head_to_x = rb.spatial.quat_from_axis_angle(jnp.array([0.0, 1.0, 0.0]), jnp.pi / 2)
head = rb.inertia.box(mass=0.6, half_extents=jnp.array([0.02, 0.02, 0.06])).transformed(
    position=jnp.array([0.0, 0.0, 0.17]), orientation=head_to_x
)
hammer = rb.inertia.compose([handle, head])
print("mass (kg):", float(hammer.mass))
print("centre of mass (m):", np.asarray(hammer.com))

# The parallel-axis theorem by hand for I_xx, as a check:
d_handle = 0.0 - float(hammer.com[2])
d_head = 0.17 - float(hammer.com[2])
by_hand = (handle.inertia[0, 0] + 0.25 * d_handle**2) + (head.inertia[0, 0] + 0.6 * d_head**2)
print("I_xx composed:", float(hammer.inertia[0, 0]), " by hand:", float(by_hand))

# %% [markdown]
# The principal axes diagonalise the inertia, $\mathbf{I} = \mathbf{A} \mathbf{I}_O
# \mathbf{A}^T$ (seed 001). `rb.principal_axes` returns the moments in ascending order and
# a rotation whose columns are the axes:

# %%
moments, axes = rb.principal_axes(hammer.inertia)
print("principal moments (kg m^2):", np.asarray(moments))
print("axes (columns):\n", np.round(np.asarray(axes), 12) + 0.0)  # + 0.0 turns -0 into 0

# %% [markdown]
# ## 2 · Scene, Params, State
#
# A `Scene` is the *static* description: which bodies, which force models. Changing it
# recompiles. `Params` (mass, inertia, gravity, …) and `State` (position, orientation
# quaternion, velocity, angular momentum, time) are pytrees of arrays with a leading body
# axis; changing their values never recompiles, and you can differentiate with respect to
# them.
#
# The state holds the angular momentum $\mathbf{L}$, as in seed 000, not the angular
# velocity: `scene.state` turns the spin you give it into $\mathbf{L} = \mathbf{I}
# \boldsymbol{\omega}$, and `rb.angular_velocity` recovers $\boldsymbol{\omega} =
# \mathbf{I}^{-1} \mathbf{L}$ with $\mathbf{I}^{-1} = \mathbf{A} \bar{\mathbf{I}}^{-1}
# \mathbf{A}^T$.
#
# From here on the body is the classic torque-free asymmetric top:
# $\bar{\mathbf{I}} = \mathrm{diag}(1, 2, 3)$ kg m², $\boldsymbol{\omega}_0 = (-0.3, 0.9,
# -0.5)$ rad/s in the body frame.

# %%
scene = rb.Scene([rb.Body("top", mass=1.0, inertia=(1.0, 2.0, 3.0))], gravity=None)
params = scene.params()
omega0 = np.array([-0.3, 0.9, -0.5])
state0 = scene.state(params, body_angular_velocity=omega0)

print(params)
print(state0)
print("L (world):", np.asarray(state0.angular_momentum[0]))
print("omega (world):", np.asarray(rb.angular_velocity(params, state0)[0]))
print("kinetic energy (J):", float(rb.kinetic_energy(params, state0)[0]))

# %% [markdown]
# ## 3 · Three integrators and their order
#
# `rb.make_step(scene, integrator, dt)` returns a pure function `step(params, state) ->
# state`; `rb.rollout` runs it as one compiled `lax.scan`.
#
# * `ExplicitEuler` (seed 000): $\mathbf{A} \leftarrow \mathbf{A} + \Delta t\,
#   \tilde{\boldsymbol{\omega}} \mathbf{A}$, $\mathbf{L} \leftarrow \mathbf{L} + \Delta t\,
#   \boldsymbol{\tau}$, then Gram–Schmidt on $\mathbf{A}$;
# * `SemiImplicitEuler` (seed 001): $\mathbf{L}_{n+1} = \mathbf{L}_n + \Delta t\,
#   \boldsymbol{\tau}$, $\boldsymbol{\omega}_{n+1} = \mathbf{I}^{-1} \mathbf{L}_{n+1}$, then
#   rotate by the angle $\lVert\boldsymbol{\omega}_{n+1}\rVert \Delta t$ about
#   $\boldsymbol{\omega}_{n+1}$;
# * `RK4`: the classical fourth-order Runge–Kutta method on $(\mathbf{x}, \mathbf{q},
#   \mathbf{v}, \mathbf{L})$.
#
# To measure the order, we run each integrator to `T_FINAL` with several step sizes $h$
# and compare the final attitude with an RK4 run at a much finer step. The error is the
# angle of the rotation between the two attitudes. An order-$p$ method has error
# $\propto h^p$: a line of slope $p$ on log–log axes.

# %%
def final_state(integrator, h, state=state0, t_final=T_FINAL):
    steps = round(t_final / h)
    # Every run must end at t_final: a T_FINAL that is not a whole number of steps of h had
    # ended the h = 0.1 s run at 5.0 s against the others' 5.05 s (orders of 8 and 1.5).
    assert abs(steps * h - t_final) < 1e-9 * t_final, f"T_FINAL = {t_final} s must be a whole number of {h} s steps"
    step = rb.make_step(scene, integrator, dt=h)
    final, _ = rb.rollout(step, params, state, num_steps=steps)
    return final


reference = rb.rotation_matrix(final_state(rb.integrators.RK4(), 1e-3))
integrators = {
    "ExplicitEuler": rb.integrators.ExplicitEuler(),
    "SemiImplicitEuler": rb.integrators.SemiImplicitEuler(),
    "RK4": rb.integrators.RK4(),
}
steps = np.array([0.1, 0.05, 0.025, 0.0125])
errors = {
    name: np.array([
        float(rb.spatial.rotation_angle(rb.rotation_matrix(final_state(integrator, h)), reference)[0])
        for h in steps
    ])
    for name, integrator in integrators.items()
}
for name, err in errors.items():
    order = np.polyfit(np.log(steps), np.log(err), 1)[0]
    print(f"{name:<18} errors (rad) {np.array2string(err, formatter={'float': '{:.2e}'.format})}"
          f"  fitted order {order:.2f}")

# %%
fig, ax = plt.subplots(figsize=(6, 4.5))
for name, err in errors.items():
    ax.loglog(steps, err, "o-", label=name)
for slope, anchor in [(1, errors["ExplicitEuler"][-1]), (4, errors["RK4"][-1])]:
    ax.loglog(steps, anchor * (steps / steps[-1]) ** slope, "k:", lw=1)
    ax.annotate(f"slope {slope}", (steps[0], anchor * (steps[0] / steps[-1]) ** slope),
                textcoords="offset points", xytext=(-45, 5))
ax.set_xticks(steps, [f"{h:g}" for h in steps], minor=False)
ax.minorticks_off()
ax.set_xlabel("step size h (s)")
ax.set_ylabel("attitude error at T_FINAL (rad)")
ax.set_title("torque-free asymmetric top, I = diag(1, 2, 3)")
ax.legend()
plt.show()

# %% [markdown]
# Both Euler methods are first order (explicit Euler's error ratio creeps towards 2 as
# $h$ shrinks; its first point is not yet in the asymptotic regime) and RK4 is fourth
# order: halving $h$ divides its error by 16. None of them changes
# $\mathbf{L}$ at all here: with no torque, $\mathbf{L} \leftarrow \mathbf{L} + \Delta t
# \cdot 0$ is exact, so every error above is in the attitude.

# %% [markdown]
# ## 4 · The rotation matrix drifts off SO(3) without Gram–Schmidt
#
# Seed 000 warns that $\mathbf{A} \leftarrow \mathbf{A} + \Delta t\,
# \tilde{\boldsymbol{\omega}} \mathbf{A}$ does not keep $\mathbf{A}$ orthonormal: each
# step stretches the directions perpendicular to $\boldsymbol{\omega}$ by
# $\sqrt{1 + \lVert\boldsymbol{\omega}\rVert^2 \Delta t^2}$, and the errors accumulate. The
# cure it gives is Gram–Schmidt: $\mathbf{b}_1 = \mathbf{a}_1 / |\mathbf{a}_1|$,
# $\mathbf{b}_2 \propto \mathbf{a}_2 - (\mathbf{b}_1 \cdot \mathbf{a}_2) \mathbf{b}_1$,
# $\mathbf{b}_3 = \mathbf{b}_1 \times \mathbf{b}_2$. `ExplicitEuler(reorthonormalize=False)`
# lets you watch the drift; the integrator carries $\mathbf{A}$ in `State.rotation`.

# %%
h = 0.01
fig, ax = plt.subplots(figsize=(6, 4))
for reorthonormalize in (False, True):
    step = rb.make_step(scene, rb.integrators.ExplicitEuler(reorthonormalize=reorthonormalize), dt=h)
    _, traj = rb.rollout(step, params, state0, num_steps=round(T_FINAL / h))
    a = traj.rotation[:, 0]  # (T, 3, 3)
    defect = jnp.linalg.norm(jnp.swapaxes(a, -1, -2) @ a - jnp.eye(3), axis=(-2, -1))
    label = "with Gram-Schmidt" if reorthonormalize else "without Gram-Schmidt"
    ax.semilogy(traj.time, jnp.maximum(defect, 1e-17), label=label)
    print(f"{label:<22} ||A^T A - E|| at T_FINAL = {float(defect[-1]):.2e}")

# Two directions are stretched, so the Frobenius norm is about sqrt(2) ((1 + |omega h|^2)^n - 1).
omega_sq = float(jnp.sum(rb.angular_velocity(params, state0) ** 2))
times = np.asarray(traj.time)
estimate = np.sqrt(2) * ((1 + omega_sq * h**2) ** (times / h) - 1)
ax.semilogy(times, estimate, "k:", lw=1, label=r"$\sqrt{2}\,((1 + |\omega h|^2)^n - 1)$")
print(f"estimate sqrt(2) ((1 + |omega h|^2)^n - 1) = {estimate[-1]:.2e}")
ax.set_xlabel("time (s)")
ax.set_ylabel(r"$\|A^T A - E\|_F$")
ax.set_title(f"seed 000's explicit Euler, h = {h} s")
ax.legend()
plt.show()

# %% [markdown]
# Without reorthonormalisation the defect grows steadily, at the rate the stretch
# factor predicts; with it, $\mathbf{A}$ stays a rotation to round-off.

# %% [markdown]
# ## 5 · An ensemble with `jax.vmap`: how long until the top flips?
#
# Spin about the *intermediate* axis is unstable (the Dzhanibekov effect, shown on a
# T-handle in `examples/tumbling.py`). A small wobble $\varepsilon$ about the other axes
# grows like $e^{\lambda t}$ with
# $\lambda = \Omega \sqrt{(I_2 - I_1)(I_3 - I_2) / (I_1 I_3)}$, so the first flip comes
# after about $\lambda^{-1} \ln(C/\varepsilon)$: ten times smaller a wobble buys only
# $\ln 10 / \lambda$ more seconds.
#
# `jax.vmap` runs a whole ensemble of initial spins as one batched computation. jaxrb's
# functions describe a single world; the batch axis comes from `vmap`.

# %%
spin = 3.0  # rad/s about the intermediate axis
wobbles = jnp.logspace(-5, -1, 16)
h = 0.01


def first_flip_time(wobble):
    omega = spin * jnp.stack([wobble, 1.0, wobble])
    state = scene.state(params, body_angular_velocity=omega)  # traced: no Python checks
    step = rb.make_step(scene, rb.integrators.RK4(), dt=h)
    _, traj = rb.rollout(step, params, state, num_steps=round(2 * T_FINAL / h))
    omega_2 = jax.vmap(rb.body_angular_velocity, in_axes=(None, 0))(params, traj)[:, 0, 1]
    # time of the first sign change of omega_2 (the end time if there is none)
    return jnp.where(jnp.any(omega_2 < 0), traj.time[jnp.argmax(omega_2 < 0)], jnp.inf)


flip = jax.jit(jax.vmap(first_flip_time))(wobbles)
lam = spin * np.sqrt((2 - 1) * (3 - 2) / (1 * 3))
flipped = np.isfinite(flip)
slope = np.polyfit(np.log(wobbles[flipped]), flip[flipped], 1)[0]
print(f"flips found for {flipped.sum()} of {len(wobbles)} wobbles")
print(f"fitted d t_flip / d ln(eps) = {slope:.4f} s,  theory -1/lambda = {-1 / lam:.4f} s")

# %%
fig, ax = plt.subplots(figsize=(6, 4))
ax.semilogx(wobbles[flipped], flip[flipped], "o", label="jaxrb, RK4 (one vmap)")
theory = flip[flipped][-1] - np.log(wobbles[flipped] / wobbles[flipped][-1]) / lam
ax.semilogx(wobbles[flipped], theory, "k:", label=r"slope $-1/\lambda$")
ax.set_xlabel(r"relative wobble $\varepsilon$")
ax.set_ylabel("time of the first flip (s)")
ax.set_title(r"spin $\Omega$ = 3 rad/s about the intermediate axis")
ax.legend()
plt.show()

# %% [markdown]
# ## 6 · Gradients with `jax.grad`
#
# Every step is a pure, differentiable function of `(params, state)`, so a rollout is
# too. How does the final pose depend on the inertia? Take as the output the world
# $z$-component of the body's first axis at `T_FINAL`, i.e. $A_{31}$, for a body that
# starts with the same spin $\boldsymbol{\omega}_0$ whatever its inertia (the state is
# built inside the function, so $\mathbf{L}_0 = \mathbf{I} \boldsymbol{\omega}_0$ depends
# on the inertia too). `jax.grad` gives the derivative with respect to every entry of
# `Params` at once; we check two of them against central finite differences.

# %%
h = 0.01
step = rb.make_step(scene, rb.integrators.RK4(), dt=h)


def final_a31(params):
    state = scene.state(params, body_angular_velocity=omega0)
    final, _ = rb.rollout(step, params, state, num_steps=round(T_FINAL / h))
    return rb.rotation_matrix(final)[0, 2, 0]


grads = jax.jit(jax.grad(final_a31))(params)
print("d A31 / d inertia (1/(kg m^2)):\n", np.asarray(grads.inertia[0]))

final_a31_jit = jax.jit(final_a31)
eps = 1e-6  # kg m^2: central differences, error ~ eps^2 (truncation) + 1e-16 / eps (round-off)
for i in (0, 1):
    bump = jnp.zeros((1, 3, 3)).at[0, i, i].set(eps)
    plus = final_a31_jit(eqx.tree_at(lambda p: p.inertia, params, params.inertia + bump))
    minus = final_a31_jit(eqx.tree_at(lambda p: p.inertia, params, params.inertia - bump))
    fd = float(plus - minus) / (2 * eps)
    print(f"I[{i},{i}]: grad {float(grads.inertia[0, i, i]):+.8f}   finite difference {fd:+.8f}")

# %% [markdown]
# The two agree to the finite difference's own accuracy. The same pattern, a loss on
# a rollout differentiated with respect to `Params`, is the basis of fitting mass,
# inertia and the other physical parameters to measured motion.
#
# **Next:** `examples/tumbling.py` builds a T-handle from two cylinders and shows its
# Dzhanibekov flips with the period predicted by Jacobi's elliptic functions.
