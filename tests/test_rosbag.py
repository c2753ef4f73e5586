"""ROS 1 / ROS 2 bags through rosbags: round trips, reading by name, topic choice, the TF-chain
mount (bags and MCAP alike), and bad input as one line."""
import json
import logging
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from slam2d.cli import main
from slam2d.errors import InputError
from slam2d.io.mcap import McapWriter, yaw_quaternion
from slam2d.io.ros_input import laser_angle, yaw_of
from slam2d.io.rosbag import RosbagLog, RosbagWriter
from slam2d.io.simulator import SimConfig, simulate
from slam2d.io.source import open_source

KINDS = {"ros1": "x.bag", "sqlite3": "x_db3", "mcap": "x_ros2"}


def sim_scans(n, seed=3):
    return [s for _, s in zip(range(n), simulate(SimConfig(seed=seed)))]


def write_bag(path, scans, kind):
    w = RosbagWriter(path, kind)
    for s in scans:
        w.write_scan(s)
    w.finish()


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_round_trip_is_bit_identical(tmp_path, kind):
    scans = sim_scans(30)
    p = tmp_path / KINDS[kind]
    write_bag(p, scans, kind)
    log = RosbagLog(p)
    assert (log.scan_topic, log.odom_topic, log.gt_topic, log.num_scans()) == ("/scan", "/odom", "/ground_truth", 30)
    back = list(log)
    assert len(back) == 30
    for a, b in zip(scans, back):
        assert a.timestamp_text == b.timestamp_text and a.timestamp == b.timestamp
        for f in ("ranges", "valid", "no_return", "odom_pose", "ground_truth", "laser_offset"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
        assert (a.angle_min, a.angle_increment) == (b.angle_min, b.angle_increment)


def test_open_source_by_name(tmp_path):
    scans = sim_scans(3)
    write_bag(tmp_path / "a.bag", scans, "ros1")
    write_bag(tmp_path / "b", scans, "sqlite3")
    write_bag(tmp_path / "c", scans, "mcap")
    assert isinstance(open_source(tmp_path / "a.bag"), RosbagLog)
    assert isinstance(open_source(tmp_path / "b"), RosbagLog)
    assert isinstance(open_source(tmp_path / "b" / "b.db3"), RosbagLog)
    assert isinstance(open_source(tmp_path / "c"), RosbagLog)
    from slam2d.io.mcap import McapLog

    assert isinstance(open_source(tmp_path / "c" / "c.mcap"), McapLog)  # a bag's MCAP file reads alone too
    for p in ("a.bag", "b", "b/b.db3", "c", "c/c.mcap"):
        assert [s.timestamp_text for s in open_source(tmp_path / p)] == [s.timestamp_text for s in scans]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="without metadata.yaml"):
        open_source(tmp_path / "empty")
    (tmp_path / "lone.db3").write_bytes(b"")
    with pytest.raises(InputError, match="metadata.yaml"):
        open_source(tmp_path / "lone.db3")


def _scan_msg(frame, sec, ranges=(1.0, 2.0, 3.0), inc=0.1):
    return {"header": {"stamp": {"sec": sec, "nanosec": 0}, "frame_id": frame}, "angle_min": -0.1,
            "angle_max": 0.1, "angle_increment": inc, "range_min": 0.1, "range_max": 10.0, "ranges": list(ranges)}


def _tf(parent, child, x, yaw, sec=0):
    z, w = yaw_quaternion(yaw)
    return {"header": {"stamp": {"sec": sec, "nanosec": 0}, "frame_id": parent}, "child_frame_id": child,
            "transform": {"translation": {"x": x, "y": 0.0, "z": 0.0}, "rotation": {"z": z, "w": w}}}


def _odom(sec, x, child="base_footprint"):
    return {"header": {"stamp": {"sec": sec, "nanosec": 0}, "frame_id": "odom"}, "child_frame_id": child,
            "pose": {"pose": {"position": {"x": x}, "orientation": {"w": 1.0}}}}


