"""`slam2d convert` round trips: a CARMEN log converted to a ROS 1 bag, ROS 2 bags (MCAP and
sqlite3 storage) and MCAP gives the trajectory of the log itself; trajectory.txt and
results.mcap pass evo's checks where the log's stamps go back."""
import bz2
import itertools

import numpy as np
import pytest

from conftest import SHARED
from slam2d.cli import main
from slam2d.io.simulator import SimConfig, simulate
from slam2d.io.trajectory import read_tum

OUTPUTS = {"ros1": ["x.bag"], "ros2_mcap": ["x_ros2"], "ros2_sqlite3": ["x_db3", "--storage", "sqlite3"],
           "mcap": ["x.mcap"]}


def sim_carmen(path, n=150):
    """A FLASER log (180 beams, 1°) of the simulator's world, with a stamp that goes back 0.3 s
    and one that repeats, as real logs have."""
    stamps = [f"{100 + 0.2 * i:.6f}" for i in range(n)]
    if n > 60:
        stamps[40], stamps[41] = stamps[41], f"{100 + 0.2 * 41 - 0.3:.6f}"
        stamps[60] = stamps[59]
    with open(path, "w") as f:
        for stamp, s in zip(stamps, itertools.islice(simulate(SimConfig(seed=11)), n)):
            r = np.nan_to_num(s.ranges[90:270], nan=12.0, posinf=12.0)  # the simulator's beams −90°…+89°
            pose = " ".join(f"{v:.6f}" for v in s.odom_pose)
            f.write(f"FLASER 180 {' '.join(f'{v:.3f}' for v in r)} {pose} {pose} {stamp} sim {stamp}\n")


def run(log, out, *extra):
    assert main(["run", str(log), "--out", str(out), "--no-progress", *extra]) == 0
    return read_tum(out / "trajectory.txt")


def assert_same_trajectory(a, b):
    np.testing.assert_allclose(a[0], b[0], rtol=0, atol=1e-6)  # stamps, in scan order
    np.testing.assert_allclose(a[1], b[1], rtol=0, atol=1e-6)  # poses


def evo_check_tum(path):
    file_interface = pytest.importorskip("evo.tools.file_interface", reason="evo not installed (pip install -e .[dev])")
    ok, details = file_interface.read_tum_trajectory_file(str(path)).check()
    assert ok, details


def evo_check_mcap(path, n):
    file_interface = pytest.importorskip("evo.tools.file_interface", reason="evo not installed (pip install -e .[dev])")
    from rosbags.rosbag2 import Reader

    bag = Reader(path)
    bag.open()
    try:
        traj = file_interface.read_bag_trajectory(bag, "/slam2d/pose")
    finally:
        bag.close()
    ok, details = traj.check()
    assert ok and traj.num_poses == n, details


def round_trip(tmp_path, log, *run_args):
    ref = run(log, tmp_path / "run_log", *run_args)
    for kind, out in OUTPUTS.items():
        assert main(["convert", str(log), str(tmp_path / out[0]), *out[1:], "--no-progress"]) == 0, kind
        assert not list(tmp_path.glob("*.partial")) and not list(tmp_path.glob(".*.partial"))
        assert_same_trajectory(run(tmp_path / out[0], tmp_path / f"run_{kind}", *run_args), ref)
    return ref


def test_carmen_to_every_format_gives_the_same_trajectory(tmp_path):
    log = tmp_path / "sim.clf"
    sim_carmen(log)
    ref = round_trip(tmp_path, log)
    assert len(ref[0]) == 150
    text = (tmp_path / "run_log" / "trajectory.txt").read_text()
    assert text.startswith("# scans 0-39 41 40 42-149\n")  # the stamp that went back is sorted in
    evo_check_tum(tmp_path / "run_log" / "trajectory.txt")


def test_convert_refuses_what_it_cannot_write(tmp_path, capsys):
    log = tmp_path / "sim.clf"
    sim_carmen(log, n=3)
    (tmp_path / "exists").mkdir()
    for out, extra, msg in [("x.txt", [], "output must end in .mcap or .bag"), ("exists", [], "exists"),
                            ("x.bag", ["--storage", "sqlite3"], "--storage applies to a ROS 2 bag folder")]:
        assert main(["convert", str(log), str(tmp_path / out), *extra]) == 2
        assert msg in capsys.readouterr().err


