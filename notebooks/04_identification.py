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
# # 04 · Identification: fitting mass, inertia, restitution and friction to data
#
# A differentiable simulator turns "which parameters explain my measurements?" into an
# optimisation. `jaxrb.identify` does it with three pieces:
#
# 1. **`FreeParameters`**: which entries of `Params` are free, and unconstrained
#    coordinates that keep every iterate physical (log mass, sigmoid restitution,
#    log-Cholesky pseudo-inertia, so that every inertia satisfies the triangle inequality);
# 2. **`fit`** (optax, Adam by default) and **`fit_least_squares`** (Levenberg–Marquardt);
# 3. **`identifiability`**: the singular values of the sensitivity matrix, the directions
#    the data cannot determine, and the Gauss–Newton covariance $\sigma^2 (J^T J)^{-1}$.
#
# This notebook fits a ball's restitution to noisy bounce heights, fits a tumbling body's
# inertia ratios to gyro readings, and shows what the identifiability report says when the
# data cannot determine a parameter. CI runs it as it is; the sizes are small, and most of
# the time is compilation.

# %%
import jax

jax.config.update("jax_enable_x64", True)  # sensitivities and covariances in float64

import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxrb as rb  # noqa: E402

rng = np.random.default_rng(0)
SAMPLES = 150  # bounce record: 10 ms samples

# %% [markdown]
# ## 1. Restitution from a bouncing ball
#
# The "measurements" are a simulated drop with $e = 0.8$ plus 1 mm of noise. The model is
# the same scene with $e$ free; the time of impact is located inside each step, so the
# heights, and their derivative in $e$, do not depend on the 10 ms step.

# %%
scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
step = rb.make_step(scene, rb.integrators.SemiImplicitEuler(), 1e-2)


def heights(params):
    state = scene.state(params, position=(0.0, 0.0, 1.1))
    return rb.rollout(step, params, state, SAMPLES)[1].position[:, 0, 2]


truth = scene.params(restitution=0.8, dtype=jnp.float64)
measured = heights(truth) + 1e-3 * rng.standard_normal(SAMPLES)
guess = scene.params(restitution=0.4, dtype=jnp.float64)

result = rb.identify.fit(lambda p, d: jnp.mean((heights(p) - d) ** 2), scene, guess, "restitution",
                         data=measured, keep_iterates=True)
print(result)
e_fit = float(result.params.restitution[0])
print(f"e: truth 0.8, fit {e_fit:.6f}, relative error {abs(e_fit / 0.8 - 1):.1e}")

# %%
t = 0.01 * np.arange(1, SAMPLES + 1)
fig, axes = plt.subplots(1, 2, figsize=(10, 3.2))
axes[0].plot(t, measured, ".", ms=3, label="measured (1 mm noise)")
axes[0].plot(t, heights(guess), label="initial guess e = 0.4")
axes[0].plot(t, heights(result.params), label=f"fit e = {e_fit:.4f}")
axes[0].set_xlabel("t (s)")
axes[0].set_ylabel("height (m)")
axes[0].legend(fontsize=8)
axes[1].semilogy(result.loss_history)
axes[1].set_xlabel("Adam step")
axes[1].set_ylabel("mean squared error (m²)")
fig.tight_layout()

# %% [markdown]
# Every iterate was physical: the sigmoid keeps $e$ in $(0, 1)$ whatever Adam does.

# %%
path = np.array([float(p.restitution[0]) for p in result.iterates])
print(f"{len(path)} iterates, e in [{path.min():.4f}, {path.max():.4f}]")
assert np.all((path > 0) & (path < 1))

# %% [markdown]
# ## 2. Inertia ratios from a tumbling body
#
# A body tumbles freely; a gyro reads its body-frame angular velocity every 20 ms with
# 1 mrad/s of noise. The data come from the exact (Jacobi elliptic) solution, not from
# jaxrb. Given the initial angular velocity, the motion depends on the inertia only up to
# a common factor: scaling $I$ scales $L = I\omega$ and leaves $\omega(t)$ unchanged. So
# the fit can find the *ratios*, and the identifiability report must say that the scale
# is undetermined.

