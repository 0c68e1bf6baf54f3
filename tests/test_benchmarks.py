"""Benchmark scripts must keep running (tiny sizes); their figures are never asserted."""

import importlib.util
import json
import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def load(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("extra", [[], ["--shared-params"]])
def test_free_body_benchmark_quick(tmp_path, extra):
    load("free_body").main(["--quick", "--out", str(tmp_path), *extra])
    stem = "free_body_shared_params" if extra else "free_body"
    record = json.loads((tmp_path / f"{stem}.json").read_text())
    assert {r["integrator"] for r in record["results"]} >= {"ExplicitEuler", "SemiImplicitEuler", "RK4"}
    assert (tmp_path / f"{stem}.png").stat().st_size > 0


def test_free_body_benchmark_quick_on_two_cpu_devices(tmp_path):
    # --devices asks JAX for two CPU devices, which only works before JAX starts: a fresh process.
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "free_body.py"), "--quick", "--devices", "2",
         "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=300, env=env,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    record = json.loads((tmp_path / "free_body_2dev.json").read_text())
    assert record["devices"] == 2 and (tmp_path / "free_body_2dev.png").stat().st_size > 0


def test_kernel_count_benchmark_quick(tmp_path):
    load("kernels").main(["--quick", "--out", str(tmp_path)])
    record = json.loads((tmp_path / "kernels_free.json").read_text())
    forward, reverse = record["forward"], record["reverse"]
    assert forward["kernels_per_step"] > 0
    # The reverse pass runs the forward steps and their transposes: more kernels, some marked T.
    assert reverse["kernels_per_step"] > forward["kernels_per_step"]
    assert any(key.startswith("T ") for key in reverse["by_source"])
    assert abs(sum(reverse["by_source"].values()) - reverse["kernels_per_step"]) < 1e-9
    # Thread-pool handoffs are counted apart from the kernels (a count, so whole per call).
    for mode in (forward, reverse):
        assert mode["threadpool_handoffs_per_step"] >= 0
        calls = mode["threadpool_handoffs_per_step"] * record["steps"]
        assert abs(calls - round(calls)) < 1e-9
    # The same kernels by the jaxrb source line that traced them: most have one, among them
    # the splitting's axis rotations (SymplecticSplitting is the free body's integrator).
    by_line = forward["by_line"]
    assert abs(sum(by_line.values()) - forward["kernels_per_step"]) < 1e-9
    assert sum(n for key, n in by_line.items() if key.startswith("(no jaxrb frame)")) < 0.25 * sum(by_line.values())
    assert any(key.startswith("integrators/_splitting.py:_rotate_about_principal_axis:") for key in by_line)


def test_step_pieces_benchmark_quick(tmp_path):
    load("step_pieces").main(["--quick", "--out", str(tmp_path)])
    results = json.loads((tmp_path / "step_pieces.json").read_text())["results"]
    assert {"step", "detect", "separations", "free step", "detect + frames + 1 sweep"} <= set(results)
    # The narrow phase is part of "detect + frames", which is part of the solves, and a
    # second sweep adds kernels to the first.
    kernels = {name: r["kernels"] for name, r in results.items()}
    assert kernels["detect"] < kernels["detect + frames"] < kernels["detect + frames + 1 sweep"]
    assert kernels["detect + frames + 1 sweep"] < kernels["detect + frames + 2 sweeps"]
    assert all(r["us_best"] > 0 and r["us_median"] >= r["us_best"] for r in results.values())
    assert (tmp_path / "step_pieces.png").stat().st_size > 0


