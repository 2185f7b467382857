"""The GM-PHD recursion through Stone Soup's components (the reference for ``gmjax.multitarget.phd``).

Stone Soup's pieces: ``KalmanPredictor``, ``KalmanUpdater``, ``DistanceHypothesiser`` (no gate:
``missed_distance=inf``) inside ``GaussianMixtureHypothesiser(order_by_detection=True)``, ``PHDUpdater``
and ``GaussianMixtureReducer``; the loop around them is the one of Stone Soup's GM-PHD tutorial.

Convention bridges (so that both compute Vo & Ma's Table I on identical inputs):

* Stone Soup applies ``P_S`` inside ``PHDUpdater`` to every component not tagged ``"birth"``, and
  gives ``"birth"``-tagged components no missed-detection term. Vo & Ma's birth components do get
  one and are not multiplied by ``P_S``. We therefore add the birth intensity untagged with weight
  ``w_b / P_S`` (so ``P_S w_b / P_S = w_b``) and timestamp equal to the scan time.
* The transition model has ``F(0) = I``, ``Q(0) = 0`` (``_StepModel``), so the births are not
  propagated (the Vo & Ma intensity ``gamma_k`` is already at time ``k``) while survivors get the
  ``dt = 1`` matrices of the gmjax model.
* Stone Soup has no state extraction component: Table III (``w > 0.5``, ``round(w)`` copies) is
  applied to its reduced mixture here.

Differences that remain (by design of the two libraries, measured in ``tests/multitarget/test_phd.py``):
Stone Soup's reducer keeps ``w >= T`` and *redistributes* the pruned weight equally over the
survivors (Vo & Ma and gmjax drop it); it merges with ``d < U`` measured against the running merged
component (Vo & Ma: ``d <= U`` against the heaviest component) and **caps a merged weight at 1**;
truncation to ``J_max`` redistributes the truncated weight as well.
"""

from __future__ import annotations

import datetime

import numpy as np


def _stonesoup():
    from stonesoup.base import Property
    from stonesoup.models.transition.linear import LinearGaussianTransitionModel

    class _StepModel(LinearGaussianTransitionModel):
        """``x' = F x + v``, ``v ~ N(0, Q)`` for a positive time step; the identity for ``dt = 0``."""

        F: np.ndarray = Property(doc="transition matrix for one step")
        Q: np.ndarray = Property(doc="process noise covariance for one step")

        @property
        def ndim_state(self):
            return self.F.shape[0]

        def matrix(self, time_interval=None, **kwargs):
            if time_interval is not None and time_interval.total_seconds() == 0:
                return np.eye(self.ndim_state)
            return self.F

        def covar(self, time_interval=None, **kwargs):
            from stonesoup.types.array import CovarianceMatrix

            if time_interval is not None and time_interval.total_seconds() == 0:
                return CovarianceMatrix(np.zeros((self.ndim_state, self.ndim_state)))
            return CovarianceMatrix(self.Q)

    return _StepModel


class StoneSoupGMPHD:
    """Vo & Ma's GM-PHD (linear Gaussian) through Stone Soup components; one ``step`` per scan."""

    def __init__(
        self,
        F,
        Q,
        H,
        R,
        birth,
        *,
        survival_prob,
        detection_prob,
        clutter_intensity,
        prune_threshold=1e-5,
        merge_threshold=4.0,
        max_components=100,
    ):
        from stonesoup.hypothesiser.distance import DistanceHypothesiser
        from stonesoup.hypothesiser.gaussianmixture import GaussianMixtureHypothesiser
        from stonesoup.measures import Mahalanobis
        from stonesoup.mixturereducer.gaussianmixture import GaussianMixtureReducer
        from stonesoup.models.measurement.linear import LinearGaussian
        from stonesoup.predictor.kalman import KalmanPredictor
        from stonesoup.updater.kalman import KalmanUpdater
        from stonesoup.updater.pointprocess import PHDUpdater

        H = np.asarray(H, float)
        mapping = tuple(int(np.argmax(row)) for row in H)
        if not np.allclose(H, np.eye(H.shape[1])[list(mapping)]):
            raise ValueError("H: this adapter handles coordinate-selecting H (LinearGaussian mapping)")
        self.measurement_model = LinearGaussian(
            ndim_state=H.shape[1], mapping=mapping, noise_covar=np.asarray(R, float)
        )
        self.predictor = KalmanPredictor(_stonesoup()(F=np.asarray(F, float), Q=np.asarray(Q, float)))
        kalman_updater = KalmanUpdater(self.measurement_model)
        self.updater = PHDUpdater(
            kalman_updater,
            clutter_spatial_density=float(clutter_intensity),
            prob_detection=float(detection_prob),
            prob_survival=float(survival_prob),
        )
        self.hypothesiser = GaussianMixtureHypothesiser(
            DistanceHypothesiser(self.predictor, kalman_updater, Mahalanobis(), missed_distance=np.inf),
            order_by_detection=True,
        )
        self.reducer = GaussianMixtureReducer(
            prune_threshold=prune_threshold,
            merge_threshold=merge_threshold,
            max_number_components=max_components,
        )
        self.birth = [(float(w), np.asarray(m, float), np.asarray(P, float)) for w, m, P in birth]
        self.p_s = float(survival_prob)
        self.start = datetime.datetime(2000, 1, 1)

    def _components(self, comps, timestamp):
        from stonesoup.types.state import TaggedWeightedGaussianState

        return [
            TaggedWeightedGaussianState(
                np.asarray(m, float).reshape(-1, 1),
                np.asarray(P, float),
                weight=float(w),
                timestamp=timestamp,
                tag=f"c{i}",
            )
            for i, (w, m, P) in enumerate(comps)
        ]

    def step(self, components, zs, k):
        """One predict + update + reduce from ``components`` (list of ``(w, m, P)`` at step ``k - 1``).

        Returns:
            ``(updated, reduced)``, each a list of ``(w, m (d,), P (d, d))``.
        """
        from stonesoup.types.detection import Detection

        t_prev = self.start + datetime.timedelta(seconds=k - 1)
        t = self.start + datetime.timedelta(seconds=k)
        comps = self._components(components, t_prev)
        births = self._components([(w / self.p_s, m, P) for w, m, P in self.birth], t)
        for b in births:
            b.tag = "b" + b.tag
        detections = {
            Detection(
                np.asarray(z, float).reshape(-1, 1), timestamp=t, measurement_model=self.measurement_model
            )
            for z in zs
        }
        hypotheses = self.hypothesiser.hypothesise(comps + births, detections, t)
        updated = list(self.updater.update(hypotheses))
        upd = [
            (float(c.weight), np.asarray(c.state_vector, float).ravel(), np.asarray(c.covar, float))
            for c in updated
        ]
        reduced = self.reducer.reduce(updated)
        red = [
            (float(c.weight), np.asarray(c.state_vector, float).ravel(), np.asarray(c.covar, float))
            for c in reduced
        ]
        return upd, red

    def run(self, scans, initial=()):
        """Run over a list of scans (arrays ``(n_k, m)``); returns the reduced mixtures per step."""
        comps, out = list(initial), []
        for k, zs in enumerate(scans, start=1):
            _, comps = self.step(comps, zs, k)
            out.append(comps)
        return out


def extract(components, threshold=0.5):
    """Vo & Ma Table III on a list of ``(w, m, P)``: ``#{r >= 0 : w > r + threshold}`` copies of ``m``."""
    est = []
    for w, m, _ in components:
        if w > threshold:
            est += [m] * int(np.ceil(w - threshold))
    return np.array(est).reshape(-1, components[0][1].shape[0] if components else 0)
