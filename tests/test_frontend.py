"""Local SLAM's set-up: the submap size follows whether a pose graph follows."""
from slam2d.config import config_from_dict
from slam2d.frontend import LocalSlam


def test_submap_size_depends_on_loop_closure():
    cfg = config_from_dict({"submaps": {"num_range_data": 30, "num_range_data_without_loop_closure": 70}})
    assert LocalSlam(cfg).submaps.num_range_data == 30  # loop closure is on by default
    assert LocalSlam(cfg, loop_closure=True).submaps.num_range_data == 30
    assert LocalSlam(cfg, loop_closure=False).submaps.num_range_data == 70
    off = config_from_dict({"loop_closure": {"enabled": False},
                            "submaps": {"num_range_data": 30, "num_range_data_without_loop_closure": 70}})
    assert LocalSlam(off).submaps.num_range_data == 70


def test_local_only_run_finishes_submaps_at_the_local_only_size(tmp_path):
    from slam2d.io.source import open_source
    from slam2d.mapper import Mapper
    from conftest import BUNDLED

    cfg = config_from_dict({"submaps": {"num_range_data": 10, "num_range_data_without_loop_closure": 25}})
    tracker = LocalSlam(cfg, loop_closure=False)
    Mapper(cfg, tracker).run(open_source(BUNDLED))
    assert tracker.finished_submaps, "the bundled run should finish submaps"
    # a submap starts every 25 insertions and is finished after 2 × 25
    assert all(s.num_range_data == 50 for s in tracker.finished_submaps)
    assert tracker.submaps.count == tracker.num_inserted // 25 + (tracker.num_inserted % 25 > 0)
