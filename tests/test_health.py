"""The map health report flags a broken map and passes a good one (no ground truth used)."""
import math

import numpy as np

from slam2d.config import config_from_dict
from slam2d.geometry import compose
from slam2d.health import assess


def _bundled_local_run():
    from conftest import BUNDLED
    from slam2d.frontend import LocalSlam
    from slam2d.io.source import open_source
    from slam2d.mapper import Mapper

    cfg = config_from_dict({})
    tracker = LocalSlam(cfg, loop_closure=False)
    result = Mapper(cfg, tracker).run(open_source(BUNDLED))
    return cfg, tracker, result


def test_health_passes_a_good_map_and_flags_a_broken_one():
    cfg, tracker, result = _bundled_local_run()
    good = assess(cfg, result.nodes, result.poses, tracker.summary()["local_slam"])
    assert good["status"] == "OK", good
    assert good["scans_agreeing_with_map"] > 0.95
    # break it: the second half of the trajectory turned by 8° and shifted by 0.5 m (a failed match)
    poses = result.poses.copy()
    half = len(poses) // 2
    kink = np.array([0.5, 0.0, math.radians(8.0)])
    for i in range(half, len(poses)):
        poses[i] = compose(kink, poses[i])
    bad = assess(cfg, result.nodes, poses, tracker.summary()["local_slam"])
    assert bad["status"] == "BROKEN", bad
    assert bad["reasons"]


def test_health_flags_untrusted_matches():
    local = {"matched_scans": 900, "untrusted": 100}
    h = assess(config_from_dict({}), [], np.zeros((0, 3)), local)
    assert h["status"] == "BROKEN" and "matched with confidence" in h["reasons"][0]
