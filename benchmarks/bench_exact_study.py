"""Studies you can trust to the bit: one EKF study of seed 000's jump system, 10^5 runs, done six ways.

The whole study in one process; split at block boundaries into 2 and into 3 parts (each part its own
process) and merged; killed by SIGKILL at random moments (after a checkpoint write, and during one) and
resumed until done; and run by two processes under ``jax.distributed`` on 127.0.0.1 (one CPU device
each, chunks twice as large, so the same blocks). Every field of every result (each number, each
accumulator, each node of the block sums) must equal the whole study's bit for bit; the script raises
if one does not. Recorded: each way's wall and run seconds, so the two-process study's time stands
beside one process's (both on this 2-core machine, so two processes share the same cores).

Usage: python benchmarks/bench_exact_study.py [--runs N] [--steps T] [--block B] [--note ...] [--quick]
       (--quick: 10^4 runs, results *_quick.*)
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
ROOT = Path(__file__).resolve().parent.parent

SETUP = """
import sys, json, time
import jax
jax.config.update("jax_enable_x64", True)
from gmjax import montecarlo
from gmjax.filters import build_ekf
from gmjax.scenarios.jump_system import jump_system
cfg = json.loads(sys.argv[1])
sc = jump_system(n_steps=cfg["steps"])
filt = build_ekf(sc.model)
def study(runs, chunk, checkpoint=None):
    return montecarlo.monte_carlo(filt, sc, cfg["runs"], jax.random.key(7), chunk_size=chunk,
                                  runs=runs, checkpoint=checkpoint, progress=False)
"""

PART = (
    SETUP
    + """
t0 = time.perf_counter()
r = study(range(cfg["start"], cfg["stop"]), cfg["block"])
r.save(cfg["out"])
print(json.dumps({"wall_s": time.perf_counter() - t0, "run_s": r.run_s, "compile_s": r.compile_s}))
"""
)

KILLED = (
    SETUP
    + """
import os, random, signal
rng = random.Random(cfg["seed"])
writes, kill_at = [], rng.randint(1, cfg["n_chunks"] - 1)
original, savez = montecarlo.driver._write_checkpoint, montecarlo._files.np.savez
def write_then_die(*args, **kwargs):
    original(*args, **kwargs)
    writes.append(1)
    if len(writes) == kill_at and cfg["when"] == "after":
        os.kill(os.getpid(), signal.SIGKILL)
def die_while_writing(f, **arrays):  # half a file, then the kill: the temporary file stays behind
    if len(writes) + 1 == kill_at:
        savez(f, **{k: arrays[k] for k in list(arrays)[:3]})
        f.flush()
        os.kill(os.getpid(), signal.SIGKILL)
    savez(f, **arrays)
montecarlo.driver._write_checkpoint = write_then_die
if cfg["when"] == "during":
    montecarlo._files.np.savez = die_while_writing
r = study(range(cfg["runs"]), cfg["block"], checkpoint=cfg["checkpoint"])
r.save(cfg["out"])
print(json.dumps({"resumed_runs": r.resumed_runs}))
"""
)

TWO_PROCESSES = (
    """
import sys, json
import jax
jax.config.update("jax_cpu_collectives_implementation", "gloo")
_cfg = json.loads(sys.argv[1])
jax.distributed.initialize(coordinator_address=_cfg["address"], num_processes=2, process_id=_cfg["pid"])
assert jax.process_count() == 2 and len(jax.devices()) == 2, jax.devices()
"""
    + SETUP
    + """
