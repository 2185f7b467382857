"""gmjax's R-GSF against the same filter written as a compiled numba per-run loop (issue 46).

"R-GSF per run-step within 1.5x of the same GSF built on the numba reducer": the honest compiled
baseline is the whole Gaussian sum filter (EKF components, Runnalls reduction to 20) written as one
numba ``@njit`` loop over the time steps of a run, with a ``prange`` batch driver over the runs
(``references/gsf_numba.py``; its Runnalls is ``references/reduction_numba.py``'s core). For each
system (1-D: the seed 000 jump system, 120 steps, 3 x 1 noise components; 4-D: the seed 000 Table 8
range-bearing system, ``duration=1.0``: 100 steps, 1 x 4), float64, the same simulated measurement
sequences (``gmjax.models.base.simulate``, keys split from ``jax.random.key(0)``, as
``bench_gsf_kernel.py``) are filtered by

* gmjax: ``jit(vmap(run(build_gsf(model, "ekf", Runnalls(num_out=20), capacity=20))))`` returning
  the estimates and their covariances (``info.mean``, ``info.cov``), one core;
* the numba batch driver ``gsf_batch`` on all threads (``numba.get_num_threads()``) and on one thread.

Timing (``_common.time_alternating``): the first call of each program (compile + run) apart from the
steady calls, which run in alternating rounds in one process (gmjax, numba all threads, numba one
thread, gmjax, ...), so a slow spell of the machine slows all alike; the best round of each is
reported as µs per run-step (median in the JSON). numba's compile time is its first call's time minus
its median run (no on-disk cache; both systems share one compiled signature, so the second system
shows ~0). The estimates are compared: max abs difference of the means and of the covariances.

Usage: ``python benchmarks/bench_gsf_numba.py [--quick] [--runs 200] [--repeats 3]
[--systems 1-D 4-D] [--note "..."]`` (or ``gmjax bench gsf_numba``). Needs numba
(``pip install -e .[bench]``). Writes ``results/gsf_numba.json`` and ``.md`` (``gsf_numba_quick.*``
with ``--quick``).
"""

from __future__ import annotations

import argparse
import functools
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # references/

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from references import gsf_numba as gn  # noqa: E402

CAPACITY = 20
STEPS = {"1-D": 120, "4-D": 100}


def mixture_arrays(gm, capacity: int | None = None) -> tuple[np.ndarray, ...]:
    """``(weights, means, covs, mask)`` of a GaussianMixture as float64 NumPy arrays, padded with
    ``(0, 0, I)`` slots (mask False) up to ``capacity``."""
    w, m, P, mask = (np.asarray(a) for a in gm)
    w, m, P = (a.astype(np.float64) for a in (w, m, P))
    mask = mask.astype(bool)
    if capacity is not None and capacity > len(w):
        pad, d = capacity - len(w), m.shape[1]
        w = np.concatenate([w, np.zeros(pad)])
        m = np.concatenate([m, np.zeros((pad, d))])
        P = np.concatenate([P, np.broadcast_to(np.eye(d), (pad, d, d))])
        mask = np.concatenate([mask, np.zeros(pad, bool)])
    return w, m, P, mask


@functools.cache
def _simulated(system: str, n_runs: int):
    """``(model, zs (B, T, mz), ts (T,))`` of one system, simulated once per process (``simulate``
    compiles for every new scenario object)."""
    from gmjax.models.base import simulate
    from gmjax.scenarios.glint_range_bearing import range_bearing
    from gmjax.scenarios.jump_system import jump_system

    if system == "1-D":
        sc = jump_system(dtype=jnp.float64)
    else:
        sc = range_bearing(duration=1.0, dtype=jnp.float64)  # 100 steps of the 4-D Table 8 system
    keys = jax.random.split(jax.random.key(0), n_runs)
    _, zs, ts = jax.jit(jax.vmap(lambda k: simulate(sc, k)))(keys)
    return sc.model, zs, ts[0]


