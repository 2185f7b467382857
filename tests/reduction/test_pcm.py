"""gmjax.reduction.pcm: the PCM reducer (seed 000) against the reference pipeline, jit/vmap/padding/dtypes,
relaxed modes' gradients, bad arguments and the search keywords."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from eise_cases import K, _grid_for, case, random_gm

from gmjax.mixture import pad
from gmjax.reduction.eise import (
    ConfidenceSearch,
    SearchOptions,
    relaxed_eise,
)
from gmjax.reduction.gmrcm import GMRCM, gmrcm
from gmjax.reduction.merge import merge_labels
from gmjax.reduction.pcm import PCM, pcm
from references import pcm_numpy as ref


def test_pcm_matches_reference_pipeline():
    gm, w, m, P = random_gm(3, n=10)
    out, info = pcm(gm, newton_steps=0)
    kept, wk, mk, Pk = ref.prune_censored(w, m, P, 0.9544)
    lam_ref, (ow, om, oP, clusters, e_ref) = ref.pcm_grid(w, m, P, grid=11)
    assert float(info.aux["lambda"]) == pytest.approx(lam_ref)
    assert float(info.cost) == pytest.approx(e_ref, rel=1e-10)
    assert int(info.n_out) == len(clusters) == int(info.aux["n_clusters"])
    assert int(info.aux["n_reference"]) == len(kept)
    got = sorted(zip(np.asarray(out.weights)[: len(ow)], np.asarray(out.means)[: len(ow), 0]))
    exp = sorted(zip(ow, om[:, 0]))
    np.testing.assert_allclose(got, exp, rtol=1e-10)
    assert float(info.pruned_mass) == pytest.approx(1 - w[kept].sum(), abs=1e-12)
    assert float(jnp.sum(out.weights)) == pytest.approx(1.0, rel=1e-12)
    # labels: merging the kept input slots by info.labels reproduces the output (eq 41 weights)
    again = merge_labels(gm, info.labels, K, "ci")
    again = again._replace(weights=again.weights / jnp.sum(again.weights))
    for a, b in zip(again, out):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)


def _check_jit_vmap_padding_dtypes(**kw):
    gms = [random_gm(s, n=9)[0] for s in range(3)]
    eager = [pcm(g, **kw) for g in gms]
    cfg = PCM(**kw)
    jitted = jax.jit(lambda c, g: c(g))
    for g, (o, i) in zip(gms, eager):
        oj, ij = jitted(cfg, g)
        np.testing.assert_allclose(oj.weights, o.weights, rtol=1e-12)
        assert float(ij.aux["lambda"]) == pytest.approx(float(i.aux["lambda"]))
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gms)
    ob, ib = jax.vmap(lambda g: pcm(g, **kw))(stacked)
    for k, (o, i) in enumerate(eager):
        np.testing.assert_allclose(ob.means[k], o.means, rtol=1e-12, atol=1e-14)
        np.testing.assert_array_equal(ib.labels[k], i.labels)
        assert float(ib.cost[k]) == pytest.approx(float(i.cost), rel=1e-12)
    # extra padded slots change nothing but the capacity
    gm, *_ = random_gm(4, n=9, capacity=9)
    o9, i9 = pcm(gm, capacity=K, **kw)
    o12, i12 = pcm(pad(gm, K), **kw)
    np.testing.assert_allclose(o9.weights, o12.weights, rtol=1e-12)
    np.testing.assert_array_equal(i9.labels, i12.labels[:9])
    assert float(i9.cost) == pytest.approx(float(i12.cost), rel=1e-12)
    # float32 agrees with float64 to float32 rounding
    g32 = random_gm(0, n=9, dtype=jnp.float32)[0]
    o32, i32 = pcm(g32, **kw)
    assert o32.means.dtype == jnp.float32 and i32.cost.dtype == jnp.float32
    assert int(i32.n_out) == int(eager[0][1].n_out)
    np.testing.assert_allclose(o32.weights, eager[0][0].weights, rtol=1e-4, atol=1e-6)
    assert float(i32.cost) == pytest.approx(float(eager[0][1].cost), rel=1e-4)
    # float32 under vmap (the batch rules' buffers take the dtype of one evaluation, weak types
    # kept: a float32 batch failed to trace with x64 on until 2026-12-08)
    s32 = jax.tree_util.tree_map(
        lambda *a: jnp.stack(a), *[random_gm(s, n=9, dtype=jnp.float32)[0] for s in range(3)]
    )
    ob32, ib32 = jax.jit(jax.vmap(lambda g: pcm(g, **kw)))(s32)
    assert ob32.means.dtype == jnp.float32 and ib32.cost.dtype == jnp.float32
    np.testing.assert_array_equal(ib32.labels[0], i32.labels)
    np.testing.assert_allclose(ob32.means[0], o32.means, rtol=1e-6, atol=1e-6)


def test_pcm_jit_eager_vmap_padding_and_dtypes_grid_search():
    _check_jit_vmap_padding_dtypes(newton_steps=0)


@pytest.mark.slow
def test_pcm_jit_eager_vmap_padding_and_dtypes_with_newton():
    _check_jit_vmap_padding_dtypes()


def test_pcm_fixed_lambda_and_overflow():
    gm = case("multimodal")
    out, info = pcm(gm, lam=1.0, prune=False, alpha=0.01)
    assert int(info.n_out) == 6 and int(info.aux["iterations"]) == 0
    out, info = pcm(gm, lam=1.0, prune=False, capacity=4)
    assert bool(info.overflow) and int(info.n_out) == 4


def test_pcm_gradients_finite_with_padding():
    gm = case("bimodal")
    grid, labels, counts = _grid_for(gm)

    def f(means, weights):
        g = gm._replace(means=means, weights=weights)
        return relaxed_eise(1.7, g, grid, labels, counts, temperature=0.2, alpha=0.01)

    gm_, gw = jax.jit(jax.grad(f, argnums=(0, 1)))(gm.means, gm.weights)
    assert np.all(np.isfinite(gm_)) and np.all(np.isfinite(gw))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(lambda_range=(3.0, 1.0)), "lambda_range"),
        (dict(merge="kl"), "merge"),
        (dict(dims=(3,)), "dims"),
        (dict(temperature=0.0), "temperature"),
        (dict(rho=1.5), "rho"),
        (dict(grid_size=1), "grid_size"),
    ],
)
def test_pcm_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        pcm(case("unimodal"), **kwargs)


def test_pcm_and_gmrcm_search_keywords():
    """The search settings are ``**search`` keywords (:class:`SearchOptions`): a misspelt one is a
    ``TypeError`` naming it; each reducer starts from its paper's search, and its config class's
    defaults are those values (the two places a default is written agree)."""
    gm = case("unimodal")
    with pytest.raises(TypeError, match="pcm.. got an unexpected keyword argument 'lambda_rnage'"):
        pcm(gm, lambda_rnage=(1.0, 2.0))
    with pytest.raises(TypeError, match="gmrcm.. got an unexpected keyword argument 'rho'"):
        gmrcm(gm, rho=0.9)
    for config, preset in ((PCM(), ConfidenceSearch.seed000()), (GMRCM(), ConfidenceSearch.seed003())):
        for name in SearchOptions.__annotations__:
            assert getattr(config, name) == getattr(preset, name), (type(config).__name__, name)
    assert ConfidenceSearch.seed000("moment").criterion.method == "moment"
    # the defaults are the ones used: an explicit preset value gives the same bits
    for reducer, preset in ((pcm, ConfidenceSearch.seed000()), (gmrcm, ConfidenceSearch.seed003())):
        out = reducer(gm)
        explicit = reducer(
            gm, lambda_range=preset.lambda_range, alpha=preset.alpha, temperature=preset.temperature
        )
        jax.tree_util.tree_map(np.testing.assert_array_equal, out, explicit)
