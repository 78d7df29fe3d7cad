"""Sample times of a fixed-rate sensor from arrival stamps: samples a host delivered late put back in time.

A bag's header stamps are often the time a message reached the recording computer, not the time the sensor
sampled it. Normally the difference (the latency) is a few milliseconds; when the host stalls, the samples queue
up and arrive late, in a burst, and a VIO integrating the IMU at those stamps loses its track (a hand-held rig's
figures in docs/results/measurements.md).

The one-way delay model: a stamp is the sample time plus a delay that is never negative, and a fixed-rate
sensor's samples are at least one period apart. So a sample was taken no later than its own stamp, and no later
than one period before the next sample was taken. The backward minimum

    t̂_k = min(t_k, t̂_{k+1} − T)  =  min over j ≥ k of (t_j − (j − k) T)

is the latest time consistent with both: a burst of late samples is spread back at the sensor's period until it
meets a sample that arrived on time. A dropped sample leaves a gap longer than T, which the minimum keeps.
``T`` is the period measured over baselines of about a second (the median, robust to the jitter and to drops),
less a margin (`PERIOD_MARGIN`) so that an over-estimated period cannot pull the stamps earlier and earlier; the
minimum reaches at most `HORIZON_S` ahead, which bounds what a wrong period could move.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import minimum_filter1d

# T = (1 - margin) x the measured period: a stall of n samples is put back to within n x margin x T; a period
# over-estimated by more than the margin pulls stamps earlier by at most the horizon x the excess
PERIOD_MARGIN = 0.002
HORIZON_S = 5.0  # the longest delivery delay corrected [s]
BASELINE_S = 1.0  # the period is measured over stamps about this far apart [s]


@dataclass(frozen=True)
class Restamped:
    t_ns: np.ndarray  # the sample times, int64, in the input's order
    period_s: float  # the sensor's period measured from the stamps [s]
    moved: int  # samples moved by more than half a period
    max_shift_s: float  # the largest move [s]
    max_at_ns: int | None  # the stamp of the sample moved most

    def note(self, topic: str, origin_ns: int) -> str | None:
        """One line for the conversion summary when samples were delivered late, else None."""
        if not self.moved or self.max_at_ns is None:
            return None
        at = (self.max_at_ns - origin_ns) * 1e-9
        return (
            f"{topic}: {self.moved} samples stamped more than half a period after their {1.0 / self.period_s:.4g} Hz "
            f"sample times (up to {self.max_shift_s:.3f} s, at {at:.1f} s): re-stamped to their sample times "
            "(arrival stamps of a host that delivered them late)"
        )


def measured_period(t_ns: np.ndarray) -> float | None:
    """The median period over baselines of about `BASELINE_S` [s] (None: too few samples)."""
    t = np.asarray(t_ns, np.int64)
    if len(t) < 3:
        return None
    d = np.diff(t)
    step = float(np.median(d[d > 0])) if (d > 0).any() else 0.0
    if step <= 0:
        return None
    m = int(min(len(t) - 1, max(1, round(BASELINE_S * 1e9 / step))))
    return float(np.median(t[m:] - t[:-m])) * 1e-9 / m


def sample_times(t_ns: np.ndarray) -> Restamped:
    """The sample times of a fixed-rate sensor's increasing arrival stamps (the module docstring's backward
    minimum); stamps that are already consistent with the rate come back unchanged."""
    t = np.asarray(t_ns, np.int64)
    period = measured_period(t)
    if period is None:
        return Restamped(t.copy(), 0.0, 0, 0.0, None)
    T = period * (1.0 - PERIOD_MARGIN)
    n = len(t)
    rel = (t - t[0]).astype(np.float64) * 1e-9 - np.arange(n) * T  # t_j - j T, seconds from the first stamp
    span = int(min(n, max(1, round(HORIZON_S / period))))
    # min over j in [k, k + span): minimum_filter1d's window shifted to look ahead only
    ahead = minimum_filter1d(rel, size=span, origin=-(span // 2), mode="nearest")
    shift = np.maximum(rel - ahead, 0.0)  # how much earlier than its stamp each sample was taken
    i = int(np.argmax(shift))
    return Restamped(
        t - np.round(shift * 1e9).astype(np.int64),
        period,
        int((shift > 0.5 * period).sum()),
        float(shift[i]),
        int(t[i]),
    )


__all__ = ["Restamped", "measured_period", "sample_times"]