def problem(system: str, n_runs: int, n_steps: int | None = None, start: int = 0, capacity: int = CAPACITY):
    """The model, the simulated measurements and both filters' inputs of one system.

    Returns ``(model, zs (B, T, mz), ts (T,) as simulate gives them, numba_args)``: ``numba_args``
    is everything :func:`references.gsf_numba.gsf_batch` takes before the measurements (system,
    parameters, the prior padded to ``capacity``, the noises) and after them (the float64 times).
    ``start`` / ``n_steps`` select the steps ``start .. start + n_steps - 1`` (the filters then start
    from the prior at that step).
    """
    model, zs, ts = _simulated(system, n_runs)
    sid, theta = (gn.JUMP, gn.JUMP_THETA) if system == "1-D" else (gn.RANGE_BEARING, gn.RANGE_BEARING_THETA)
    stop = None if n_steps is None else start + n_steps
    zs, ts = zs[:, start:stop], ts[start:stop]
    head = (sid, theta, *mixture_arrays(model.prior, capacity))
    head += mixture_arrays(model.process_noise)[:3] + mixture_arrays(model.measurement_noise)[:3]
    return model, zs, ts, (head, np.asarray(ts, np.float64))


def gmjax_filter(model, ts, capacity: int = CAPACITY):
    """``jit(vmap(z -> (means, covs)))`` of gmjax's R-GSF over the times ``ts``."""
    from gmjax.filters import run
    from gmjax.filters.gsf import build_gsf
    from gmjax.reduction import Runnalls

    filt = build_gsf(model, "ekf", Runnalls(num_out=capacity), capacity=capacity)

    def one(z):
        info = run(filt, z, ts)[1]
        return info.mean, info.cov

    return jax.jit(jax.vmap(one))


def numba_filter(args, batched: bool = True):
    """``zs -> (means, covs)`` by the numba batch driver (or, ``batched=False``, ``gsf_run.py_func``
    run by the interpreter per run)."""
    head, ts = args
    if batched:
        return lambda zs: gn.gsf_batch(*head, np.asarray(zs, np.float64), ts)
    fn = gn.gsf_run.py_func

    def loop(zs):
        outs = [fn(*head, np.asarray(z, np.float64), ts) for z in zs]
        return np.stack([o[0] for o in outs]), np.stack([o[1] for o in outs])

    return loop


def case(system: str, n_runs: int, repeats: int, threads: int) -> dict:
    from _common import block, time_alternating, with_numba_threads

    model, zs, ts, args = problem(system, n_runs)
    gm_fn = gmjax_filter(model, ts)
    nb_fn = numba_filter(args)
    zs_np = np.asarray(zs, np.float64)
    last = {}  # each program's last output, compared below (no extra call)

    def keep(name, fn):
        def call():
            last[name] = fn()
            return last[name]

        return call

    t_g, t_n, t_1 = time_alternating(
        [
            keep("gmjax", lambda: gm_fn(zs)),
            with_numba_threads(threads, keep("numba", lambda: nb_fn(zs_np))),
            with_numba_threads(1, lambda: nb_fn(zs_np)),
        ],
        repeats=repeats,
    )
    gm_m, gm_P = (np.asarray(a) for a in block(last["gmjax"]))
    nb_m, nb_P = last["numba"]
    n_steps = zs.shape[1]
    us = 1e6 / (n_runs * n_steps)
    return {
        "system": system,
        "dtype": "float64",
        "n_runs": n_runs,
        "n_steps": n_steps,
        "repeats": repeats,
        "numba_threads": threads,
        "gmjax_us_per_run_step": t_g["run_min_s"] * us,
        "numba_us_per_run_step": t_n["run_min_s"] * us,
        "numba_1t_us_per_run_step": t_1["run_min_s"] * us,
        "gmjax_median_us_per_run_step": t_g["run_median_s"] * us,
        "numba_median_us_per_run_step": t_n["run_median_s"] * us,
        "numba_1t_median_us_per_run_step": t_1["run_median_s"] * us,
        "ratio": t_g["run_min_s"] / t_n["run_min_s"],
        "ratio_1t": t_g["run_min_s"] / t_1["run_min_s"],
        "gmjax_compile_s": t_g["compile_s"],
        "numba_compile_s": t_n["compile_s"],
        "max_abs_diff_mean": float(np.abs(gm_m - nb_m).max()),
        "max_abs_diff_cov": float(np.abs(gm_P - nb_P).max()),
    }


