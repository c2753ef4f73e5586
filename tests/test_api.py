"""The library API (``slam2d.Slam``): one code path with ``slam2d run``, estimates while running, scans from arrays."""
import dataclasses
import json
import math
import subprocess
import sys

import numpy as np
import pytest

import slam2d
from conftest import BUNDLED, ROOT
from slam2d.cli import main
from slam2d.errors import InputError, UsageError


def test_api_loop_gives_exactly_what_slam2d_run_writes(tmp_path):
    assert main(["run", str(BUNDLED), "--out", str(tmp_path / "cli"), "--no-progress"]) == 0
    slam = slam2d.Slam()
    estimates = []
    for scan in slam2d.open_source(BUNDLED):
        estimates.append(slam.add_scan(scan))
        if scan.index % 100 == 99:
            slam.sync()  # global SLAM runs behind add_scan: let it catch up now and then
    result = slam.finish()
    result.save(tmp_path / "api")
    for name in ("trajectory.txt", "map.pgm", "map.yaml", "config.yaml"):
        assert (tmp_path / "api" / name).read_bytes() == (tmp_path / "cli" / name).read_bytes(), name

    def records(run):  # every field but the search's wall time
        return [{k: v for k, v in json.loads(line).items() if k != "search_ms"}
                for line in (tmp_path / run / "constraints.jsonl").read_text().splitlines()]

    assert records("api") == records("cli") and records("api")
    assert result.poses.shape == (len(estimates), 3)
    assert [e.index for e in estimates] == list(range(len(estimates)))
    # the estimate while running is the local pose moved by the latest correction; loops closed on the
    # way, so after them the global estimate is no longer the local pose (by how much depends on the
    # drift they correct; on the simulator about a centimetre at most), and at the end it is near the final one
    assert result.summary["loop_closure"]["optimizations"] >= 1
    moved = [np.abs(e.global_pose[:2] - e.local_pose[:2]).max() for e in estimates]
    assert moved[0] == 0.0 and max(moved) > 5e-3
    last = estimates[-1]
    assert math.hypot(*(last.global_pose[:2] - result.poses[-1][:2])) < 0.2


def test_local_and_odometry_modes_and_misuse():
    scans = [s for _, s in zip(range(120), slam2d.open_source(BUNDLED))]
    local = slam2d.Slam(mode="local")
    ests = [local.add_scan(s) for s in scans]
    assert all(np.array_equal(e.global_pose, e.local_pose) for e in ests)  # no pose graph: nothing moves it
    res = local.finish()
    np.testing.assert_array_equal(res.poses, np.array([e.local_pose for e in ests]))
    assert res.summary["mode"] == "local" and "loop_closure" not in res.summary
    with pytest.raises(UsageError):
        local.add_scan(scans[0])
    odo = slam2d.Slam(mode="odometry").run(scans)
    np.testing.assert_allclose(odo.poses, np.array([s.odom_pose for s in scans]))
    with pytest.raises(UsageError):
        slam2d.Slam(mode="fast")
    with pytest.raises(InputError):
        slam2d.Slam().finish()


def test_scans_from_range_arrays_run_like_the_source_scans():
    """``Scan.from_ranges`` as robot code would call it (ROS LaserScan fields) gives the same run."""
    scans = [s for _, s in zip(range(150), slam2d.open_source(BUNDLED))]
    rebuilt = [slam2d.Scan.from_ranges(s.timestamp, s.ranges.copy(), s.angle_min, s.angle_increment, s.range_max,
                                       odom_pose=s.odom_pose, range_min=s.range_min, laser_offset=s.laser_offset)
               for s in scans]
    a = slam2d.Slam(mode="local").run(scans).poses
    b = slam2d.Slam(mode="local").run(rebuilt).poses
    np.testing.assert_array_equal(a, b)


def test_from_ranges_classifies_readings_as_ros_does():
    s = slam2d.Scan.from_ranges(1.5, [0.0, 0.05, 1.0, 30.0, 30.5, np.inf, np.nan, -np.inf], -1.0, 0.25, 30.0,
                                range_min=0.1)
    assert s.valid.tolist() == [False, False, True, True, False, False, False, False]
    assert s.no_return.tolist() == [False, False, False, False, True, True, False, False]
    assert s.num_beams == 8 and s.odom_pose is None and s.timestamp == 1.5


