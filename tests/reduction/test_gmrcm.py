"""gmjax.reduction.gmrcm: the GMRCM reducer (seed 003): the reference at a fixed lambda, the low-weight and
large-covariance rules, the search and the config protocol."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from eise_cases import NEWTON_TOL, K, case, case_np

from gmjax.mixture import GaussianMixture, moments
from gmjax.reduction.gmrcm import GMRCM, GMRCMState, gmrcm, init_state
from references import pcm_numpy as ref


def test_gmrcm_fixed_lambda_matches_reference():
    w, m, P = case_np("multimodal")
    for lam in (1.0, 2.0, 3.0, 4.0):
        out, state, info = gmrcm(case("multimodal"), lam=lam, alpha=0.3, large_factor=jnp.inf)
        ow, om, oP, clusters, e_ref = ref.reduce_fixed(
            w,
            m,
            P,
            lam,
            merge="moment",
            triangular=True,
            subset_rule="absorb",
            alpha=0.3,
            reg="log10",
            ise_scale=1.0,
        )
        assert float(info.cost) == pytest.approx(e_ref, rel=1e-10)
        assert int(info.n_out) == len(clusters)
        np.testing.assert_array_equal(state.low_count, 0)
        # moment merging preserves the mixture mean and covariance
        for a, b in zip(moments(out), moments(case("multimodal"))):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)


def test_gmrcm_low_weight_rule_over_two_steps():
    w = np.array([0.5, 0.3, 0.005, 0.195])
    gm = GaussianMixture.create(w, [0.0, 10.0, 20.0, 30.0], [1.0] * 4, capacity=K)
    # step 1: slot 2 is low for the first time -> kept, its count becomes 1
    out, state, info = gmrcm(gm, lam=1.0)
    assert int(info.aux["n_dropped"]) == 0 and int(info.n_out) == 4
    slot2 = int(info.labels[2])
    assert int(state.low_count[slot2]) == 1 and int(jnp.sum(state.low_count)) == 1
    # step 2 (the filter hands each child its parent's count): low again -> dropped, renormalised
    out2, state2, info2 = gmrcm(out, state, lam=1.0)
    assert int(info2.aux["n_dropped"]) == 1 and int(info2.n_out) == 3
    assert float(info2.pruned_mass) == pytest.approx(0.005)
    assert float(jnp.sum(out2.weights)) == pytest.approx(1.0)
    # a component that recovers resets its count
    out3, state3, _ = gmrcm(
        gm._replace(weights=jnp.asarray(np.r_[0.4, 0.3, 0.1, 0.2, np.zeros(K - 4)])),
        GMRCMState(jnp.ones(K, jnp.int32)),
        lam=1.0,
    )
    np.testing.assert_array_equal(state3.low_count, 0)


def test_gmrcm_large_covariance_passes_through_and_state_min_rule():
    # two close small components and one broad one; the broad one is not clustered (step 4(1))
    gm = GaussianMixture.create([0.4, 0.4, 0.2], [0.0, 0.1, 0.05], [1.0, 1.0, 9.0], capacity=K)
    out, state, info = gmrcm(gm, lam=3.0)
    assert int(info.aux["n_passed"]) == 1 and int(info.n_out) == 2
    assert int(info.labels[0]) == int(info.labels[1]) != int(info.labels[2])
    out, state, info = gmrcm(gm, lam=3.0, large_factor=jnp.inf)
    assert int(info.n_out) == 1
    # a merged cluster's count is the smallest of its members'
    gm2 = GaussianMixture.create([0.005, 0.006, 0.989], [0.0, 0.1, 50.0], [1.0, 1.0, 1.0], capacity=K)
    st = GMRCMState(jnp.zeros(K, jnp.int32).at[0].set(1))  # slot 0 was low before: dropped now
    out, st2, info = gmrcm(gm2, st, lam=3.0)
    assert int(info.aux["n_dropped"]) == 1
    st = GMRCMState(jnp.zeros(K, jnp.int32))
    out, st2, info = gmrcm(gm2, st, lam=3.0)  # 0 and 1 merge, both low once -> count 1
    assert int(st2.low_count[int(info.labels[0])]) == 1


def test_gmrcm_search_and_config_protocol():
    gm = case("bimodal")
    out, state, info = GMRCM(alpha=0.01).reduce(gm, init_state(K))
    assert 0.5 <= float(info.aux["lambda"]) <= 3.0
    assert float(info.cost) <= float(info.aux["eise_grid"]) * (1 + NEWTON_TOL)
    lam = info.aux["lambda"]
    out_fixed, _, _ = gmrcm(gm, alpha=0.01, lam=lam)
    np.testing.assert_allclose(out_fixed.weights, out.weights, rtol=1e-12)
    out2, info2 = jax.jit(lambda c, g: c(g))(GMRCM(alpha=0.01, lam=lam), gm)
    np.testing.assert_allclose(out2.weights, out.weights, rtol=1e-12)
    with pytest.raises(ValueError, match="state"):
        gmrcm(gm, GMRCMState(jnp.zeros(3, jnp.int32)))
