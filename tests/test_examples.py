"""Smoke-and-physics tests of the runnable material: examples/tumbling.py and the notebooks.

The example is imported from its path and run with ``--quick``; its flip times are checked
against an independent solution of Euler's equations (scipy DOP853) and the closed form
(Jacobi elliptic functions), and its T-handle inertia against the parallel-axis theorem
done by hand. The notebook is converted with jupytext and executed with nbclient, and
the numbers it prints (convergence orders, gradient vs finite differences) are checked.
"""

from __future__ import annotations

import importlib.util
import math
import os
import pathlib
import re
import sys

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.special import ellipk

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tumbling():
    path = ROOT / "examples" / "tumbling.py"
    spec = importlib.util.spec_from_file_location("tumbling_example", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up here
    spec.loader.exec_module(module)
    yield module
    sys.modules.pop(spec.name, None)


@pytest.fixture(scope="module")
def quick_run(tumbling, tmp_path_factory):
    out = tmp_path_factory.mktemp("tumbling")
    return tumbling.main(["--quick", "--out", str(out)])


def _euler_equations_flip_times(moments, omega0, t_final):
    """Zero crossings of omega_2 for I w' = -w x I w (principal frame), DOP853 at 1e-13."""
    inertia = np.asarray(moments, dtype=float)

    def rhs(_, w):
        return -np.cross(w, inertia * w) / inertia

    def crossing(_, w):
        return w[1]

    sol = solve_ivp(rhs, (0.0, t_final), np.asarray(omega0, dtype=float), method="DOP853",
                    rtol=1e-13, atol=1e-15, events=crossing)
    assert sol.status == 0, sol.message
    return sol.t_events[0]


def test_quick_run_writes_plot_and_finds_flips(quick_run):
    assert quick_run.plot.is_file()
    assert quick_run.plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # 4 s of simulated time at ~1.3 s between flips.
    assert len(quick_run.flip_times) >= 2
    assert set(quick_run.runs) == {"RK4", "SemiImplicitEuler", "ExplicitEuler"}


def test_main_prints_readable_summary(tumbling, tmp_path, capsys):
    tumbling.main(["--quick", "--t-final", "1.0", "--dt", "2e-3", "--out", str(tmp_path / "new")])
    text = capsys.readouterr().out
    assert "principal moments (kg m^2) =" in text
    assert "flip times (s): 0.78" in text
    assert re.search(r"RK4\s+max \|dE/E\| = \S+, max \|dL\|/\|L\| = 0\.0e\+00", text)
    assert (tmp_path / "new" / "tumbling.png").is_file()  # --out is created


def test_flip_period_matches_scipy_and_closed_form(quick_run, tumbling):
    reference = _euler_equations_flip_times(
        quick_run.moments, quick_run.omega0_principal, float(quick_run.runs["RK4"].times[-1])
    )
    assert len(reference) == len(quick_run.flip_times)
    # Flip times: RK4 at dt = 1e-3 plus linear interpolation of omega_2 between samples.
    # The flips are near a separatrix, where timing is sensitive to the energy error
    # (1e-10 here); measured agreement is 6e-7 s by the third flip.
    np.testing.assert_allclose(quick_run.flip_times, reference, rtol=0, atol=5e-6)
    # The period (time between flips) to 1e-6 relative; measured 2.4e-7.
    interval_scipy = float(np.mean(np.diff(reference)))
    assert quick_run.flip_interval == pytest.approx(interval_scipy, rel=1e-6)

    # The closed form with scipy's K agrees with DOP853 to its tolerance, and the
    # example's own AGM evaluation of K agrees with scipy's.
    i1, i2, i3 = quick_run.moments
    w = quick_run.omega0_principal
    two_e = float(np.sum(quick_run.moments * w**2))
    l_sq = float(np.sum((quick_run.moments * w) ** 2))
    a = (i3 - i2) * (l_sq - two_e * i1)
    b = (i2 - i1) * (two_e * i3 - l_sq)
    closed_form = 2.0 * ellipk(min(a, b) / max(a, b)) / math.sqrt(max(a, b) / (i1 * i2 * i3))
    assert interval_scipy == pytest.approx(closed_form, rel=1e-9)
    assert quick_run.predicted_flip_interval == pytest.approx(closed_form, rel=1e-12)


def test_conservation_reported_by_the_example(quick_run):
    for run in quick_run.runs.values():
        # Torque-free, L is the state and L <- L + dt * 0: exactly constant in every method.
        assert np.max(run.momentum_drift) == 0.0, run.name
        assert np.all(np.isfinite(run.energy_drift)), run.name
    # RK4 at |omega| dt = 0.0126 over 4 s: measured max |dE/E| = 1.3e-10; 1e-8 leaves margin.
    assert np.max(np.abs(quick_run.runs["RK4"].energy_drift)) < 1e-8


def test_t_handle_inertia_by_the_parallel_axis_theorem(tumbling, quick_run):
    """Principal moments of the T-handle, composed by hand from the cylinder formulas."""
    t = tumbling
    rho = t.STEEL_DENSITY
    r_s, h_s, r_h, h_h = t.SHAFT_RADIUS, t.SHAFT_HALF_LENGTH, t.HANDLE_RADIUS, t.HANDLE_HALF_LENGTH
    m_s = rho * math.pi * r_s**2 * 2 * h_s
    m_h = rho * math.pi * r_h**2 * 2 * h_h
    z_h = h_s + r_h  # height of the handle's axis above the shaft's centre
    z_cm = m_h * z_h / (m_s + m_h)
    d_s, d_h = z_cm, z_h - z_cm
    shaft_transverse = m_s * (r_s**2 / 4 + (2 * h_s) ** 2 / 12)  # seed 001: m (3r^2 + l^2)/12
    handle_transverse = m_h * (r_h**2 / 4 + (2 * h_h) ** 2 / 12)
    about_z = m_s * r_s**2 / 2 + handle_transverse  # shaft axis: no offsets
    about_x = shaft_transverse + m_s * d_s**2 + m_h * r_h**2 / 2 + m_h * d_h**2  # along handle
    about_y = shaft_transverse + m_s * d_s**2 + handle_transverse + m_h * d_h**2
    np.testing.assert_allclose(quick_run.moments, sorted([about_x, about_y, about_z]), rtol=1e-12)
    # The spin is about the intermediate axis, which for this handle is x (along the bar).
    assert sorted([about_x, about_y, about_z])[1] == about_x
    np.testing.assert_allclose(np.abs(quick_run.axes[:, 1]), [1.0, 0.0, 0.0], atol=1e-12)


def test_flip_times_interpolates_sign_changes(tumbling):
    times = np.linspace(0.0, 10.0, 2001)
    # sin changes sign at pi, 2pi, 3pi; linear interpolation error ~ h^3/12 * |sin'''|.
    found = tumbling.flip_times(times, np.sin(times))
    np.testing.assert_allclose(found, [math.pi, 2 * math.pi, 3 * math.pi], atol=1e-7)
    assert tumbling.flip_times(times, 1.0 + 0.0 * times).size == 0


def _notebook_text(nb) -> str:
    chunks = []
    for cell in nb.cells:
        for output in cell.get("outputs", []):
            if output.get("output_type") == "stream":
                chunks.append(output["text"])
    return "".join(chunks)


def _execute_notebook(name: str, tmp_path) -> str:
    """Run notebooks/<name> (jupytext source) in a fresh kernel; return what it printed."""
    jupytext = pytest.importorskip("jupytext")
    nbclient = pytest.importorskip("nbclient")
    nb = jupytext.read(ROOT / "notebooks" / name)
    client = nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    # The kernel runs on XLA's default flags, as a user's notebook does, not on the older
    # fusion emitters this suite compiles with (see conftest): the suite's own processes
    # would not see a miscompilation of the default emitters (one crashed a contact scene,
    # benchmarks/README.md, "An XLA:CPU crash in the contact step").
    env = {key: value for key, value in os.environ.items() if key != "XLA_FLAGS"}
    client.execute(env=env)  # raises CellExecutionError, with the traceback, if any cell fails
    return _notebook_text(nb)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["01_free_body.py"])
