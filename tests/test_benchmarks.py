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
