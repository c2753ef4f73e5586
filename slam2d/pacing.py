"""``slam2d run --rate R``: the input replayed by its own timestamps at R× real time, as a robot
would deliver it, and how far the run fell behind it.

A scan stamped t is due at ``start + (t − t₀) / R`` on the wall clock; the run waits until it
is due, processes it, and its lag is the time from due to done. A run that keeps up has lags
of one scan's processing time; one that falls behind accumulates lag, because later scans are
already due when it gets to them. Stamps that go backwards (CARMEN logs have them) are paced
by the latest stamp so far.
"""
from __future__ import annotations

import time

import numpy as np


class Pacer:
    def __init__(self, rate: float, clock=time.perf_counter, sleep=time.sleep):
        if not rate > 0:
            raise ValueError("rate must be positive")
        self.rate = float(rate)
        self.clock = clock
        self.sleep = sleep
        self.t0 = None
        self.wall0 = None
        self.latest = None
        self.lags: list[float] = []
        self._due = None

    def wait(self, stamp: float) -> None:
        """Block until the scan stamped ``stamp`` is due."""
        if self.t0 is None:
            self.t0, self.wall0, self.latest = stamp, self.clock(), stamp
        self.latest = max(self.latest, stamp)
        self._due = self.wall0 + (self.latest - self.t0) / self.rate
        ahead = self._due - self.clock()
        if ahead > 0:
            self.sleep(ahead)

    def done(self) -> float:
        """The scan waited for last is processed: its lag [s]."""
        lag = max(0.0, self.clock() - self._due)
        self.lags.append(lag)
        return lag

    def report(self) -> dict:
        a = np.asarray(self.lags) if self.lags else np.zeros(1)
        return {"rate": self.rate, "scans": len(self.lags), "worst_lag_s": round(float(a.max()), 4),
                "p99_lag_s": round(float(np.percentile(a, 99)), 4), "p50_lag_s": round(float(np.percentile(a, 50)), 4),
                "scans_late_over_1s": int(np.count_nonzero(a > 1.0))}


__all__ = ["Pacer"]
