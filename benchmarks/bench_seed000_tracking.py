"""Seed 000 Tables 7 and 8: the Gaussian sum filters of the paper and a PF, over Monte Carlo runs.

Runs the studies ``jump`` (Table 7, scalar measurement-jump system) and ``range_bearing`` (Table 8,
4-D range-bearing target with glint noise) of :mod:`gmjax.studies`, 100 runs each by default (the
paper used 15 for Table 7 and does not state its count for Table 8), and writes
``benchmarks/results/seed000_tracking.{json,md}`` with an RMSE / component-count PNG per table.

Table 7 is run twice: the study ``jump`` (glint centred at the eq-50 mean; R-GSF with a cost
threshold, and R-GSF-20 with the fixed count) and the named variant ``jump_zero_glint`` (glint centred
at 0, eq 47), each with R-GSF at the extra thresholds of ``--r-thresholds``.

Usage: python benchmarks/bench_seed000_tracking.py [--quick] [--runs N]
       [--tables jump jump_zero_glint range_bearing] [--runs-table8 N] [--table8-newton S] [--table8-ise]
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
from gmjax.filters.gsf import build_gsf  # noqa: E402
from gmjax.reduction import PCM, PruneTop, Runnalls  # noqa: E402

N_U8 = 20  # the paper gives no N_u for §IV-D (as in gmjax.studies)


def table8_study(study, *, newton_steps: int = 0, track_ise: bool = False):
    """Table 8 with a configuration that runs 100 x 1000 steps in minutes on a laptop CPU.

    Profiled on 4 runs x 100 steps (shared 2-core machine): PCM-GSF with the default search
    (11-point λ grid + 8 Newton steps on the relaxed EISE) costs about 40-60 ms per step and run, the
    grid alone about 2.4 ms, a fixed λ 1.7 ms, NL pruning 0.13 ms; the ISE tracking adds little. The
    Newton steps dominate because, under ``vmap``, every run executes all 8 steps with their gradient,
    Hessian and 5 backtracking evaluations of the relaxed EISE (no early exit in a batch). So Table 8
    uses the grid search (λ spacing 0.2 over [1, 3]) and no per-step ISE by default.
    """
    filters = dict(study.filters)
    filters["NL-GSF"] = lambda sc: build_gsf(
        sc.model, "ekf", PruneTop(num_out=N_U8), capacity=N_U8, track_ise=track_ise
    )
    filters["PCM-GSF"] = lambda sc: build_gsf(
        sc.model,
        "ekf",
        PCM(max_components=N_U8, capacity=N_U8, dims=(0, 2), newton_steps=newton_steps),
        capacity=N_U8,
        track_ise=track_ise,
    )
    filters["R-GSF"] = lambda sc: build_gsf(
        sc.model, "ekf", Runnalls(num_out=N_U8), capacity=N_U8, track_ise=track_ise
    )
    note = (
        " With this scenario's truth (an unmodelled 70 m/s^2 y-acceleration against the CV model's"
        " Q = 0.175 G G^T) every filter loses the target (ANEES ~1e5), so the ARMSEs are far above the"
        " paper's (the scenario is as printed: Q cannot follow the manoeuvre). This run: PCM's λ search is the 11-point grid{' + %d Newton steps' % newton_steps if newton_steps else ''}"
        f" (--table8-newton 8 runs PCM's default search), and the per-step ISE is "
        f"{'tracked' if track_ise else 'not tracked (mean ISE column is 0)'}."
    )
    return study._replace(filters=filters, notes=study.notes + note)


READING_WHY = {
    "jump": "Reading: the glint is centred at the eq-50 mean (≈ 4.25) because eq 50 is the paper's fit of the "
    "true noise and must share its mean; R-GSF merges under a cost threshold because Fig. 10 has its component "
    "count vary over time (R-GSF-20, the fixed count, is our reading before 0.2.0).",
    "jump_zero_glint": "Reading (a named diagnostic, not the paper's configuration): the glint centred at 0 "
    "because eq 47 prints the Laplace part as exp(-|x|/η)/η, centred at 0; the filters' eq-50 mixture is "
    "translated to the same centre (same shape), and the state now changes sign, so z = x²/20 is ambiguous "
    "in sign.",
}


def with_r_thresholds(study, thresholds):
    """Add ``R-GSF τ=...`` rows: R-GSF with other cost thresholds (the paper gives none)."""
    from gmjax.studies import R_GSF_THRESHOLD

    n_u = 20
    filters = dict(study.filters)
    for tau in thresholds:
        if tau == R_GSF_THRESHOLD:
            continue
        filters[f"R-GSF τ={tau:g}"] = lambda sc, tau=tau: build_gsf(
            sc.model, "ekf", Runnalls(num_out=1, threshold=tau, capacity=n_u), capacity=n_u, track_ise=True
        )
    return study._replace(filters=filters)


def separation_note(results, why: str) -> str:
    """Which GSFs differ: |ARMSE difference| > 2 x the combined standard error (independent s.e.s, a
    conservative test: the filters run on the same simulated runs)."""
    names = [n for n in results if n != "PF"]
    pairs = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            ra, rb = results[a], results[b]
            d = ra.position_armse - rb.position_armse
            se = (ra.position_armse_stderr**2 + rb.position_armse_stderr**2) ** 0.5
            if abs(d) > 2 * se:
                pairs.append(f"{a} vs {b} ({d:+.3g} ± {se:.2g})")
    sep = "; ".join(pairs) if pairs else "none: every pair is within 2 combined standard errors"
    return f"{why} Pairs of GSFs that differ (|ΔARMSE| > 2 combined s.e.): {sep}."


def compact_curves(entry: dict, max_points: int = 200) -> dict:
    """Keep the committed JSON small: per-step curves rounded to 4 significant digits and, for long
    horizons, every ``k``-th step only (``curve_every`` records ``k``; the first kept step is ``k``)."""
    for f in entry.get("filters", {}).values():
        for key in ("position_rmse", "rmse", "nees", "n_components"):
            if key in f and isinstance(f[key], list):
                k = max(1, -(-len(f[key]) // max_points))
                f[key] = [float(f"{v:.4g}") for v in f[key][k - 1 :: k]]
                f["curve_every"] = k
    return entry


def _previous_sections(rerun):
    """Committed results of the tables not rerun now: name -> (json entry, markdown lines)."""
    import json

    js, mdp = RESULTS_DIR / "seed000_tracking.json", RESULTS_DIR / "seed000_tracking.md"
    if not js.exists() or not mdp.exists():
        return {}
    old = json.loads(js.read_text()).get("tables", {})
    text = mdp.read_text().split("\n")
    out = {}
    for name, entry in old.items():
        if name in rerun:
            continue
        head = f"## {entry.get('title', '')}"
        if head not in text:
            continue
        start = text.index(head)
        end = next((i for i in range(start + 1, len(text)) if text[i].startswith("## ")), len(text))
        out[name] = (entry, text[start:end])
    return out


def _rows(study, results):
    rows = []
    for name, r in results.items():
        p = study.paper.get(name, {})
        rows.append(
            [
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
            ]
        )
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="smoke run: 3 runs, Table 7 only")
    parser.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default 100)")
    parser.add_argument(
        "--runs-table8", type=int, default=None, help="runs for Table 8 (1000 steps each; default: --runs)"
    )
    parser.add_argument(
        "--tables", nargs="+", default=None, choices=["jump", "jump_zero_glint", "range_bearing"]
    )
    parser.add_argument(
        "--r-thresholds",
        nargs="*",
        type=float,
        default=[1e-3, 1e-1],
        help="extra R-GSF cost thresholds for Table 7 (sensitivity; default 0.001 0.1)",
    )
    parser.add_argument(
        "--table8-newton",
        type=int,
        default=0,
        help="Newton steps of PCM's λ search in Table 8 (default 0: grid only)",
    )
    parser.add_argument("--table8-ise", action="store_true", help="track the per-step ISE in Table 8")
    args = parser.parse_args(argv)
    n_runs = args.runs or (3 if args.quick else 100)
    tables = args.tables or (["jump"] if args.quick else ["jump", "jump_zero_glint", "range_bearing"])
    header = [
        "filter",
        "ARMSE ± s.e.",
        "paper ARMSE",
        "AEISE",
        "paper AEISE",
        "mean ISE",
        "components",
        "ANEES",
        "ms / run",
        "compile s",
        "paper CPU s",
    ]
    md = ["# Seed 000 Tables 7 and 8: Gaussian sum filters and a particle filter", ""]
    data = {"tables": {}}
    kept = {} if args.quick else _previous_sections(tables)
    for name in ["jump", "jump_zero_glint", "range_bearing"]:
        if name not in tables:
            if name in kept:  # a table not rerun keeps its committed numbers
                data["tables"][name], section = kept[name]
                md += section
            continue
        study = studies.STUDIES[name]()
        if name == "range_bearing":
            study = table8_study(study, newton_steps=args.table8_newton, track_ise=args.table8_ise)
        else:
            study = with_r_thresholds(study, args.r_thresholds)
        runs = args.runs_table8 if (name == "range_bearing" and args.runs_table8) else n_runs
        print(f"{study.title}: {runs} runs")
        results = studies.run_study(study, runs, jax.random.key(0))
        print(studies.format_table(study, results))
        stem = (
            "seed000_"
            + study.table.removeprefix("seed000-").replace("-", "_")
            + ("_quick" if args.quick else "")
        )
        png = studies.plot_study(study, results, RESULTS_DIR / f"{stem}.png")
        md += [
            f"## {study.title}",
            "",
            markdown_table(header, _rows(study, results)),
            "",
            f"{runs} runs here; paper: {study.paper_runs or 'not stated'}. ARMSE is the time-averaged "
            "position RMSE with its Monte Carlo standard error; AEISE is the mean EISE that PCM's search "
            "minimised (the paper does not define it for NL/R-GSF); mean ISE is between each step's updated "
            "mixture and its reduction; ms / run excludes compilation. The paper's CPU seconds are MATLAB "
            "totals for all its runs. Timings were taken on a shared, loaded 2-core machine (other benchmarks "
            "and tests running; about one core was taken by a background benchmark).",
            "",
            f"Notes: {study.notes}",
            "",
        ]
        if name != "range_bearing":
            md += [separation_note(results, READING_WHY[name]), ""]
        if png:
            md += [f"![{study.table}]({png.name})", ""]
        data["tables"][name] = compact_curves(studies.results_json(study, results))
    path = write_results("seed000_tracking", data, "\n".join(md), quick=args.quick)
    print(f"wrote {path}")
    return data


if __name__ == "__main__":
    main()
