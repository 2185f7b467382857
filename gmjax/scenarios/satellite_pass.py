"""A satellite tracked by a ground radar over one pass, Zhang et al. (PCRB from Gaussian mixtures;
seed 002 §V-C, eqs 78-87, Tables I-III).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmjax._types import Array, ArrayLike, DTypeLike
from gmjax.mixture import GaussianMixture, from_gaussian
from gmjax.pcrb import GMMPCRBConfig, PCRBModel

__all__ = [
    "kepler_propagate",
    "rv_to_elements",
    "elements_to_rv",
    "radar_measurement",
    "SatelliteScenario",
    "satellite",
]

# ------------------------------------------------------------------------------------------------

MU_EARTH = 398600.4418  # km^3 / s^2
OMEGA_EARTH = 7.2921158553e-5  # rad / s
WGS84_A = 6378.137  # km
WGS84_F = 1.0 / 298.257223563

#: Table I: radar site (geodetic latitude, longitude in degrees, altitude in m).
RADAR_SITE = (34.490, 109.340, 0.0)
#: Table II: reference state (km, km/s) at t = -33.320833 h.
SATELLITE_STATE = (2338.826455, -6729.856951, -0.308879, -1.037072, -0.351360, 7.401615)
SATELLITE_EPOCH_S = -33.320833 * 3600.0
#: Table III: equivalent orbital elements (a km, e, i, RAAN, argument of perigee, true anomaly deg).
SATELLITE_ELEMENTS = (7129.326543, 0.001353, 98.414902, 289.163500, 61.278714, 298.718775)


def kepler_propagate(x: Array, dt: Array, mu: float = MU_EARTH, n_iter: int = 10) -> Array:
    """Two-body propagation of ``x = [r, v]`` (km, km/s) over ``dt`` seconds (seed 002 eq 84).

    Lagrange ``f, g`` functions with the eccentric-anomaly change ``dE`` from Kepler's equation
    ``n dt = dE - (1 - r0/a) sin dE + sigma0 / sqrt(a) (1 - cos dE)``, ``sigma0 = r0.v0 / sqrt(mu)``,
    solved by ``n_iter`` Newton steps (a fixed count, so ``jax.jacfwd`` gives the state transition
    matrix of the converged solution). Elliptic orbits only.
    """
    r0v, v0v = x[:3], x[3:]
    dt = jnp.asarray(dt, x.dtype)
    r0 = jnp.sqrt(r0v @ r0v)
    sig0 = (r0v @ v0v) / jnp.sqrt(mu)
    alpha = 2.0 / r0 - (v0v @ v0v) / mu  # 1 / a
    a = 1.0 / alpha
    sa = jnp.sqrt(a)
    nmean = jnp.sqrt(mu * alpha**3)
    M = nmean * dt

    def newton(_, dE):
        s, c = jnp.sin(dE), jnp.cos(dE)
        F = dE - (1.0 - r0 / a) * s + sig0 / sa * (1.0 - c) - M
        dF = 1.0 - (1.0 - r0 / a) * c + sig0 / sa * s
        return dE - F / dF

    dE = jax.lax.fori_loop(0, n_iter, newton, M)
    s, c = jnp.sin(dE), jnp.cos(dE)
    r = a + (r0 - a) * c + sig0 * sa * s
    f = 1.0 - a / r0 * (1.0 - c)
    g = dt + jnp.sqrt(a**3 / mu) * (s - dE)
    fdot = -jnp.sqrt(mu * a) / (r * r0) * s
    gdot = 1.0 - a / r * (1.0 - c)
    return jnp.concatenate([f * r0v + g * v0v, fdot * r0v + gdot * v0v])


def rv_to_elements(x: Array, mu: float = MU_EARTH) -> Array:
    """Cartesian ``[r, v]`` -> classical elements ``[a, e, i, RAAN, argp, M]`` (radians).

    Non-circular, non-equatorial orbits (as in Table III).
    """
    r, v = x[:3], x[3:]
    rn = jnp.sqrt(r @ r)
    h = jnp.cross(r, v)
    hn = jnp.sqrt(h @ h)
    nvec = jnp.array([-h[1], h[0], 0.0], dtype=x.dtype)
    evec = jnp.cross(v, h) / mu - r / rn
    e = jnp.sqrt(evec @ evec)
    a = 1.0 / (2.0 / rn - (v @ v) / mu)
    inc = jnp.arccos(h[2] / hn)
    raan = jnp.arctan2(nvec[1], nvec[0])
    argp = jnp.arctan2((jnp.cross(nvec, evec) @ h) / hn, nvec @ evec)
    nu = jnp.arctan2((jnp.cross(evec, r) @ h) / hn, evec @ r)
    E = 2.0 * jnp.arctan2(jnp.sqrt(1.0 - e) * jnp.sin(nu / 2.0), jnp.sqrt(1.0 + e) * jnp.cos(nu / 2.0))
    M = E - e * jnp.sin(E)
    return jnp.stack([a, e, inc, raan, argp, M])


def elements_to_rv(el: Array, mu: float = MU_EARTH, n_iter: int = 10) -> Array:
    """Classical elements ``[a, e, i, RAAN, argp, M]`` -> Cartesian ``[r, v]`` (Kepler by Newton)."""
    a, e, inc, raan, argp, M = (el[k] for k in range(6))
    E = jax.lax.fori_loop(0, n_iter, lambda _, E: E - (E - e * jnp.sin(E) - M) / (1 - e * jnp.cos(E)), M)
    cE, sE = jnp.cos(E), jnp.sin(E)
    b = a * jnp.sqrt(1.0 - e * e)
    rp = jnp.stack([a * (cE - e), b * sE, 0.0 * a])
    rdot = jnp.sqrt(mu * a) / (a * (1.0 - e * cE))
    vp = jnp.stack([-a * sE * rdot / a, b * cE * rdot / a, 0.0 * a])
    co, so = jnp.cos(raan), jnp.sin(raan)
    ci, si = jnp.cos(inc), jnp.sin(inc)
    cw, sw = jnp.cos(argp), jnp.sin(argp)
    Rm = jnp.array(
        [
            [co * cw - so * sw * ci, -co * sw - so * cw * ci, so * si],
            [so * cw + co * sw * ci, -so * sw + co * cw * ci, -co * si],
            [sw * si, cw * si, ci],
        ]
    )
    return jnp.concatenate([Rm @ rp, Rm @ vp])


def geodetic_to_ecef(lat_deg: float, lon_deg: float, alt_m: float) -> np.ndarray:
    """WGS-84 geodetic coordinates -> Earth-fixed position (km)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    e2 = WGS84_F * (2.0 - WGS84_F)
    N = WGS84_A / np.sqrt(1.0 - e2 * np.sin(lat) ** 2)
    h = alt_m / 1000.0
    return np.array(
        [
            (N + h) * np.cos(lat) * np.cos(lon),
            (N + h) * np.cos(lat) * np.sin(lon),
            (N * (1.0 - e2) + h) * np.sin(lat),
        ]
    )