t0 = time.perf_counter()
r = study(range(cfg["runs"]), 2 * cfg["block"])
r.save(cfg["out"])
print(json.dumps({"wall_s": time.perf_counter() - t0, "run_s": r.run_s, "compile_s": r.compile_s}))
"""
)


def _env() -> dict:
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
    env.pop("XLA_FLAGS", None)
    return env


def _python(script: str, cfg: dict, timeout: float = 3600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", script, json.dumps(cfg)],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _last_json(res: subprocess.CompletedProcess, what: str) -> dict:
    if res.returncode != 0:
        raise SystemExit(f"{what} failed (exit {res.returncode}):\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def differences(a, b) -> list[str]:
    """The fields of two results that differ in any bit (numbers, accumulators, block-sum nodes)."""
    import numpy as np

    out = []
    for name in (
        "rmse", "position_rmse", "armse", "armse_stderr", "position_armse", "position_armse_stderr",
        "nees", "anees", "median_nees", "cep", "mean_cost", "mean_ise", "n_components", "flag_rate",
        "n_runs_flagged", "n_runs", "runs",
    ):  # fmt: skip
        if not np.array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), equal_nan=True):
            out.append(name)
    for name in a.moments._fields:
        if not np.array_equal(getattr(a.moments, name), getattr(b.moments, name), equal_nan=True):
            out.append(f"moments.{name}")
    if (a.sums is None) != (b.sums is None) or a.sums is None:
        return out + ["sums"]
    if [n[:2] for n in a.sums.nodes] != [n[:2] for n in b.sums.nodes]:
        return out + ["sums.nodes"]
    for (lv, ix, ma), (_, _, mb) in zip(a.sums.nodes, b.sums.nodes):
        for name in ma._fields:
            if not np.array_equal(getattr(ma, name), getattr(mb, name), equal_nan=True):
                out.append(f"sums[{lv},{ix}].{name}")
    return out


def check(n_runs: int, steps: int, block: int, kills: int = 4, seed: int = 0) -> dict:
    """Run every way of doing the study and compare each with the whole; raise on any difference."""
    from gmjax import montecarlo

    tmp = Path(tempfile.mkdtemp(prefix="gmjax_exact_"))
    base = {"runs": n_runs, "steps": steps, "block": block}
    timings: dict[str, dict] = {}
    rng = random.Random(seed)

    def part(name: str, start: int, stop: int) -> montecarlo.MonteCarloResult:
        out = str(tmp / f"{name}.npz")
        timings[name] = _last_json(_python(PART, dict(base, start=start, stop=stop, out=out)), name)
        return montecarlo.load_result(out)

    whole = part("whole", 0, n_runs)
    n_blocks = -(-n_runs // block)
    ways: dict[str, montecarlo.MonteCarloResult] = {}
    for n_parts in (2, 3):
        cuts = sorted(rng.sample(range(1, n_blocks), n_parts - 1))
        bounds = [0, *(c * block for c in cuts), n_runs]
        parts = [part(f"part{n_parts}_{i}", a, b) for i, (a, b) in enumerate(zip(bounds, bounds[1:]))]
        ways[f"{n_parts} parts at {bounds[1:-1]}"] = montecarlo.merge(parts[::-1])
    # killed and resumed: each kill at a random chunk, alternately after and during a checkpoint write
    ckpt = tmp / "killed.npz"
    n_kills = 0
    for i in range(kills + 1):
        cfg = dict(
            base,
            n_chunks=n_blocks,
            seed=seed * 100 + i,
            checkpoint=str(ckpt),
            out=str(tmp / "killed_out.npz"),
        )
        cfg["when"] = "none" if i == kills else ("after" if i % 2 == 0 else "during")
        res = _python(KILLED, cfg)
        if res.returncode == -signal.SIGKILL:
            n_kills += 1
            continue
        _last_json(res, "killed study")
        break
    leftovers = sorted(p.name for p in tmp.iterdir() if p.name.startswith("killed.npz.tmp-"))
    if leftovers:
        raise AssertionError(f"temporary files left after the resumed study finished: {leftovers}")
    ways[f"killed {n_kills}x and resumed"] = montecarlo.load_result(tmp / "killed_out.npz")
    # two processes under jax.distributed, one device each, chunks of 2 blocks
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-c",
                TWO_PROCESSES,
                json.dumps(dict(base, pid=pid, address=f"127.0.0.1:{port}", out=str(tmp / f"two{pid}.npz"))),
            ],
            env=_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for pid in (0, 1)
    ]
    outs = [p.communicate(timeout=3600) for p in procs]
    for pid, (p, (out, err)) in enumerate(zip(procs, outs)):
        if p.returncode != 0:
            raise SystemExit(f"process {pid} of the two failed:\n{err[-3000:]}")
        timings[f"two processes ({pid})"] = json.loads(out.strip().splitlines()[-1])
    two = [montecarlo.load_result(tmp / f"two{pid}.npz") for pid in (0, 1)]
    ways["two processes: process 0"], ways["two processes: process 1"] = two
    report = {name: differences(r, whole) for name, r in ways.items()}
    bad = {k: v for k, v in report.items() if v}
    if bad:
        raise AssertionError(f"not bit-identical to the whole study: {bad}")
    return {"whole": whole, "ways": list(report), "timings": timings, "kills": n_kills}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=None, help="runs (default 10^5; --quick 10^4)")
    parser.add_argument("--steps", type=int, default=30, help="steps per run (default 30)")
    parser.add_argument("--block", type=int, default=1000, help="runs per block (default 1000)")
    parser.add_argument("--note", default="", help="a note recorded with the results (e.g. machine load)")
    parser.add_argument("--quick", action="store_true", help="smoke run: 10^4 runs")
    args = parser.parse_args(argv)
    from _common import machine_info, markdown_table, write_results

    n_runs = args.runs or (10_000 if args.quick else 100_000)
    with open("/proc/loadavg") as f:
        load_before = f.read().split()[:3]
    t0 = time.perf_counter()
    out = check(n_runs, args.steps, args.block)
    with open("/proc/loadavg") as f:
        load_after = f.read().split()[:3]
    t = out["timings"]
    rows = [[name, "bit-identical"] for name in out["ways"]]
    one, two = t["whole"], t["two processes (0)"]
    timing_rows = [
        ["one process, one device", one["compile_s"], one["run_s"], one["wall_s"], 1.0],
        ["two processes, one device each", two["compile_s"], two["run_s"], two["wall_s"], two["wall_s"] / one["wall_s"]],
    ]  # fmt: skip
    whole = out["whole"]
    data = {
        "scenario": f"seed000 jump system, {args.steps} steps",
        "filter": "EKF",
        "n_runs": n_runs,
        "block_size": args.block,
        "ways": out["ways"],
        "kills": out["kills"],
        "timings": t,
        "armse": whole.armse,
        "armse_stderr": whole.armse_stderr,
        "machine": machine_info(),
        "loadavg_before": load_before,
        "loadavg_after": load_after,
        "total_s": time.perf_counter() - t0,
        "note": args.note,
    }
    md = (
        f"# Exact studies: {n_runs} EKF runs of seed 000's jump system ({args.steps} steps), blocks of "
        f"{args.block}\n\n"
        f"Whole study: ARMSE {whole.armse:.6f} ± {whole.armse_stderr:.6f}. Each way below equals it in every "
        "field (every number, accumulator and block-sum node) bit for bit; the script raises otherwise.\n\n"
        + markdown_table(["way", "against the whole study"], rows)
        + "\n\n"
        + markdown_table(["how", "compile s", "run s", "wall s", "wall / one process"], timing_rows)
        + "\n\nTwo processes share this machine's 2 cores (XLA's thread pool in each), so they show the"
        " protocol's cost, not a speed-up: on two hosts each would have its own cores. Load average before"
        f" / after: {' '.join(load_before)} / {' '.join(load_after)}."
        + (f"\n\nNote: {args.note}\n" if args.note else "\n")
    )
    path = write_results("exact_study", data, md, quick=args.quick)
    print(md)
    print(f"wrote {path}")
    return data


if __name__ == "__main__":
    main()