def test_intel_slice_bag_round_trip_and_evo(tmp_path):
    """Real data: Intel's first 300 scans (165 of them stamped before an earlier scan)."""
    src = SHARED / "intel" / "intel.clf.bz2"
    if not src.exists():
        pytest.skip(f"real-data test: {src} not found (../shared/datasets is not beside the repo)")
    log = tmp_path / "intel300.clf"
    with bz2.open(src, "rt") as f, open(log, "w") as out:
        scans = 0
        for line in f:
            scans += line.startswith("FLASER")
            if scans > 300:
                break
            out.write(line)
    ref = round_trip(tmp_path, log)
    n = len(ref[0])
    assert n == 300
    assert (tmp_path / "run_log" / "trajectory.txt").read_text().startswith("# scans 0-25 27 26 28-131 133-136 132 ")
    evo_check_tum(tmp_path / "run_log" / "trajectory.txt")
    run(tmp_path / "x.bag", tmp_path / "with_mcap", "--mcap")
    evo_check_mcap(tmp_path / "with_mcap" / "results.mcap", n)


def test_failed_convert_leaves_nothing(tmp_path, capsys):
    log = tmp_path / "bad.clf"
    sim_carmen(log, n=5)
    with open(log, "a") as f:
        f.write("FLASER 3 1.0 oops 3.0 0 0 0 0 0 0 200.0 h 1.0\n")
    for out in ("x.bag", "x_ros2", "x.mcap"):
        assert main(["convert", str(log), str(tmp_path / out), "--no-progress"]) == 2
        assert "bad.clf:6:" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.clf"]


def test_stamps_a_ros_time_cannot_hold_are_one_line(tmp_path, capsys):
    log = tmp_path / "wrapped.clf"
    with open(log, "w") as f:  # infinite-corridor's corrected log stamps scans 4.29497e+09 (a 32-bit wrap)
        for k in range(3):
            f.write(f"FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 4.29497e+09 h {k}\n")
    for out in ("x.bag", "x.mcap", "x_ros2"):
        assert main(["convert", str(log), str(tmp_path / out), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert f"{log}: record 0: scan stamp 4.29497e+09 is outside the seconds a ROS time holds" in err, err
        assert err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["wrapped.clf"]


def test_a_log_with_unusable_stamps_runs_with_scan_period(tmp_path, capsys):
    """The simulated log with its stamps replaced by a 32-bit wrap (4.29497e+09) after three negative
    ones: `slam2d run` stops with one line naming the line and --scan-period; with --scan-period 0.2
    (the log's true period) every pose is the one of the log with good stamps, stamped k × 0.2 s."""
    good = tmp_path / "good.clf"
    sim_carmen(good, n=120)
    lines = good.read_text().splitlines(keepends=True)
    broken = tmp_path / "broken.clf"
    with open(broken, "w") as f:
        for k, line in enumerate(lines):
            parts = line.split()
            stamp = ("-1.392", "-0.446", "-1.82")[k] if k < 3 else "4.29497e+09"
            parts[-3] = parts[-1] = stamp
            f.write(" ".join(parts) + "\n")
    assert main(["run", str(broken), "--out", str(tmp_path / "x"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{broken}:3:" in err[0] and "--scan-period" in err[0], err
    assert not (tmp_path / "x" / "trajectory.txt").exists()
    stamps, poses, _ = run(broken, tmp_path / "restamped", "--scan-period", "0.2")
    np.testing.assert_allclose(stamps, 0.2 * np.arange(120), rtol=0, atol=1e-9)
    _, good_poses, _ = run(good, tmp_path / "good")
    np.testing.assert_allclose(poses, good_poses, rtol=0, atol=1e-6)


def test_a_rear_laser_beside_the_front_one_leaves_the_front_ones_run_unchanged(tmp_path):
    """The simulator's 360° scans split into a front laser (FLASER) and a rear one (RLASER, mounted
    backwards, stamped 0.1 s later). Read as one stream, every rear scan carried the front scan's
    odometry, local SLAM took the odometry for stalled, and the map broke (ATE 0.60 m against 0.048 m
    from the front alone). One laser is read: the run is the front-only log's, pose for pose."""
    import math

    front_only, both = tmp_path / "front.clf", tmp_path / "both.clf"
    with open(front_only, "w") as f, open(both, "w") as g:
        for k, s in enumerate(itertools.islice(simulate(SimConfig(seed=11)), 150)):
            r = np.nan_to_num(s.ranges, nan=12.0, posinf=12.0)
            x, y, th = s.odom_pose
            t = 100 + 0.2 * k
            pose = f"{x:.6f} {y:.6f} {th:.6f}"
            fl = f"FLASER 180 {' '.join(f'{v:.3f}' for v in r[90:270])} {pose} {pose} {t:.3f} sim {t:.3f}\n"
            rear = np.r_[r[270:], r[:90]]
            rl = (f"RLASER 180 {' '.join(f'{v:.3f}' for v in rear)} {x:.6f} {y:.6f} "
                  f"{math.remainder(th + math.pi, 2 * math.pi):.6f} {pose} {t + 0.1:.3f} sim {t + 0.1:.3f}\n")
            f.write(fl)
            g.write(fl + rl)
    a, b = run(front_only, tmp_path / "a"), run(both, tmp_path / "b")
    assert_same_trajectory(a, b)
