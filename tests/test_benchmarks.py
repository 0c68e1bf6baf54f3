"""Benchmark scripts must keep running (tiny sizes); their figures are never asserted."""

import importlib.util
import json
import pathlib

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
