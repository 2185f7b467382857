"""Shared helpers for the benchmark scripts: timing with compile time apart, and result files.

Every ``benchmarks/bench_NAME.py`` exposes ``main(argv=None)`` (so ``gmjax bench NAME`` can run it),
accepts ``--quick`` for a small smoke configuration, and writes ``benchmarks/results/NAME.json`` and a
readable ``NAME.md`` table through :func:`write_results`.
"""

from __future__ import annotations

import json
import platform
import re
import statistics
import time
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def block(x: Any) -> Any:
    """``block_until_ready`` on every leaf of a pytree."""
    return jax.tree_util.tree_map(
        lambda a: a.block_until_ready() if hasattr(a, "block_until_ready") else a, x
    )


def with_numba_threads(n: int, fn: Callable[[], Any]) -> Callable[[], Any]:
    """``fn`` as a call that runs with numba's thread count set to ``n`` (restored after), for timing a
    ``prange`` driver on one thread beside its default (numba imported on the call)."""

    def call():
        import numba

        old = numba.get_num_threads()
        numba.set_num_threads(n)
        try:
            return fn()
        finally:
            numba.set_num_threads(old)

    return call


def time_jax(fn: Callable, *args: Any, repeats: int = 5) -> dict[str, float]:
    """Time a jitted function: first call (compile + run) apart from ``repeats`` steady calls.

    Returns ``{"compile_s", "run_min_s", "run_median_s"}`` where ``compile_s`` is the first call's
    time minus the median steady run time.
    """
    return time_alternating([lambda: fn(*args)], repeats=repeats)[0]


def time_alternating(calls: list[Callable[[], Any]], repeats: int = 5) -> list[dict[str, float]]:
    """Time several jitted zero-argument calls in alternating rounds, one call of each per round.

    For a ratio of two programs on a machine whose speed drifts (identical runs differ by up to
    ~30 % here): each round times every call once, so a slow spell slows all of them alike. Returns
    one :func:`time_jax`-style dict per call, in order.
    """
    firsts = []
    for call in calls:
        t0 = time.perf_counter()
        block(call())
        firsts.append(time.perf_counter() - t0)
    runs: list[list[float]] = [[] for _ in calls]
    for _ in range(repeats):
        for call, times in zip(calls, runs):
            t0 = time.perf_counter()
            block(call())
            times.append(time.perf_counter() - t0)
    out = []
    for first, times in zip(firsts, runs):
        med = statistics.median(times)
        out.append({"compile_s": max(first - med, 0.0), "run_min_s": min(times), "run_median_s": med})
    return out


def time_python(fn: Callable, *args: Any, repeats: int = 3) -> dict[str, float]:
    """Time a plain Python/NumPy function over ``repeats`` calls."""
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(*args)
        runs.append(time.perf_counter() - t0)
    return {"run_min_s": min(runs), "run_median_s": statistics.median(runs)}


def run_in_fresh_process(script: str, payload: Any, timeout: float, tries: int = 2) -> tuple[Any, str | None]:
    """Run ``python script --one <payload as JSON>`` in a fresh process and parse its last stdout line.

    Returns ``(result, None)``, or ``(None, why)`` when the process failed, or gave no result within
    ``timeout`` seconds ``tries`` times. A fresh process per case: programs with LAPACK calls inside
    loops hung in the XLA CPU runtime (every thread idle on a futex), and a hung case must not stop a
    benchmark.
    """
    import subprocess
    import sys

    cmd = [sys.executable, script, "--one", json.dumps(payload)]
    for _ in range(tries):
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            continue
        if res.returncode != 0:
            lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
            # the exception's own line, not a note printed after it (JAX's "removed its internal
            # frames" line hid a dtype error of the float32 PCM-GSF rows for a day)
            errors = [ln for ln in lines if re.match(r"[A-Za-z_][\w.]*(Error|Exception)\b", ln)]
            return None, (errors or lines or [f"exit code {res.returncode}"])[-1]
        return json.loads(res.stdout.strip().splitlines()[-1]), None
    return None, f"no result within {timeout:.0f} s ({tries} tries)"


def machine_info() -> dict[str, Any]:
    """Where the numbers were measured."""
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "devices": [str(d) for d in jax.devices()],
        "cpu_count": __import__("os").cpu_count(),
        "x64": bool(jax.config.jax_enable_x64),
    }


def markdown_table(header: list[str], rows: list[list[Any]]) -> str:
    """A GitHub-flavoured markdown table; floats printed with 4 significant digits."""

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def write_results(name: str, data: dict[str, Any], markdown: str, *, quick: bool = False) -> Path:
    """Write ``results/NAME.json`` and ``results/NAME.md`` (``NAME_quick.*`` for quick runs)."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    stem = f"{name}_quick" if quick else name
    payload = {"benchmark": name, "quick": quick, "machine": machine_info(), **data}
    (RESULTS_DIR / f"{stem}.json").write_text(json.dumps(payload, indent=2, default=_jsonable) + "\n")
    (RESULTS_DIR / f"{stem}.md").write_text(markdown.rstrip() + "\n")
    return RESULTS_DIR / f"{stem}.md"


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, (np.ndarray, jax.Array)):
        return np.asarray(obj).tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def per_run_contrib(sq: np.ndarray) -> tuple[float, np.ndarray]:
    """ARMSE of ``sq (N, T)`` and each run's linearised contribution (delta method; bench_tune and
    bench_fit pair two configurations on the same runs through these contributions)."""
    rmse = np.sqrt(sq.mean(0))
    return float(rmse.mean()), (sq / (2 * sq.shape[1] * rmse)).sum(1)
