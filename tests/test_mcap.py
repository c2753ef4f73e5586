import numpy as np
import pytest

from slam2d.errors import InputError
from slam2d.io.mcap import McapLog, McapWriter
from slam2d.io.simulator import SimConfig, simulate


def write_scans(path, scans, **kw):
    with open(path, "wb") as f:
        w = McapWriter(f, **kw)
        for s in scans:
            w.write_scan(s)
        w.finish()


def test_round_trip_scans_odometry_ground_truth(tmp_path):
    scans = [s for _, s in zip(range(40), simulate(SimConfig(seed=3)))]
    p = tmp_path / "x.mcap"
    write_scans(p, scans)
    log = McapLog(p)
    assert (log.scan_topic, log.odom_topic, log.gt_topic) == ("/scan", "/odom", "/ground_truth")
    back = list(log)
    assert len(back) == 40 and log.num_scans() == 40
    for a, b in zip(scans, back):
        assert a.timestamp_text == b.timestamp_text
        np.testing.assert_array_equal(a.ranges, b.ranges)  # NaN and inf included
        np.testing.assert_array_equal(a.valid, b.valid)
        np.testing.assert_array_equal(a.no_return, b.no_return)
        np.testing.assert_allclose(a.odom_pose, b.odom_pose, atol=1e-9)
        np.testing.assert_allclose(a.ground_truth, b.ground_truth, atol=1e-9)
        assert b.angle_increment == pytest.approx(a.angle_increment, rel=1e-6)


def test_read_with_mcap_ros2_reader(tmp_path):
    from mcap_ros2.reader import read_ros2_messages

    scans = [s for _, s in zip(range(5), simulate(SimConfig(seed=1)))]
    p = tmp_path / "x.mcap"
    write_scans(p, scans)
    msgs = [m for m in read_ros2_messages(str(p), topics=["/scan"])]
    assert len(msgs) == 5
    assert msgs[0].schema.name == "sensor_msgs/msg/LaserScan"
    assert msgs[0].ros_msg.header.stamp.sec == 1_700_000_000


def test_explicit_topics_and_errors(tmp_path):
    scans = [s for _, s in zip(range(3), simulate(SimConfig(seed=1)))]
    p = tmp_path / "x.mcap"
    write_scans(p, scans, scan_topic="/front/scan")
    assert McapLog(p, scan_topic="/front/scan").scan_topic == "/front/scan"
    with pytest.raises(InputError, match="no topic '/nope'"):
        McapLog(p, scan_topic="/nope")
    with pytest.raises(InputError, match="is nav_msgs/msg/Odometry"):
        McapLog(p, scan_topic="/odom")


def test_mcap_without_laserscan(tmp_path):
    p = tmp_path / "poses.mcap"
    with open(p, "wb") as f:
        w = McapWriter(f)
        w.write_pose("/pose", np.zeros(3), 1, 0)
        w.finish()
    with pytest.raises(InputError) as e:
        McapLog(p)
    assert "no sensor_msgs/msg/LaserScan topic" in str(e.value) and str(p) in str(e.value)


def test_corrupt_and_truncated_mcap(tmp_path):
    scans = [s for _, s in zip(range(30), simulate(SimConfig(seed=1)))]
    p = tmp_path / "x.mcap"
    write_scans(p, scans)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError):
        list(McapLog(p))
    p.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 100)
    with pytest.raises(InputError):
        list(McapLog(p))
    p.write_text("not an mcap")
    with pytest.raises(InputError):
        McapLog(p)


def _rewrite(src, dst, **kw):
    """``src``'s messages written again by the mcap writer with ``kw`` (as another recorder would)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f:
        msgs = list(make_reader(f).iter_messages())
    with open(dst, "wb") as f:
        w = Writer(f, **kw)
        w.start("ros2", "test")
        sids, cids = {}, {}
        for sch, ch, m in msgs:
            if sch.id not in sids:
                sids[sch.id] = w.register_schema(sch.name, sch.encoding, sch.data)
            if ch.id not in cids:
                cids[ch.id] = w.register_channel(ch.topic, ch.message_encoding, sids[sch.id], ch.metadata)
            w.add_message(cids[ch.id], m.log_time, m.data, m.publish_time, m.sequence)
        w.finish()


def test_an_mcap_without_summary_or_cut_off_is_read_up_to_its_break(tmp_path, caplog):
    """A recorder that never closed its file leaves no summary section; one cut off (power lost) leaves
    half a record at the end. Both are read in file order, the second up to the break, with a warning."""
    import logging

    from mcap.writer import IndexType

    scans = [s for _, s in zip(range(40), simulate(SimConfig(seed=2)))]
    full = tmp_path / "full.mcap"
    write_scans(full, scans)
    want = list(McapLog(full))
    live = tmp_path / "live.mcap"
    _rewrite(full, live, index_types=IndexType.NONE, use_chunking=False, use_statistics=False,
             use_summary_offsets=False, repeat_channels=False, repeat_schemas=False)
    got = list(McapLog(live))
    assert [s.timestamp_text for s in got] == [s.timestamp_text for s in want]
    for a, b in zip(want, got):
        np.testing.assert_array_equal(a.ranges, b.ranges)
        np.testing.assert_array_equal(a.odom_pose, b.odom_pose)
    cut = tmp_path / "cut.mcap"
    data = live.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    with caplog.at_level(logging.WARNING, logger="slam2d.io"):
        part = list(McapLog(cut))
    assert 10 < len(part) < 40
    assert [s.timestamp_text for s in part] == [s.timestamp_text for s in want[: len(part)]]
    assert any("a broken record after" in r.getMessage() and "cut off" in r.getMessage() for r in caplog.records)
