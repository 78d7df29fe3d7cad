"""Sample times of a fixed-rate sensor from arrival stamps (`convert.sample_times`): a burst of samples a stalled
host delivered late is put back at the sensor's period; stamps consistent with the rate, and the gap of a dropped
sample, are kept."""

import numpy as np

from uwbcal.convert.sample_times import PERIOD_MARGIN, measured_period, sample_times

T = 10_000_000  # 100 Hz


def _host(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(sample times, arrival stamps): a few ms of latency, and a 3 s stall whose samples queue up to 0.8 s."""
    rng = np.random.default_rng(seed)
    true = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * T
    delay = rng.exponential(2e6, n).astype(np.int64)  # 2 ms mean latency
    k = np.arange(n)
    stall = (k >= 1000) & (k < 1300)
    delay[stall] += ((k[stall] - 1000) * 0.8 / 300 * 1e9).astype(np.int64)  # up to 0.8 s late
    arrive = true + delay
    arrive[1300:1380] = np.maximum(arrive[1300:1380], arrive[1299])  # the queue flushed in a burst
    arrive = np.maximum.accumulate(arrive) + np.arange(n)  # arrival order, strictly increasing
    return true, arrive


def test_regular_stamps_come_back_unchanged():
    t = 5_000 + np.arange(2000, dtype=np.int64) * T
    r = sample_times(t)
    assert np.array_equal(r.t_ns, t) and r.moved == 0 and r.max_shift_s == 0.0
    assert r.note("/imu", int(t[0])) is None


def test_a_stall_of_late_samples_is_put_back_to_the_sample_times():
    true, arrive = _host(3000)
    # the period within the margin that keeps the backward minimum from running away
    assert abs(measured_period(arrive) / (T * 1e-9) - 1) < PERIOD_MARGIN
    r = sample_times(arrive)
    err = (arrive - true) * 1e-9
    assert err.max() > 0.7  # the stamps as delivered: up to 0.8 s late
    fixed = (r.t_ns - true) * 1e-9
    # what is left is the latency of the on-time samples (ms), never a sample time after the stamp
    assert np.abs(fixed).max() < 0.015 and np.all(r.t_ns <= arrive)
    assert np.all(np.diff(r.t_ns) > 0)
    assert r.moved >= 250 and 0.7 < r.max_shift_s < 0.85
    assert "re-stamped" in r.note("/imu", int(arrive[0]))


def test_a_dropped_sample_keeps_its_gap():
    t = np.arange(1000, dtype=np.int64) * T
    t = np.delete(t, [400, 401, 402])  # three samples lost
    r = sample_times(t)
    assert np.array_equal(r.t_ns, t)
