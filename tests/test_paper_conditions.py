"""The VIO-degrade knob, the paired comparison and the paper-conditions report (tiny synthetic inputs)."""

from __future__ import annotations

import json
import re

import numpy as np
import polars as pl
import pytest

from uwbcal.convert.simulator import SimConfig
from uwbcal.evaluate.experiments.paired import paired_difference
from uwbcal.evaluate.experiments.paper_conditions import (
    first_paying_level,
    main,
    skf_vs_ekf,
    table1_claims,
    write_report,
)
from uwbcal.evaluate.experiments.ri_vs_lsi_drift import parse_levels, summarise
from uwbcal.evaluate.experiments.vio_degrade import VioDegrade
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run.config import load_config
from uwbcal.pipeline.vio.imu import ImuNoise

PNG = b"\x89PNG\r\n\x1a\n"


def test_degrade_scales_simulated_and_believed_noise_alike():
    base = SimConfig(seed=3)
    assert VioDegrade.of(1.0).sim(base) == base
    assert VioDegrade.of(1.0).config() == {"vio": {"pixel_sigma": 1.0, "on_failure": "warn"}}
    assert VioDegrade.of(3, 3).config() == VioDegrade.of(3).config()  # told = simulated: the default
    d = VioDegrade.of(3)
    s = d.sim(base)
    for name in (
        "gyro_noise_density",
        "gyro_random_walk",
        "acc_noise_density",
        "acc_random_walk",
        "pixel_sigma",
    ):
        assert getattr(s, name) == pytest.approx(3 * getattr(base, name)), name
    assert s.seed == base.seed and s.max_features == base.max_features
    assert d.config()["vio"]["pixel_sigma"] == pytest.approx(s.pixel_sigma)
    for bad in (0, -2.0, 101.0, "2", float("nan")):
        with pytest.raises(InputError, match="vio_noise_scale"):
            VioDegrade.of(bad)


def _believed_imu(degrade: VioDegrade, base: SimConfig) -> ImuNoise:
    """The IMU noise the MSCKF uses: the recording's calibration (written from the simulated figures) times the
    pipeline's ``vio.imu_noise_inflation`` (as `pipeline.msckf` builds it)."""
    s = degrade.sim(base)
    calib = {
        "imu": {
            "gyroscope_noise_density": s.gyro_noise_density,
            "gyroscope_random_walk": s.gyro_random_walk,
            "accelerometer_noise_density": s.acc_noise_density,
            "accelerometer_random_walk": s.acc_random_walk,
        }
    }
    cfg = load_config(None, degrade.config())
    return ImuNoise.from_calibration(calib, inflate=cfg.vio.imu_noise_inflation)


def test_told_factor_changes_what_the_filter_is_told_not_the_simulation():
    base = SimConfig(seed=3)
    consistent, over, under = VioDegrade.of(4), VioDegrade.of(4, 1.5), VioDegrade.of(4, 8)
    # the simulated sensors are those of the simulated factor, whatever the filter is told
    assert over.sim(base) == consistent.sim(base) == under.sim(base)
    assert over.told_scale == 1.5 and consistent.told_scale == 4.0
    one = _believed_imu(VioDegrade.of(1.0), base)
    for d, t in ((consistent, 4.0), (over, 1.5), (under, 8.0)):
        cfg = load_config(None, d.config())
        assert cfg.vio.pixel_sigma == pytest.approx(4 * base.pixel_sigma)  # the pixel noise is told right
        got = _believed_imu(d, base)
        for name in ("sigma_g", "sigma_a", "sigma_bg", "sigma_ba"):
            assert getattr(got, name) == pytest.approx(t * getattr(one, name), rel=1e-12), (t, name)
    for bad in (0, -1.0, 101.0, "2", float("nan"), True):
        with pytest.raises(InputError, match=r"^vio_noise_told="):
            VioDegrade.of(4, bad)


def test_parse_levels():
    assert parse_levels("4, 1,2") == [1.0, 2.0, 4.0]
    for bad in ("", "1,1", "1,x", "0,1", "1,200"):
        with pytest.raises(InputError, match="vio_noise_scales"):
            parse_levels(bad)


def test_paired_difference_closed_form_and_coverage():
    d = paired_difference(np.arange(1.0, 6.0) + 10.0, np.full(5, 10.0))
    # mean 3, sd sqrt(2.5), t_{0.975, 4} = 2.7764451052
    half = 2.7764451052 * np.sqrt(2.5) / np.sqrt(5)
    assert (d.mean, d.n, d.share_b) == (3.0, 5, 1.0)
    assert d.lo == pytest.approx(3 - half, rel=1e-9) and d.hi == pytest.approx(3 + half, rel=1e-9)
    assert d.significant
    # NaN pairs are dropped
    assert paired_difference([1.0, np.nan, 2.0], [0.0, 0.0, np.nan]).n == 1
    # the 95 % interval covers the true mean difference in ~95 % of repeated experiments
    rng = np.random.default_rng(1)
    hits = 0
    for _ in range(2000):
        a = rng.normal(0.3, 1.0, 8)
        b = rng.normal(0.0, 1.0, 8) + 0.5 * a  # correlated pairs
        r = paired_difference(a, b)
        hits += r.lo <= 0.3 - 0.15 <= r.hi
    assert 0.93 < hits / 2000 < 0.97


