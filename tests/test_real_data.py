"""Regressions on the real benchmark logs in ../shared/datasets (skipped, with the reason, where absent)."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slam2d.eval.relations import read_relations, relations_metric
from slam2d.io.trajectory import read_tum

from conftest import dataset, relations

ROOT = Path(__file__).resolve().parents[1]

FACTS = {"intel": (13631, 2691.3, 180), "aces": (7374, 1365.5, 180), "fr079": (4934, 1061.4, 360)}


def slam2d(*args):
    return subprocess.run([sys.executable, "-m", "slam2d.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=1800)


@pytest.mark.parametrize("name", sorted(FACTS))
def test_info_reports_the_logs_facts(name):
    r = slam2d("info", dataset(name), "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    scans, duration, beams = FACTS[name]
    assert info["scans"] == scans
    assert round(info["duration_s"], 1) == pytest.approx(duration, abs=0.051)
    assert info["beams"] == beams
    assert info["has_odometry"]
    assert info["angle_min_deg"] == pytest.approx(-90.0)
    assert info["no_return_readings"] == {"intel": 68313, "aces": 11139, "fr079": 36881}[name]


def test_convert_intel_round_trips_through_mcap_ros2(tmp_path):
    from mcap_ros2.reader import read_ros2_messages

    from slam2d.io.carmen import CarmenLog

    src = dataset("intel")
    out = tmp_path / "intel.mcap"
    r = slam2d("convert", src, out, "--no-progress")
    assert r.returncode == 0, r.stderr
    scans = iter(CarmenLog(src))
    n = 0
    for m in read_ros2_messages(str(out), topics=["/scan"]):
        s = next(scans)
        msg = m.ros_msg
        np.testing.assert_array_equal(np.asarray(msg.ranges, dtype=np.float32), s.ranges)
        sec, frac = s.timestamp_text.split(".")
        assert msg.header.stamp.sec == int(sec)
        assert msg.header.stamp.nanosec // 1000 == int(frac.ljust(6, "0")[:6])
        n += 1
    assert n == 13631


@pytest.fixture(scope="module")
def intel_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("intel")
    r = slam2d("run", dataset("intel"), "--out", out, "--no-progress")
    assert r.returncode == 0, r.stderr
    return out


def test_intel_run_has_a_pose_at_every_relation_endpoint(intel_run):
    t, poses, stamps = read_tum(intel_run / "trajectory.txt")
    assert len(t) == 13631
    stamp_set = set(stamps)
    rel_file = relations("intel")
    ends = set()
    for line in rel_file.read_text().splitlines():
        a, b = line.split()[:2]
        ends.update((a, b))
    assert ends <= stamp_set  # the exact strings of ipc_ts
    for name in ("map.pgm", "map.yaml", "map.png", "config.yaml", "summary.json"):
        assert (intel_run / name).stat().st_size > 0
    assert (intel_run / "map.pgm").read_bytes()[:2] == b"P5"


def test_intel_global_slam_accuracy_regression(intel_run):
    t, poses, _ = read_tum(intel_run / "trajectory.txt")
    m = relations_metric(t, poses, read_relations(relations("intel")))
    assert m["counts"]["evaluated"] == 2984 and m["counts"]["unmatched"] == 0
    # raw odometry scores 7.37 m, Karto's sequential matcher 0.141 m, Cartographer 0.0229 m (published);
    # slam2d measured 0.021 m: guard against regressions
    assert m["abs_trans_m"]["mean"] < 0.035
    assert m["abs_rot_deg"]["mean"] < 0.6
    summary = json.loads((intel_run / "summary.json").read_text())
    assert summary["mode"] == "global" and summary["loop_closure"]["in_final_graph"] > 100


# Local SLAM alone, below the Karto peer (aces 0.111 m, intel 0.141 m; scan matching in Kümmerle et al.
# 2009 scores 0.220 m on intel). slam2d measured aces 0.048-0.061 m and intel 0.046-0.089 m over runs
# with the world rotated by small angles (tools/spread.py: a null change that shows the run-to-run spread).
@pytest.mark.parametrize("name, bound", [("aces", 0.09), ("intel", 0.10)])
def test_local_slam_accuracy_regression(tmp_path, name, bound):
    out = tmp_path / name
    r = slam2d("run", dataset(name), "--out", out, "--no-loop-closure", "--no-progress")
    assert r.returncode == 0, r.stderr
    t, poses, _ = read_tum(out / "trajectory.txt")
    m = relations_metric(t, poses, read_relations(relations(name)))
    assert m["abs_trans_m"]["mean"] <= bound
    assert json.loads((out / "summary.json").read_text())["mode"] == "local"


def test_fr_clinic_no_return_readings_never_become_hits():
    """fr-clinic writes no-returns as 81.83 m and as 81.91 m (header max_range 81.9): both are
    no-returns, and on a slice of the log no beam at either value yields a hit."""
    from slam2d.config import RangeFilterConfig
    from slam2d.io.carmen import CarmenLog
    from slam2d.range_data import range_data

    p = ROOT.parent / "shared" / "datasets" / "fr-clinic" / "fr-clinic_robotlaser.clf.bz2"
    if not p.exists():
        pytest.skip(f"real-data test: {p} not found (../shared/datasets is not beside the repo)")
    log = CarmenLog(p)
    values = {e["value"] for e in log.facts().no_return_evidence}
    assert {81.83, 81.91} <= values
    cfg = RangeFilterConfig()
    seen = 0
    for scan in log:
        if scan.index >= 400:
            break
        at_no_return = np.isclose(scan.ranges, 81.83, atol=1e-3) | np.isclose(scan.ranges, 81.91, atol=1e-3)
        seen += int(at_no_return.sum())
        assert not scan.valid[at_no_return].any() and scan.no_return[at_no_return].all()
        rd = range_data(scan, cfg)
        # hits are exactly the valid readings within the usable range
        usable = scan.valid & (scan.ranges <= cfg.max_range)
        assert len(rd.hits) == int(usable.sum())
        assert (np.hypot(*(rd.hits - rd.origin).T) <= cfg.max_range + 1e-6).all()
    assert seen > 1000  # the slice does hold both kinds


def test_intel_without_odometry_local_slam_follows_the_scans():
    """Intel's scans without their odometry (constant-velocity prediction), local SLAM alone over the
    first 1500 scans (300 s), where bursts of scans stamped a millisecond apart used to make the
    velocity, and with it the prediction, jump metres (a 7.6 m step at 101 s): no step may differ
    from the log's own odometry step by more than 0.5 m or 10° (its odometry is good over one step)."""
    import dataclasses
    import math

    import slam2d as api
    from slam2d.geometry import between

    slam = api.Slam(mode="local")
    prev = prev_odom = None
    worst_t = worst_r = 0.0
    for k, scan in enumerate(api.open_source(dataset("intel"))):
        if k == 1500:
            break
        est = slam.add_scan(dataclasses.replace(scan, odom_pose=None))
        if prev is not None:
            e = between(between(prev_odom, scan.odom_pose), between(prev, est.local_pose))
            worst_t, worst_r = max(worst_t, math.hypot(e[0], e[1])), max(worst_r, abs(math.degrees(e[2])))
        prev, prev_odom = est.local_pose, scan.odom_pose
    assert worst_t < 0.5 and worst_r < 10.0, (worst_t, worst_r)