def _enu_matrix(lat_deg: float, lon_deg: float) -> np.ndarray:
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    return np.array(
        [
            [-np.sin(lon), np.cos(lon), 0.0],
            [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
            [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)],
        ]
    )


def radar_measurement(
    x: Array,
    t: ArrayLike,
    theta0: float,
    *,
    range_rate: bool = False,
    site: tuple[float, float, float] = RADAR_SITE,
) -> Array:
    """Range (km), azimuth, elevation (rad) and optionally range rate (km/s) of an inertial state.

    The Earth (and the site) rotates about z with ``theta(t) = theta0 + omega_E t``; the
    topocentric vector is expressed in the site's east-north-up frame; the range rate uses the
    velocity relative to the rotating Earth.
    """
    th = theta0 + OMEGA_EARTH * jnp.asarray(t, x.dtype)
    c, s = jnp.cos(th), jnp.sin(th)
    rot_fixed_to_inertial = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=x.dtype)
    site_ecef = jnp.asarray(geodetic_to_ecef(*site), x.dtype)
    enu = jnp.asarray(_enu_matrix(site[0], site[1]), x.dtype)
    r, v = x[:3], x[3:]
    rho_fixed = rot_fixed_to_inertial.T @ (r - rot_fixed_to_inertial @ site_ecef)
    omega = jnp.array([0.0, 0.0, OMEGA_EARTH], dtype=x.dtype)
    vrel_fixed = rot_fixed_to_inertial.T @ (v - jnp.cross(omega, r))
    loc = enu @ rho_fixed
    rng = jnp.sqrt(loc @ loc)
    az = jnp.arctan2(loc[0], loc[1])
    el = jnp.arcsin(loc[2] / rng)
    out = [rng, az, el]
    if range_rate:
        out.append((rho_fixed @ vrel_fixed) / rng)
    return jnp.stack(out)


@jax.jit
def _element_split_prior(x0, Sigma0, library):
    """Sigma_0 -> element space (linear), split along a, back to Cartesian by eqs 25-26."""
    from gmjax.split import split_mixture

    G = jax.jacfwd(rv_to_elements)(x0)
    el0 = rv_to_elements(x0)
    P_el = G @ Sigma0 @ G.T
    gm_el = split_mixture(from_gaussian(el0, P_el), library, 0)
    means = jax.vmap(elements_to_rv)(gm_el.means)
    Jb = jax.vmap(jax.jacfwd(elements_to_rv))(gm_el.means)
    covs = jnp.einsum("kij,kjl,kml->kim", Jb, gm_el.covs, Jb)
    covs = 0.5 * (covs + jnp.swapaxes(covs, -1, -2))
    return GaussianMixture(gm_el.weights, means, covs, gm_el.mask)