def render(data: dict) -> str:
    from _common import markdown_table

    th = data["numba_threads"]
    header = [
        "system",
        "runs",
        "steps",
        "gmjax µs/run-step",
        f"numba µs/run-step ({th} threads)",
        "numba µs/run-step (1 thread)",
        f"gmjax / numba ({th} thr)",
        "gmjax / numba (1 thr)",
        "gmjax compile s",
        "numba compile s",
        "max abs diff mean",
        "max abs diff cov",
    ]
    table = [
        [
            r["system"],
            r["n_runs"],
            r["n_steps"],
            r["gmjax_us_per_run_step"],
            r["numba_us_per_run_step"],
            r["numba_1t_us_per_run_step"],
            r["ratio"],
            r["ratio_1t"],
            r["gmjax_compile_s"],
            r["numba_compile_s"],
            f"{r['max_abs_diff_mean']:.1e}",
            f"{r['max_abs_diff_cov']:.1e}",
        ]
        for r in data["rows"]
    ]
    md = (
        "# gmjax's R-GSF vs the same GSF as a compiled numba per-run loop, float64\n\n"
        f"Measured {data['date']} on a {data['cpu_count']}-core CPU machine, load average "
        f"{' '.join(data['loadavg_before'])} before and {' '.join(data['loadavg_after'])} after. "
        f"R-GSF: EKF components, Runnalls to 20, capacity 20. 1-D: seed 000 jump system (120 steps, 3 x 1 "
        "noise components, 60 -> 20 per step); 4-D: seed 000 Table 8 range-bearing system (100 steps, "
        "1 x 4, 80 -> 20). The same simulated measurement sequences for both. gmjax: "
        "`jit(vmap(run(build_gsf(...))))`, one core; numba: `references/gsf_numba.gsf_batch`, the runs "
        f"in parallel with `prange` on {th} threads ({data['numba_threading_layer']} threading layer) "
        f"and on one thread (the per-core comparison). Best of {data['repeats']} alternating rounds "
        f"(medians in the JSON); compile time apart. numba {data['numba_version']}, jax {jax.__version__}.\n\n"
        + markdown_table(header, table)
        + "\n\nnumba compile time: the first call of the batch driver (both systems share one compiled "
        "signature, so the second shows ~0). `max abs diff`: of the per-step estimate means and covariances "
        "over every run and step.\n"
    )
    if data.get("note"):
        md += f"\nNote: {data['note']}\n"
    return md


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="smoke run: 20 runs, 1 round")
    p.add_argument("--runs", type=int, default=200)
    p.add_argument("--repeats", type=int, default=3, help="alternating timing rounds")
    p.add_argument("--systems", nargs="+", default=["1-D", "4-D"], choices=["1-D", "4-D"])
    p.add_argument("--note", default="")
    args = p.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    try:
        import numba
    except ImportError:
        numba = None
    if numba is None or not gn.HAVE_NUMBA:
        raise SystemExit("bench_gsf_numba needs numba: pip install numba (or pip install -e .[bench])")
    from _common import write_results

    n_runs, repeats = (20, 1) if args.quick else (args.runs, args.repeats)
    threads = numba.get_num_threads()
    date = subprocess.run(["date"], capture_output=True, text=True).stdout.strip()
    with open("/proc/loadavg") as f:
        load_before = f.read().split()[:3]
    t0 = time.perf_counter()
    rows = []
    for system in args.systems:
        r = case(system, n_runs, repeats, threads)
        rows.append(r)
        print(
            f"{system}: gmjax {r['gmjax_us_per_run_step']:.2f} µs/run-step (compile {r['gmjax_compile_s']:.1f} s), "
            f"numba {r['numba_us_per_run_step']:.2f} ({threads} thr) / {r['numba_1t_us_per_run_step']:.2f} (1 thr) "
            f"(compile {r['numba_compile_s']:.1f} s), ratio {r['ratio']:.2f} / {r['ratio_1t']:.2f}, "
            f"max |diff| mean {r['max_abs_diff_mean']:.1e} cov {r['max_abs_diff_cov']:.1e}",
            flush=True,
        )
    with open("/proc/loadavg") as f:
        load_after = f.read().split()[:3]
    note = (
        "The machine may have been loaded by other processes during the run (shared 2-core machine); "
        "the load averages above say how much."
    )
    data = {
        "date": date,
        "cpu_count": os.cpu_count(),
        "numba_version": numba.__version__,
        "numba_threads": threads,
        "numba_threading_layer": numba.threading_layer(),
        "repeats": repeats,
        "capacity": CAPACITY,
        "loadavg_before": load_before,
        "loadavg_after": load_after,
        "wall_s": time.perf_counter() - t0,
        "rows": rows,
        "note": f"{note} {args.note}".strip(),
    }
    md = render(data)
    path = write_results("gsf_numba", data, md, quick=args.quick)
    print(md)
    print(f"wrote {path}")
    return data


if __name__ == "__main__":
    main()