def test_from_yaml(tmp_path):
    (tmp_path / "c.yaml").write_text("submaps:\n  num_range_data: 33\n")
    slam = slam2d.Slam.from_yaml(tmp_path / "c.yaml")
    assert slam.config.submaps.num_range_data == 33 and slam.tracker.submaps.num_range_data == 33


def test_example_script_runs(tmp_path):
    out = tmp_path / "run"
    p = subprocess.run([sys.executable, str(ROOT / "examples" / "online_slam.py"), str(BUNDLED), str(out), "--every", "500"],
                       capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert p.returncode == 0, p.stderr
    assert "loop closures" in p.stdout and (out / "trajectory.txt").exists() and (out / "summary.json").exists()
    n = sum(1 for _ in slam2d.open_source(BUNDLED))
    assert len((out / "trajectory.txt").read_text().splitlines()) == n


def test_outputs_identical_with_one_and_two_threads(tmp_path):
    """Determinism: the same input gives byte-identical trajectory, map and constraints whatever the
    thread count (numba kernels that use threads split work so that the result does not depend on it)."""
    import os

    outs = []
    for n in ("1", "2"):
        out = tmp_path / f"t{n}"
        env = dict(os.environ, NUMBA_NUM_THREADS=n)
        p = subprocess.run([sys.executable, "-m", "slam2d.cli", "run", str(BUNDLED), "--out", str(out), "--no-progress"],
                           env=env, capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, p.stderr
        outs.append(out)
    for name in ("trajectory.txt", "map.pgm", "map.yaml"):
        assert (outs[0] / name).read_bytes() == (outs[1] / name).read_bytes(), name
    strip = [[{k: v for k, v in json.loads(x).items() if k != "search_ms"} for x in (o / "constraints.jsonl").read_text().splitlines()]
             for o in outs]
    assert strip[0] == strip[1] and strip[0]
    health = [json.loads((o / "summary.json").read_text())["health"] for o in outs]
    assert health[0] == health[1]  # its free-space test is split over the threads too


def test_finish_frees_the_submaps_and_keeps_a_complete_map():
    """After finish no scan is matched or inserted again: submap grids and search grids are released
    (memory then holds the map, not the map twice), and the map still holds every node."""
    from slam2d.config import config_from_dict
    from slam2d.grid.map_builder import build_map

    # without the final refinement, the result's node poses are those the map was built from
    slam = slam2d.Slam(config_from_dict({"final_refinement": {"enabled": False}}))
    scans = [s for _, s in zip(range(400), slam2d.open_source(BUNDLED))]
    for s in scans:
        slam.add_scan(s)
    slam.sync()
    subs = slam.tracker.all_submaps()
    newer = slam.tracker.submaps.submaps[1:]  # the newer active submap keeps its scans for a batch: no grid yet
    assert len(slam.global_slam.matchers) >= 2 and all(s.grid.prob.size > 0 for s in subs if s not in newer)
    res = slam.finish()
    assert all(s.grid.prob.size == 0 and s.grid.known.size == 0 for s in subs)
    assert slam.global_slam.stacks.nbytes == 0  # no search grid is left
    assert res.map.logodds.size == 0 and res.map.prob.dtype == np.float32  # the finished map: 5 bytes a cell
    again = build_map(slam.config, res.nodes, {n.scan_index: res.poses[n.scan_index] for n in res.nodes})
    np.testing.assert_array_equal(again.prob, res.map.prob)
    assert (res.map.known > 0).sum() > 10000


def test_map_image_is_top_row_first(tmp_path):
    """map.pgm row 0 is the map's top (largest y), as map_server reads it."""
    from slam2d.grid.map_export import OCCUPIED, occupancy_image
    from slam2d.grid.probability_grid import ProbabilityGrid

    g = ProbabilityGrid(0.1)
    for _ in range(10):  # a hit 2 m above the sensor, free space below it
        g.insert((0.0, 0.0), np.array([[0.0, 2.0]]))
    img, ox, oy = occupancy_image(g, 0.65, 0.196)
    r, c = np.argwhere(img == OCCUPIED)[0]
    y = oy + (img.shape[0] - 1 - r + 0.5) * g.resolution
    x = ox + (c + 0.5) * g.resolution
    assert abs(y - 2.0) < 0.1 and abs(x) < 0.1
    assert (np.argwhere(img == OCCUPIED)[:, 0] == r).all()


def test_map_cells_by_evidence_show_what_a_few_scans_saw(tmp_path):
    """A place seen by a few scans (a sparse log): by evidence (the default), a cell that rays crossed
    twice is free and a cell hit twice is occupied; map_saver's thresholds on Cartographer's
    probabilities would leave both unknown. A cell hit once and crossed by many rays later (a
    person who walked away) is free either way; a cell no ray reached stays unknown."""
    from slam2d.config import SlamConfig
    from slam2d.grid.map_export import FREE, OCCUPIED, UNKNOWN, read_pgm, write_map
    from slam2d.grid.probability_grid import ProbabilityGrid

    cfg = SlamConfig()
    g = ProbabilityGrid.from_config(cfg.grid, resolution=0.1)
    wall = np.array([[x, 3.0] for x in np.arange(-2.0, 2.01, 0.1)])
    for o in ((0.0, 0.0), (0.05, 0.0)):  # two scans of a wall 3 m ahead
        g.insert(o, wall)
    g.insert((0.0, 0.0), np.array([[1.0, 0.0]]))  # a person 1 m to the right, once, then rays through that cell
    for _ in range(60):
        g.insert((0.0, 0.0), np.zeros((0, 2)), np.array([[1.5, 0.0]]))

    def cell(img, ox, oy, x, y):
        r = img.shape[0] - 1 - int(np.floor((y - oy) / g.resolution))
        return img[r, int(np.floor((x - ox) / g.resolution))]

    def export(mode):
        out = tmp_path / mode
        out.mkdir()
        m = SlamConfig(map={"cells": mode}).map
        write_map(out, g, m.occupied_thresh, m.free_thresh, cells=m.cell_thresholds(cfg.grid))
        meta = dict(line.split(": ", 1) for line in (out / "map.yaml").read_text().splitlines())
        ox, oy = (float(v) for v in meta["origin"].strip("[]").split(",")[:2])
        assert float(meta["occupied_thresh"]) == m.occupied_thresh  # map_server's reading of the pixels
        return read_pgm(out / "map.pgm"), ox, oy

    img, ox, oy = export("evidence")
    assert cell(img, ox, oy, 0.0, 3.02) == OCCUPIED
    assert cell(img, ox, oy, 0.02, 1.52) == FREE
    assert cell(img, ox, oy, 1.02, 0.02) == FREE
    assert cell(img, ox, oy, -1.52, 0.52) == UNKNOWN  # inside the image's bounds, beside the rays
    img, ox, oy = export("thresholds")
    assert cell(img, ox, oy, 0.0, 3.02) == UNKNOWN and cell(img, ox, oy, 0.02, 1.52) == UNKNOWN
    assert cell(img, ox, oy, 1.02, 0.02) == FREE


def test_refinement_points_kept_compactly_are_the_matched_points():
    """A scan that became a node keeps only which of the node's hits it matched; the final refinement
    gets back exactly the points local SLAM matched (as float32), for nodes and other scans alike."""
    slam = slam2d.Slam()
    for _, s in zip(range(300), slam2d.open_source(BUNDLED)):
        slam.add_scan(s)
    slam.sync()
    got = slam._refinement_points()
    assert len(got) == 300
    kinds = {p.ndim for (p,) in slam._points.records() if p is not None}
    assert kinds == {1, 2}  # some scans kept as indices (nodes), others as points
    # the same scans once more through local SLAM alone: the points it matched (they depend on the scan only)
    again = slam2d.Slam(mode="local")
    for i, s in zip(range(300), slam2d.open_source(BUNDLED)):
        res = again.tracker.add_scan(s)
        want = None if res.points is None else res.points.astype(np.float32)
        if want is None:
            assert got[i] is None
        else:
            np.testing.assert_array_equal(got[i], want)
            assert got[i].dtype == np.float32
    slam.finish()


def _ok_scan(t=0.0, **kw):
    args = dict(ranges=np.full(180, 3.0), angle_min=-math.pi / 2, angle_increment=math.pi / 180, range_max=30.0)
    args.update(kw)
    return slam2d.Scan.from_ranges(t, args.pop("ranges"), args.pop("angle_min"), args.pop("angle_increment"),
                                   args.pop("range_max"), **args)


@pytest.mark.parametrize("kw, needle", [
    ({"ranges": np.ones((2, 180))}, "ranges must be one row of readings, not an array of shape (2, 180)"),
    ({"ranges": None}, "ranges must be one row of readings, not an array of shape ()"),
    ({"ranges": []}, "ranges must be a non-empty 1-D array of floats"),
    ({"ranges": ["a", "b"]}, "ranges must be numbers, not list"),
    ({"ranges": [1.0, -2.0, 3.0]}, "negative range reading -2 at beam 1"),
    ({"range_max": True}, "range_max must be a number, not True"),
    ({"angle_min": "0.5"}, "angle_min must be a number, not '0.5'"),
    ({"angle_increment": 0.0}, "angle_increment must not be 0"),
    ({"angle_min": math.nan}, "angle_min must be a finite number, not nan"),
    ({"range_max": 0.0}, "range_max must be positive, not 0.0"),
    ({"odom_pose": [1.0, 2.0]}, "odom_pose must be (x, y, θ), not [1.0, 2.0]"),
    ({"odom_pose": [1.0, 2.0, math.inf]}, "odom_pose must be (x, y, θ), three finite numbers"),
    ({"laser_offset": [0.0, math.nan, 0.0]}, "laser_offset must be (x, y, θ), three finite numbers"),
    ({"intensities": np.ones(10)}, "intensities has shape (10,), ranges (180,)"),
])
def test_from_ranges_refuses_what_cannot_be_mapped(kw, needle):
    """These went through and broke deep inside (a NaN angle: 'cannot convert float NaN to integer' in
    the grid; a 2-D array: silently one scan of 360 beams; odd intensities: an invalid results.mcap)."""
    with pytest.raises(UsageError) as e:
        _ok_scan(**kw)
    assert needle in str(e.value) and str(e.value).startswith("Scan.from_ranges: ")
    with pytest.raises(UsageError, match="^Scan.from_ranges: timestamp must be a finite number, not inf"):
        _ok_scan(math.inf)


def test_add_scan_refuses_bad_calls_and_a_refused_call_changes_nothing():
    scans = [s for _, s in zip(range(60), slam2d.open_source(BUNDLED))]
    alone = slam2d.Slam(mode="local")
    for s in scans:
        alone.add_scan(s)
    slam = slam2d.Slam(mode="local")
    for i, s in enumerate(scans):
        if i == 30:
            with pytest.raises(UsageError, match="add_scan takes a slam2d.Scan"):
                slam.add_scan({"ranges": s.ranges})
            broken = dataclasses.replace(s, angle_increment=math.nan)  # built directly, not by from_ranges
            with pytest.raises(UsageError, match=r"^input: scan 30: angle_increment must be a finite number, not nan"):
                slam.add_scan(broken)
            with pytest.raises(UsageError, match=r"^input: scan 30: stamped .*, 5 s before an earlier scan"):
                slam.add_scan(dataclasses.replace(s, timestamp=scans[29].timestamp - 5.0))
        slam.add_scan(s)
    np.testing.assert_array_equal(slam.finish().poses, alone.finish().poses)


def test_slam_takes_a_config_dict_and_names_other_things():
    assert slam2d.Slam({"grid": {"resolution": 0.1}}).config.grid.resolution == 0.1
    with pytest.raises(slam2d.Slam2dError, match="grid.resolution"):
        slam2d.Slam({"grid": {"resolution": -1}})
    with pytest.raises(UsageError, match=r"a YAML file: Slam.from_yaml\(path\)"):
        slam2d.Slam("x.yaml")


def test_save_refuses_no_folder_a_folder_in_the_way_and_clears_another_run_s_files(tmp_path):
    scans = [s for _, s in zip(range(120), slam2d.open_source(BUNDLED))]
    glob_ = slam2d.Slam()
    for s in scans:
        glob_.add_scan(s)
    first = glob_.finish()
    out = tmp_path / "run"
    first.save(out, mcap_scans=scans)
    assert (out / "constraints.jsonl").exists() and (out / "results.mcap").exists()
    for bad in (None, ""):
        with pytest.raises(UsageError, match="save needs a folder"):
            first.save(bad)
    with pytest.raises(UsageError, match="results.mcap needs the run's 120 scans again; the scans given are fewer"):
        first.save(tmp_path / "short", mcap_scans=scans[:10])
    shifted = [dataclasses.replace(s, timestamp=s.timestamp + 100, timestamp_text=None) for s in scans]
    with pytest.raises(UsageError, match=r"results.mcap needs the run's scans again: scan 0 given is stamped 1700000100.0"):
        first.save(tmp_path / "other", mcap_scans=shifted)
    local = slam2d.Slam(mode="local")
    for s in scans:
        local.add_scan(s)
    second = local.finish()
    second.save(out)  # a local run over the global one: its constraints and results.mcap must not stay
    assert not (out / "constraints.jsonl").exists() and not (out / "results.mcap").exists()
    assert json.loads((out / "summary.json").read_text())["mode"] == "local"
    blocked = tmp_path / "blocked"
    (blocked / "map.pgm").mkdir(parents=True)
    before = sorted(p.name for p in blocked.iterdir())
    with pytest.raises(UsageError, match="map.pgm: is a folder"):
        second.save(blocked)
    assert sorted(p.name for p in blocked.iterdir()) == before  # nothing renamed, no partial left


def test_a_stamp_far_ahead_is_warned_about_and_stamps_are_written_short(tmp_path, caplog):
    """Five scans stamped 0, then the clock: the run was 1.7e9 s long without a word. A scan without the
    source's stamp text is written with the shortest decimal of its stamp (1700000000.2, not .200000048)."""
    import logging

    slam = slam2d.Slam(mode="local", source_name="api")
    with caplog.at_level(logging.WARNING, logger="slam2d.slam"):
        for i in range(8):
            slam.add_scan(_ok_scan(0.0 if i < 5 else 1700000000.0 + 0.2 * i, odom_pose=(0.01 * i, 0, 0)))
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 1 and msgs[0].startswith("api: scan 5 is stamped 1700000001.0, 1.7e+09 s after"), msgs
    slam.finish().save(tmp_path / "o")
    stamps = [line.split()[0] for line in (tmp_path / "o" / "trajectory.txt").read_text().splitlines()
              if not line.startswith("#")]
    assert stamps[5:] == ["1700000001.0", "1700000001.2", "1700000001.4"]


def test_from_ranges_refuses_a_turn_and_more_and_range_min_above_range_max():
    with pytest.raises(UsageError, match=r"360 beams 1 rad apart span 20569°, more than a full turn"):
        _ok_scan(ranges=np.full(360, 3.0), angle_increment=1.0)
    with pytest.raises(UsageError, match=r"range_min 20.0 must be below range_max 12.0"):
        _ok_scan(range_min=20.0, range_max=12.0)


def test_a_scan_without_returns_mid_run_does_not_carve_the_map():
    """A glitch scan whose every beam is a no-return cannot be matched; inserted at its predicted pose it
    cleared a half-disc of free space outside the building. Scans local SLAM could not match are not
    inserted once a submap exists."""
    scans = [s for _, s in zip(range(120), slam2d.open_source(BUNDLED))]
    clean = slam2d.Slam(mode="local")
    glitch = slam2d.Slam(mode="local")
    for i, s in enumerate(scans):
        clean.add_scan(s)
        glitch.add_scan(dataclasses.replace(s, valid=np.zeros_like(s.valid), no_return=np.ones_like(s.valid))
                        if i == 50 else s)
    a, b = clean.finish(), glitch.finish()
    assert 50 not in {n.scan_index for n in b.nodes}
    assert a.map.shape == b.map.shape  # inserted, the glitch grew the map from 392 to 466 rows
    free = lambda r: int(np.count_nonzero((r.map.known > 0) & (r.map.prob < 0.5)))  # noqa: E731
    assert free(b) <= 1.01 * free(a)  # the runs differ only by the steps after the glitch
