"""Rerun recording and results.mcap of a run on the bundled dataset."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slam2d.grid.map_export import read_pgm
from slam2d.io.trajectory import read_tum

from conftest import BUNDLED

ROOT = Path(__file__).resolve().parents[1]
RERUN = Path(sys.executable).with_name("rerun")


@pytest.fixture(scope="module")
def run_with_outputs(tmp_path_factory):
    out = tmp_path_factory.mktemp("viz")
    r = subprocess.run([sys.executable, "-m", "slam2d.cli", "run", str(BUNDLED), "--out", str(out / "run"),
                        "--rerun", str(out / "run.rrd"), "--mcap", "--no-progress"],
                       capture_output=True, text=True, timeout=900, env={"RERUN_ANALYTICS": "0", "PATH": ""})
    assert r.returncode == 0, r.stderr
    return out


def test_rrd_verifies_and_has_the_entities(run_with_outputs):
    rrd = run_with_outputs / "run.rrd"
    assert rrd.exists() and not Path(f"{rrd}.partial").exists()
    v = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=300)
    assert v.returncode == 0, v.stderr
    p = subprocess.run([str(RERUN), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=300)
    text = p.stdout + p.stderr
    for entity in ("/world/scan/hits", "/world/scan/no_return", "/world/robot", "/world/trajectory",
                   "/world/submaps/active", "/world/submaps/0", "/world/graph/nodes", "/world/graph/node_in_submap",
                   "/world/map", "/metrics/timing/match", "/metrics/score/local_match", "/events",
                   "/world/graph/loops", "/world/graph/rejected", "/metrics/timing/loop_search", "/metrics/score/loop",
                   "/metrics/optimization/time_ms", "/metrics/optimization/error"):
        assert entity in text, entity


def test_results_mcap_reads_back(run_with_outputs):
    from mcap_ros2.reader import read_ros2_messages

    run = run_with_outputs / "run"
    t, poses, stamps = read_tum(run / "trajectory.txt")
    got_poses = [m.ros_msg for m in read_ros2_messages(str(run / "results.mcap"), topics=["/slam2d/pose"])]
    assert len(got_poses) == len(t) == 1480
    for msg, p, s in zip(got_poses[::97], poses[::97], stamps[::97]):
        assert f"{msg.header.stamp.sec}.{msg.header.stamp.nanosec:09d}" == s
        assert msg.pose.position.x == pytest.approx(p[0], abs=1e-6)
    (grid,) = [m.ros_msg for m in read_ros2_messages(str(run / "results.mcap"), topics=["/map"])]
    pgm = read_pgm(run / "map.pgm")[::-1]  # bottom row first, as OccupancyGrid
    data = np.asarray(grid.data, dtype=np.int8).reshape(grid.info.height, grid.info.width)
    assert data.shape == pgm.shape
    assert np.array_equal(data == 100, pgm == 0) and np.array_equal(data == 0, pgm == 254)
    assert np.array_equal(data == -1, pgm == 205)
    tf = [m.ros_msg for m in read_ros2_messages(str(run / "results.mcap"), topics=["/tf"])]
    assert len(tf) == 1480 and [x.child_frame_id for x in tf[0].transforms] == ["odom", "base_link"]
    scans = list(read_ros2_messages(str(run / "results.mcap"), topics=["/scan"]))
    assert len(scans) == 1480
