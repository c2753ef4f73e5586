"""The command line as a new user meets it: outputs, one-line errors, no half-written files."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slam2d.cli import main
from slam2d.grid.map_export import read_pgm
from slam2d.io.trajectory import read_tum

from conftest import BUNDLED

ROOT = Path(__file__).resolve().parents[1]


def slam2d(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "slam2d.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd or ROOT, timeout=600)


def test_help_has_examples():
    r = slam2d("--help")
    assert r.returncode == 0 and "examples:" in r.stdout and "slam2d run" in r.stdout
    r = slam2d("run", "--help")
    assert r.returncode == 0 and "example" in r.stdout


def test_run_on_bundled_dataset_writes_the_output_contract(tmp_path):
    out = tmp_path / "run"
    assert main(["run", str(BUNDLED), "--out", str(out), "--no-progress"]) == 0
    names = {p.name for p in out.iterdir()}
    assert {"trajectory.txt", "map.pgm", "map.yaml", "map.png", "config.yaml", "summary.json"} <= names
    assert not any(n.endswith(".partial") for n in names)
    t, poses, stamps = read_tum(out / "trajectory.txt")
    assert len(t) == 1480
    assert stamps[0] == "1700000000.000000000" and np.all(np.diff(t) > 0)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scans"] == 1480 and summary["mode"] == "global"
    assert summary["loop_closure"]["in_final_graph"] > 0
    assert (out / "constraints.jsonl").exists()
    assert summary["real_time_factor"] > 0 and summary["duration_s"] == pytest.approx(295.8)
    assert summary["timings"]["match"]["p99_ms"] > 0
    y = (out / "map.yaml").read_text()
    for key in ("image: map.pgm", "resolution: 0.05", "origin: [", "occupied_thresh:", "free_thresh:", "negate: 0"):
        assert key in y
    img = read_pgm(out / "map.pgm")
    assert set(np.unique(img)) <= {0, 205, 254} and (img == 0).sum() > 500 and (img == 254).sum() > 5000
    assert (out / "map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the map is from the corrected poses: the corridor ring closes within the ground truth's error
    from slam2d.io.mcap import McapLog

    gt = np.array([s.ground_truth for s in McapLog(BUNDLED)])
    from slam2d.geometry import between

    rel_gt = between(gt[:-50], gt[50:])
    rel = between(poses[:-50], poses[50:])
    err = np.hypot(*(between(rel_gt, rel)[:, :2]).T).mean()
    assert err < 0.08


def test_odometry_only_and_config(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("grid:\n  resolution: 0.1\nmap:\n  resolution: 0.1\n")
    out = tmp_path / "o"
    r = slam2d("run", BUNDLED, "--out", out, "--odometry-only", "--config", cfg, "--max-scans", "100", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "resolution: 0.1" in (out / "map.yaml").read_text()
    assert len(read_tum(out / "trajectory.txt")[0]) == 100
    assert json.loads((out / "summary.json").read_text())["mode"] == "odometry"


def test_info_json_and_dump_config(tmp_path):
    r = slam2d("info", BUNDLED, "--json")
    info = json.loads(r.stdout)
    assert info["scans"] == 1480 and info["beams"] == 360 and info["has_odometry"] and info["has_ground_truth"]
    assert info["odometry_changes_between_scans"] > 0.9 and "odometry_note" not in info
    r = slam2d("dump-config")
    assert r.stdout == (ROOT / "configs" / "default.yaml").read_text()


def test_info_says_when_a_log_s_odometry_never_changes(tmp_path, flaser_line):
    """A log written without wheel odometry, its FLASER pose fields all zero: ``info`` reports that no
    two scans' readings differ and what local SLAM does about it; one moving reading changes that."""
    still = tmp_path / "zero.clf"
    still.write_text("".join(flaser_line([1.0 + 0.01 * i, 2.0, 3.0], ts=f"{100 + i}.0") for i in range(6)))
    info = json.loads(slam2d("info", still, "--json").stdout)
    assert info["has_odometry"] and info["odometry_changes_between_scans"] == 0
    assert "no motion" in info["odometry_note"]
    moving = tmp_path / "moving.clf"
    moving.write_text("".join(flaser_line([1.0, 2.0, 3.0], pose=(0.0, 0.0, 0.0) if i < 5 else (0.1, 0.0, 0.0),
                                          ts=f"{100 + i}.0") for i in range(6)))
    info = json.loads(slam2d("info", moving, "--json").stdout)
    assert info["odometry_changes_between_scans"] == 0.2 and "odometry_note" not in info


