"""ROS input (bags, MCAP) that is broken, or legal but unusual: one line naming the file and the
record, or a run that works; never a traceback or a result made of nothing."""
import logging
import math

import numpy as np
import pytest

from slam2d.cli import main
from slam2d.errors import InputError
from slam2d.io.mcap import McapLog, McapWriter, yaw_quaternion
from slam2d.io.rosbag import RosbagWriter
from slam2d.io.simulator import SimConfig, simulate
from slam2d.io.source import open_source
from slam2d.io.tf_tree import TfTree
from slam2d.slam import Slam
from slam2d.types import Scan


def _scan(sec, ranges=(1.0, 2.0, 3.0), inc=0.1, angle_max=0.1, range_min=0.1, range_max=10.0):
    return {"header": {"stamp": {"sec": sec, "nanosec": 0}, "frame_id": "laser"}, "angle_min": -0.1,
            "angle_max": angle_max, "angle_increment": inc, "range_min": range_min, "range_max": range_max,
            "ranges": list(ranges)}


def _odom(sec, x, w=1.0):
    return {"header": {"stamp": {"sec": sec, "nanosec": 0}, "frame_id": "odom"}, "child_frame_id": "base_link",
            "pose": {"pose": {"position": {"x": x}, "orientation": {"w": w}}}}


def _tf(x):
    z, w = yaw_quaternion(0.0)
    return {"transforms": [{"header": {"stamp": {"sec": 1, "nanosec": 0}, "frame_id": "base_link"},
                            "child_frame_id": "laser",
                            "transform": {"translation": {"x": x, "y": 0.0, "z": 0.0}, "rotation": {"z": z, "w": w}}}]}


def _bag(path, scans=(), odoms=(), tfs=()):
    w = RosbagWriter(path, "ros1")
    for tf in tfs:
        w.write("/tf_static", "tf2_msgs/TFMessage", tf, 1, 0)
    for sec, m in odoms:
        w.write("/odom", "nav_msgs/Odometry", m, sec, 0)
    for sec, m in scans:
        w.write("/scan", "sensor_msgs/LaserScan", m, sec, 0)
    w.finish()
    return path


def _error(path) -> str:
    with pytest.raises(InputError) as e:
        list(open_source(path))
    return str(e.value)


def test_a_transform_with_a_nan_translation_names_its_record(tmp_path):
    with pytest.raises(ValueError, match="not finite"):
        TfTree().add("a", "b", (math.nan, 0, 0), (0, 0, 0, 1), True)
    p = _bag(tmp_path / "x.bag", scans=[(1, _scan(1))], tfs=[_tf(0.2), _tf(math.nan)])
    assert _error(p) == f"{p}: record 1: bad transform on /tf_static: translation (nan, 0.0, 0.0) is not finite"


def test_minus_inf_is_too_close_and_a_negative_reading_names_its_beam(tmp_path):
    # REP 117: -inf is a detection too close to measure: no hit and no free space, not an error
    p = _bag(tmp_path / "ok.bag", scans=[(1, _scan(1, ranges=(1.0, -math.inf, 3.0)))])
    s, = open_source(p)
    assert s.valid.tolist() == [True, False, True] and s.no_return.tolist() == [False, False, False]
    p = _bag(tmp_path / "bad.bag", scans=[(1, _scan(1)), (2, _scan(2, ranges=(1.0, 2.0, -0.5)))])
    assert _error(p) == f"{p}: record 1: negative range reading -0.5 at beam 2 (1 in this scan)"


@pytest.mark.parametrize("range_min, range_max", [(20.0, 10.0), (math.nan, 10.0), (-1.0, 10.0)])
def test_a_range_min_that_leaves_no_reading_is_an_error(tmp_path, range_min, range_max):
    p = _bag(tmp_path / "x.bag", scans=[(1, _scan(1, range_min=range_min, range_max=range_max))])
    assert _error(p).startswith(f"{p}: record 0: LaserScan range_min {range_min} unusable")


def test_odometry_errors_name_the_odometry_message_and_its_stamp(tmp_path):
    tfs = [_tf(0.2)] * 3  # TF messages come before the odometry: the record counts /odom's messages alone
    odoms = [(s, _odom(s, 0.1 * s)) for s in range(1, 4)]
    scans = [(s, _scan(s)) for s in range(1, 4)]
    p = _bag(tmp_path / "nan.bag", scans, odoms[:2] + [(3, _odom(3, math.nan))], tfs)
    err = _error(p)
    assert err.startswith(f"{p}: record 2: non-finite pose (nan, ") and err.endswith("on /odom (stamp 3.000000000)")
    p = _bag(tmp_path / "quat.bag", scans, odoms[:1] + [(2, _odom(2, 0.2, w=0.0))], tfs)
    assert _error(p) == f"{p}: record 1: orientation quaternion (0.0, 0.0, 0.0, 0.0) on /odom (stamp 2.000000000) " \
                        "has no rotation"


def test_a_scan_topic_without_messages_is_named(tmp_path, capsys):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    p = tmp_path / "empty.bag"
    w = Writer(p)
    w.open()
    w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=get_typestore(Stores.ROS1_NOETIC))
    w.close()
    for cmd in ("run", "info"):
        assert main([cmd, str(p)] + (["--out", str(tmp_path / "o"), "--no-progress"] if cmd == "run" else [])) == 2
        err = capsys.readouterr().err
        assert err == f"slam2d: error: {p}: no messages on /scan\n"


