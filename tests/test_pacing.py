"""``--rate``: scans are released when their stamp is due, and the lag behind the data is measured."""
import json

from conftest import BUNDLED
from slam2d.cli import main
from slam2d.pacing import Pacer


class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now

    def sleep(self, dt):
        assert dt > 0
        self.now += dt


def test_pacer_waits_for_due_scans_and_accumulates_lag_when_behind():
    c = FakeClock()
    p = Pacer(2.0, clock=c, sleep=c.sleep)  # 2× real time: stamps 1 s apart are due 0.5 s apart
    p.wait(10.0)
    c.now += 0.1  # processing
    assert abs(p.done() - 0.1) < 1e-12
    p.wait(11.0)
    assert abs(c.now - 100.5) < 1e-12  # slept until due
    c.now += 0.2
    assert abs(p.done() - 0.2) < 1e-12
    p.wait(10.5)  # a stamp going back is paced by the latest one: due at once
    c.now += 1.3  # too slow: the next scans are late when the run gets to them
    p.done()
    p.wait(12.0)  # due at 101.0, now 102.0: no sleep
    c.now += 0.1
    assert abs(p.done() - 1.1) < 1e-12
    r = p.report()
    assert r["scans"] == 4 and abs(r["worst_lag_s"] - 1.5) < 1e-9 and r["scans_late_over_1s"] == 2


def test_run_with_rate_reports_lag(tmp_path, capsys):
    assert main(["run", str(BUNDLED), "--out", str(tmp_path), "--no-progress", "--rate", "50", "--max-scans", "200",
                 "--no-loop-closure"]) == 0
    rt = json.loads((tmp_path / "summary.json").read_text())["realtime"]
    assert rt["rate"] == 50 and rt["scans"] == 200 and rt["worst_lag_s"] >= 0
    assert "worst lag behind the data" in capsys.readouterr().out
    assert main(["run", str(BUNDLED), "--out", str(tmp_path), "--rate", "0"]) == 2