def test_fr079_whose_odometry_misses_a_turn_is_not_mapped_at_the_wrong_heading(tmp_path):
    """fr079 with odometry far worse than the benchmark's degraded copies (the harsh suite's
    ``degrade.py --seed 4 --rot-scale 0.5 --trans-scale 0.1 --keep-every 3``): near scan 1370 the
    robot turns about 24° a scan for five scans while the odometry reads almost none. The real-time
    search ended on its window's edge, and the recovery's clear peak, where the turn went on, lay
    beyond the odometry's own error bound, which grows only with the motion the odometry read: it
    was not taken, two low peaks at the wrong heading were mapped as new ground, and everything
    after the turn lay 90° off (relations 0.34 m, health WARN). Constant velocity, the recovery's
    second prediction, predicts the turn going on; within its bound the peak is taken."""
    tool = ROOT.parent / "shared" / "tools" / "degrade.py"
    log = dataset("fr079")
    if not tool.exists():
        pytest.skip(f"real-data test: {tool} not found")
    harsh = tmp_path / "fr079-harsh.clf"
    subprocess.run([sys.executable, str(tool), str(log), str(harsh), "--seed", "4", "--rot-scale", "0.5",
                    "--trans-scale", "0.1", "--keep-every", "3"], check=True, capture_output=True, timeout=600)
    m, summary = _run_and_score(harsh, tmp_path / "run", "fr079")
    # Cartographer's published figure for the clean log: 0.0452 m
    assert m["abs_trans_m"]["mean"] < 0.0452, m["abs_trans_m"]
    assert summary["health"]["status"] == "OK", summary["health"]["reasons"]


