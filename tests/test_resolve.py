"""`run.resolve`: every "auto" key decided from the recording, with its reason; the input config untouched."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from uwbcal.pipeline.core.topics import TOPIC_CAM0, TOPIC_FEATURES, TOPIC_IMU, TOPIC_ODOM, TOPIC_RANGE
from uwbcal.pipeline.run.config import load_config
from uwbcal.pipeline.run.resolve import ALLAN_NOISE_INFLATION, imu_is_real, resolve

S = 1_000_000_000


class StubReader:
    """What `resolve` reads of a recording: topics, source, calibration, ranges, odometry poses."""

    def __init__(self, topics, dataset="simulation", calibration=None, anchors_late=False):
        self.path = "stub.mcap"
        self._topics = {t: SimpleNamespace(start_ns=0, end_ns=90 * S, count=100) for t in topics}
        self.source = {"dataset": dataset}
        self.calibration = calibration or {}
        t = np.arange(0, 90 * S, S // 10)
        anchor = np.where(np.arange(len(t)) % 2 == 0, 1, 2)
        if anchors_late:  # anchor 2 ranged only in the last third
            anchor = np.where(t < 60 * S, 1, anchor)
        self._ranges = SimpleNamespace(t_ns=t, anchor=anchor)

    def topics(self):
        return self._topics

    def read_ranges(self):
        return self._ranges

    def read_poses(self, topic):
        t = np.arange(0, 90 * S, S // 10)
        p = np.c_[np.cos(t / 1e10), np.sin(t / 1e10), 0 * t]
        return SimpleNamespace(t_ns=t, p=p, q_xyzw=np.tile([0, 0, 0, 1.0], (len(t), 1)))


def _choices(res):
    return {c.key: c.value for c in res.choices}


def test_simulated_msckf_keeps_the_papers_defaults_and_never_changes_the_input():
    cfg = load_config(None, {"run": {"recording": "stub.mcap"}})
    before = cfg.model_dump()
    res = resolve(cfg, StubReader([TOPIC_IMU, TOPIC_FEATURES, TOPIC_RANGE]))
    assert cfg.model_dump() == before  # resolved, not rewritten
    got = _choices(res)
    assert got["run.pose_source"] == "msckf" and got["uwb.init_method"] == "ri"
    assert res.config.vio.init_from_groundtruth and not any(k.startswith("vio.") for k in got)
    assert all(c.reason for c in res.choices)


def test_real_imu_defaults_fill_only_unset_keys():
    cfg = load_config(None, {"run": {"recording": "stub.mcap"}, "vio": {"max_clones": 12}})
    allan = {"imu": {"noise_origin": "allan"}}
    res = resolve(cfg, StubReader([TOPIC_IMU, TOPIC_FEATURES, TOPIC_RANGE], "euroc", allan))
    got = _choices(res)
    assert res.config.vio.max_clones == 12 and "vio.max_clones" not in got
    assert got["vio.imu_noise_inflation"] == ALLAN_NOISE_INFLATION
    assert got["vio.init_from_groundtruth"] is False and got["uwb.init_method"] == "ri-robust"
    assert imu_is_real({"dataset": "hybrid", "real": ["/imu"]}) and not imu_is_real(
        {"dataset": "x", "real": []}
    )


def test_real_imu_noise_is_taken_as_given_unless_declared_a_static_figure():
    cfg = load_config(None, {"run": {"recording": "stub.mcap"}})
    for origin, want in ((None, 1.0), ("tuned", 1.0), ("allan", ALLAN_NOISE_INFLATION)):
        cal = {"imu": {"noise_origin": origin} if origin else {}}
        res = resolve(cfg, StubReader([TOPIC_IMU, TOPIC_FEATURES, TOPIC_RANGE], "bag", cal))
        choice = next(c for c in res.choices if c.key == "vio.imu_noise_inflation")
        assert choice.value == want and "noise_origin" in choice.reason
    told = load_config(None, {"run": {"recording": "stub.mcap"}, "vio": {"imu_noise_inflation": 2.0}})
    res = resolve(told, StubReader([TOPIC_IMU, TOPIC_FEATURES, TOPIC_RANGE], "bag", {}))
    assert res.config.vio.imu_noise_inflation == 2.0


def test_a_slow_camera_gets_the_descriptor_tracker_with_its_reason():
    cfg = load_config(None, {"run": {"recording": "stub.mcap"}})
    res = resolve(cfg, StubReader([TOPIC_IMU, TOPIC_CAM0, TOPIC_RANGE], "bag", {}))  # 100 frames over 90 s
    choice = next(c for c in res.choices if c.key == "frontend.tracker")
    assert choice.value == "descriptor" and "descriptor_below_hz" in choice.reason
    told = load_config(None, {"run": {"recording": "stub.mcap"}, "frontend": {"tracker": "klt"}})
    res = resolve(told, StubReader([TOPIC_IMU, TOPIC_CAM0, TOPIC_RANGE], "bag", {}))
    assert res.config.frontend.tracker == "klt" and not any(c.key == "frontend.tracker" for c in res.choices)


def test_odometry_takes_the_declared_noise_and_error_model():
    cal = {
        "odometry": {"error_model": "drift", "noise": {"sigma_p_per_sqrt_m": 0.005, "initial_sigma_p": 0.002}}
    }
    cfg = load_config(None, {"run": {"recording": "stub.mcap"}, "odometry": {"initial_sigma_p": 0.05}})
    res = resolve(cfg, StubReader([TOPIC_ODOM, TOPIC_RANGE], calibration=cal))
    got = _choices(res)
    assert got["run.pose_source"] == "odometry" and got["odometry.error_model"] == "drift"
    assert res.config.odometry.sigma_p_per_sqrt_m == 0.005 and res.config.odometry.initial_sigma_p == 0.05
    assert "odometry.initial_sigma_p" not in got


def test_late_anchor_switches_to_the_per_anchor_schedule_refined_to_the_end():
    cfg = load_config(None, {"run": {"recording": "stub.mcap"}})
    res = resolve(cfg, StubReader([TOPIC_IMU, TOPIC_FEATURES, TOPIC_RANGE], anchors_late=True))
    got = _choices(res)
    assert got["run.schedule"] == "per-anchor" and got["run.vio_extent"] == "full"
    assert got["run.refine_window_s"] == pytest.approx(
        61.0, abs=0.01
    )  # from the 30 s init end to 90 s, + 1 s


def test_bounded_odometry_without_search_calibrates_over_two_thirds():
    cal = {"odometry": {"error_model": "bounded"}}
    cfg = load_config(
        None, {"run": {"recording": "stub.mcap", "schedule": "windows"}, "uwb": {"search": False}}
    )
    res = resolve(cfg, StubReader([TOPIC_ODOM, TOPIC_RANGE], calibration=cal))
    assert res.config.run.init_window_s == pytest.approx(
        60.0
    ) and res.config.run.refine_window_s == pytest.approx(31.0)
    assert _choices(res)["uwb.lever_arms"] in ("given", "planar")


def test_a_resolved_config_resolves_to_itself():
    cfg = load_config(None, {"run": {"recording": "stub.mcap"}})
    reader = StubReader([TOPIC_IMU, TOPIC_FEATURES, TOPIC_RANGE], dataset="euroc")
    once = resolve(cfg, reader).config
    twice = resolve(once, reader)
    assert twice.config == once and twice.choices == ()


def test_every_config_key_is_described_and_the_reference_is_current():
    from pathlib import Path

    from uwbcal.pipeline.run.config import PipelineConfig
    from uwbcal.pipeline.run.config_reference import reference_markdown

    missing = [
        f"{sec}.{k}"
        for sec, info in PipelineConfig.model_fields.items()
        for k, f in info.annotation.model_fields.items()
        if not f.description
    ]
    assert missing == []
    doc = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"
    assert doc.read_text() == reference_markdown(), (
        "regenerate: uwbcal config --reference > docs/configuration.md"
    )