def test_notebook_executes(name, tmp_path):
    text = _execute_notebook(name, tmp_path)

    # Convergence orders fitted in the notebook (measured 1.15, 1.00, 4.03).
    orders = dict(re.findall(r"^(\w+)\s+errors .* fitted order ([\d.]+)$", text, flags=re.M))
    assert set(orders) == {"ExplicitEuler", "SemiImplicitEuler", "RK4"}
    assert 0.9 < float(orders["ExplicitEuler"]) < 1.3
    assert 0.9 < float(orders["SemiImplicitEuler"]) < 1.1
    assert 3.8 < float(orders["RK4"]) < 4.2
    # jax.grad of the final pose against central finite differences (measured to 1e-8).
    pairs = re.findall(r"grad ([-+\d.]+)\s+finite difference ([-+\d.]+)", text)
    assert len(pairs) == 2
    for grad, fd in pairs:
        assert float(grad) == pytest.approx(float(fd), abs=1e-6)
    # The vmap ensemble's flip-time slope against -1/lambda (measured 0.1 %).
    slope, theory = map(float, re.search(r"= (-[\d.]+) s,\s+theory -1/lambda = (-[\d.]+) s",
                                         text).groups())
    assert slope == pytest.approx(theory, rel=0.02)


@pytest.mark.slow
def test_notebook_02_executes(tmp_path):
    """notebooks/02_speed_vs_accuracy.py runs, and the numbers it prints obey the physics."""
    text = _execute_notebook("02_speed_vs_accuracy.py", tmp_path)
    names = {"ExplicitEuler", "SemiImplicitEuler", "ImplicitGyroscopic", "ImplicitMidpoint",
             "SymplecticSplitting", "SymmetricTopSplitting", "RK4", "RKMK4"}

    def table(key):
        rows = re.findall(rf"^{key} (\w+) (\S+)$", text, flags=re.M)
        return {name: float(value) for name, value in rows}

    # Fitted convergence orders on the asymmetric top, h = 0.01 ... 0.0025, T = 10 s,
    # against the closed form (measured 1.009, 1.027, 0.996, 2.000, 2.000, 4.001, 4.003).
    # +-0.2 leaves room for a pre-asymptotic first point, not for a wrong order.
    orders = table("ORDER")
    assert set(orders) == names
    nominal = {"ExplicitEuler": 1, "SemiImplicitEuler": 1, "ImplicitGyroscopic": 1, "ImplicitMidpoint": 2,
               "SymplecticSplitting": 2, "SymmetricTopSplitting": 2, "RK4": 4, "RKMK4": 4}
    for name, order in orders.items():
        assert abs(order - nominal[name]) <= 0.2, (name, order)

    # Long run, h = 0.01 s (|omega| h = 0.011), 2e4 steps: max |E - E0| / E0.
    energy = table("ENERGY")
    assert set(energy) == names
    assert energy["ImplicitMidpoint"] <= 1e-12  # conserved to the Newton tolerance; measured 1.3e-14
    assert energy["SymplecticSplitting"] <= 1e-6  # bounded O(h^2) error; measured 1.5e-7
    assert energy["SymmetricTopSplitting"] <= 1e-5  # bounded O(h^2) error; measured 1.7e-6
    assert energy["RK4"] <= 1e-8 and energy["RKMK4"] <= 1e-8  # O(h^4) drift; measured 1.2e-10, 9.7e-11
    final = table("ENERGY_FINAL")
    assert final["SemiImplicitEuler"] > 0.0  # drifts up, towards minor-axis spin (docstring); +0.60
    assert final["ImplicitGyroscopic"] < 0.0  # backward Euler is dissipative; measured -0.30
    # World L is the state and the torque is 0: exactly conserved except by ImplicitGyroscopic,
    # which rebuilds L = A I w from its solve (measured 0.12).
    momentum = table("MOMENTUM")
    assert set(momentum) == names
    assert all(momentum[name] == 0.0 for name in names - {"ImplicitGyroscopic"}), momentum
    assert momentum["ImplicitGyroscopic"] > 0.0

    # Fast spin: |omega| h = 0.1 ... 2. With L exact and the attitude a rotation the energy stays in
    # [|L|^2 / 2 I_3, |L|^2 / 2 I_1], i.e. E / E0 - 1 <= |L|^2 / (2 I_1 E0) - 1 for every method but
    # ImplicitGyroscopic (whose energy falls). SemiImplicitEuler reaches the bound: minor-axis spin.
    moments = np.array([1.0, 2.0, 3.0])
    omega0 = np.array([-0.3, 0.9, -0.5])
    upper = np.sum((moments * omega0) ** 2) / (moments[0] * np.sum(moments * omega0**2)) - 1.0  # 1.268
    extreme = re.findall(r"^EXTREME (\w+) (\S+) (\S+) (\S+)$", text, flags=re.M)
    assert len(extreme) == len(names) * 4
    for name, spin, energy_error, attitude in extreme:
        assert math.isfinite(float(attitude)), (name, spin)
        assert float(energy_error) <= upper * (1 + 1e-9), (name, spin, energy_error)
        if name == "ImplicitMidpoint":  # energy to the Newton tolerance up to |omega| h = 2; measured 1.6e-15
            assert float(energy_error) <= 1e-12, (spin, energy_error)

    # A symmetric top is SymmetricTopSplitting's exact case, at any step (measured 7.6e-15 rad
    # against SymplecticSplitting's 5.0e-2 after 100 steps of 0.1 s); nearly symmetric, two
    # orders of magnitude closer (measured 1.7e-4 against 4.9e-2).
    symmetric = {(label, name): float(error) for label, name, error in
                 re.findall(r"^SYMMETRIC_TOP (\w+) (\w+) (\S+)$", text, flags=re.M)}
    assert len(symmetric) == 4
    assert symmetric["symmetric", "SymmetricTopSplitting"] <= 1e-12
    assert symmetric["symmetric", "SymplecticSplitting"] >= 1e-3
    assert symmetric["nearly", "SymmetricTopSplitting"] <= symmetric["nearly", "SymplecticSplitting"] / 20

    # One step of the flat body at |omega| h = 2: the linearised (single Newton) step gains energy
    # (measured x377), the converged solve loses it (x0.617), as every solution of the equation must.
    single = float(re.search(r"^SINGLE_NEWTON_ENERGY_RATIO (\S+)$", text, flags=re.M).group(1))
    converged = float(re.search(r"^CONVERGED_ENERGY_RATIO (\S+)$", text, flags=re.M).group(1))
    assert single > 1.0
    assert converged <= 1.0
    # Over 2 bodies x 64 directions x 4 spins x 200 steps, no step whose implicit equation was
    # solved gained more than round-off (measured 2.2e-15).
    # The default (continuation + safeguard) solve never gains energy, on any step at any
    # |omega| h of the audit (measured 3e-15, round-off).
    rise = float(re.search(r"^DEFAULT_MAX_STEP_RISE (\S+)$", text, flags=re.M).group(1))
    assert rise <= 1e-12
    # It solved the full-step equation on every step up to |omega| h = 1; beyond, a few steps
    # take the shorter-step fallback (reported, not asserted, so a better solver does not fail this).
    fallback = {float(spin): int(count) for spin, count in
                re.findall(r"^FALLBACK_STEPS (\S+) (\d+) \d+$", text, flags=re.M)}
    assert set(fallback) == {0.1, 0.5, 1.0, 2.0}
    assert fallback[0.1] == fallback[0.5] == fallback[1.0] == 0

    # Adaptive solves to T = 10 s: the error falls as rtol tightens, and stays within 100 rtol
    # (the global error is ~rtol times the horizon in natural units, |omega| T ~ 10; measured <= 15 rtol).
    adaptive = re.findall(r"^ADAPTIVE (\w+) (\S+) (\d+) (\S+)$", text, flags=re.M)
    assert {solver for solver, *_ in adaptive} == {"Tsit5", "Dopri8"}
    for solver in ("Tsit5", "Dopri8"):
        rows = [(float(rtol), int(steps), float(error)) for s, rtol, steps, error in adaptive if s == solver]
        assert len(rows) == 4
        assert all(a[2] > b[2] and a[1] < b[1] for a, b in zip(rows[:-1], rows[1:], strict=True)), rows
        assert all(error <= 100 * rtol for rtol, _, error in rows), rows
    # Dense output between the steps, Dopri8 at rtol 1e-10: measured 2.5e-8 rad at worst.
    dense = float(re.search(r"^DENSE Dopri8 \S+ steps \d+ max_between (\S+) ", text, flags=re.M).group(1))
    assert dense <= 1e-6

    # rb.tradeoff on the box-and-capsule scene: the cheapest run within 1e-6 rad is one of the
    # integrators at one of the step sizes swept (measured: RK4 at 0.005 s, the only run within it).
    cheapest = re.search(r"^CHEAPEST (\w+) (\S+)$", text, flags=re.M)
    assert cheapest is not None, "no run reached the tolerance"
    assert cheapest.group(1) in names
    assert float(cheapest.group(2)) in (0.02, 0.01, 0.005)