def test_beam_count_against_angle_max_and_the_odometry_clock_warn_once(tmp_path, caplog):
    odoms = [(s + 100, _odom(s + 100, 0.1 * s)) for s in range(1, 4)]  # another clock: 100 s later
    scans = [(s, _scan(s, angle_max=0.3)) for s in range(1, 4)]  # 3 ranges, but -0.1..0.3 by 0.1 is 5 beams
    p = _bag(tmp_path / "x.bag", scans, odoms, [_tf(0.2)])
    with caplog.at_level(logging.WARNING, logger="slam2d.io"):
        got = list(open_source(p))
    assert len(got) == 3
    msgs = [r.getMessage() for r in caplog.records]
    assert sum("3 ranges, but angle_min -0.1 to angle_max 0.3" in m for m in msgs) == 1, msgs
    assert sum("lies outside the odometry's stamps (101.000 to 103.000)" in m for m in msgs) == 1, msgs
    caplog.clear()
    p = _bag(tmp_path / "y.bag", [(s, _scan(s)) for s in range(1, 4)], [(s, _odom(s, 0.1 * s)) for s in range(1, 4)],
             [_tf(0.2)])
    with caplog.at_level(logging.WARNING, logger="slam2d.io"):
        list(open_source(p))
    assert not caplog.records  # a consistent bag says nothing


def test_a_file_named_as_another_kind_is_named_by_its_content(tmp_path, capsys):
    scans = [s for _, s in zip(range(3), simulate(SimConfig(seed=1)))]
    with open(tmp_path / "x.bag", "wb") as f:  # an MCAP named .bag
        w = McapWriter(f)
        for s in scans:
            w.write_scan(s)
        w.finish()
    _bag(tmp_path / "y.mcap", scans=[(1, _scan(1))])  # a ROS 1 bag named .mcap
    for name, what, suffix in (("x.bag", "an MCAP file", ".mcap"), ("y.mcap", "a ROS 1 bag", ".bag")):
        assert main(["info", str(tmp_path / name)]) == 2
        assert capsys.readouterr().err == (f"slam2d: error: {tmp_path / name}: this file is {what} (its first bytes say "
                                           f"so), not what its name says: name it *{suffix}\n")


def test_a_ros1_encoded_mcap_is_named(tmp_path):
    from mcap.writer import Writer

    p = tmp_path / "ros1.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start("ros1", "test")
        sid = w.register_schema("sensor_msgs/LaserScan", "ros1msg", b"float32 angle_min")
        cid = w.register_channel("/scan", "ros1", sid)
        w.add_message(cid, 1, b"\x00" * 4, 1)
        w.finish()
    with pytest.raises(InputError) as e:
        McapLog(p)
    assert "/scan is 'ros1'-encoded" in str(e.value) and "give slam2d the .bag itself" in str(e.value)


def _scans(n, ranges, stamps=None):
    return [Scan.from_ranges(float(i if stamps is None else stamps[i]), np.asarray(ranges, dtype=np.float32),
                             -math.pi / 2, math.pi / 180, 30.0, odom_pose=(0.01 * i, 0.0, 0.0))
            for i in range(n)]


@pytest.mark.parametrize("value, what", [(math.nan, "0 no-returns"), (math.inf, "1800 no-returns")])
def test_a_run_without_a_single_return_is_an_input_error(value, what):
    slam = Slam(mode="local", source_name="nothing.mcap")
    for s in _scans(10, np.full(180, value)):
        slam.add_scan(s)
    with pytest.raises(InputError) as e:
        slam.finish()
    assert str(e.value) == ("nothing.mcap: none of the 10 scans holds a usable reading (every beam is invalid, out of "
                            f"range or a no-return: {what} of 1800 readings)")


def test_a_run_whose_scans_all_carry_one_stamp_is_an_input_error():
    slam = Slam(mode="local", source_name="same.bag")
    ranges = 2.0 + np.abs(np.sin(np.linspace(0, 6, 180)))
    for s in _scans(10, ranges, stamps=[5.0] * 10):
        slam.add_scan(s)
    with pytest.raises(InputError, match=r"^same.bag: every scan is stamped 5.0: the timestamps are unusable"):
        slam.finish()


@pytest.mark.parametrize("content", [b"", b"abc", b"junk\n", b"\x89MCAP0\r\n", None])
def test_a_few_bytes_named_mcap_are_one_line(tmp_path, capsys, content):
    """Shorter than a record header they were a struct.error traceback (None: the first 100 bytes of a real file)."""
    from conftest import BUNDLED

    p = tmp_path / "x.mcap"
    p.write_bytes(BUNDLED.read_bytes()[:100] if content is None else content)
    for cmd in ("info", "run"):
        assert main([cmd, str(p)] + (["--out", str(tmp_path / "o"), "--no-progress"] if cmd == "run" else [])) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"slam2d: error: {p}") and err.count("\n") == 1 and "Traceback" not in err, err


def test_a_scan_spanning_more_than_a_turn_names_its_record(tmp_path):
    """angle_increment given in degrees: 3 beams 10 rad apart."""
    p = _bag(tmp_path / "deg.bag", scans=[(1, _scan(1)), (2, _scan(2, inc=10.0, angle_max=19.9))])
    assert _error(p).startswith(f"{p}: record 1: 3 beams 10 rad apart span 1146°, more than a full turn")
