"""Coulomb friction against its closed forms: a sliding box, a box on an incline, a rolling ball.

* A 1 kg cube (half-extent 0.1 m) launched at 5 m/s along the ground with mu = 0.5 stops
  after v0 / (mu g) s and v0^2 / (2 mu g) = 2.548 m.
* On a plane tilted by theta it slides down at g (sin theta - mu cos theta) if tan theta >
  mu (30 deg: 0.657 m/s^2) and stays put otherwise (25 deg).
* A ball (radius 0.1 m) launched at v0 with no spin, mu = 0.2, slips until t = 2 v0 / (7
  mu g), then rolls at 5 v0 / 7. Box and ball share a scene, with friction per pair.
Run ``python examples/contacts_friction.py`` (``--quick`` for CI: shorter runs).
"""

import argparse
import math

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxrb as rb  # noqa: E402

G, HALF, RADIUS, DT, V_BOX, V_BALL, MU_BOX, MU_BALL = 9.81, 0.1, 0.1, 1e-2, 5.0, 2.0, 0.5, 0.2
BOX = rb.Body("box", shape=rb.Box((HALF,) * 3), mass=1.0)  # a 0.2 m cube
STEP = dict(integrator=rb.integrators.SymplecticSplitting(), dt=DT, contact=rb.ContactSettings())


def root(t, y):
    """When y (falling linearly, then 0) hits 0, from its last two positive samples. A step's
    contact impulses act once, so its tangential velocity is the step's mean: time t - dt/2."""
    k, t = np.flatnonzero(y > 1e-6 * y[0])[-1], t - DT / 2
    return t[k] + y[k] * (t[k] - t[k - 1]) / (y[k - 1] - y[k])


def flat(t_final):
    scene = rb.Scene([BOX, rb.Body("ball", shape=rb.Sphere(RADIUS), mass=1.0)], ground=rb.Plane(),
                     contacts=[("box", "ground"), ("ball", "ground")])  # box and ball never meet
    params = scene.params(friction={("box", "ground"): MU_BOX, ("ball", "ground"): MU_BALL})
    state = scene.state(params, position=[(0, 0, HALF), (0, 1, RADIUS)], velocity=[(V_BOX, 0, 0), (V_BALL, 0, 0)])
    _, traj = rb.rollout(rb.make_step(scene, **STEP), params, state, num_steps=round(t_final / DT))
    t, v = np.asarray(traj.time), np.asarray(traj.velocity[:, :, 0])
    omega_y = np.asarray(jax.vmap(rb.angular_velocity, in_axes=(None, 0))(params, traj)[:, 1, 1])
    return dict(stop_time=root(t, v[:, 0]), stop_distance=float(traj.position[-1, 0, 0]),
                roll_time=root(t, v[:, 1] - RADIUS * omega_y), roll_speed=v[-1, 1])


def incline(degrees, t_final):
    """Acceleration down the slope (m/s^2): a quadratic fit of the box's displacement along it."""
    th = math.radians(degrees)
    normal, downhill = np.array([-math.sin(th), 0, math.cos(th)]), np.array([-math.cos(th), 0, -math.sin(th)])
    scene = rb.Scene([BOX], ground=rb.Plane(normal=normal), contacts="all")
    params = scene.params(friction=MU_BOX)
    tilt = rb.spatial.quat_from_axis_angle(np.array([0.0, 1.0, 0.0]), -th)  # the box's face on the plane
    state = scene.state(params, position=HALF * normal, orientation=tilt)
    _, traj = rb.rollout(rb.make_step(scene, **STEP), params, state, num_steps=round(t_final / DT))
    s = (np.asarray(traj.position[:, 0]) - HALF * normal) @ downhill
    return 2 * np.polyfit(np.asarray(traj.time), s, 2)[0], s[-1]


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="CI size: 1.5 s runs instead of 3 s")
    t_final = 1.5 if parser.parse_args(argv).quick else 3.0
    out = flat(t_final)
    for degrees in (25, 30):
        out[f"accel_{degrees}"], out[f"slide_{degrees}"] = incline(degrees, t_final)
    theory = dict(stop_time=V_BOX / (MU_BOX * G), stop_distance=V_BOX**2 / (2 * MU_BOX * G),
                  roll_time=2 * V_BALL / (7 * MU_BALL * G), roll_speed=5 * V_BALL / 7, accel_25=0.0,
                  accel_30=G * (math.sin(math.radians(30)) - MU_BOX * math.cos(math.radians(30))))
    print(f"{'quantity':<14} {'measured':>12} {'closed form':>12}   (dt = {DT} s, {t_final} s)")
    for key, value in theory.items():
        print(f"{key:<14} {round(out[key], 6) + 0.0:12.6f} {value:12.6f}")  # + 0.0: no -0
    print(f"box on the 25 deg incline moved {out['slide_25']:.1e} m; on 30 deg {out['slide_30']:.3f} m")
    return {"measured": out, "theory": theory}


if __name__ == "__main__":
    main()