def test_contact_fuzz_quick(tmp_path):
    # In a fresh process on XLA's default flags, as users run (the suite compiles with the
    # older fusion emitters, see conftest): stop 80's fuzz found a crash only the default
    # emitters have.
    env = {key: value for key, value in os.environ.items() if key != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "fuzz_contacts.py"), "--quick", "--out",
                          str(tmp_path)], capture_output=True, text=True, timeout=600, env=env, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    (run,) = json.loads((tmp_path / "fuzz_contacts.json").read_text())["runs"]
    assert run["composition"] == "sy" and run["pairs"] == 11 and run["cases"] == [0, 1]
    assert run["non_finite_cases"] == [] and len(run["worst_step_gain_J"]) == 2
    assert (tmp_path / "fuzz_contacts.png").stat().st_size > 0
    with pytest.raises(ValueError, match="letters of sbcy"):
        load("fuzz_contacts").main(["--compositions", "sx", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match="--only takes case numbers"):
        load("fuzz_contacts").main(["--cases", "4", "--only", "4", "--out", str(tmp_path)])


def test_contact_fuzz_gradients_quick(tmp_path):
    import jax.numpy as jnp
    import numpy as np

    import jaxrb as rb

    # The gradient mode on the smallest pen (one sphere, five planes), in this process.
    record = load("fuzz_contacts").main(["--compositions", "s", "--cases", "2", "--steps", "10", "--gradients",
                                         "--out", str(tmp_path)])
    (run,) = record["runs"]
    assert run["non_finite_gradient_cases"] == [] and run["non_finite_gradient_leaves"] == []
    assert run["gradient_seconds_with_compile"] > 0
    # The check finds a NaN where there is one: the second case's mass made NaN.
    fuzz = load("fuzz_contacts")
    scene = fuzz.pen("s")
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
    params, state = fuzz.random_cases(scene, step, 2, 0, jnp.float64)
    params = params.replace(mass=params.mass.at[1].set(jnp.nan))
    found = fuzz.gradient_fuzz(step, params, state, 10, np.arange(2))
    assert found["non_finite_gradient_cases"] == [1] and "[0].mass" in found["non_finite_gradient_leaves"]


@pytest.mark.slow
def test_gradient_growth_quick(tmp_path):
    # One turned cube resting on the ground, 3 steps: a shift of its height stays a shift,
    # so d sum(z_final) / d z_initial is 1 and no step grows the cotangent.
    (row,) = load("gradient_growth").main(["cube_rot30", "--steps", "3", "--out", str(tmp_path)])
    assert row["first_nonfinite_step"] is None
    assert abs(row["dz0"][0] - 1.0) < 1e-5 and abs(row["largest_state_gradient"] - 1.0) < 1e-5
    assert len(row["cotangent_size"]) == 3
    assert json.loads((tmp_path / "gradient_growth.json").read_text())[0]["scene"] == "cube_rot30"
    assert (tmp_path / "gradient_growth.png").stat().st_size > 0


def test_work_precision_benchmark_quick(tmp_path):
    import jaxrb as rb

    load("work_precision").main(["--quick", "--out", str(tmp_path)])
    record = json.loads((tmp_path / "work_precision.json").read_text())
    table = (tmp_path / "work_precision_table.md").read_text()
    integrators = [n for n in rb.integrators.__all__ if n != "Integrator"]
    rows = record["problems"]["asymmetric_top"]["rows"]
    assert {r["method"] for r in rows} == {*integrators, "Tsit5", "Dopri8"}
    assert {r["dtype"] for r in rows} == {"float32", "float64"}
    assert set(record["long_horizon"]["methods"]) == set(record["stability"]["methods"]) == set(integrators)
    assert all(name in table for name in integrators)
    for stem in ["front", "convergence", "energy", "stability", "ucurves_asymmetric_top"]:
        assert (tmp_path / f"work_precision_{stem}.png").stat().st_size > 0
    # Physics, not just "it ran": halving h (0.156 -> 0.078 s) divides each integrator's float64 attitude
    # error by about 2^order. Measured ratios: 2.0-2.4 for the order-1 methods, 4.0 for order 2, 14.6-15.0
    # for order 4; 0.6 * 2^order leaves room for the pre-asymptotic constant without passing a wrong order.
    for name in integrators:
        coarse, fine = (r["attitude_error"] for r in rows if r["method"] == name and r["dtype"] == "float64")
        assert coarse / fine > 0.6 * 2 ** getattr(rb.integrators, name).order, (name, coarse, fine)
    # --replot redoes the orders, tables and figures from the JSON alone, and the same rows give the
    # same table; the rows themselves are kept as measured.
    again = tmp_path / "again"
    replotted = load("work_precision").main(["--replot", str(tmp_path / "work_precision.json"), "--out", str(again)])
    assert (again / "work_precision_table.md").read_text() == table
    assert replotted["problems"]["asymmetric_top"]["rows"] == rows and "replotted" in replotted
    for stem in ["front", "convergence", "stability", "ucurves_asymmetric_top"]:
        assert (again / f"work_precision_{stem}.png").stat().st_size > 0


def check_header(record):
    """``_machine.record_header``'s keys: what timings need to be read, the code measured
    and how busy the machine was."""
    assert record["commit"] is None or len(record["commit"]) >= 7
    load = record["machine"]["load_1min_at_start"]
    assert load is None or load >= 0


@pytest.mark.slow
def test_contacts_benchmark_quick(tmp_path):
    record = load("contacts").main(["--quick", "--no-peers", "--out", str(tmp_path)])
    check_header(record)
    results = record["results"]
    assert set(results) >= {"box_stack", "ball_drop"}
    for engines in (results["box_stack"], results["ball_drop"]):
        for r in engines.values():
            assert r["finite"] and r["compile_s"] > 0 and r["steps_per_s_1env"] > 0
    # The stack is timed over the whole scene (20 steps here, as a chain of 5-step calls),
    # as the peers' calls are, and its first call alone.
    stack = results["box_stack"]["jaxrb pgs"]
    assert stack["timed_steps_1env"] == 20 and stack["steps_per_s_1env_first_5"] > 0
    assert (tmp_path / "contacts.png").stat().st_size > 0


@pytest.mark.slow
def test_gradients_benchmark_quick(tmp_path):
    record = load("gradients").main(["--quick", "--no-plain", "--out", str(tmp_path)])
    assert record["bounce"]["gradient_finite"] and record["bounce"]["ratio_reverse_over_forward"] > 0
    # Timed hot, in blocks of consecutive calls, and one by one beside it.
    assert record["bounce"]["timing_block"] == 10 and record["bounce"]["interleaved"]["ratio_reverse_over_forward"] > 0
    # The cost split: flight only, the contact program's free steps and the bare integrator
    # step are the same arithmetic, so their gradients with respect to the state agree.
    split = record["bounce"]["cost_split_s"]
    cases = ("bounce", "flight", "no_contacts", "no_contacts_attitude_kept")
    assert set(split) == {f"{d}_{case}" for d in ("forward", "reverse") for case in cases}
    assert all(t > 0 for t in split.values())
    assert record["bounce"]["flight_state_gradient_max_abs_difference"] <= 1e-12
    # The same ratio beside the peers', measured as they are: a one-thread XLA pool.
    pool = record["bounce_one_thread_pool"]
    # (Where the OS cannot pin a process to one CPU, peers.py keeps the default pool and says so.)
    expected = "one thread" if hasattr(os, "sched_setaffinity") else "default ("
    assert pool["xla_cpu_pool"].startswith(expected) and pool["ratio_reverse_over_forward"] > 0
    long = record["free_body_long"]["checkpointed"]
    assert long["gradient_finite"] and long["xla_memory_bytes"] > 0
    assert json.loads((tmp_path / "gradients.json").read_text())["bounce"]["steps"] == 50
    check_header(record)
    assert (tmp_path / "gradients.png").stat().st_size > 0


def test_gradient_spread_benchmark_quick(tmp_path):
    record = load("gradient_spread").main(["--quick", "--out", str(tmp_path)])
    rows = record["results"]["float64"]["rows"]
    assert [r["horizon"] for r in rows] == [30, 60] and all(len(r["values"]) == 2 for r in rows)
    # 60 steps of free fall from 0.5 m: the loss is smooth there, and the two starts' mass
    # derivatives agree (gravity does not depend on the mass; only rounding moves them).
    assert all(abs(r["std"]) <= 1e-9 * max(1.0, abs(r["mean"])) for r in rows)
    check_header(record)
    assert (tmp_path / "gradient_spread.png").stat().st_size > 0


def test_gradient_spread_benchmark_refuses_fewer_than_two_starts(tmp_path):
    with pytest.raises(ValueError, match="--starts must be at least 2"):
        load("gradient_spread").main(["--starts", "1", "--out", str(tmp_path)])


def test_ab_benchmark_quick(tmp_path):
    """Two versions side by side (here a git revision and this checkout, the same code):
    each is imported, compiled and set aside in turn, and the jaxrb of this process is
    the one it had before."""
    import jaxrb as rb

    before = {name: m for name, m in sys.modules.items() if name == "jaxrb" or name.startswith("jaxrb.")}
    record = load("ab").main(["HEAD", "WORKTREE", "--quick", "--programs", "stack", "--out", str(tmp_path)])
    after = {name: m for name, m in sys.modules.items() if name == "jaxrb" or name.startswith("jaxrb.")}
    assert after == before and sys.modules["jaxrb"] is rb
    rows = record["summary"]["programs"]
    assert set(rows) == {"stack first 20", "stack settled 20"}
    for r in rows.values():
        assert len(r["a_times_s"]) == len(r["b_times_s"]) == 3 and r["b_over_a_min"] > 0
    # The same code on both sides: the same program, line for line (its size is deterministic).
    cost = rows["stack first 20"]
    assert cost["a_cost"]["stablehlo_lines"] == cost["b_cost"]["stablehlo_lines"] > 1000
    assert record["a"]["source"] != record["b"]["source"]  # HEAD came from `git archive`
    assert (tmp_path / "ab.json").is_file() and (tmp_path / "ab.png").stat().st_size > 0


def test_ab_benchmark_refuses_an_unknown_version_or_program(tmp_path):
    ab = load("ab")
    with pytest.raises(SystemExit, match="neither a git revision"):
        ab.main(["no-such-revision", "WORKTREE", "--quick", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="--programs takes"):
        ab.main(["HEAD", "WORKTREE", "--programs", "stak", "--out", str(tmp_path)])
