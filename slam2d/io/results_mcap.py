"""``DIR/results.mcap``: a run's results in the ROS 2 profile, for Foxglove and ROS 2 tools.

Topics: the input scans (``/scan``, ``/odom``), ``/slam2d/pose`` (``geometry_msgs/msg/PoseStamped``,
the final pose of every scan, frame ``map``), ``/tf`` (``tf2_msgs/msg/TFMessage``:
map→odom and odom→base_link at every scan, as a ROS SLAM node publishes them) and ``/map``
(``nav_msgs/msg/OccupancyGrid``, the final map: 100 occupied, 0 free, −1 unknown, exactly
the cells of ``map.pgm``).

Messages are written scan by scan in the order of ``trajectory.txt``: ascending stamps, a
repeated stamp moved 1 µs later (`slam2d.io.trajectory`), which ``/slam2d/pose`` and ``/tf``
carry; so evo (``evo_traj mcap results.mcap /slam2d/pose``) accepts the poses where the log's
own stamps go back (Intel). The input scans keep their own header stamps.
"""
from __future__ import annotations

import numpy as np

from slam2d.geometry import compose, inverse
from slam2d.grid.map_export import FREE, OCCUPIED, UNKNOWN
from slam2d.io.mcap import McapWriter, _header, _pose_dict
from slam2d.io.ros2_msgs import stamp_from_text
from slam2d.io.trajectory import ascending_stamps


def _tf(parent, child, pose, sec, nsec):
    q = _pose_dict(pose)["orientation"]
    return {"header": _header(sec, nsec, parent), "child_frame_id": child,
            "transform": {"translation": {"x": float(pose[0]), "y": float(pose[1]), "z": 0.0}, "rotation": q}}


def occupancy_grid_msg(img_top_first: np.ndarray, resolution: float, origin_xy, sec, nsec) -> dict:
    rows = img_top_first[::-1]  # OccupancyGrid rows start at the origin (bottom)
    data = np.full(rows.shape, -1, dtype=np.int8)
    data[rows == OCCUPIED] = 100
    data[rows == FREE] = 0
    assert np.all((rows == OCCUPIED) | (rows == FREE) | (rows == UNKNOWN))
    h, w = rows.shape
    return {"header": _header(sec, nsec, "map"),
            "info": {"map_load_time": {"sec": sec, "nanosec": nsec}, "resolution": float(resolution),
                     "width": int(w), "height": int(h),
                     "origin": _pose_dict((float(origin_xy[0]), float(origin_xy[1]), 0.0))},
            "data": data.ravel().tolist()}


def write_results_mcap(path, source, poses: np.ndarray, map_img, resolution, origin_xy, stamps=None) -> int:
    """``source``: the run's scans again, as many as it has poses and, given the run's ``stamps``,
    stamped as those (else a UsageError: another run's scans would carry its stamps into the file)."""
    from slam2d.errors import UsageError

    try:
        it = iter(source)
    except TypeError:
        raise UsageError(f"results.mcap needs the run's scans (e.g. open_source(path)), not {type(source).__name__}") from None
    scans = [scan for scan, _ in zip(it, poses)]
    if len(scans) < len(poses) or next(it, None) is not None:
        raise UsageError(f"results.mcap needs the run's {len(poses)} scans again; the scans given are "
                         f"{'fewer' if len(scans) < len(poses) else 'more'}")
    if stamps is not None:
        for i, (scan, stamp) in enumerate(zip(scans, stamps)):
            if scan.stamp_text != stamp:
                raise UsageError(f"results.mcap needs the run's scans again: scan {i} given is stamped {scan.stamp_text}, "
                                 f"the run's {stamp}")
    order, texts = ascending_stamps([s.stamp_text for s in scans])
    with open(path, "wb") as f:
        w = McapWriter(f)
        sec = nsec = 0
        for i, text in zip(order, texts):
            scan, pose = scans[i], poses[i]
            w.write_scan(scan)
            sec, nsec = stamp_from_text(text)
            w.write_pose("/slam2d/pose", pose, sec, nsec, "map")
            odom = scan.odom_pose if scan.odom_pose is not None else np.zeros(3)
            map_to_odom = compose(pose, inverse(odom))
            w.write("/tf", "tf2_msgs/TFMessage", {"transforms": [_tf("map", "odom", map_to_odom, sec, nsec),
                                                                 _tf("odom", "base_link", odom, sec, nsec)]}, sec, nsec)
        w.write("/map", "nav_msgs/OccupancyGrid", occupancy_grid_msg(map_img, resolution, origin_xy, sec, nsec), sec, nsec)
        w.finish()
    return len(scans)