def _robot_bag(path, kind, static=True, scan_topics=("/scan",), frame="lidar_link"):
    """A bag as a robot records it: odometry of base_footprint, the laser two fixed transforms away."""
    w = RosbagWriter(path, kind)
    tf_topic = "/tf_static" if static else "/tf"
    for sec in range(1, 4):
        if sec == 1 or not static:
            w.write(tf_topic, "tf2_msgs/TFMessage", {"transforms": [
                _tf("base_footprint", "base_link", 0.5, 0.0, sec), _tf("base_link", "lidar_link", 0.2, math.pi / 2, sec)]},
                sec, 0)
        if not static:  # the moving odom -> base_footprint edge on /tf is not part of the mount
            w.write("/tf", "tf2_msgs/TFMessage", {"transforms": [_tf("odom", "base_footprint", 0.1 * sec, 0.0, sec)]},
                    sec, 0)
        w.write("/odom", "nav_msgs/Odometry", _odom(sec, 0.1 * sec), sec, 0)
        for t in scan_topics:
            w.write(t, "sensor_msgs/LaserScan", _scan_msg(frame, sec), sec, 0)
    w.finish()


@pytest.mark.parametrize("kind,static", [("ros1", True), ("ros1", False), ("sqlite3", True), ("mcap", False)])
def test_mount_from_a_chain_of_transforms(tmp_path, kind, static):
    p = tmp_path / ("r.bag" if kind == "ros1" else "r")
    _robot_bag(p, kind, static)
    scans = list(open_source(p))
    assert len(scans) == 3
    np.testing.assert_allclose(scans[0].laser_offset, [0.7, 0.0, math.pi / 2], atol=1e-12)
    np.testing.assert_allclose([s.odom_pose[0] for s in scans], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(scans[0].angle_increment, 0.1, rtol=1e-7)


def test_mcap_reader_uses_the_same_tf_chain(tmp_path):
    p = tmp_path / "robot.mcap"
    with open(p, "wb") as f:
        w = McapWriter(f)
        w.write("/tf_static", "tf2_msgs/TFMessage", {"transforms": [
            _tf("base_footprint", "base_link", 0.5, 0.0), _tf("base_link", "lidar_link", 0.2, math.pi / 2)]}, 1, 0)
        for sec in (1, 2):
            w.write("/odom", "nav_msgs/Odometry", {**_odom(sec, 0.0), "twist": {}}, sec, 0)
            w.write("/scan", "sensor_msgs/LaserScan", {**_scan_msg("lidar_link", sec), "time_increment": 0.0,
                                                       "scan_time": 0.0, "intensities": []}, sec, 0)
        w.finish()
    (s, _) = list(open_source(p))
    np.testing.assert_allclose(s.laser_offset, [0.7, 0.0, math.pi / 2], atol=1e-12)


def test_no_mount_warns_and_uses_zero(tmp_path, caplog):
    p = tmp_path / "r.bag"
    _robot_bag(p, "ros1", frame="mystery_laser")
    with caplog.at_level(logging.WARNING, logger="slam2d.io"):
        scans = list(open_source(p))
    np.testing.assert_array_equal(scans[0].laser_offset, np.zeros(3))
    (rec,) = [r for r in caplog.records if "mount" in r.message]
    assert "'base_footprint' to 'mystery_laser'" in rec.message and "zero laser mount" in rec.message


def test_several_scan_topics_need_a_choice(tmp_path, capsys):
    p = tmp_path / "two.bag"
    _robot_bag(p, "ros1", scan_topics=("/front/scan", "/rear/scan"))
    with pytest.raises(InputError, match=r"several sensor_msgs/msg/LaserScan topics \(/front/scan, /rear/scan\); "
                                         "choose one with --scan-topic"):
        open_source(p)
    assert len(list(open_source(p, scan_topic="/rear/scan"))) == 3
    with pytest.raises(InputError, match="is nav_msgs/msg/Odometry, not sensor_msgs"):
        open_source(p, scan_topic="/odom")
    assert main(["info", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "two.bag: several" in err
    assert main(["info", str(p), "--scan-topic", "/front/scan", "--json"]) == 0


def test_bad_bags_are_one_line(tmp_path, capsys):
    good = tmp_path / "good.bag"
    write_bag(good, sim_scans(20), "ros1")
    data = good.read_bytes()
    cases = {"garbage.bag": b"not a bag at all", "truncated.bag": data[: len(data) // 2], "empty.bag": b""}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        assert main(["run", str(tmp_path / name), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"slam2d: error: {tmp_path / name}") and err.count("\n") == 1, err
        assert "Traceback" not in err


def test_bad_ros2_bags_are_one_line(tmp_path, capsys):
    for name in ("yaml", "db3"):
        write_bag(tmp_path / name, sim_scans(20), "sqlite3")
    (tmp_path / "yaml" / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n")
    db3 = tmp_path / "db3" / "db3.db3"
    db3.write_bytes(db3.read_bytes()[:5000])
    for name in ("yaml", "db3"):
        assert main(["info", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"slam2d: error: {tmp_path / name}: not a readable ROS bag") and err.count("\n") == 1, err


def test_bad_laserscan_names_the_record(tmp_path):
    p = tmp_path / "bad.bag"
    w = RosbagWriter(p, "ros1")
    w.write("/scan", "sensor_msgs/LaserScan", _scan_msg("laser", 1), 1, 0)
    w.write("/scan", "sensor_msgs/LaserScan", _scan_msg("laser", 2, inc=0.0), 2, 0)
    w.finish()
    with pytest.raises(InputError) as e:
        list(open_source(p))
    assert str(e.value) == f"{p}: record 1: LaserScan angle_increment is 0.0"


def test_yaw_and_angles_read_back_exactly():
    rng = np.random.default_rng(5)
    for th in [0.0, math.pi, -math.pi / 2, *rng.uniform(-math.pi, math.pi, 2000)]:
        z, w = yaw_quaternion(th)
        assert abs(math.hypot(z, w) - 1) < 1e-15

        class Q:
            x = y = 0.0

        Q.z, Q.w = z, w
        assert yaw_of(Q) == th
    for n in (180, 181, 360, 361, 1081):
        for v in (-math.pi / 2, math.pi / n, math.pi / (n - 1), -1.570796, 0.017453, -3 * math.pi / 4):
            assert laser_angle(float(np.float32(v)), n) == v
    odd = float(np.float32(0.0123456789))
    assert abs(laser_angle(odd, 100) - odd) < 1e-9



def _upside_down_bag(path, scans, kind, yaw_deg):
    """The simulator's scans (360 beams, one a degree from -180°) as a laser hanging upside down on
    the robot records them: its TF mount is rolled by 180° and turned by ``yaw_deg``, so its beam at
    laser angle b looks along yaw - b in the robot's plane."""
    from slam2d.io.mcap import scan_messages

    n = scans[0].num_beams
    order = (yaw_deg - np.arange(n)) % n  # the upright scan's beam that each upside-down beam repeats
    yaw = math.radians(yaw_deg)
    w = RosbagWriter(path, kind)
    for k, s in enumerate(scans):
        for topic, type_name, msg, sec, nsec in scan_messages(s, with_mount=False):
            if type_name == "sensor_msgs/LaserScan":
                if k == 0:
                    w.write("/tf_static", "tf2_msgs/TFMessage", {"transforms": [{
                        "header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": "base_link"},
                        "child_frame_id": "laser",
                        "transform": {"translation": {"x": 0.1, "y": 0.0, "z": 0.4},  # roll π, then the yaw
                                      "rotation": {"x": math.cos(yaw / 2), "y": math.sin(yaw / 2), "z": 0.0,
                                                   "w": 0.0}}}]}, sec, nsec)
                msg = dict(msg, ranges=[msg["ranges"][i] for i in order])
            w.write(topic, type_name, msg, sec, nsec)
    w.finish()


def _robot_points(s):
    """A scan's hits in the robot frame."""
    p = s.points()
    c, si = math.cos(s.laser_offset[2]), math.sin(s.laser_offset[2])
    return np.c_[s.laser_offset[0] + c * p[:, 0] - si * p[:, 1], s.laser_offset[1] + si * p[:, 0] + c * p[:, 1]]


@pytest.mark.parametrize("kind,yaw_deg", [("ros1", 0), ("mcap", 90), ("ros1", 180)])
def test_an_upside_down_laser_is_mirrored_into_the_robot_plane(tmp_path, kind, yaw_deg, caplog):
    scans = [s for s in sim_scans(20) if np.array_equal(s.laser_offset, np.zeros(3))]
    assert len(scans) == 20 and scans[0].num_beams == 360
    p = tmp_path / ("u.bag" if kind == "ros1" else "u")
    _upside_down_bag(p, scans, kind, yaw_deg)
    with caplog.at_level(logging.INFO, logger="slam2d.io"):
        log = RosbagLog(p)
        back = list(log)
    assert log.laser_mount.mirrored and "upside down" in caplog.text
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]  # exactly upside down: nothing to warn of
    for a, b in zip(scans, back):
        np.testing.assert_allclose(b.laser_offset, [0.1, 0.0, math.radians(yaw_deg)], atol=1e-12)
        assert np.all(np.diff(b.angles) > 0)
        # the same hits where the robot is, up to the mount's 0.1 m ahead
        got, want = _robot_points(b), _robot_points(a) + [0.1, 0.0]
        assert len(got) == len(want) > 300
        assert np.max(cKDTree(want).query(got)[0]) < 1e-5


def test_slam_maps_an_upside_down_laser_as_an_upright_one(tmp_path, capsys):
    scans = sim_scans(150)
    up, down = tmp_path / "up.bag", tmp_path / "down.bag"
    write_bag(up, scans, "ros1")
    _upside_down_bag(down, scans, "ros1", 0)
    poses = {}
    for name, p in (("up", up), ("down", down)):
        assert main(["run", str(p), "--out", str(tmp_path / name), "--no-progress", "--no-loop-closure"]) == 0
        poses[name] = np.loadtxt(tmp_path / name / "trajectory.txt")[:, 1:3]
    # the upside-down laser sits 0.1 m ahead: trajectories are the robot's, so they agree
    assert np.max(np.hypot(*(poses["up"] - poses["down"]).T)) < 0.02
    assert np.ptp(poses["up"][:, 0]) > 2.0  # the robot went somewhere
    capsys.readouterr()
    for name, p in (("up", up), ("down", down)):  # `slam2d info` says what it decided
        assert main(["info", str(p), "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["laser_upside_down"] == (name == "down")


def _tf_odometry_bag(path, scans, kind):
    """The simulator's scans as a bag recorded for slam_toolbox: no nav_msgs/Odometry, the wheel
    odometry only as the TF edge odom → base_footprint on /tf, beside a moving map → odom (a SLAM
    node ran while it was recorded) and a fixed base_footprint → laser on /tf_static."""
    from slam2d.io.mcap import scan_messages

    def tf(parent, child, pose, sec, nsec):
        z, w = yaw_quaternion(pose[2])
        return {"header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": parent}, "child_frame_id": child,
                "transform": {"translation": {"x": float(pose[0]), "y": float(pose[1]), "z": 0.0},
                              "rotation": {"z": z, "w": w}}}

    w = RosbagWriter(path, kind)
    for k, s in enumerate(scans):
        for topic, type_name, msg, sec, nsec in scan_messages(s, with_mount=False):
            if type_name == "nav_msgs/Odometry":
                w.write("/tf", "tf2_msgs/TFMessage", {"transforms": [
                    tf("map", "odom", (0.01 * k, 0.0, 0.001 * k), sec, nsec),
                    tf("odom", "base_footprint", s.odom_pose, sec, nsec)]}, sec, nsec)
                continue
            if k == 0 and type_name == "sensor_msgs/LaserScan":
                w.write("/tf_static", "tf2_msgs/TFMessage", {"transforms": [
                    tf("base_footprint", "laser", (0.0, 0.0, 0.0), sec, nsec)]}, sec, nsec)
            w.write(topic, type_name, msg, sec, nsec)
    w.finish()


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_without_an_odometry_topic_the_moving_tf_edge_into_the_robot_is_the_odometry(tmp_path, kind, capsys):
    scans = sim_scans(120)
    plain, tf_only = tmp_path / "plain.bag", tmp_path / ("tf.bag" if kind == "ros1" else "tf")
    write_bag(plain, scans, "ros1")
    _tf_odometry_bag(tf_only, scans, kind)
    log = RosbagLog(tf_only)
    assert log.odom_topic is None
    back = list(log)
    assert log.odometry_from.startswith("TF odom -> base_footprint (120 transforms")
    for a, b in zip(scans, back):
        np.testing.assert_allclose(b.odom_pose, a.odom_pose, atol=1e-12)
        np.testing.assert_array_equal(b.laser_offset, np.zeros(3))
    runs = {}
    for name, p in (("plain", plain), ("tf", tf_only)):
        assert main(["run", str(p), "--out", str(tmp_path / name), "--no-progress"]) == 0
        runs[name] = np.loadtxt(tmp_path / name / "trajectory.txt")[:, 1:4]
    assert np.max(np.abs(runs["plain"] - runs["tf"])) < 1e-3
    capsys.readouterr()
    assert main(["info", str(tf_only), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["odometry_from"].startswith("TF odom -> base_footprint")