# ----------------------------------------------------------------------------- contacts


def _run_example(name: str, argv: list[str]):
    """Import examples/<name>.py from its path and call its ``main(argv)``."""
    spec = importlib.util.spec_from_file_location(f"{name}_example", ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
        return module.main(argv)
    finally:
        sys.modules.pop(spec.name, None)


def test_contacts_bounce_example_apexes_follow_e_to_the_2n(tmp_path, capsys):
    result = _run_example("contacts_bounce", ["--quick", "--out", str(tmp_path)])
    text = capsys.readouterr().out
    theory = 0.8 ** (2 * np.arange(1, 5))
    np.testing.assert_allclose(result["theory"], theory, rtol=1e-15)
    # The time of impact makes the apexes independent of dt: measured to 7e-16 m at both.
    for name in ("dt=0.01", "dt=1/60"):
        assert len(result[name]) >= 4, name
        np.testing.assert_allclose(result[name][:4], theory, rtol=0, atol=1e-6, err_msg=name)
    assert re.search(r"^ 1\s+0\.640000\s+0\.640000\s+0\.640000$", text, flags=re.M)
    assert "dt=0.01 no TOI" not in result  # the full run only
    assert (tmp_path / "contacts_bounce.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_contacts_friction_example_matches_closed_forms(capsys):
    result = _run_example("contacts_friction", ["--quick"])
    measured, theory = result["measured"], result["theory"]
    assert theory["stop_distance"] == pytest.approx(25 / (2 * 0.5 * 9.81), rel=1e-12)
    assert theory["accel_30"] == pytest.approx(0.6571454, abs=1e-7)
    # Measured at dt = 10 ms: every quantity within 1.1e-6 of its closed form.
    for key in ("stop_time", "stop_distance", "roll_time", "roll_speed", "accel_30"):
        assert measured[key] == pytest.approx(theory[key], abs=1e-4), key
    # Below the friction angle (25 deg < atan 0.5 = 26.6 deg) the box stays: it moved 1.1e-6 m.
    assert abs(measured["accel_25"]) < 1e-4
    assert abs(measured["slide_25"]) < 1e-4
    assert measured["slide_30"] == pytest.approx(0.5 * theory["accel_30"] * 1.5**2, rel=1e-3)  # --quick: 1.5 s
    text = capsys.readouterr().out
    assert re.search(r"^stop_distance\s+2\.5484\d\d\s+2\.548420$", text, flags=re.M)


@pytest.mark.slow
def test_contacts_stack_example_holds_the_stack_and_swings_the_cradle(capsys):
    result = _run_example("contacts_stack", ["--quick"])
    # Exact normal solve: measured 1.6e-12 m of sink and 4.4e-5 m sideways (5 boxes, 0.5 s at 10 ms).
    sink, sideways, _ = result["exact"]
    assert sink < 1e-6 and sideways < 1e-3
    # PGS settles lower (measured 3.3e-4 m at this step, 2026-12-02; 2.4e-3 before box-box
    # contacts preferred faces, jaxrb.collision._box.EDGE_PREFERENCE); bounded only loosely.
    assert 0.0 <= result["pgs"][0] < 0.05
    for moving in (1, 2, 3):  # k balls in, k balls out, at 1 m/s
        expected = np.r_[np.zeros(5 - moving), np.ones(moving)]
        np.testing.assert_allclose(result[f"cradle_{moving}"], expected, atol=1e-9, err_msg=str(moving))
    text = capsys.readouterr().out
    assert re.search(r"^1 in:\s+0\.000\s+0\.000\s+0\.000\s+0\.000\s+1\.000 ", text, flags=re.M)


@pytest.mark.slow
def test_notebook_03_contacts_executes(tmp_path):
    """notebooks/03_contacts.py runs, and what it prints agrees with the closed forms."""
    text = _execute_notebook("03_contacts.py", tmp_path)

    # Bouncing ball at dt = 10 ms: apexes e^(2n) to round-off with the time of impact (measured
    # 7e-16 m over 8 bounces); without it, too high by O(dt) (measured 6.9e-2 m).
    first = re.search(r"^ 1\s+(\S+)\s+(\S+)\s+(\S+)$", text, flags=re.M)
    assert float(first.group(1)) == pytest.approx(0.64, abs=1e-12)
    assert float(first.group(2)) == pytest.approx(0.64, abs=1e-3)
    assert float(first.group(3)) > 0.64 + 1e-3
    with_toi = float(re.search(r"time_of_impact=True: max .* = (\S+) m", text).group(1))
    assert with_toi < 1e-6

    # Sliding box, rolling ball and can, and the 30 deg incline: measured within 1.1e-6 of the
    # closed forms.
    pairs = re.findall(r"([\d.]+) (?:s|m|m/s|m/s\^2) \(closed form (?:5 v0 / 7 = |2 v0 / 3 = )?([\d.]+)", text)
    assert len(pairs) == 7, pairs
    for measured, closed in pairs:
        assert float(measured) == pytest.approx(float(closed), abs=1e-4)
    # The slope sweep by tilted gravity (measured 1.1e-7, 5.4e-14 and 1.4e-7 m/s^2 for the
    # box, the ball and the can).
    box, ball, can = map(float, re.search(r"box (\S+) m/s\^2, ball (\S+) m/s\^2, can (\S+) m/s\^2", text).groups())
    assert box < 1e-4 and ball < 1e-4 and can < 1e-4

    # Newton's cradle, e = 1: k in, k out; momentum and energy kept.
    for moving in (1, 2, 3):
        line = re.search(rf"^e = 1\.0, {moving} in:  after = \[([^\]]*)\]  momentum (\S+)  energy (\S+) J$",
                         text, flags=re.M)
        after = np.array([float(v) for v in line.group(1).split(",")])
        np.testing.assert_allclose(after, np.r_[np.zeros(5 - moving), np.ones(moving)], atol=1e-4)
        assert float(line.group(2)) == pytest.approx(moving, abs=1e-6)
        assert float(line.group(3)) == pytest.approx(moving / 2, abs=1e-6)

    # Heavy ball on a light one: the exact solve holds it (measured 9e-12 m); PGS is reported.
    exact = float(re.search(r"^exact: the heavy ball sinks up to (\S+) m", text, flags=re.M).group(1))
    assert exact < 1e-6
    # The markdown beside it quotes PGS's sag (measured 6.1 mm, 2.2 mm low at the end): it had
    # quoted 7 and 4.5 mm long after the solver changed. Kept to the text's figures here.
    sag, end = (float(x) for x in re.search(r"^pgs  : the heavy ball sinks up to (\S+) m \((\S+) m at the end\)",
                                            text, flags=re.M).groups())
    assert 5.5e-3 < sag < 6.5e-3 and 1.9e-3 < end < 2.5e-3, (sag, end)


def test_identification_example_runs_from_its_command_line(capsys):
    """The command line, on its cheapest scenario: each of the five scenarios (at --quick
    sizes) is run, and its recovery checked, in tests/test_identify.py."""
    path = ROOT / "examples" / "identify_parameters.py"
    spec = importlib.util.spec_from_file_location("identify_example", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    errors = module.main(["tumbling", "--quick"])
    assert list(errors) == ["tumbling"] and errors["tumbling"] < 0.01
    out = capsys.readouterr().out
    assert "== tumbling" in out and "largest relative error per scenario: tumbling" in out
    with pytest.raises(SystemExit):
        module.main(["bouncing"])
    assert "unknown scenario(s) ['bouncing']" in capsys.readouterr().err


@pytest.mark.slow
def test_notebook_04_identification_executes(tmp_path):
    text = _execute_notebook("04_identification.py", tmp_path)
    e_fit = float(re.search(r"e: truth 0.8, fit ([0-9.]+)", text).group(1))
    assert abs(e_fit / 0.8 - 1) < 0.01
    ratios = [float(x) for x in re.search(r"ratios I2/I1, I3/I1: \[([0-9. ]+)\]", text).group(1).split()]
    np.testing.assert_allclose(ratios, [2.0, 3.0], rtol=0.01)
    assert text.count("UNIDENTIFIABLE") == 2 and "mass[ball]" in text
