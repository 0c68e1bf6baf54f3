"""What machine a benchmark ran on, and helpers shared by the benchmark scripts."""

from __future__ import annotations

import datetime
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def record_header(script: str, argv) -> dict:
    """The start of a results record: when (UTC), the command that reproduces it, and where.

    ``script`` is the file name in ``benchmarks/``; ``argv`` the arguments given to ``main``
    (``None``: the process's own).
    """
    import jax

    args = sys.argv[1:] if argv is None else argv
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join(["python", f"benchmarks/{script}", *args]),
        "commit": source_commit(),
        "machine": {"cpu": cpu_model(), "device": str(jax.devices()[0]), "jax": jax.__version__,
                    # Timings on these shared 2-core machines move with their load: the
                    # same gradient/forward ratio was 4.08x at a load of 0.9 and 4.31x at 1.6.
                    "load_1min_at_start": load_average()},
    }


def load_average() -> float | None:
    """The machine's 1-minute load average (runnable processes), or None where unknown."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return None


def source_commit() -> str | None:
    """The git commit of the code being measured (``jaxrb/``, ``benchmarks/*.py``), with
    ``+changes`` when that code differs from it; None outside a git checkout."""
    here = Path(__file__).resolve().parent

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=here, capture_output=True, text=True, check=True).stdout.strip()

    try:
        commit = git("rev-parse", "--short", "HEAD")
        changed = git("status", "--porcelain", "--untracked-files=no", "--", "../jaxrb", "*.py")
    except (OSError, subprocess.CalledProcessError):
        return None
    return commit + ("+changes" if changed else "")


def json_from_python(python: str, code: str, marker: str, timeout: int = 3600) -> dict:
    """Run ``code`` in the interpreter ``python``; return the JSON it printed after ``marker``.

    ``{"error": <the end of its output>}`` if it printed none (a failed peer run is
    reported, never raised).
    """
    out = subprocess.run([python, "-c", code], capture_output=True, text=True, timeout=timeout)
    for line in out.stdout.splitlines():
        if line.startswith(marker):
            return json.loads(line[len(marker):])
    return {"error": (out.stderr or out.stdout)[-3000:]}


def peak_rss_bytes() -> int:
    """This process's peak resident set, bytes.

    ``VmHWM`` from /proc/self/status where there is one: unlike ``ru_maxrss`` it starts
    afresh at ``exec``, so a child process started by a large parent does not inherit the
    parent's peak (Linux keeps ``ru_maxrss`` across ``execve``).
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def timed(fn, args, repeats: int) -> float:
    """Best wall time (s) of ``repeats`` calls of ``fn(*args)``, after one warm-up call.

    Every call ends with ``jax.block_until_ready``, so asynchronous dispatch is timed too.
    """
    import jax  # noqa: PLC0415 - only the scripts that time JAX code pay for the import

    jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def _jsonable(x):
    """JSON's value for what ``json`` cannot write itself: numpy and JAX scalars as numbers
    (bools as bools), anything else (a dtype, a path) as its string."""
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    try:
        return float(x)
    except (TypeError, ValueError):
        return str(x)


def write_results(out: Path, name: str, record: dict, plot=None) -> None:
    """Write ``record`` to ``out/<name>.json`` and, with ``plot(record, path)``, the figure to
    ``out/<name>.png``; then say where they are."""
    paths = [out / f"{name}.json"]
    paths[0].write_text(json.dumps(record, indent=2, default=_jsonable) + "\n")
    if plot is not None:
        paths.append(out / f"{name}.png")
        plot(record, paths[1])
    print(f"\nwrote {' and '.join(map(str, paths))}")
