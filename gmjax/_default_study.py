"""The default study run by plain ``gmjax``.

Seed 000's static random cases (Tables 5–6: 30 components reduced to 20, 100 components reduced to
60, 1-D, weights/means/standard deviations drawn uniformly from the paper's ranges), ``draws``
mixtures each, every approximation applied to all draws at once under ``jit(vmap(...))``. It prints
mean ± standard deviation of ISE and NISE (seed 000 eqs 42–43) and the final component count, and
writes a JSON file and a PNG of one draw's densities.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax import metrics
from gmjax import mixture as mx
from gmjax.mixture import GaussianMixture


class StaticCase(NamedTuple):
    """Seed 000 random static case (Tables 5–6)."""

    name: str
    n_components: int
    target: int
    weight_range: tuple[float, float]
    mean_range: tuple[float, float]
    std_range: tuple[float, float]


CASES = (
    StaticCase("30 -> 20", 30, 20, (1e-2, 0.2), (-2.0, 4.0), (0.4, 1.0)),
    StaticCase("100 -> 60", 100, 60, (1e-3, 0.1), (-7.0, 6.0), (0.3, 2.0)),
)


def draw_mixtures(case: StaticCase, key: jax.Array, n: int) -> GaussianMixture:
    """``n`` random 1-D mixtures ``(n, K)`` with uniform weights/means/std in the case's ranges."""
    kw, km, ks = jax.random.split(key, 3)
    K = case.n_components
    w = jax.random.uniform(kw, (n, K), minval=case.weight_range[0], maxval=case.weight_range[1])
    w = w / w.sum(-1, keepdims=True)
    m = jax.random.uniform(km, (n, K, 1), minval=case.mean_range[0], maxval=case.mean_range[1])
    s = jax.random.uniform(ks, (n, K), minval=case.std_range[0], maxval=case.std_range[1])
    return GaussianMixture(w, m, (s**2)[..., None, None], jnp.ones((n, K), bool))


def moment_matched(gm: GaussianMixture) -> GaussianMixture:
    """The single Gaussian with the mixture's mean and covariance."""
    mu, P = mx.moments(gm)
    return mx.from_gaussian(mu, P)


def approximations(case: StaticCase) -> dict[str, Callable[[GaussianMixture], GaussianMixture]]:
    """Name -> reduction ``gm -> gm`` for this case."""
    from gmjax import reduction

    return {
        "moment-matched Gaussian": moment_matched,
        f"keep {case.target} heaviest (renormalised)": lambda g: mx.top_k(g, case.target, renormalize=True),
        f"Runnalls to {case.target}": lambda g: reduction.runnalls(g, case.target)[0],
        "PCM (Xu et al.)": lambda g: reduction.pcm(g)[0],
    }


_CHUNK = 100  # draws per compiled call of the static study


def _draw_slice(gms: GaussianMixture, start: int, size: int) -> GaussianMixture:
    """Draws ``start .. start + size`` (the last chunk padded with copies of the first draws)."""
    n = gms.weights.shape[0]
    idx = (start + np.arange(size)) % n
    return jax.tree_util.tree_map(lambda a: a[idx], gms)


def _score(full: GaussianMixture, approx: GaussianMixture) -> dict[str, jax.Array]:
    return {
        "ise": metrics.ise(full, approx),
        "nise": metrics.nise(full, approx),
        "count": mx.n_active(approx),
    }