def _run_and_score(log: Path, out: Path, name: str, exact: bool = False) -> tuple[dict, dict]:
    """``slam2d run`` of ``log`` (default config): its relations metric on dataset ``name``'s
    relations (``exact``: only those whose two stamps the log keeps), and its summary."""
    r = slam2d("run", log, "--out", out, "--no-progress")
    assert r.returncode == 0, r.stderr
    t, poses, _ = read_tum(out / "trajectory.txt")
    return (relations_metric(t, poses, read_relations(relations(name)), exact=exact),
            json.loads((out / "summary.json").read_text()))


def _narrow_copy(log: Path, out: Path, fov_deg: float) -> None:
    """A 180° FLASER log as a scanner seeing only the middle ``fov_deg`` would record it: the same
    readings of those beams, as ROBOTLASER1 lines (which state their angles)."""
    import bz2
    import math

    with bz2.open(log, "rt") as f, open(out, "w") as g:
        for line in f:
            p = line.split()
            if not p or p[0] != "FLASER":
                g.write(line)
                continue
            n = int(p[1])
            step = math.pi / n  # the benchmark logs' 180 / 360 beams
            keep = [i for i in range(n) if abs(-math.pi / 2 + i * step) <= math.radians(fov_deg) / 2 + 1e-9]
            lx, ly, lt, ox, oy, ot, ts, host, lts = p[2 + n:11 + n]
            start = -math.pi / 2 + keep[0] * step
            g.write(" ".join(["ROBOTLASER1", "0", repr(start), repr((len(keep) - 1) * step), repr(step), "81.9", "0.01",
                              "0", str(len(keep)), *[p[2 + i] for i in keep], "0", lx, ly, lt, ox, oy, ot,
                              "0", "0", "0", "0", "0", ts, host, lts]) + "\n")


def test_intel_seen_through_a_90_degree_scanner_is_mapped_by_its_loops(tmp_path):
    """Intel's scans cut to their middle 91 beams (a scanner that sees 90°). Turning in its rooms,
    local SLAM's heading drifts far more per metre than driving does; a pose graph that let the
    heading drift only with the path held the submaps so stiffly that the optimizer removed 280 true
    loops as contradicting them, and the map came out worse than local SLAM's alone (relations
    0.27 m, health WARN). The heading's drift now counts the turns too."""
    narrow = tmp_path / "intel-90.clf"
    _narrow_copy(dataset("intel"), narrow, 90.0)
    m, summary = _run_and_score(narrow, tmp_path / "run", "intel")
    assert m["abs_trans_m"]["mean"] < 0.05, m["abs_trans_m"]
    assert summary["health"]["status"] == "OK", summary["health"]["reasons"]


