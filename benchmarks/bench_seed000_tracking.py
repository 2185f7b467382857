"""Seed 000 Tables 7 and 8: the Gaussian sum filters of the paper and a PF, over Monte Carlo runs.

Runs the studies ``jump`` (Table 7, scalar measurement-jump system) and ``range_bearing`` (Table 8,
4-D range-bearing target with glint noise) of :mod:`gmjax.studies`, 100 runs each by default (the
paper used 15 for Table 7 and does not state its count for Table 8), and writes
``benchmarks/results/seed000_tracking.{json,md}`` with an RMSE / component-count PNG per table.

Usage: python benchmarks/bench_seed000_tracking.py [--quick] [--runs N] [--tables jump range_bearing]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from _common import RESULTS_DIR, markdown_table, write_results  # noqa: E402

from gmjax import studies  # noqa: E402


def _rows(study, results):
    rows = []
    for name, r in results.items():
        p = study.paper.get(name, {})
        rows.append([
            name,
            f"{r.position_armse:.4g} ± {r.position_armse_stderr:.2g}",
            p.get("armse", "-"),
            f"{r.mean_cost:.3g}" if name in study.eise_filters else "-",
            p.get("aeise", "-"),
            f"{r.mean_ise:.3g}",
            f"{r.n_components.mean():.1f}",
            f"{r.anees:.3g}",
            f"{1e3 * r.run_s / r.n_runs:.1f}",
            f"{r.compile_s:.1f}",
            p.get("cpu_s", "-"),
        ])
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smoke run: 3 runs, Table 7 only")
    parser.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default 100)")
    parser.add_argument("--runs-table8", type=int, default=None,
                        help="runs for Table 8 (1000 steps each; default: --runs)")
    parser.add_argument("--tables", nargs="+", default=None, choices=["jump", "range_bearing"])
    args = parser.parse_args(argv)
    n_runs = args.runs or (3 if args.quick else 100)
    tables = args.tables or (["jump"] if args.quick else ["jump", "range_bearing"])
    header = ["filter", "ARMSE ± s.e.", "paper ARMSE", "AEISE", "paper AEISE", "mean ISE", "components",
              "ANEES", "ms / run", "compile s", "paper CPU s"]
    md = ["# Seed 000 Tables 7 and 8: Gaussian sum filters and a particle filter", ""]
    data = {"tables": {}}
    for name in tables:
        study = studies.STUDIES[name]()
        runs = args.runs_table8 if (name == "range_bearing" and args.runs_table8) else n_runs
        print(f"{study.title}: {runs} runs")
        results = studies.run_study(study, runs, jax.random.key(0))
        print(studies.format_table(study, results))
        stem = f"seed000_{study.table.split('-')[-1]}" + ("_quick" if args.quick else "")
        png = studies.plot_study(study, results, RESULTS_DIR / f"{stem}.png")
        md += [f"## {study.title}", "", markdown_table(header, _rows(study, results)), "",
               f"{runs} runs here; paper: {study.paper_runs or 'not stated'}. ARMSE is the time-averaged "
               "position RMSE with its Monte Carlo standard error; AEISE is the mean EISE that PCM's search "
               "minimised (the paper does not define it for NL/R-GSF); mean ISE is between each step's updated "
               "mixture and its reduction; ms / run excludes compilation. The paper's CPU seconds are MATLAB "
               "totals for all its runs.", "", f"Notes: {study.notes}", ""]
        if png:
            md += [f"![{study.table}]({png.name})", ""]
        data["tables"][name] = studies.results_json(study, results)
    path = write_results("seed000_tracking", data, "\n".join(md), quick=args.quick)
    print(f"wrote {path}")
    return data


if __name__ == "__main__":
    main()
