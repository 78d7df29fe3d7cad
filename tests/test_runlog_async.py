"""Rerun logging in the helper process: the same .rrd as in-process, failures reported not raised, discard."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_runlog import _log_everything  # tests/ is on sys.path (no package)

from uwbcal.pipeline.viz import runlog as L
from uwbcal.pipeline.viz.log_server import AsyncRunLog, start_log_server


@pytest.fixture
def server():
    srv = start_log_server()
    assert srv is not None
    yield srv
    srv.stop()
    assert not srv._proc.is_alive()


def test_helper_writes_what_the_in_process_log_writes(tmp_path: Path, server, caplog) -> None:
    ref = tmp_path / "ref.rrd"
    with L.RunLog(ref, recording_id="rid", run_kind="euroc", blueprint=False) as log:
        _log_everything(log)
    path = tmp_path / "logs" / "02_vio.rrd"
    path.parent.mkdir()
    with server.open(path, recording_id="rid", run_kind="euroc", blueprint=False) as alog:
        assert isinstance(alog, AsyncRunLog) and alog.enabled
        _log_everything(alog)
        t = np.arange(3, dtype=np.int64)
        alog.scalars("filter/x", t, np.ones(4))  # shape mismatch: raised in the helper, reported at close
    assert not alog.enabled
    assert "filter/x" in caplog.text and "ValueError" in caplog.text
    a, b = L.read_rrd_summary(path), L.read_rrd_summary(ref)
    assert a.rows == b.rows and a.static == b.static and a.recording_ids == ["rid"]
    # the merge runs in the helper too: one run.rrd with one blueprint
    merged = server.merge([path, ref], tmp_path / "run.rrd", "euroc")
    assert merged == tmp_path / "run.rrd" and L.read_rrd_summary(merged).blueprints == 1


def test_discarded_log_leaves_no_file(tmp_path: Path, server) -> None:
    path = tmp_path / "x.rrd"
    with pytest.raises(KeyError):
        with server.open(path, recording_id="r", blueprint=False) as alog:
            alog.text("hello")
            raise KeyError("stage failed")
    assert not path.exists() and list(tmp_path.iterdir()) == []
    assert server.open(tmp_path / "y.rrd", recording_id="r", blueprint=False).close() == tmp_path / "y.rrd"


def test_no_helper_in_daemonic_process(monkeypatch) -> None:
    from types import SimpleNamespace

    import uwbcal.pipeline.viz.log_server as A

    monkeypatch.setattr(A.mp, "current_process", lambda: SimpleNamespace(daemon=True))
    assert start_log_server() is None
