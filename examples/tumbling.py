"""The Dzhanibekov effect: a spinning T-handle flips over and over, with no torque at all.

A steel T-handle (a wing nut, a tennis racket) is spun about its *intermediate* principal
axis, the one whose moment of inertia lies between the other two. Spin about the smallest
or the largest axis is stable; spin about the intermediate one is not: a tiny wobble
grows until the handle turns upside down, spins the other way for a while, and flips
back, periodically. Vladimir Dzhanibekov saw it happen to a wing nut on Salyut 7.

This script

1. builds the T-handle's mass properties from two cylinders (seed 001's primitive
   inertias, composed by the parallel-axis theorem) and finds its principal axes;
2. spins it about the intermediate axis with a small perturbation and simulates the
   torque-free motion with RK4, then with the two first-order methods of the seeds;
3. prints the flip times, the flip period (and the closed-form period from Jacobi's
   elliptic functions), and the energy and angular-momentum drift of each integrator;
4. saves a plot of the body-frame angular velocity and of the energy drift.

Run ``python examples/tumbling.py`` (about 10 s on two CPU cores) or
``python examples/tumbling.py --quick`` (a few seconds of simulated time, for CI).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib
import time

import jax

# The example runs in float64 so that the energy error shows the integrator's own
# truncation error (about 1e-9 for RK4 at dt = 1 ms) rather than float32 round-off. jaxrb never sets
# this flag itself; applications like this one choose their precision.
jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxrb as rb  # noqa: E402

# ----------------------------------------------------------------------------- geometry

STEEL_DENSITY = 7850.0  # kg/m^3
SHAFT_RADIUS = 0.004  # m: an 8 mm rod ...
SHAFT_HALF_LENGTH = 0.030  # m: ... 60 mm long, along z
HANDLE_RADIUS = 0.004  # m: the cross bar, 8 mm ...
HANDLE_HALF_LENGTH = 0.025  # m: ... 50 mm long, along x, on top of the shaft

SPIN_RATE = 2.0 * 2.0 * math.pi  # rad/s: two turns per second about the intermediate axis
PERTURBATION = 1e-2  # relative size of the initial spin about the two other axes


def t_handle() -> rb.MassProperties:
    """Mass properties of the T-handle in its construction frame (kg, m, kg m^2).

    The shaft is a solid cylinder along z centred at the origin; the handle is a solid
    cylinder turned onto the x axis and sitting on top of the shaft. ``compose`` moves
    both inertias to the common centre of mass (parallel-axis theorem).
    """
    cylinder_mass = lambda r, h: STEEL_DENSITY * math.pi * r**2 * 2.0 * h  # noqa: E731
    shaft = rb.inertia.cylinder(
        cylinder_mass(SHAFT_RADIUS, SHAFT_HALF_LENGTH), SHAFT_RADIUS, SHAFT_HALF_LENGTH
    )
    # A quarter turn about y takes the cylinder's z axis onto x.
    z_to_x = rb.spatial.quat_from_axis_angle(jnp.array([0.0, 1.0, 0.0]), math.pi / 2)
    handle = rb.inertia.cylinder(
        cylinder_mass(HANDLE_RADIUS, HANDLE_HALF_LENGTH), HANDLE_RADIUS, HANDLE_HALF_LENGTH
    ).transformed(jnp.array([0.0, 0.0, SHAFT_HALF_LENGTH + HANDLE_RADIUS]), z_to_x)
    return rb.inertia.compose([shaft, handle])


# ----------------------------------------------------------------------------- analysis


def flip_times(times: np.ndarray, omega_intermediate: np.ndarray) -> np.ndarray:
    """Times (s) where the spin about the intermediate axis changes sign (linear interpolation)."""
    w0, w1 = omega_intermediate[:-1], omega_intermediate[1:]
    k = np.flatnonzero(np.signbit(w0) != np.signbit(w1))
    return times[k] + (times[k + 1] - times[k]) * w0[k] / (w0[k] - w1[k])


def _complete_elliptic_k(m: float) -> float:
    """``K(m) = pi / (2 AGM(1, sqrt(1 - m)))``, parameter ``m = k^2`` in [0, 1)."""
    a, b = 1.0, math.sqrt(1.0 - m)
    while abs(a - b) > 1e-15 * a:
        a, b = 0.5 * (a + b), math.sqrt(a * b)
    return math.pi / (2.0 * a)


def predicted_flip_interval(moments, omega0_principal) -> float:
    """Time (s) between flips from the closed-form torque-free solution (Landau & Lifshitz §37).

    With ``I1 < I2 < I3``, energy ``E`` and ``L^2``, the spin about the intermediate axis
    is ``omega_2 ∝ sn(rate t, k)``, which changes sign every ``2 K(k^2) / rate``, with
    ``a = (I3 - I2)(L^2 - 2 E I1)``, ``b = (I2 - I1)(2 E I3 - L^2)``,
    ``rate = sqrt(max(a, b) / (I1 I2 I3))`` and ``k^2 = min(a, b) / max(a, b)``.
    """
    i1, i2, i3 = (float(x) for x in moments)
    w = np.asarray(omega0_principal, dtype=float)
    two_e = float(np.sum(np.array([i1, i2, i3]) * w**2))
    l_sq = float(np.sum((np.array([i1, i2, i3]) * w) ** 2))
    a = (i3 - i2) * (l_sq - two_e * i1)
    b = (i2 - i1) * (two_e * i3 - l_sq)
    rate = math.sqrt(max(a, b) / (i1 * i2 * i3))
    return 2.0 * _complete_elliptic_k(min(a, b) / max(a, b)) / rate


@dataclasses.dataclass
class Run:
    """One integrator's trajectory, with the initial state prepended (t = 0 first)."""

    name: str
    dt: float
    times: np.ndarray  # (T,) s
    omega_principal: np.ndarray  # (T, 3) rad/s, body angular velocity on the principal axes
    energy_drift: np.ndarray  # (T,) (E - E0) / E0
    momentum_drift: np.ndarray  # (T,) |L - L0| / |L0|, world frame
    wall_time: float  # s, compile included