def test_convert_then_run_on_mcap(tmp_path, flaser_line):
    log = tmp_path / "small.clf"
    log.write_text("".join(flaser_line([1.0 + 0.01 * i, 2.0, 81.83, 3.0], ts=f"{100 + i}.250000") for i in range(20)))
    out = tmp_path / "small.mcap"
    r = slam2d("convert", log, out, "--no-progress")
    assert r.returncode == 0, r.stderr
    from slam2d.io.mcap import McapLog

    back = list(McapLog(out))
    assert [s.timestamp_text for s in back] == [f"{100 + i}.250000000" for i in range(20)]
    assert all(not s.valid[2] and s.valid[[0, 1, 3]].all() for s in back)


BAD_CARMEN = {
    "truncated.clf": "FLASER 180 1.0 2.0\n",
    "nonnumeric.clf": "FLASER 2 1.0 x 0 0 0 0 0 0 1.0 h 1.0\n",
    "negative.clf": "FLASER 2 1.0 -1 0 0 0 0 0 0 1.0 h 1.0\n",
    "mismatch.clf": "FLASER 3 1.0 2.0 0 0 0 0 0 0 1.0 h 1.0\n",
    "backwards.clf": "FLASER 1 1.0 0 0 0 0 0 0 10.0 h 1.0\nFLASER 1 1.0 0 0 0 0 0 0 5.0 h 1.0\n",
    "empty.clf": "",
    "unknown.xyz": "hello\n",
    "corrupt.clf.gz": "\x1f\x8bnot really gzip",
    "corrupt.clf.bz2": "BZh9 not really bzip2",
    "nolaser.mcap": None,
}


@pytest.mark.parametrize("name", sorted(BAD_CARMEN))
@pytest.mark.parametrize("command", ["run", "info", "convert"])
def test_bad_input_one_line_error(tmp_path, name, command):
    p = tmp_path / name
    if name == "nolaser.mcap":
        from slam2d.io.mcap import McapWriter

        with open(p, "wb") as f:
            w = McapWriter(f)
            w.write_pose("/pose", np.zeros(3), 1, 0)
            w.finish()
    else:
        p.write_text(BAD_CARMEN[name])
    out = tmp_path / "out"
    args = {"run": ["run", p, "--out", out, "--no-progress"], "info": ["info", p],
            "convert": ["convert", p, tmp_path / "x.mcap", "--no-progress"]}[command]
    r = slam2d(*args)
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("slam2d: error: ") and name in lines[0]
    assert "Traceback" not in r.stderr
    if out.exists():
        assert list(out.iterdir()) == []
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "x.mcap.partial").exists()


def test_missing_file_and_bad_config(tmp_path):
    r = slam2d("run", tmp_path / "nope.clf", "--out", tmp_path / "o")
    assert r.returncode != 0 and r.stderr.strip().count("\n") == 0 and "no such file" in r.stderr
    cfg = tmp_path / "c.yaml"
    cfg.write_text("grid:\n  hit_probability: 2\n")
    r = slam2d("run", BUNDLED, "--out", tmp_path / "o", "--config", cfg)
    assert r.returncode != 0 and "grid.hit_probability" in r.stderr and r.stderr.strip().count("\n") == 0