# %%
moments, omega0 = np.array([0.1, 0.2, 0.3]), np.array([1.0, 0.3, 2.0])
times = 0.02 * np.arange(1, 61)
exact = rb.exact.torque_free_top(moments, omega0, times)
gyro_data = exact.omega_body + 1e-3 * rng.standard_normal(exact.omega_body.shape)

body = rb.Scene([rb.Body("body", mass=1.0, inertia=(0.2, 0.2, 0.2))], gravity=None)
body_step = rb.make_step(body, rb.integrators.SymplecticSplitting(), 2e-3)


def gyro(params):
    state = body.state(params, body_angular_velocity=omega0)
    _, traj = rb.rollout(body_step, params, state, 10 * len(times), save_every=10)
    return jax.vmap(rb.body_angular_velocity, in_axes=(None, 0))(params, traj)[:, 0]


def residuals(params, data):
    return gyro(params) - data


start = body.params(dtype=jnp.float64).replace(inertia=jnp.asarray(np.diag([0.15, 0.15, 0.2]))[None])
tumble = rb.identify.fit_least_squares(residuals, body, start, "inertia", data=gyro_data)
fitted = np.asarray(tumble.params.inertia[0])
print("fitted inertia (kg m²):\n", fitted.round(5))
print("ratios I2/I1, I3/I1:", (np.diag(fitted)[1:] / fitted[0, 0]).round(4), " truth: [2. 3.]")

# %%
# From the fit's last Jacobian by the chain rule; where a parameter map is flat (1:2:3 is a
# flat plate's, the log-Cholesky map's limit) it linearises the residuals again instead.
# rb.identify.identifiability(residuals, body, params, "inertia", data=...) does the same
# at any params.
report = tumble.identifiability()
print(report)

# %% [markdown]
# The smallest relative singular value is at rounding level, and its direction is the
# inertia itself: the scale. So every moment's standard error is `inf`, but what the data
# do determine keeps a finite one: `report.std_of(quantity)` propagates the covariance to
# any function of the free values (in the order of `report.labels`), here the ratios.

# %%
ratio_std = report.std_of(lambda v: v[1:3] / v[0])  # labels: xx, yy, zz, xy, xz, yz
print("I2/I1, I3/I1:", (np.diag(fitted)[1:] / fitted[0, 0]).round(4), "+-", ratio_std.round(4))

# %%
fig, ax = plt.subplots(figsize=(6, 3))
relative = report.singular_values / report.singular_values[0]
ax.semilogy(np.arange(1, len(relative) + 1), relative, "o-")
ax.axhline(report.rcond, color="k", ls="--", lw=0.8, label="rcond: below is unidentifiable")
ax.set_xlabel("singular value index")
ax.set_ylabel("relative singular value")
ax.set_title("tumbling: sensitivity of the gyro record to the six inertia entries")
ax.legend(fontsize=8)
fig.tight_layout()

# %% [markdown]
# ## 3. What free fall says about mass: nothing
#
# A ball thrown in vacuum follows the same parabola whatever its mass. Asking the report
# about mass and gravity together names mass as the undetermined direction, while gravity
# is measured to a fraction of a percent.

# %%
fall = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
fall_step = rb.make_step(fall, rb.integrators.SemiImplicitEuler(), 1e-2)


def track(params):
    return rb.rollout(fall_step, params, fall.state(params, velocity=(0.5, 0.0, 3.0)), 50)[1].position[:, 0]


fall_truth = fall.params(dtype=jnp.float64)
fall_data = track(fall_truth) + 1e-3 * rng.standard_normal((50, 3))
print(rb.identify.identifiability(lambda p, d: track(p) - d, fall, fall_truth, ["mass", "gravity"], data=fall_data))