@dataclasses.dataclass
class Result:
    moments: np.ndarray  # (3,) kg m^2, ascending
    axes: np.ndarray  # (3, 3) columns: principal axes in the body (construction) frame
    omega0_principal: np.ndarray  # (3,) rad/s
    flip_times: np.ndarray  # (K,) s, RK4
    flip_interval: float  # s, mean time between flips (nan if fewer than 2 flips)
    predicted_flip_interval: float  # s, closed form
    runs: dict[str, Run]
    plot: pathlib.Path


def simulate(name, integrator, scene, params, state, axes, dt, num_steps) -> Run:
    """Roll the scene out with ``integrator`` and reduce the trajectory to NumPy arrays."""
    start = time.perf_counter()
    step = rb.make_step(scene, integrator, dt=dt)
    _, traj = rb.rollout(step, params, state, num_steps=num_steps)
    # Put the initial state in front: rollout returns the states after each step.
    traj = jax.tree.map(
        lambda first, rest: jnp.concatenate([first[None], rest]),
        step.prepare(state),
        traj,
    )
    per_state = jax.vmap(
        lambda s: (rb.body_angular_velocity(params, s)[0], rb.kinetic_energy(params, s)[0]),
    )
    omega_body, energy = jax.block_until_ready(per_state(traj))
    wall_time = time.perf_counter() - start

    momentum = np.asarray(traj.angular_momentum[:, 0])
    energy = np.asarray(energy)
    return Run(
        name=name,
        dt=dt,
        times=np.asarray(traj.time),
        omega_principal=np.asarray(omega_body) @ axes,
        energy_drift=(energy - energy[0]) / energy[0],
        momentum_drift=np.linalg.norm(momentum - momentum[0], axis=-1) / np.linalg.norm(momentum[0]),
        wall_time=wall_time,
    )


def plot(result: Result, path: pathlib.Path) -> None:
    """Save the figure as a PNG with matplotlib's Agg renderer."""
    # A bare Figure draws with Agg without touching pyplot's global backend, so calling
    # main() from a notebook leaves the notebook's plotting set-up alone.
    from matplotlib.figure import Figure

    rk4 = result.runs["RK4"]
    fig = Figure(figsize=(9, 9), layout="constrained")
    top, middle, bottom = fig.subplots(3, 1, sharex=True)
    labels = [f"$\\omega_{i}$ ($I_{i}$ = {m:.2e} kg m$^2$)" for i, m in enumerate(result.moments, 1)]
    for k, (label, color) in enumerate(zip(labels, ["C0", "C1", "C2"], strict=True)):
        top.plot(rk4.times, rk4.omega_principal[:, k], color=color, lw=1.2, label=label)
    for i, t in enumerate(result.flip_times):
        top.axvline(t, color="0.6", lw=0.8, ls="--", label="flip" if i == 0 else None)
    top.set_ylabel("body angular velocity (rad/s)")
    top.set_title(
        f"T-handle spun about its intermediate axis (RK4, dt = {rk4.dt:g} s): "
        f"{len(result.flip_times)} flips"
    )
    top.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)

    for run in result.runs.values():
        middle.plot(run.times, run.omega_principal[:, 1], lw=1.0, label=run.name)
    middle.set_ylabel("$\\omega_2$ (rad/s)")
    middle.set_title("same spin, each integrator: the first-order ones drift to the minor axis")
    middle.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)

    for run in result.runs.values():
        drift = np.abs(run.energy_drift[1:])
        bottom.semilogy(run.times[1:], np.maximum(drift, 1e-17), lw=1.0, label=run.name)
    bottom.set_xlabel("time (s)")
    bottom.set_ylabel("|E - E0| / E0")
    bottom.set_title("kinetic-energy drift (angular momentum is the state: exactly conserved)")
    bound = result.moments[1] / result.moments[0] - 1.0
    bottom.axhline(bound, color="0.6", lw=0.8, ls=":", label="spin about the minor axis")
    bottom.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    fig.savefig(path, dpi=120)


