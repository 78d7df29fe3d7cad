"""The rerun run log: entity tree, timelines, row counts read back from the .rrd, no-op mode, atomicity."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.viz import runlog as L

from support import T0

N = 200
ANCHORS = {"a0": [5.0, 5.0, 2.0], "a1": [-5.0, 5.0, 1.0], "7": [5.0, -5.0, 3.0]}


def _log_everything(log: L.RunLog) -> dict[str, int]:
    """Use every method once; returns the expected temporal row count per entity."""
    rng = np.random.default_rng(1)
    t = T0 + np.arange(N, dtype=np.int64) * 50_000_000
    th = np.linspace(0, 2 * np.pi, N)
    p = np.c_[3 * np.cos(th), 3 * np.sin(th), np.ones(N)]
    q = np.c_[np.zeros((N, 2)), np.sin(th / 2), np.cos(th / 2)]
    covs = np.einsum("nij,nkj->nik", *(2 * [rng.normal(0, 0.05, (N, 3, 3))])) + 1e-4 * np.eye(3)
    exp: dict[str, int] = {}

    log.stage("recording", int(t[0]))
    log.trajectory(L.GT, t, p, q)
    exp[L.GT_POSE] = N
    log.points3d(L.FEATURES, rng.uniform(-5, 5, (50, 3)), colors=L.COLORS["features"], static=True)
    for a, pa in ANCHORS.items():
        log.points3d(L.anchor_world(a, "truth"), [pa], labels=[a], static=True)

    log.stage("frontend", int(t[0]))
    log.pinhole(L.CAM, [458.0, 457.0, 367.0, 248.0], [752, 480])
    for k in range(0, N, 50):
        log.image(L.CAM_IMAGE, int(t[k]), np.full((48, 64), k, dtype=np.uint8))
        log.tracks(L.CAM_TRACKS, int(t[k]), rng.uniform(0, 48, (10, 2)), np.arange(10) + k)
    exp[L.CAM_IMAGE] = exp[L.CAM_TRACKS] = 4
    log.image("cam0/raw", int(t[0]), np.zeros((8, 8), dtype=np.float32))  # not uint8: logged raw
    exp["cam0/raw"] = 1

    log.stage("vio", int(t[0]))
    log.trajectory(L.VIO, t, p)  # no orientation: per-time points
    exp[L.VIO_POSE] = N
    log.ellipsoid_series(L.VIO_COV, t[::10], p[::10], covs[::10])
    exp[L.VIO_COV] = N // 10

    log.stage("init", int(t[N // 2]))
    for m in ("lsi", "ri", "ri-robust"):
        for a, pa in ANCHORS.items():
            log.points3d(L.anchor_world(a, m), [pa], colors=L.COLORS[m])
            exp[L.anchor_world(a, m)] = 1
        log.scalars(L.init(m, "cost"), t[:7], rng.random(7))
        exp[L.init(m, "cost")] = 7
    log.text("planar motion: z poorly observable", level="warn", t_ns=int(t[N // 2]))
    exp[L.LOG] = 1

    log.stage("refine", int(t[N // 2]))
    for a, pa in ANCHORS.items():
        r = rng.normal(0, 0.1, N)
        log.scalars(L.uwb(a, "residual"), t, r)
        log.scalars(L.uwb(a, "nis"), t, r**2 / 0.01)
        log.constant(L.uwb(a, "nis_gate"), t, 3.84, names=["chi2 95%"])
        log.scalars(L.anchor_param(a, "beta"), t, np.ones(N))
        log.ellipsoids(L.anchor_world(a, "cov"), [pa], 0.01 * np.eye(3)[None], t_ns=int(t[-1]))
        exp[L.uwb(a, "residual")] = exp[L.uwb(a, "nis")] = exp[L.anchor_param(a, "beta")] = N
        exp[L.uwb(a, "nis_gate")] = 2
        exp[L.anchor_world(a, "cov")] = 1
    log.scalars(L.SIGMA, t, np.abs(rng.normal(0, 0.1, (N, 3))), names=["x", "y", "z"])
    log.constant(L.NEES_POSE + "_bounds", t, [1.24, 14.45], names=["lo", "hi"])
    exp[L.SIGMA] = N
    exp[L.NEES_POSE + "_bounds"] = 2
    log.series_static_style(L.NEES_POSE, ["nees"], [(255, 0, 0)], points=True)
    log.scalars(L.NEES_POSE, t, rng.chisquare(6, N))
    exp[L.NEES_POSE] = N

    log.stage("localize", int(t[-1]))
    exp[L.LOG_STAGES] = exp[L.LOG_STAGE_INDEX] = 6
    return exp


def test_full_run_roundtrip(tmp_path: Path) -> None:
    path = tmp_path / "run" / "run.rrd"
    with L.RunLog(path, recording_id="rid-1", run_kind="euroc") as log:
        assert log.enabled
        exp = _log_everything(log)
        assert sorted(log.anchors()) == sorted(ANCHORS)
    assert path.is_file()
    assert [p.name for p in path.parent.iterdir()] == ["run.rrd"]  # no temp left behind

    s = L.read_rrd_summary(path)
    assert s.recording_ids == ["rid-1"] and s.application_ids == {"uwbcal"}
    assert s.timelines == {L.T_SENSOR, L.T_STAGE}
    for ent, n in exp.items():
        assert s.rows.get(ent) == n, ent
    assert set(s.rows) == set(exp)
    # static: whole-path strips, truth anchors, features, pinhole, styling
    for ent in (
        L.GT_TRAJECTORY,
        L.VIO_TRAJECTORY,
        L.FEATURES,
        L.CAM,
        L.anchor_world("7", "truth"),
        L.GT_POSE,
    ):
        assert ent in s.static, ent
    # every temporal row carries both timelines (the stage was set before anything temporal was logged)
    assert all(tl == {L.T_SENSOR, L.T_STAGE} for tl in s.timelines_by_entity.values())
    # blueprint: one, with per-anchor views and the fixed views
    assert s.blueprints == 1
    for name in (
        "world: trajectories, anchors, 3σ ellipsoids",
        "cam0",
        "a0: NIS",
        "7: range residual and gate band [m]",
        "log",
        "NEES pose (6 dof)",
        "σ position [m]",
        "β",
        "γ [m]",
    ):
        assert name in s.blueprint_names, name
    assert "NIS of the UWB updates" not in s.blueprint_names  # not logged in this run: no empty view


def test_sensor_time_is_exact_ns_and_stage_index(tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    path = tmp_path / "t.rrd"
    t = T0 + np.array([0, 1, 123_456_789], dtype=np.int64)
    with L.RunLog(path) as log:
        log.stage("refine", int(t[0]))
        log.scalars(L.uwb("a0", "range"), t, [1.0, 2.0, 3.0])
    [ch] = [c for c in RrdReader(path).stream().to_chunks() if c.entity_path == "/uwb/a0/range"]
    rb = ch.to_record_batch()
    ts = rb.column(L.T_SENSOR).cast("int64").to_numpy()
    np.testing.assert_array_equal(np.sort(ts), t)
    assert set(rb.column(L.T_STAGE).to_pylist()) == {L.STAGE_INDEX["refine"]}
    vals = [v[0] for v in rb.column("Scalars:scalars").to_pylist()]
    assert sorted(vals) == [1.0, 2.0, 3.0]


@pytest.mark.parametrize("kw", [{"path": None}, {"enabled": False}])
def test_noop_writes_nothing(tmp_path: Path, kw: dict) -> None:
    path = kw.pop("path", tmp_path / "run.rrd")
    log = L.RunLog(path, **kw)
    assert not log.enabled
    _log_everything(log)
    log.scalars("x", [0, 1, 2], [1.0])  # not even validated: the no-op returns at once
    assert log.close() is None
    assert list(tmp_path.iterdir()) == []


def test_exception_leaves_no_rrd(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    with pytest.raises(RuntimeError):
        with L.RunLog(path) as log:
            log.scalars("x", [0, 1], [1.0, 2.0])
            raise RuntimeError("stage failed")
    assert list(tmp_path.iterdir()) == []

    # the pipeline's pattern: close() in a finally while the exception propagates
    with pytest.raises(ValueError):
        log = L.RunLog(path)
        try:
            log.scalars("x", [0, 1], [1.0, 2.0])
            raise ValueError("stage failed")
        finally:
            log.close()
    assert list(tmp_path.iterdir()) == []

    log = L.RunLog(path)
    log.abort()
    assert list(tmp_path.iterdir()) == []
    assert log.close() is None  # closing twice is harmless


def test_previous_rrd_survives_failed_rewrite(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    with L.RunLog(path, recording_id="old") as log:
        log.scalars("x", [0], [1.0])
    before = path.read_bytes()
    with pytest.raises(KeyError):
        with L.RunLog(path, recording_id="new") as log:
            raise KeyError("boom")
    assert path.read_bytes() == before


def test_scalars_shape_mismatch(tmp_path: Path) -> None:
    with L.RunLog(tmp_path / "r.rrd") as log:
        with pytest.raises(ValueError, match="3 values for 2 stamps"):
            log.scalars("x", [0, 1], [1.0, 2.0, 3.0])


def test_two_logs_coexist(tmp_path: Path) -> None:
    a, b = L.RunLog(tmp_path / "a.rrd", recording_id="A"), L.RunLog(tmp_path / "b.rrd", recording_id="B")
    for k in range(3):
        a.scalars("only/a", [k], [float(k)])
        b.scalars("only/b", [k, k + 10], [1.0, 2.0])
    a.close()
    b.close()
    sa, sb = L.read_rrd_summary(tmp_path / "a.rrd"), L.read_rrd_summary(tmp_path / "b.rrd")
    assert sa.rows == {"only/a": 3} and sa.recording_ids == ["A"]
    assert sb.rows == {"only/b": 6} and sb.recording_ids == ["B"]
    assert sa.timelines == {L.T_SENSOR}  # no stage logged yet: no stage timeline


def test_merge_run_logs_one_blueprint_with_all_anchors(tmp_path: Path) -> None:
    t = T0 + np.arange(5, dtype=np.int64)
    parts = []
    for i, (stage, anchor) in enumerate([("vio", "a0"), ("refine", "a1")]):
        parts.append(tmp_path / "logs" / f"{i:02d}_{stage}.rrd")
        with L.RunLog(parts[-1], recording_id="R", blueprint=False) as log:
            log.stage(stage, int(t[0]))
            log.scalars(L.uwb(anchor, "residual"), t, np.zeros(5))
    out = L.merge_run_logs(parts, tmp_path / "run.rrd", run_kind="ntu-viral")
    s = L.read_rrd_summary(out)
    assert s.recording_ids == ["R"] and s.blueprints == 1
    assert s.rows[L.uwb("a0", "residual")] == 5 and s.rows[L.uwb("a1", "residual")] == 5
    assert s.rows[L.LOG_STAGES] == 2
    assert {"a0: NIS", "a1: NIS"} <= set(s.blueprint_names)
    assert "cam0" not in s.blueprint_names  # without camera data
    assert (
        "σ position [m]" not in s.blueprint_names and "NEES pose (6 dof)" not in s.blueprint_names
    )  # nothing logged there
    with pytest.raises(InputError, match="nope.rrd: missing"):
        L.merge_run_logs([tmp_path / "nope.rrd"], tmp_path / "x.rrd")


def test_cov_to_ellipsoid_reconstructs_covariance() -> None:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    A = rng.normal(size=(50, 3, 3))
    covs = A @ np.swapaxes(A, 1, 2)
    covs[0] = np.diag([4.0, 1.0, 0.0])  # degenerate (planar) covariance: zero half size, still a rotation
    half, quat = L.cov_to_ellipsoid(covs, n_sigma=2.0)
    R = Rotation.from_quat(quat).as_matrix()
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    rebuilt = R @ (((half / 2.0) ** 2)[:, :, None] * np.swapaxes(R, 1, 2))
    np.testing.assert_allclose(rebuilt, covs, atol=1e-9)
    np.testing.assert_allclose(np.sort(half[0]), [0.0, 2.0, 4.0], atol=1e-12)


def test_path_builders() -> None:
    assert L.anchor_world(7, "ri-robust") == "world/anchors/7/ri-robust"
    assert L.uwb("a_0", "nis") == "uwb/a_0/nis"
    assert L.init("ri", "fim_logdet") == "init/ri/fim_logdet"
    assert L.anchor_param("3", "gamma") == "anchors/3/gamma"
    assert L.uwb("a b/c", "range") == "uwb/a_b_c/range"  # odd ids stay one path part


def test_viewer_command(tmp_path: Path) -> None:
    runs = []
    for name in ("r1", "r2"):
        with L.RunLog(tmp_path / name / "run.rrd", recording_id=name) as log:
            log.text("hi")
        runs.append(tmp_path / name)
    cmd = L.viewer_command(runs)
    assert cmd[-2:] == [str(runs[0] / "run.rrd"), str(runs[1] / "run.rrd")]
    assert Path(cmd[0]).name == "rerun" or cmd[:3] == [sys.executable, "-m", "rerun"]
    web = L.viewer_command([runs[0] / "run.rrd"], web=True, port=9123, grpc_port=9124)
    assert "--serve-web" in web and web[web.index("--web-viewer-port") + 1] == "9123"
    assert web[web.index("--bind") + 1] == "127.0.0.1" and web[web.index("--port") + 1] == "9124"
    assert "9123" in L.web_url(9123, 9124) and "9124%2Fproxy" in L.web_url(9123, 9124)

    with pytest.raises(InputError, match=r"missing/run\.rrd: missing"):
        L.viewer_command([runs[0], tmp_path / "missing"])
    with pytest.raises(InputError, match="missing"):
        L.view_runs([tmp_path / "missing"], web=True)


def test_read_summary_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="none.rrd: missing"):
        L.read_rrd_summary(tmp_path / "none.rrd")


def _time_column(path: Path, entity: str):
    from rerun.chunk import RrdReader

    r = RrdReader(path)
    for st in r.recordings():
        for ch in r.stream(store=st).to_chunks():
            if ch.entity_path.lstrip("/") == entity and not ch.is_static:
                return ch.to_record_batch().column(L.T_SENSOR)
    raise AssertionError(entity)


def test_time_origin_gives_seconds_from_start(tmp_path: Path) -> None:
    t = T0 + np.array([0, 1_500_000_000], np.int64)
    with L.RunLog(tmp_path / "sim.rrd", time_origin_ns=T0) as log:
        log.scalars("x", t, [1.0, 2.0])
        log.points3d("p", [[0.0, 0.0, 0.0]], t_ns=int(t[1]))
    with L.RunLog(tmp_path / "real.rrd") as log:
        log.scalars("x", t, [1.0, 2.0])
    sim, real = _time_column(tmp_path / "sim.rrd", "x"), _time_column(tmp_path / "real.rrd", "x")
    assert str(sim.type) == "duration[ns]" and sim.cast("int64").to_pylist() == [0, 1_500_000_000]
    assert str(real.type).startswith("timestamp") and real.cast("int64").to_pylist() == t.tolist()
    assert _time_column(tmp_path / "sim.rrd", "p").cast("int64").to_pylist() == [1_500_000_000]


def test_moving_nis_band_holds_95_percent_of_consistent_averages() -> None:
    from scipy.stats import chi2

    rng = np.random.default_rng(5)
    nis = rng.chisquare(1, 20_000)
    t = np.arange(len(nis), dtype=np.int64)[::-1]  # any order: sorted by time inside
    tt, avg, lo, hi = L.moving_nis(t, nis[::-1], dof=1, window=50)
    assert len(avg) == len(nis) - 49 and np.all(np.diff(tt) > 0)
    assert lo == pytest.approx(chi2.ppf(0.025, 50) / 50) and hi == pytest.approx(chi2.ppf(0.975, 50) / 50)
    np.testing.assert_allclose(avg[0], nis[:50].mean())
    inside = np.mean((avg >= lo) & (avg <= hi))
    assert 0.93 < inside < 0.97
    assert 0.5 < np.mean(4 * avg > hi)  # a 4x over-confident filter leaves the band


def test_sliding_mean_is_the_mean_of_each_window() -> None:
    from uwbcal.pipeline.core.series import sliding_mean

    x = np.random.default_rng(0).normal(size=(40, 3))
    got = sliding_mean(x, 7)
    assert got.shape == (34, 3)
    np.testing.assert_allclose(got, [x[i : i + 7].mean(axis=0) for i in range(34)], rtol=0, atol=1e-12)
    np.testing.assert_allclose(sliding_mean(x[:, 0], 40), [x[:, 0].mean()], atol=1e-12)
    assert sliding_mean(x, 41).shape == (0, 3)
