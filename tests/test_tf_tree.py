"""The TF chain helper: composed mounts against 2D composition, direction, moving edges, warnings."""
import logging
import math

import numpy as np
import pytest

from slam2d.geometry import compose, inverse
from slam2d.io.tf_tree import TfTree, laser_mount


def _q(yaw, roll=0.0):
    """(x, y, z, w) of roll about x then yaw about z."""
    cr, sr, cy, sy = math.cos(roll / 2), math.sin(roll / 2), math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cy, sr * sy, cr * sy, cr * cy)


def _add(tree, parent, child, pose, static=True, z=0.0):
    tree.add(parent, child, (pose[0], pose[1], z), _q(pose[2]), static)


def test_chain_of_three_matches_2d_composition():
    rng = np.random.default_rng(4)
    poses = [np.array([*rng.uniform(-1, 1, 2), rng.uniform(-math.pi, math.pi)]) for _ in range(3)]
    tree = TfTree()
    _add(tree, "base_link", "plate", poses[0])
    _add(tree, "/plate", "mount", poses[1], z=0.3)  # a leading '/' (ROS 1) and a height change nothing
    _add(tree, "mount", "laser", poses[2])
    want = compose(compose(poses[0], poses[1]), poses[2])
    np.testing.assert_allclose(tree.pose_of("laser", "base_link"), want, atol=1e-12)
    np.testing.assert_allclose(tree.pose_of("base_link", "laser"), inverse(want), atol=1e-12)
    np.testing.assert_array_equal(tree.pose_of("laser", "laser"), np.zeros(3))


def test_branches_and_unconnected_frames():
    tree = TfTree()
    _add(tree, "base_link", "laser", (0.2, 0.0, 0.0))
    _add(tree, "base_link", "camera", (0.1, 0.3, 1.0))
    _add(tree, "map", "elsewhere", (5.0, 0.0, 0.0))
    np.testing.assert_allclose(tree.pose_of("laser", "camera"), compose(inverse([0.1, 0.3, 1.0]), [0.2, 0, 0]),
                               atol=1e-12)
    assert tree.pose_of("laser", "map") is None


def test_moving_tf_edge_is_not_a_mount_but_a_fixed_one_is():
    tree = TfTree()
    for k in range(5):
        _add(tree, "odom", "base_link", (0.1 * k, 0.0, 0.0), static=False)  # robot motion
        _add(tree, "base_link", "laser", (0.3, 0.0, 0.0), static=False)     # fixed, published on /tf
    np.testing.assert_allclose(tree.pose_of("laser", "base_link"), [0.3, 0.0, 0.0])
    assert tree.pose_of("base_link", "odom") is None


def test_missing_mount_warns_once_and_is_zero(caplog):
    tree = TfTree()
    _add(tree, "base_link", "camera", (0.1, 0.0, 0.0))
    with caplog.at_level(logging.WARNING, logger="slam2d.io"):
        m = laser_mount(tree, "laser", "base_link", "robot.bag")
    np.testing.assert_array_equal(m.pose, np.zeros(3))
    assert not m.mirrored
    (rec,) = caplog.records
    assert "robot.bag" in rec.message and "'base_link' to 'laser'" in rec.message
    assert "zero laser mount" in rec.message and "base_link, camera" in rec.message


@pytest.mark.parametrize("roll_deg,pitch_deg,mirrored,warned", [
    (180, 0, True, False), (0, 180, True, False), (177, 0, True, False),  # upside down, by roll or pitch
    (170, 0, True, True), (10, 0, False, True), (3, 0, False, False)])   # tilted: projected, and said so
def test_upside_down_laser_is_mirrored_and_a_tilted_one_warned_about(caplog, roll_deg, pitch_deg, mirrored, warned):
    """The mount's planar yaw is that of the laser's x axis; a laser whose z axis points down sweeps
    the plane the other way round. Checked by projecting a beam through the 3D transform."""
    from slam2d.io.tf_tree import transform_matrix

    roll, pitch, yaw = math.radians(roll_deg), math.radians(pitch_deg), 0.7
    cr, sr, cp, sp, cy, sy = (f(a / 2) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    q = (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
         cr * cp * cy + sr * sp * sy)  # roll about x, pitch about y, yaw about z (ZYX)
    tree = TfTree()
    tree.add("base_link", "laser", (0.1, -0.2, 0.3), q, True)
    with caplog.at_level(logging.INFO, logger="slam2d.io"):
        m = laser_mount(tree, "laser", "base_link", "x.bag")
    assert m.mirrored == mirrored
    assert bool([r for r in caplog.records if r.levelno >= logging.WARNING]) == warned
    assert ("upside down" in caplog.text) == mirrored
    # a beam at 0.4 rad in the laser's plane, 3 m out: where the 3D transform puts it, in the plane
    beam = 3.0 * np.array([math.cos(0.4), math.sin(0.4), 0.0, 1.0 / 3.0])
    want = (transform_matrix((0.1, -0.2, 0.3), q) @ beam)[:2]
    a = (-0.4 if m.mirrored else 0.4) + m.pose[2]
    got = m.pose[:2] + 3.0 * np.array([math.cos(a), math.sin(a)])
    tol = 1e-9 if roll_deg in (0, 180) and pitch_deg in (0, 180) else 3.0 * (1 - math.cos(math.radians(10))) + 0.1
    np.testing.assert_allclose(got, want, atol=tol)


def test_bad_quaternion_is_an_error():
    with pytest.raises(ValueError, match="no rotation"):
        TfTree().add("a", "b", (0, 0, 0), (0, 0, 0, 0), True)


def test_without_odometry_the_robot_is_the_root_of_the_lasers_tree(caplog):
    tree = TfTree()
    _add(tree, "base_footprint", "base_link", (0.5, 0.0, 0.0))
    _add(tree, "base_link", "laser", (0.2, 0.0, 0.0))
    with caplog.at_level(logging.DEBUG, logger="slam2d.io"):
        np.testing.assert_allclose(laser_mount(tree, "laser", None, "x.bag").pose, [0.7, 0.0, 0.0])
        np.testing.assert_array_equal(laser_mount(TfTree(), "laser", None, "x.bag").pose, np.zeros(3))
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_the_moving_edge_into_a_frame_is_kept_in_stamp_order():
    tree = TfTree()
    for k in (2, 0, 1, 3):  # arrival order is not stamp order
        tree.add("odom", "base_link", (0.1 * k, 0.0, 0.0), _q(0.05 * k), False, stamp=10.0 + k)
        tree.add("map", "odom", (0.0, 0.01 * k, 0.0), _q(0.0), False, stamp=10.0 + k)
        tree.add("base_link", "laser", (0.2, 0.0, 0.0), _q(0.0), False, stamp=10.0 + k)  # fixed though on /tf
    parent, rows = tree.moving_edge("base_link")
    assert parent == "odom"
    np.testing.assert_allclose(rows, [[10.0 + k, 0.1 * k, 0.0, 0.05 * k] for k in range(4)], atol=1e-12)
    assert tree.moving_edge("laser") is None  # it never moved: a mount
    assert tree.moving_edge("odom")[0] == "map"
    tree.add("elsewhere", "base_link", (0.0, 0.0, 0.0), _q(0.0), False, stamp=1.0)
    tree.add("elsewhere", "base_link", (1.0, 0.0, 0.0), _q(0.0), False, stamp=2.0)
    assert tree.moving_edge("base_link") is None  # two moving edges into one frame: neither is the odometry