# ----------------------------------------------------------------------------- main


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--t-final", type=float, default=20.0, help="simulated time (s)")
    parser.add_argument("--dt", type=float, default=1e-3, help="time step (s)")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out"),
                        help="directory for the plot (created if missing)")
    parser.add_argument("--quick", action="store_true",
                        help="small run for CI: at most 4 s of simulated time")
    args = parser.parse_args(argv)
    if args.quick:
        args.t_final = min(args.t_final, 4.0)
    if not args.dt > 0 or not args.t_final >= args.dt:
        parser.error("need dt > 0 and t-final >= dt")
    return args


def main(argv=None) -> Result:
    args = parse_args(argv)
    num_steps = round(args.t_final / args.dt)

    mass_properties = t_handle()
    moments, axes = (np.asarray(x) for x in rb.principal_axes(mass_properties.inertia))
    scene = rb.Scene([rb.Body("t_handle", mass_properties=mass_properties)], gravity=None)
    params = scene.params()

    # Spin about the intermediate axis, with a small part about the other two. The
    # principal axes are the columns of `axes`, in the body frame.
    omega0_principal = SPIN_RATE * np.array([PERTURBATION, 1.0, PERTURBATION])
    state = scene.state(params, body_angular_velocity=axes @ omega0_principal)

    fmt = lambda v: "(" + ", ".join(f"{x + 0.0:.4g}" for x in v) + ")"  # noqa: E731 (+0.0: no -0)
    print(f"T-handle: mass = {float(mass_properties.mass) * 1e3:.1f} g, centre of mass "
          f"{fmt(np.asarray(mass_properties.com) * 1e3)} mm above the shaft's centre")
    print("principal moments (kg m^2) = " + ", ".join(f"{m:.4e}" for m in moments))
    print(f"spin: {SPIN_RATE:.3f} rad/s about the intermediate axis {fmt(axes[:, 1])} "
          f"(body frame), {PERTURBATION:g} of it about each of the other two")

    integrators = {
        "RK4": rb.integrators.RK4(),
        "SemiImplicitEuler": rb.integrators.SemiImplicitEuler(),  # seed 001
        "ExplicitEuler": rb.integrators.ExplicitEuler(reorthonormalize=True),  # seed 000
    }
    runs = {
        name: simulate(name, integrator, scene, params, state, axes, args.dt, num_steps)
        for name, integrator in integrators.items()
    }

    rk4 = runs["RK4"]
    flips = flip_times(rk4.times, rk4.omega_principal[:, 1])
    interval = float(np.mean(np.diff(flips))) if len(flips) >= 2 else math.nan
    predicted = predicted_flip_interval(moments, omega0_principal)
    print(f"\nflip times (s): {', '.join(f'{t:.4f}' for t in flips) or 'none'}")
    print(f"time between flips {interval:.7f} s (closed form {predicted:.7f} s, relative "
          f"difference {abs(interval - predicted) / predicted:.1e}); period {2 * interval:.7f} s")

    print(f"\n{num_steps} steps of dt = {args.dt:g} s; drifts are the maximum over the run")
    width = max(len(name) for name in runs)
    for run in runs.values():
        print(f"{run.name:<{width}}  max |dE/E| = {np.max(np.abs(run.energy_drift)):.1e}, "
              f"max |dL|/|L| = {np.max(run.momentum_drift):.1e}   "
              f"({run.wall_time:.1f} s incl. compile)")
    bound = moments[1] / moments[0] - 1.0
    print(f"(L is the state, so it is exact. A drift of {bound:.2f} = I2/I1 - 1 is spin about "
          "the minor axis: at this dt\n the first-order methods lose the flips; see the plot.)")

    args.out.mkdir(parents=True, exist_ok=True)
    result = Result(
        moments=moments,
        axes=axes,
        omega0_principal=omega0_principal,
        flip_times=flips,
        flip_interval=interval,
        predicted_flip_interval=predicted,
        runs=runs,
        plot=args.out / "tumbling.png",
    )
    plot(result, result.plot)
    print(f"\nplot saved to {result.plot}")
    return result


if __name__ == "__main__":
    main()