def _drift_runs(rng) -> pl.DataFrame:
    rows = []
    for k, sig, gain in ((1.0, 0.02, 0.0), (4.0, 0.08, 0.3), (8.0, 0.16, 0.8)):
        for seed in range(6):
            for a in range(4):
                e_ri = 0.2 + k * 0.05 + rng.uniform(0, 0.05)
                for m, e in (("lsi", e_ri + gain + rng.normal(0, 0.02)), ("ri", e_ri), ("ri-robust", e_ri)):
                    rows.append(
                        {
                            "vio_noise_scale": k,
                            "seed": seed,
                            "anchor": a,
                            "method": m,
                            "anchor_error_m": e,
                            "vio_sigma_m": sig,
                            "vio_rmse_m": 1.5 * sig,
                        }
                    )
    return pl.DataFrame(rows)


def test_drift_summary_and_where_ri_pays():
    t = summarise(_drift_runs(np.random.default_rng(0)))
    assert t["vio_noise_scale"].to_list() == [1.0, 4.0, 8.0]
    assert t["vio_sigma_m"].to_list() == pytest.approx([0.02, 0.08, 0.16])
    assert t["ri_gain_m"].to_list() == pytest.approx([0.0, 0.3, 0.8], abs=0.02)
    assert (t["lsi_p90_m"] >= t["lsi_median_m"]).all()
    assert t["ri_wins"][2] == 1.0 and t["lsi_failed"].to_list() == [0, 0, 0]
    failed = _drift_runs(np.random.default_rng(0)).with_row_index()
    failed = failed.with_columns(
        pl.when(pl.col("index") == 0)
        .then(float("nan"))
        .otherwise(pl.col("anchor_error_m"))
        .alias("anchor_error_m")
    )
    assert summarise(failed.drop("index"))["lsi_failed"].to_list() == [1, 0, 0]
    pay = first_paying_level(t)
    assert pay is not None and pay["vio_noise_scale"] == 4.0


def _table1_runs(rng) -> pl.DataFrame:
    rows = []
    for prior in ("fixed", "tuned"):
        for si, su in ((0.1, 1.0), (0.3, 1.0), (0.3, 0.9), (0.5, 0.9)):
            for seed in range(5):
                base = rng.uniform(0.2, 0.4)
                for m, extra in (("ekf", 0.1 * (si > 0.2)), ("skf", 0.0)):
                    rows.append(
                        {
                            "seed": seed,
                            "sigma_i": si,
                            "sigma_u": su,
                            "method": m,
                            "prmse_m": 0.38 + extra,
                            "prmse_calib_m": 0.30 + 0.05 * (m == "skf"),
                            "anchor_error_m": base + extra,
                            "rejected": 0,
                            "vio_sigma_m": 0.05,
                            "vio_rmse_m": 0.07,
                            "prior": prior,
                        }
                    )
    return pl.DataFrame(rows)


def test_skf_vs_ekf_is_paired_per_seed():
    d = skf_vs_ekf(_table1_runs(np.random.default_rng(0)).filter(pl.col("prior") == "fixed"))
    assert d.height == 4 and (d["seeds"] == 5).all()
    r = {(x["sigma_i"], x["sigma_u"]): x for x in d.iter_rows(named=True)}
    # pairs differ by exactly 0.1 at sigma_I >= 0.3 (the seed-to-seed spread cancels): a zero-width interval
    assert r[(0.3, 1.0)]["anchor_d_m"] == pytest.approx(0.1)
    assert r[(0.3, 1.0)]["anchor_lo"] == pytest.approx(0.1)
    assert r[(0.1, 1.0)]["anchor_d_m"] == pytest.approx(0.0)
    assert r[(0.1, 1.0)]["anchor_paper_d"] == pytest.approx(0.271 - 0.312)
    assert r[(0.5, 0.9)]["prmse_paper_d"] == pytest.approx(0.679 - 0.495)
    claims = {(c["cell"], c["claim"]): c["holds"] for c in table1_claims(d).iter_rows(named=True)}
    # EKF is worse by exactly 0.1 at sigma_I >= 0.3 (SKF claims hold), equal at 0.1 (zero-width interval at 0)
    assert claims[("σ_I=0.3, σ_U=1", "SKF better anchors")] == "yes"
    assert claims[("σ_I=0.5, σ_U=0.9", "SKF better PRMSE")] == "yes"
    assert claims[("σ_I=0.1, σ_U=1", "EKF better PRMSE")] == "unclear"
    # the calibration-window PRMSE is paired and judged on its own, against the paper's one PRMSE
    assert r[(0.1, 1.0)]["prmse_calib_d_m"] == pytest.approx(-0.05)
    assert r[(0.5, 0.9)]["prmse_calib_paper_d"] == pytest.approx(0.679 - 0.495)
    assert claims[("σ_I=0.1, σ_U=1", "EKF better PRMSE (calibration window)")] == "yes"
    assert claims[("σ_I=0.5, σ_U=0.9", "SKF better PRMSE (calibration window)")] == "no"
    flipped = d.with_columns(
        -pl.col("anchor_d_m"),
        -pl.col("anchor_hi").alias("anchor_lo"),
        -pl.col("anchor_lo").alias("anchor_hi"),
    )
    assert (
        table1_claims(flipped).filter(pl.col("claim") == "SKF better anchors")["holds"].to_list()
        == ["no"] * 3
    )