def test_outputs_that_cannot_be_written_are_refused_before_any_work(tmp_path, flaser_line, capsys):
    """A recording, a conversion or a simulation whose file cannot be made fails at once, in one line
    (it was a traceback at the end of the work)."""
    log = tmp_path / "a.clf"
    log.write_text("".join(flaser_line([1.0, 2.0, 3.0], ts=f"{100 + i}.0") for i in range(5)))
    blocker = tmp_path / "afile"
    blocker.write_text("x")  # a file where a folder would have to be
    (tmp_path / "d.mcap").mkdir()
    cases = [(["convert", str(log), str(blocker / "x.mcap")], f"{blocker / 'x.mcap'}: cannot create the folder"),
             (["convert", str(log), str(tmp_path / "d.mcap")], f"{tmp_path / 'd.mcap'}: is a folder; the output is a file"),
             (["run", str(log), "--out", str(tmp_path / "o"), "--rerun", str(blocker / "r.rrd")],
              f"{blocker / 'r.rrd'}: cannot create the folder for the Rerun recording"),
             (["simulate", str(blocker / "s.mcap")], f"{blocker / 's.mcap'}: cannot create the folder"),
             (["run", str(log), "--out", str(tmp_path / "o"), "--rate", "1e-300"], "--rate must lie between")]
    for argv, needle in cases:
        assert main(argv + ["--no-progress"] if argv[0] != "simulate" else argv) == 2, argv
        err = capsys.readouterr().err
        assert needle in err and err.count("\n") == 1, err
    assert main(["convert", str(log), str(tmp_path / "new" / "x.mcap"), "--no-progress"]) == 0  # a missing folder is made


def test_config_that_is_not_text_or_asks_for_cells_too_small(tmp_path, capsys):
    bad = tmp_path / "c.yaml"
    bad.write_bytes(b"\xff\xfe\x00")
    tiny = tmp_path / "t.yaml"
    tiny.write_text("grid: {resolution: 1.0e-9}\n")  # asked for 2.5 EiB of cells
    for cfg, needle in ((bad, "not a text file (byte 0 is not UTF-8)"),
                        (tiny, "grid.resolution': Input should be greater than or equal to 0.01")):
        assert main(["run", str(BUNDLED), "--out", str(tmp_path / "o"), "--config", str(cfg)]) == 2
        err = capsys.readouterr().err
        assert needle in err and err.count("\n") == 1, err


def test_eval_refuses_what_it_cannot_score(tmp_path, capsys):
    traj = tmp_path / "t.txt"
    traj.write_text("".join(f"{100 + i}.0 {0.1 * i} 0 0 0 0 0 1\n" for i in range(10)))
    rel = tmp_path / "r.relations"
    rel.write_text("500.0 501.0 0.1 0 0 0 0 0\n")  # another log's stamps
    gz = tmp_path / "r.gz"
    gz.write_bytes(b"\x1f\x8b\x08\x00\xff\xfe")
    cases = [(["relations", str(traj), str(rel)], "none of its relations falls within the trajectory's stamps"),
             (["relations", str(traj), str(tmp_path)], "is a folder, not a file of relations"),
             (["relations", str(traj), str(gz)], "not a text file of relations"),
             (["relations", str(traj), str(rel), "--tolerance", "-1"], "--tolerance must lie in [0, 1) s"),
             (["ate", str(traj), str(traj), "--plot", str(tmp_path / "p.xyz")], "the picture must end in .png")]
    for argv, needle in cases:
        assert main(["eval"] + argv) == 2, argv
        err = capsys.readouterr().err
        assert needle in err and err.count("\n") == 1, err


def test_failed_run_keeps_previous_outputs_whole(tmp_path, flaser_line):
    good = tmp_path / "good.clf"
    good.write_text("".join(flaser_line([1.0, 2.0, 3.0], ts=f"{100 + i}.0") for i in range(5)))
    out = tmp_path / "o"
    assert slam2d("run", good, "--out", out, "--no-progress").returncode == 0
    before = (out / "trajectory.txt").read_text()
    bad = tmp_path / "bad.clf"
    bad.write_text(good.read_text() + "FLASER 3 1.0 oops 3.0 0 0 0 0 0 0 200.0 h 1.0\n")
    r = slam2d("run", bad, "--out", out, "--no-progress")
    assert r.returncode != 0 and "bad.clf:6:" in r.stderr
    assert (out / "trajectory.txt").read_text() == before
    assert not [p for p in out.iterdir() if p.name.endswith(".partial")]


