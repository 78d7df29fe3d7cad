"""SLAM features (OpenVINS' UpdaterSLAM): long tracks as landmarks in the state.

A selected track that is still seen in the current frame and reached the oldest clone becomes a landmark
(``Kind.LANDMARK``, world xyz) instead of an MSCKF feature, while there is room (``max_slam_features``): its feature
Jacobian's invertible part defines the landmark and its cross-covariances, the rest updates the state
(`State.initialize`). It is then updated in every frame that sees it (residual at the current estimates, Jacobians
at the first estimates of clone and landmark), and marginalised when its track ends or fails the chi-squared test.
OpenVINS keeps SLAM features in anchored inverse depth, which linearises well at any depth; in world xyz the first
estimate must be close, so a track becomes a landmark only when its pixels fix its depth to
``slam_max_depth_sigma`` of its distance (`landmark_sigma`): the tracks of a rotation in place or of a slow start
(depth uncertain by its own size) stay MSCKF features.
"""

from __future__ import annotations

import numpy as np

from uwbcal.pipeline.core.state import Kind, State, Vec, chi2_quantile, ekf_update
from uwbcal.pipeline.vio.camera import Camera
from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.features import Tracks, clone_name, landmark_name, landmark_sigma, observe
from uwbcal.pipeline.vio.stats import VioStats


