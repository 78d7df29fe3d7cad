"""The MSCKF update (OpenVINS' UpdaterMSCKF): the selected feature tracks, triangulated and projected onto the
left nullspace of their feature Jacobians, a chi-squared test per track, stacking, compression and one
``ekf_update``. Tracks still seen now and long enough to have reached the oldest clone are handed to the SLAM
updater (`SlamUpdater.choose`) instead, while it has room."""

from __future__ import annotations

import numpy as np

from uwbcal.pipeline.core.state import State, chi2_quantile, ekf_update
from uwbcal.pipeline.vio.camera import Camera
from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.features import (
    FeatureDatabase,
    Tracks,
    compress_normal,
    nullspace_project,
    observe,
    triangulate,
)
from uwbcal.pipeline.vio.stats import VioStats
from uwbcal.pipeline.vio.update_slam import SlamUpdater


class MsckfUpdater:
    """MSCKF feature updates of a `State` whose clones the manager keeps; counts into the shared `VioStats`
    (``features_used`` / ``features_rejected_chi2`` and the per-update record ``update_t/used/rejected``)."""

    def __init__(self, config: VioConfig, camera: Camera, stats: VioStats) -> None:
        self.config = config
        self.camera = camera
        self.stats = stats
        self.chi2 = chi2_quantile(config.chi2_quantile, np.maximum(np.arange(2 * config.max_clones + 8), 1))

    def linearize(self, state: State, db: FeatureDatabase, rows: np.ndarray) -> Tracks:
        """Triangulate the tracks of the database ``rows`` at the current clone estimates and linearise their
        observations (residuals at the current estimates, Jacobians at the first estimates when FEJ is on), in
        pixels divided by ``pixel_sigma`` (unit noise)."""
        cfg = self.config
        rows = rows[np.lexsort((db.t[rows], db.ids[rows]))]
        # the ids sorted: the tracks' lengths from where the id changes (np.unique without its sort)
        sid = db.ids[rows]
        new_track = np.empty(len(sid), bool)
        new_track[:1] = True
        np.not_equal(sid[1:], sid[:-1], out=new_track[1:])
        starts = np.flatnonzero(new_track)
        counts = np.diff(starts, append=len(sid))
        nf = len(starts)
        M = int(counts.max())
        # padded (feature, observation) layout: slot j < counts[f] holds an observation, the rest are masked
        valid = np.arange(M)[None, :] < counts[:, None]
        O = np.where(valid, starts[:, None] + np.arange(M)[None, :], starts[:, None])
        orow = rows[O]
        clones = state.clones
        clone_t = np.array([t for t, _ in clones], np.int64)
        C = np.searchsorted(clone_t, db.t[orow])  # (F, M) clone index
        names = [n for _, n in clones]
        cur = [state.value(n) for n in names]
        Rc = np.stack([c.R for c in cur])
        pc = np.stack([c.p for c in cur])
        cam = self.camera
        pts, ok = triangulate(
            Rc @ cam.R_imu_cam,
            pc + Rc @ cam.p_imu_cam,
            C,
            db.xy[orow],
            valid,
            cfg.triangulation_iterations,
            np.radians(cfg.min_parallax_deg),
        )
        Cf = C.reshape(-1)
        pf_rep = np.repeat(pts, M, axis=0)
        at = None
        if state.use_fej:  # the clones' first estimates; a feature has none (triangulated anew)
            fej = [state.fej(n) for n in names]
            at = (np.stack([c.R for c in fej])[Cf], np.stack([c.p for c in fej])[Cf], pf_rep)
        uv_hat, H_pose, H_f, p_c = observe(cam, Rc[Cf], pc[Cf], pf_rep, at)
        vflat = valid.reshape(-1)
        depth_ok = ((p_c[:, 2] > cfg.min_depth) & (p_c[:, 2] < cfg.max_depth)) | ~vflat
        good = ok & np.isfinite(pts).all(axis=1) & depth_ok.reshape(nf, M).all(axis=1)
        w = (vflat / cfg.pixel_sigma)[:, None]
        return Tracks(
            ids=sid[starts],
            counts=counts,
            rows=orow,
            C=C,
            valid=valid,
            last_t=db.t[rows[starts + counts - 1]],
            pts=pts,
            good=good,
            r=((db.uv[orow].reshape(-1, 2) - uv_hat) * w).reshape(nf, 2 * M),
            H_f=(H_f * w[:, :, None]).reshape(nf, 2 * M, 3),
            H_pose=(H_pose * w[:, :, None]).reshape(nf, M, 2, 6),
            names=names,
        )

    def update(
        self,
        state: State,
        db: FeatureDatabase,
        rows: np.ndarray,
        t_ns: int,
        trace: dict | None,
        slam: SlamUpdater,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """MSCKF update with the selected tracks; returns the padded database rows and their validity of the
        tracks ``slam`` chose to become SLAM features (`SlamUpdater.initialize`, after this update), or None."""
        tr = self.linearize(state, db, rows)
        good = tr.good
        self.stats.features_failed_triangulation += int((~good).sum())
        if trace is not None:
            trace["t"].append(t_ns)
        if not good.any():
            _trace(trace, 0, 0, 0.0, None)
            return None
        nc = len(tr.names)
        Ho, ro = nullspace_project(tr.H_f[good], tr.H_pose[good], tr.C[good], nc, tr.r[good], tr.valid[good])
        Sidx = state.index(tr.names)
        Pcc = state.P[Sidx][:, Sidx]  # rows first: a row gather is a copy of rows
        HoP = (Ho.reshape(-1, 6 * nc) @ Pcc).reshape(Ho.shape)  # one GEMM instead of k small ones
        S = HoP @ np.swapaxes(Ho, 1, 2) + np.eye(Ho.shape[1])
        nis = np.einsum("ki,ki->k", ro, np.linalg.solve(S, ro[..., None])[..., 0])
        counts = tr.counts[good]
        accept = nis < self.chi2[2 * counts - 3]
        k = len(ro)
        n_used = int(accept.sum())
        n_rej = k - n_used
        st = self.stats
        st.features_used += n_used
        st.features_rejected_chi2 += n_rej
        st.update_t.append(t_ns)
        st.update_used.append(n_used)
        st.update_rejected.append(n_rej)
        _trace(trace, n_used, n_rej, float(nis[accept].sum()), tr.pts[good][accept])
        if not n_used:
            return None
        chosen = slam.choose(state, tr, accept, counts, t_ns)
        H, rr = compress_normal(Ho[accept].reshape(-1, 6 * nc), ro[accept].reshape(-1))
        ekf_update(state, {n: H[:, 6 * j : 6 * j + 6] for j, n in enumerate(tr.names)}, rr, 1.0)
        self.stats.updates += 1
        if chosen.any():
            return tr.rows[good][chosen], tr.valid[good][chosen]
        return None


def _trace(trace: dict | None, used: int, rejected: int, nis: float, pts: np.ndarray | None) -> None:
    if trace is None:
        return
    trace["used"].append(used)
    trace["rejected"].append(rejected)
    trace["nis"].append(nis)
    if pts is not None and len(pts):
        trace["points"].append(pts[:50])
