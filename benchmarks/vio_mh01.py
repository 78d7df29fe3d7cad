"""MSCKF on simulated EuRoC MH_01_easy: accuracy (posyaw-aligned RMSE), speed (real-time factor, ms per camera
update) and consistency (ANEES over Monte Carlo runs, FEJ vs no FEJ).

    uv run python -m uwbcal.benchmarks.vio_mh01 --seeds 10                    # accuracy + speed, full 182 s
    uv run python -m uwbcal.benchmarks.vio_mh01 --nees-runs 25 --duration 40  # consistency, FEJ and no FEJ

"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from uwbcal.convert.recording import RecordingReader
from uwbcal.convert.simulator import SimConfig, simulate_to_file
from uwbcal.pipeline.core.geometry import log_so3, quat_slerp, quat_to_rot
from uwbcal.pipeline.run.driver import msckf_from_recording, run_estimator
from uwbcal.pipeline.vio.config import VioConfig


def simulate(path: Path, seed: int, duration: float | None) -> str:
    kw = {"trajectory": "MH_01_easy", "seed": seed}
    if duration:
        kw["duration"] = duration
    simulate_to_file(SimConfig(**kw), path)
    return "uwbcal.convert.simulator"


def posyaw_align(p_est: np.ndarray, p_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw rotation Rz and translation t minimising sum |Rz p_est + t - p_gt|^2."""
    a, b = p_est - p_est.mean(0), p_gt - p_gt.mean(0)
    yaw = np.arctan2(
        np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])
    )
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return Rz, p_gt.mean(0) - Rz @ p_est.mean(0)


def run_one(args: tuple[int, bool, float | None, str]) -> dict:
    seed, fej, duration, workdir = args

    path = Path(workdir) / f"mh01_{seed}_{duration}.mcap"
    sim = "cached"
    if not path.exists():
        sim = simulate(path, seed, duration)
    reader = RecordingReader(path)
    est = msckf_from_recording(reader, VioConfig(fej=fej))
    t0 = time.perf_counter()
    run_estimator(est, reader, None, None)
    wall = time.perf_counter() - t0
    h = est.history().arrays()
    gt = reader.read_poses("/groundtruth/pose")
    i = np.clip(np.searchsorted(gt.t_ns, h["t_ns"], side="right") - 1, 0, len(gt.t_ns) - 2)
    s = (h["t_ns"] - gt.t_ns[i]) / (gt.t_ns[i + 1] - gt.t_ns[i])
    p_gt = (1 - s)[:, None] * gt.p[i] + s[:, None] * gt.p[i + 1]
    R_gt = quat_to_rot(quat_slerp(gt.q_xyzw[i], gt.q_xyzw[i + 1], s))
    R_est = quat_to_rot(h["q_xyzw"])
    # unaligned errors (world frame, init from GT) for NEES
    dth = log_so3(np.swapaxes(R_est, 1, 2) @ R_gt)
    dp = p_gt - h["p"]
    cov = h["cov"]
    nees_p = np.einsum("ki,ki->k", dp, np.linalg.solve(cov[:, 3:6, 3:6], dp[..., None])[..., 0])
    nees_t = np.einsum("ki,ki->k", dth, np.linalg.solve(cov[:, 0:3, 0:3], dth[..., None])[..., 0])
    Rz, tz = posyaw_align(h["p"], p_gt)
    ep = p_gt - (h["p"] @ Rz.T + tz)
    eth = log_so3(np.swapaxes(Rz @ R_est, 1, 2) @ R_gt)
    span = (h["t_ns"][-1] - h["t_ns"][0]) * 1e-9
    return {
        "seed": seed,
        "fej": fej,
        "sim": sim,
        "data_s": span,
        "wall_s": wall,
        "realtime_x": span / wall,
        "ms_per_frame": 1e3 * wall / max(est.stats.frames, 1),
        "prmse_m": float(np.sqrt((ep**2).sum(1).mean())),
        "ormse_deg": float(np.degrees(np.sqrt((eth**2).sum(1).mean()))),
        "nees_p_t": nees_p.tolist(),
        "nees_th_t": nees_t.tolist(),
        "features_used": est.stats.features_used,
        "rejected": est.stats.features_rejected_chi2,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=0)
    ap.add_argument("--nees-runs", type=int, default=0)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--workdir", default=None)
    ap.add_argument("-o", "--output", default=None)
    a = ap.parse_args()
    work = a.workdir or tempfile.mkdtemp(prefix="vio_mh01_")
    out: dict = {}
    with ProcessPoolExecutor(a.jobs) as ex:
        if a.seeds:
            res = list(ex.map(run_one, [(s, True, a.duration, work) for s in range(a.seeds)]))
            for r in res:
                print(
                    f"seed {r['seed']}: PRMSE {r['prmse_m']:.3f} m  ORMSE {r['ormse_deg']:.3f} deg  "
                    f"{r['realtime_x']:.1f}x real time  {r['ms_per_frame']:.2f} ms/frame  ({r['sim']})"
                )
            out["accuracy"] = [{k: v for k, v in r.items() if not k.startswith("nees")} for r in res]
        if a.nees_runs:
            for fej in (True, False):
                res = list(ex.map(run_one, [(100 + s, fej, a.duration, work) for s in range(a.nees_runs)]))
                n = len(res)
                m = min(len(r["nees_p_t"]) for r in res)
                Np = np.array([r["nees_p_t"][:m] for r in res]).mean(0)
                Nt = np.array([r["nees_th_t"][:m] for r in res]).mean(0)
                lo, hi = chi2.ppf(0.025, 3 * n) / n, chi2.ppf(0.975, 3 * n) / n
                line = {
                    "fej": fej,
                    "runs": n,
                    "anees_pos": float(Np.mean()),
                    "anees_ori": float(Nt.mean()),
                    "bounds": [lo, hi],
                    "frac_inside_pos": float(np.mean((Np > lo) & (Np < hi))),
                    "frac_inside_ori": float(np.mean((Nt > lo) & (Nt < hi))),
                    "prmse_mean": float(np.mean([r["prmse_m"] for r in res])),
                }
                print(json.dumps(line))
                out[f"nees_fej_{fej}"] = line
    if a.output:
        Path(a.output).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