class SlamUpdater:
    """Initialises, updates and marginalises the landmarks of a `State`; counts into the shared `VioStats`
    (``slam_initialized``, ``slam_used`` / ``slam_rejected``: the observations passing / failing its chi2 test)."""

    def __init__(self, config: VioConfig, camera: Camera, stats: VioStats) -> None:
        self.config = config
        self.camera = camera
        self.stats = stats
        self.chi2 = chi2_quantile(config.chi2_quantile, np.maximum(np.arange(2 * config.max_clones + 8), 1))

    def choose(
        self, state: State, tr: Tracks, accept: np.ndarray, counts: np.ndarray, t_ns: int
    ) -> np.ndarray:
        """Which of the MSCKF update's good tracks (``accept``: passed its chi2 test, ``counts``: their lengths)
        become SLAM features: seen now, depth-determined, the longest first while there is room."""
        good = tr.good
        slam = np.zeros(len(accept), bool)
        room = self.config.max_slam_features - len(state.of_kind(Kind.LANDMARK))
        if room > 0:
            cand = np.flatnonzero(accept & (tr.last_t[good] == t_ns))
            if len(cand):
                cand = cand[self._depth_determined(state, tr.H_f[good][cand], tr.pts[good][cand], t_ns)]
            slam[cand[np.argsort(-counts[cand], kind="stable")[:room]]] = True
        return slam

    def _depth_determined(self, state: State, H_f: np.ndarray, pts: np.ndarray, t_ns: int) -> np.ndarray:
        """Which tracks (their whitened feature Jacobians ``H_f`` (k, 2M, 3) and points) fix their landmark to
        ``slam_max_depth_sigma`` of its distance from the camera, on their pixels alone: a landmark in the state
        keeps the Jacobians of its first estimate, which must be close (a track from a rotation or a slow start
        triangulates with its depth uncertain by its own size, and its next residual is tens of pixels)."""
        x = state.value(clone_name(t_ns))
        depth = np.linalg.norm(pts - (x.p + x.R @ self.camera.p_imu_cam), axis=1)
        return landmark_sigma(H_f) < self.config.slam_max_depth_sigma * depth

    def initialize(self, state: State, tr: Tracks) -> None:
        """Each track of ``tr`` (linearised anew at the updated state) becomes a SLAM feature (OpenVINS' delayed
        initialisation, `State.initialize`): its feature Jacobian's invertible part defines the landmark and its
        cross-covariances. The rest of its rows, the left nullspace of the feature Jacobian, is what the MSCKF
        update used just before: with the update first and the landmark defined from the updated state
        (relinearised there) the joint posterior is the one of the landmark first and the rest after (its rows
        carry no information on the old state), at one update per frame instead of one per landmark. Its
        Jacobians are at the first estimates from then on, the landmark's its initial value."""
        for f in np.flatnonzero(tr.good):
            m = int(tr.counts[f])  # observations in slots 0..m-1 (the padded layout), one clone each
            H_old: dict[str, np.ndarray] = {}
            for j in range(m):
                Hb = np.zeros((2 * m, 6))
                Hb[2 * j : 2 * j + 2] = tr.H_pose[f, j]
                H_old[tr.names[tr.C[f, j]]] = Hb
            state.initialize(
                landmark_name(int(tr.ids[f])),
                Vec(tr.pts[f]),
                H_old,
                tr.H_f[f, : 2 * m],
                tr.r[f, : 2 * m],
                np.ones(2 * m),
                update_rest=False,
                kind=Kind.LANDMARK,
                key=int(tr.ids[f]),
            )
            self.stats.slam_initialized += 1

    def frame(
        self, state: State, t_ns: int, ids: np.ndarray, uv: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Update with the SLAM features seen in this frame (its clone is in the state), marginalise those not
        seen (lost tracks) and those failing the chi-squared test; returns the other observations."""
        landmarks = dict(state.of_kind(Kind.LANDMARK))
        if not landmarks:
            return ids, uv
        seen = np.isin(ids, np.fromiter(landmarks, np.int64, len(landmarks)))
        for key in set(landmarks) - set(ids[seen].tolist()):
            state.remove(landmarks.pop(key))
        if seen.any():
            self._update(state, t_ns, ids[seen], uv[seen], [landmarks[int(i)] for i in ids[seen]])
        return ids[~seen], uv[~seen]

    def _update(self, st: State, t_ns: int, ids: np.ndarray, uv: np.ndarray, names: list[str]) -> None:
        cfg = self.config
        cam = self.camera
        clone = clone_name(t_ns)
        K = len(ids)
        x = st.value(clone)
        pf = np.stack([st.value(n).x for n in names])
        at = None
        if st.use_fej:  # the clone's and the landmarks' first estimates
            xf = st.fej(clone)
            at = (
                np.broadcast_to(xf.R, (K, 3, 3)),
                np.broadcast_to(xf.p, (K, 3)),
                np.stack([st.fej(n).x for n in names]),
            )
        uv_hat, H_pose, H_f, p_c = observe(
            cam, np.broadcast_to(x.R, (K, 3, 3)), np.broadcast_to(x.p, (K, 3)), pf, at
        )
        s = 1.0 / cfg.pixel_sigma
        r = (uv - uv_hat) * s
        H_pose, H_f = H_pose * s, H_f * s
        # per feature: S = [H_pose H_f] P[(clone, feature)] [H_pose H_f]^T + I, its NIS against chi2(2)
        ic = st.index([clone])
        il = np.stack([st.index([n]) for n in names])  # (K, 3)
        P = st.P
        H9 = np.concatenate([H_pose, H_f], axis=2)  # (K, 2, 9)
        idx = np.concatenate([np.broadcast_to(ic, (K, 6)), il], axis=1)  # (K, 9)
        Pk = P[idx[:, :, None], idx[:, None, :]]
        S = H9 @ Pk @ np.swapaxes(H9, 1, 2) + np.eye(2)
        nis = np.einsum("ki,ki->k", r, np.linalg.solve(S, r[..., None])[..., 0])
        depth_ok = (p_c[:, 2] > cfg.min_depth) & (p_c[:, 2] < cfg.max_depth)
        accept = depth_ok & (nis < self.chi2[2])
        self.stats.slam_used += int(accept.sum())
        self.stats.slam_rejected += int((~accept).sum())
        # a SLAM feature failing the test is dropped (its track goes on unused)
        for k in np.flatnonzero(~accept):
            st.remove(names[k])
        a = np.flatnonzero(accept)
        if not len(a):
            return
        H: dict[str, np.ndarray] = {clone: H_pose[a].reshape(-1, 6)}
        for i, k in enumerate(a):
            Hb = np.zeros((2 * len(a), 3))
            Hb[2 * i : 2 * i + 2] = H_f[k]
            H[names[k]] = Hb
        ekf_update(st, H, r[a].reshape(-1), 1.0)