def run(
    *,
    draws: int = 1000,
    seed: int = 0,
    out: Path = Path("gmjax_out"),
    plot: bool = True,
    progress: bool = True,
) -> int:
    """Run the study; print the tables; write ``out/default_study.json`` (and a PNG).

    With ``progress`` each compilation is announced and a bar over the ``(case, approximation)`` pairs
    moves on stderr; the tables go to stdout, with compile and run seconds apart.
    """
    from gmjax._progress import Progress
    from gmjax._version import __version__

    if isinstance(draws, bool) or not isinstance(draws, int) or draws < 1:
        raise ValueError(f"draws: must be a positive int, got {draws!r}")
    out.mkdir(parents=True, exist_ok=True)
    key = jax.random.key(seed)
    dtype = str(jnp.zeros(()).dtype)
    results = {}
    print(
        f"gmjax {__version__} (JAX {jax.__version__}): static random cases of Xu et al. (PCM), {draws} draws "
        f"each, seed {seed}, {dtype}, on {jax.devices()[0].platform.upper()}"
    )
    first_draws = {}
    n_pairs = sum(len(approximations(c)) for c in CASES)
    chunk = min(draws, _CHUNK)
    bar = Progress(n_pairs * draws, desc="static cases", unit="reductions", enabled=progress)
    for case_key, case in zip(jax.random.split(key, len(CASES)), CASES):
        gms = draw_mixtures(case, case_key, draws)
        first_draws[case.name] = jax.tree_util.tree_map(lambda a: a[0], gms)
        rows: dict[str, dict[str, Any]] = {}
        print(f"\ncase {case.name} ({case.n_components} components, 1-D)")
        print(
            f"{'approximation':38s} {'ISE mean ± std':>24s} {'NISE mean ± std':>24s} {'count':>7s} "
            f"{'compile s':>9s} {'run s':>7s}"
        )
        for name, fn in approximations(case).items():
            scored = jax.jit(jax.vmap(lambda g: _score(g, fn(g))))  # noqa: B023 (run in this iteration)
            t0 = time.perf_counter()
            with bar.compiling(f"{case.name}: {name}"):
                compiled = scored.lower(_draw_slice(gms, 0, chunk)).compile()
            t1 = time.perf_counter()
            parts = []
            for start in range(0, draws, chunk):  # chunks of the draws, so the bar moves
                parts.append(jax.tree_util.tree_map(np.asarray, compiled(_draw_slice(gms, start, chunk))))
                bar.update(min(chunk, draws - start))
            res = jax.tree_util.tree_map(lambda *a: np.concatenate(a)[:draws], *parts)
            t2 = time.perf_counter()
            rows[name] = {k: {"mean": float(v.mean()), "std": float(v.std())} for k, v in res.items()}
            rows[name]["compile_s"] = t1 - t0
            rows[name]["run_s"] = t2 - t1
            r = rows[name]
            print(
                f"{name:38s} {r['ise']['mean']:11.3e} ± {r['ise']['std']:10.3e} "
                f"{r['nise']['mean']:11.3e} ± {r['nise']['std']:10.3e} {r['count']['mean']:7.1f} "
                f"{t1 - t0:9.2f} {t2 - t1:7.2f}",
                flush=True,
            )
        results[case.name] = rows
    from gmjax.montecarlo import json_safe

    summary = {
        "draws": draws,
        "seed": seed,
        "dtype": dtype,
        "gmjax_version": __version__,
        "jax_version": jax.__version__,
        "config": {
            "cases": [c._asdict() for c in CASES],
            "approximations": {c.name: list(approximations(c)) for c in CASES},
        },
        "cases": results,
    }
    (out / "default_study.json").write_text(json.dumps(json_safe(summary), indent=2, allow_nan=False))
    print(f"\nwrote {out / 'default_study.json'}")
    if plot:
        _plot(first_draws, out / "default_study.png")
    return 0


def _plot(first_draws: dict[str, GaussianMixture], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed (pip install 'gmjax[plot]'): no PNG written")
        return
    fig, axes = plt.subplots(1, len(CASES), figsize=(6 * len(CASES), 4))
    for ax, case in zip(np.atleast_1d(axes), CASES):
        gm = first_draws[case.name]
        lo, hi = case.mean_range
        x = jnp.linspace(lo - 4, hi + 4, 800)[:, None]
        ax.plot(x[:, 0], mx.pdf(gm, x), "k", lw=2, label=f"original ({case.n_components})")
        for name, fn in approximations(case).items():
            ax.plot(x[:, 0], mx.pdf(jax.jit(fn)(gm), x), lw=1.2, label=name)
        ax.set_title(f"case {case.name}: first draw")
        ax.set_xlabel("x")
        ax.set_ylabel("density")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")