def test_intel_with_half_a_minute_of_scans_missing_is_mapped_whole(tmp_path):
    """Intel without its scans 3000-3149 (and the odometry lines between): 30 s in which the robot
    drove 8.4 m while the odometry turned 35° the wrong way. The first scan after the hole scored
    0.07 at its best peak; taken as a weak match it was mapped 26° off into the submaps of the
    first half, and the rest of the map hung from it (relations 1.43 m, health WARN). Now local SLAM
    lost track there and starts new submaps, which loop closure ties to the old ones."""
    import bz2

    holed = tmp_path / "intel-hole.clf"
    k = 0
    with bz2.open(dataset("intel"), "rt") as f, open(holed, "w") as g:
        for line in f:
            kind = line.split(maxsplit=1)[0] if line.strip() else ""
            if kind == "FLASER":
                k += 1
                if 3000 < k <= 3150:
                    continue
            elif kind == "ODOM" and 3000 <= k < 3150:
                continue
            g.write(line)
    m, summary = _run_and_score(holed, tmp_path / "run", "intel", exact=True)
    assert m["abs_trans_m"]["mean"] < 0.0229, m["abs_trans_m"]  # Cartographer's figure for the whole log
    assert summary["health"]["status"] == "OK", summary["health"]["reasons"]


def test_fr_clinic_loops_through_the_hall_bend_the_weak_matches_back(tmp_path):
    """fr-clinic's first 2450 scans pass its wide hall twice (scans 300-370 and 2330-2420). There
    local SLAM's matches are weak (a clear peak scoring below the trust limit: far, fuzzy walls), and
    over the second pass's twenty weak matches its heading turned 2.2° more than the wheel
    odometry's. Some 30 loops between the passes (both ways) said so. While a weak match's step
    was held in the pose graph as tightly as a trusted one's (0.14° a step), the chain outweighed
    them, the residual check removed every loop from 2357 on, and the hall was mapped twice, 0.5 m
    and 3° apart (health BROKEN: 54 % of the revisits agreeing). A weak step is now as loose as its
    match's score surface."""
    log = ROOT.parent / "shared" / "datasets" / "fr-clinic" / "fr-clinic_robotlaser.clf.bz2"
    if not log.exists():
        pytest.skip(f"real-data test: {log} not found")
    out = tmp_path / "run"
    r = slam2d("run", log, "--out", out, "--no-progress", "--max-scans", 2450)
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["health"]["revisits_agreeing"] >= 0.8, summary["health"]["reasons"]
    records = [json.loads(line) for line in (out / "constraints.jsonl").read_text().splitlines()]
    # loops between the second pass's weak stretch and the first pass, either way (0 before)
    ends = [sorted((c["from_scan"], c["to_scan"])) for c in records if c["in_final_graph"]]
    hall = [(a, b) for a, b in ends if 300 <= a <= 370 and 2357 <= b <= 2402]
    assert len(hall) >= 5, hall


def test_the_corridor_log_with_unusable_stamps_runs_with_scan_period(tmp_path):
    """The MIT Infinite Corridor's corrected log (``../shared/datasets/sparse``; its SOURCE.md: the stamps
    are a 32-bit wrap after four negative ones). As it is: one line naming the line and the option;
    with --scan-period: a map, and a trajectory stamped in file order."""
    from conftest import SHARED

    log = SHARED / "sparse" / "infinite-corridor" / "infinite-corridor-corrected.log.gz"
    if not log.exists():
        pytest.skip(f"real-data test: {log} not found (../shared/datasets is not beside the repo)")
    r = slam2d("run", log, "--out", tmp_path / "x", "--no-progress", "--max-scans", "300")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--scan-period" in r.stderr and f"{log}:" in r.stderr
    r = slam2d("run", log, "--out", tmp_path / "y", "--no-progress", "--max-scans", "300", "--scan-period", "0.2")
    assert r.returncode == 0, r.stderr
    stamps, _, _ = read_tum(tmp_path / "y" / "trajectory.txt")
    np.testing.assert_allclose(stamps, 0.2 * np.arange(300), atol=1e-9)
    assert (tmp_path / "y" / "map.pgm").exists()