class SatelliteScenario(NamedTuple):
    """The satellite tracking problem of seed 002 §V-C.

    Attributes:
        model: the :class:`PCRBModel` (state index 0 at ``t = -33.320833 h``, index ``n >= 1`` at
            ``times[n]``).
        times: ``(T + 1,)`` seconds: ``times[0]`` the Table II epoch, ``times[1:] = 0, 5, 10, ...``
            over the visible arc.
        theta0: Earth rotation angle at ``t = 0`` (see :func:`satellite`).
        prior_gm: the 49-component GMM of ``x_0`` (split along the semimajor axis in element space).
        config: Algorithm 1 settings (``mode="small"``, linear propagator, threshold 0.01).
    """

    model: PCRBModel
    times: np.ndarray
    theta0: float
    prior_gm: GaussianMixture
    config: GMMPCRBConfig


def _rising_theta0(x_t0: np.ndarray) -> float:
    """Earth angle at ``t = 0`` that puts the satellite on the horizon (elevation 0), rising."""
    from scipy.optimize import brentq

    x = jnp.asarray(x_t0)
    el_fn = jax.jit(jax.vmap(lambda th: radar_measurement(x, 0.0, th)[2]))
    el = lambda th: float(el_fn(jnp.asarray([th]))[0])  # noqa: E731
    grid = np.linspace(0.0, 2 * np.pi, 721)
    vals = np.asarray(el_fn(jnp.asarray(grid)))
    x5 = jax.jit(kepler_propagate)(x, 5.0)
    el5 = jax.jit(lambda th: radar_measurement(x5, 5.0, th)[2])
    for k in range(len(grid) - 1):
        if np.sign(vals[k]) != np.sign(vals[k + 1]):
            th = brentq(el, grid[k], grid[k + 1], xtol=1e-14)
            if float(el5(th)) > 0:  # rising: positive elevation 5 s later
                return float(th)
    raise ValueError("no Earth angle puts the reference orbit on the site's horizon at t = 0")


@partial(jax.jit, static_argnames=("max_steps",))
def _arc_elevations(x_t0, theta0, dt, max_steps):
    def step(x, k):
        x1 = kepler_propagate(x, dt)
        return x1, radar_measurement(x1, k * dt, theta0)[2]

    _, els = jax.lax.scan(step, x_t0, jnp.arange(1, max_steps, dtype=x_t0.dtype))
    return els


def satellite(
    *,
    range_rate: bool = False,
    dt: float = 5.0,
    max_steps: int = 400,
    num_split_sigma: float = 0.25,
    dtype: DTypeLike | None = None,
) -> SatelliteScenario:
    """Seed 002 §V-C: two-body orbit, ground radar, 49-component prior.

    Readings where the paper is silent: (i) the epoch (Earth angle) is not given, so ``theta0`` is
    chosen so that the reference orbit rises through the site's horizon exactly at ``t = 0`` (the
    paper: ``t = 0`` is "the first observation of the current arc"); (ii) the visible arc is every
    5 s while the reference elevation is positive; (iii) the prior GMM is built by linearly mapping
    ``Sigma_0`` (eq 85) to classical elements ``[a, e, i, RAAN, argp, M]``, splitting along ``a`` with
    the uniform library ``sigma = 1/4`` (49 terms; the marginal of ``a`` is split and the conditional
    of the other elements given ``a`` kept) and mapping each component back with eqs 25-26.
    ``Q`` and ``R`` are eqs 86-87 (``R`` restricted to R, A, E without range rate).
    """
    from gmjax.split import uniform_library

    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    x0 = jnp.asarray(SATELLITE_STATE, dtype)
    x_t0 = jax.jit(kepler_propagate)(x0, -SATELLITE_EPOCH_S)
    theta0 = _rising_theta0(np.asarray(x_t0))
    els = np.asarray(
        _arc_elevations(x_t0, jnp.asarray(theta0, dtype), jnp.asarray(dt, dtype), int(max_steps))
    )
    n_vis = int(np.argmax(els <= 0)) if np.any(els <= 0) else len(els)
    times = np.concatenate([[SATELLITE_EPOCH_S], dt * np.arange(n_vis + 1)])
    times_j = jnp.asarray(times, dtype)

    def f(x, n):
        return kepler_propagate(x, times_j[n + 1] - times_j[n])

    def h(x, n):
        return radar_measurement(x, times_j[n], theta0, range_rate=range_rate)

    Sigma0 = jnp.diag(jnp.asarray([1e-2] * 3 + [1e-8] * 3, dtype))
    Q = jnp.diag(jnp.asarray([1e-6] * 3 + [1e-12] * 3, dtype))
    Rdiag = [4e-6, 1e-6, 1e-6] + ([1e-12] if range_rate else [])
    R = jnp.diag(jnp.asarray(Rdiag, dtype))
    model = PCRBModel(f=f, h=h, Q=Q, R=R, prior=from_gaussian(x0, Sigma0))
    # prior GMM in element space
    prior_gm = _element_split_prior(x0, Sigma0, uniform_library(num_split_sigma))
    config = GMMPCRBConfig(
        num_components=prior_gm.capacity, mode="small", propagator="linear", threshold=0.01
    )
    return SatelliteScenario(model, times, theta0, prior_gm, config)