def _folder(path, name: str, per_run: pl.DataFrame, **config):
    path.mkdir()
    per_run.write_parquet(path / "runs.parquet")
    (path / "config.json").write_text(
        json.dumps({"experiment": name, "runs": 5, "jobs": 2, "seed": 0, **config})
    )
    (path / "summary.json").write_text(json.dumps({"wall_s": 12.5}))
    return path


def test_report_from_experiment_folders(tmp_path, capsys):
    rng = np.random.default_rng(2)
    t1 = _folder(tmp_path / "t1", "table1", _table1_runs(rng), prior="both", vio_noise_scale=5.0)
    dr = _folder(tmp_path / "dr", "ri-vs-lsi-drift", _drift_runs(rng), vio_noise_scales="1,4,8")
    out = tmp_path / "docs"
    assert main(["--table1", str(t1), "--drift", str(dr), "-o", str(out)]) == 0
    md = (out / "table1_paper_drift.md").read_text()
    assert "### prior = fixed" in md and "### prior = tuned" in md
    assert "--param vio_noise_scale=5.0" in md and "12 s wall" in md
    assert "0.379" in md and "0.271" in md  # the paper's numbers beside ours
    assert "5 seeds. VIO over the initialisation window: own position σ 0.050 m, actual RMSE 0.070 m" in md
    assert re.search(r"\| σ_I=0.3, σ_U=1 +\| SKF better anchors +\|.*\| yes +\|", md)
    dmd = (out / "ri_vs_lsi_drift.md").read_text()
    assert "RI pays" in dmd and "from k = 4" in dmd
    for png in ("table1_paper_drift.png", "ri_vs_lsi_drift.png"):
        assert (out / png).read_bytes()[:8] == PNG
    # a folder of another experiment, or none: exit 2 with one line naming it
    assert main(["--table1", str(dr), "-o", str(out)]) == 2
    assert "expected 'table1'" in capsys.readouterr().err
    assert main(["--drift", str(tmp_path / "missing"), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "missing" in err and err.count("\n") == 1


def test_ri_vs_lsi_drift_experiment_on_a_short_simulation(tmp_path):
    """Two drift levels x one seed on the built-in trajectory: every initialiser's error per anchor, the VIO's own
    sigma grows with the level, the same seed at both levels."""
    from uwbcal.evaluate.experiments.ri_vs_lsi_drift import ri_vs_lsi_drift

    table, extra = ri_vs_lsi_drift(
        tmp_path, 1, 1, None, 0, vio_noise_scales="1,3", trajectory="", duration=20.0
    )
    runs = extra["per_run"]
    assert set(runs["method"]) == {"lsi", "ri", "ri-robust"} and runs["seed"].n_unique() == 1
    assert runs.height == 2 * 3 * runs["anchor"].n_unique()
    assert table["vio_sigma_m"][1] > 2 * table["vio_sigma_m"][0]
    assert (tmp_path / "ri_vs_lsi_drift.png").read_bytes()[:8] == PNG
    assert set(extra["summary"]) == {f"k{k}.{m}.anchor_error_m" for k in (1, 3) for m in ("lsi", "ri")}


def test_table1_report_sets_both_prmse_windows_beside_the_paper(tmp_path):
    """A finished table1 folder -> Markdown with each prior's cell table (refinement- and calibration-window
    PRMSE beside the paper's one PRMSE), the paired differences, the claims, and the three-panel plot."""

    folder = tmp_path / "t1"
    folder.mkdir()
    _table1_runs(np.random.default_rng(1)).write_parquet(folder / "runs.parquet")
    config = {"experiment": "table1", "runs": 5, "jobs": 2, "scheduler": None, "seed": 0, "prior": "both"}
    (folder / "config.json").write_text(json.dumps(config))
    (folder / "summary.json").write_text(json.dumps({"wall_s": 12.0}))
    written = write_report([folder], [], tmp_path / "out")
    text = written[0].read_text()
    assert "prmse_calib_m_ours" in text and "prmse_m_paper" in text and "prmse_calib_d_m" in text
    assert "EKF better PRMSE (calibration window)" in text
    assert text.count("### prior = ") == 2
    assert written[1].stat().st_size > 10_000