def test_odometry_only_without_odometry_names_the_file(tmp_path):
    from slam2d.io.mcap import McapWriter
    from slam2d.io.simulator import SimConfig, simulate

    p = tmp_path / "no_odom.mcap"
    with open(p, "wb") as f:
        w = McapWriter(f)
        for _, s in zip(range(5), simulate(SimConfig(seed=1))):
            s.odom_pose = None
            w.write_scan(s)
        w.finish()
    r = slam2d("run", p, "--out", tmp_path / "o", "--odometry-only", "--no-progress")
    assert r.returncode != 0 and r.stderr.strip().count("\n") == 0
    assert "no_odom.mcap: record 0: scan has no odometry" in r.stderr
    # local SLAM without odometry still runs (constant-velocity prediction)
    assert slam2d("run", p, "--out", tmp_path / "l", "--no-progress").returncode == 0


def test_no_odometry_ignores_the_inputs_odometry(tmp_path):
    """--no-odometry: local SLAM predicts from the matches' velocity alone (the run's config says so)
    and still follows the bundled log's ground truth; with --odometry-only it is a usage error."""
    r = slam2d("run", BUNDLED, "--out", tmp_path / "n", "--no-odometry", "--no-loop-closure", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "use_odometry: false" in (tmp_path / "n" / "config.yaml").read_text()
    s = json.loads((tmp_path / "n" / "summary.json").read_text())
    assert s["ate_vs_ground_truth"]["trans_m"]["rmse"] < 0.15
    r = slam2d("run", BUNDLED, "--out", tmp_path / "m", "--no-odometry", "--odometry-only")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "exclude each other" in r.stderr


def test_view_refuses_what_is_no_recording(tmp_path, capsys):
    """An empty, text or MCAP file named .rrd went straight to the viewer (Rerun's own log lines, exit 1)."""
    (tmp_path / "empty.rrd").write_bytes(b"")
    (tmp_path / "text.rrd").write_text("hello")
    for name, why in (("empty.rrd", "empty"), ("text.rrd", "not an .rrd file")):
        assert main(["view", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"slam2d: error: {tmp_path / name}: not a Rerun recording ({why};") and err.count("\n") == 1
    assert main(["view", str(tmp_path)]) == 2
    assert "is a folder, not a Rerun recording" in capsys.readouterr().err


def test_consistency_refuses_a_trajectory_of_another_log(tmp_path, flaser_line, capsys):
    run = tmp_path / "run"
    assert main(["run", str(BUNDLED), "--out", str(run), "--no-progress", "--max-scans", "60", "--no-loop-closure"]) == 0
    capsys.readouterr()
    other = tmp_path / "other.clf"
    other.write_text("".join(flaser_line([1.0, 2.0, 3.0], ts=f"{100 + i}.0") for i in range(80)))
    assert main(["eval", "consistency", str(run / "trajectory.txt"), "--run-input", str(other)]) == 2
    err = capsys.readouterr().err
    assert "scan 0 is stamped 100.000000 but the trajectory's pose 0 1700000000.000000" in err and err.count("\n") == 1
    assert main(["eval", "consistency", str(run / "trajectory.txt")]) == 0  # its own log


def test_odometry_only_says_when_the_odometry_never_moves(tmp_path, flaser_line):
    log = tmp_path / "still.clf"
    log.write_text("".join(flaser_line([1.0 + 0.01 * i, 2.0, 3.0], ts=f"{100 + i}.0") for i in range(20)))
    r = slam2d("run", log, "--out", tmp_path / "o", "--odometry-only", "--no-progress")
    assert r.returncode == 0 and "the odometry never moves: every scan gets the same pose" in r.stderr, r.stderr


def test_eval_finds_the_run_input_from_any_folder(tmp_path):
    """summary.json keeps the input as given and absolute: read from another folder, a relative path named
    another log of the same name (or none), silently or with a misleading error."""
    import shutil

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    shutil.copy(BUNDLED, tmp_path / "a" / "x.mcap")
    r = slam2d("run", "x.mcap", "--out", "run", "--no-progress", "--max-scans", "40", "--no-loop-closure",
               cwd=tmp_path / "a")
    assert r.returncode == 0, r.stderr
    summary = json.loads((tmp_path / "a" / "run" / "summary.json").read_text())
    assert summary["input"] == "x.mcap" and summary["input_absolute"] == str((tmp_path / "a" / "x.mcap").resolve())
    r = slam2d("eval", "consistency", tmp_path / "a" / "run" / "trajectory.txt", cwd=tmp_path / "b")
    assert r.returncode == 0 and "20 scans" in r.stdout, r.stderr
