"""Real NTU-VIRAL ranges: anchor initialisation against the published anchor estimates (SLICT frame).

Setup: SLICT odometry poses interpolated at the range stamps, constant pose covariance (0.05 m, 1 deg), antenna
lever arms from uwb_antennas.yaml, gamma prior +0.75 m (= -ranging_bias) with sigma 0.01 m (the published
estimates were computed with that bias fixed), beta prior 1 +- 0.001 (estimated at init), sigma_range 0.2 m,
Cauchy loss (scale 0.5 m).
Window: the whole sequence (60 s and 120 s windows are too short: the first minute of eee_01 is mostly take-off
and the anchors end up metres off). Plain `ri` is thrown off by the NLOS ranges of eee_01 anchor 100; the robust
variant `ri-robust` puts every anchor within 0.15 m.
"""

import numpy as np
import polars as pl
import pytest
import yaml

from uwbcal.pipeline.uwb.config import UwbConfig
from uwbcal.pipeline.uwb.updater import initialize_anchors, windows_from_trajectory


def _calibration(root):
    y = yaml.safe_load((root / "uwb_antennas.yaml").read_text())
    ao, tags, i = y["antenna_offset"], {}, 0
    while i < len(ao):
        tag, n = int(ao[i]), int(ao[i + 1])
        tags[str(tag)] = {"antennas": [ao[i + 2 + 3 * k : i + 5 + 3 * k] for k in range(n)]}
        i += 2 + 3 * n
    gamma = -float(y["ranging_bias"][1])
    return {
        "uwb": {
            "tags": tags,
            "sigma_range": 0.2,
            "gamma_prior": {"mean": gamma, "sigma": 0.01},  # as convert/ntu_viral.py
            "beta_prior": {"mean": 1.0, "sigma": 0.001},  # as convert/ntu_viral.py writes it
        }
    }


def _load(seq_dir):
    od = pl.read_csv(seq_dir / "slict_odometry.csv")
    traj = {
        "t_ns": od["field.header.stamp"].to_numpy().astype(np.int64),
        "p": od.select([f"field.pose.pose.position.{a}" for a in "xyz"]).to_numpy(),
        "q_xyzw": od.select([f"field.pose.pose.orientation.{a}" for a in "xyzw"]).to_numpy(),
    }
    traj["cov"] = np.broadcast_to(
        np.diag([np.deg2rad(1.0) ** 2] * 3 + [0.05**2] * 3), (len(traj["t_ns"]), 6, 6)
    )
    rg = pl.read_csv(seq_dir / "uwb_ranges.csv")
    ranges = {
        "t_ns": rg["stamp"].to_numpy().astype(np.int64),
        "tag": rg["tag"].to_numpy(),
        "antenna": rg["antenna"].to_numpy(),
        "anchor": rg["anchor"].to_numpy(),
        "distance": rg["distance"].to_numpy(),
    }
    return traj, ranges


@pytest.mark.data
@pytest.mark.parametrize("seq,site", [("eee_01", "eee"), ("nya_01", "nya")])
def test_ri_robust_matches_published_anchors(data_dir, seq, site):
    root = data_dir / "ntu_viral"
    calib = _calibration(root)
    traj, ranges = _load(root / seq)
    windows = windows_from_trajectory(traj, ranges, calib)
    res = initialize_anchors(windows, UwbConfig(init_method="ri-robust"), calib)
    pub = pl.read_csv(root / "published_anchors.csv").filter(pl.col("site") == site)
    errors = {}
    for row in pub.iter_rows(named=True):
        r = res[int(row["anchor"])]
        assert r.ok, r.warnings
        errors[row["anchor"]] = float(np.linalg.norm(r.x[:3] - [row["x"], row["y"], row["z"]]))
    print(seq, {a: round(e, 3) for a, e in errors.items()})
    assert max(errors.values()) < 0.15, errors
