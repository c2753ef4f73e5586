"""tools/spread.py: run 0 is the plain local-SLAM run; the rotated runs are real, different samples."""
import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slam2d.eval.relations import read_relations, relations_metric
from slam2d.geometry import between, yaw_to_quaternion
from slam2d.io.source import open_source
from slam2d.io.trajectory import read_tum

from conftest import BUNDLED

ROOT = Path(__file__).resolve().parents[1]


def test_spread_run_zero_equals_the_cli_and_rotations_are_null_changes(tmp_path):
    scans = list(open_source(BUNDLED))
    t = np.array([s.timestamp for s in scans])
    gt = np.array([s.ground_truth for s in scans])
    rel = tmp_path / "sim.relations"
    with rel.open("w") as f:
        for i in range(0, len(scans) - 40, 15):
            d = between(gt[i], gt[i + 40])
            f.write(f"{t[i]:.6f} {t[i + 40]:.6f} {d[0]:.6f} {d[1]:.6f} 0 0 0 {d[2]:.6f}\n")
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "slam2d.cli", "run", str(BUNDLED), "--out", str(out), "--no-loop-closure",
                        "--no-progress"], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    tt, poses, _ = read_tum(out / "trajectory.txt")
    expected = relations_metric(tt, poses, read_relations(rel))["abs_trans_m"]["mean"]
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "spread.py"), str(BUNDLED), str(rel), "--runs", "3"],
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    rows = [line for line in r.stdout.splitlines() if line.startswith("rotated")]
    assert len(rows) == 3
    values = [float(line.split(":")[1].split()[0]) for line in rows]
    assert abs(values[0] - expected) < 5e-5  # printed to 4 decimals
    # rotating the world is invisible to the metric, so every run must still track the truth
    assert max(values) < 0.1 and max(values) > 0.0


def _fake_shared(tmp_path, every=6, count=100):
    """A tiny ../shared: one relations dataset, one corrected log, one fr-clinic log, all made from the
    simulator's front 180 beams (FLASER geometry: -90° + i·1°), and the real tools beside them."""
    import bz2
    import gzip

    tools = ROOT.parent / "shared" / "tools"
    if not (tools / "make_sparse.py").exists():
        pytest.skip(f"{tools} not found (../shared is not beside the repo)")
    shared = tmp_path / "shared"
    (shared / "datasets" / "tiny").mkdir(parents=True)
    (shared / "datasets" / "sparse" / "corner").mkdir(parents=True)
    (shared / "datasets" / "fr-clinic").mkdir(parents=True)
    (shared / "tools").symlink_to(tools)
    raw, corrected, gts, stamps = [], [], [], []
    for k, s in enumerate(open_source(BUNDLED)):
        if k % every or len(raw) == count:
            continue
        r = np.where(np.isfinite(s.ranges), s.ranges, 20.0)[90:270]
        txt = " ".join(f"{v:.3f}" for v in r)
        gt, odo = s.ground_truth, s.odom_pose
        raw.append(f"FLASER 180 {txt} {odo[0]:.6f} {odo[1]:.6f} {odo[2]:.6f} {odo[0]:.6f} {odo[1]:.6f} {odo[2]:.6f} "
                   f"{s.timestamp:.6f} sim {s.timestamp:.6f}\n")
        corrected.append(f"FLASER 180 {txt} {gt[0]:.6f} {gt[1]:.6f} {gt[2]:.6f} {gt[0]:.6f} {gt[1]:.6f} {gt[2]:.6f} 0 sim 0\n")
        gts.append(gt)
        stamps.append(s.timestamp)
    with bz2.open(shared / "datasets" / "tiny" / "tiny.clf.bz2", "wt") as f:
        f.writelines(raw)
    with bz2.open(shared / "datasets" / "fr-clinic" / "clinic_robotlaser.clf.bz2", "wt") as f:
        f.writelines(raw)
    with gzip.open(shared / "datasets" / "sparse" / "corner" / "corner-corrected.log.gz", "wt") as f:
        f.writelines(corrected)
    (shared / "datasets" / "sparse" / "corner" / "README.md").write_text("not a log\n")
    with open(shared / "datasets" / "tiny" / "tiny.relations", "w") as f:
        for i in range(0, len(gts) - 5, 3):
            d = between(gts[i], gts[i + 5])
            f.write(f"{stamps[i]:.6f} {stamps[i + 5]:.6f} {d[0]:.6f} {d[1]:.6f} 0 0 0 {d[2]:.6f}\n")
    return shared


def test_benchmark_peak_rss_sums_the_process_tree_and_tells_file_backed_memory_apart():
    """``timed`` samples the resident memory of a process and its children: a child holding 200 MB
    of anonymous memory counts in the peak and not in its file-backed part (shared libraries'
    pages, which move with the page cache)."""
    sys.path.insert(0, str(ROOT / "tools"))
    import time

    import benchmark

    # a process without children (this one may have some: earlier tests' solver processes)
    lone = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(5)"])
    try:
        time.sleep(0.5)
        total, file_mb = benchmark._tree_rss_mb(lone.pid)
        status = dict(line.split(":", 1) for line in Path(f"/proc/{lone.pid}/status").read_text().splitlines()
                      if ":" in line)
    finally:
        lone.kill()
        lone.wait()
    assert abs(total - int(status["VmRSS"].split()[0]) / 1024) < 1
    assert 0 < file_mb < total
    child = "import time; x = b'\\x01' * 200_000_000; time.sleep(1.5)"
    parent = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {child!r}])"
    r = benchmark.timed([sys.executable, "-c", parent])
    assert r["returncode"] == 0
    assert r["peak_rss_mb"] > 200 and r["peak_rss_file_mb"] is not None
    assert r["peak_rss_mb"] - r["peak_rss_file_mb"] > 190
    # a small program started from a large process reports its own peak, not the large one's (the
    # rusage figure of a child holds the peak of the address space its exec replaced)
    ballast = b"\x01" * 300_000_000
    small = benchmark.timed([sys.executable, "-c", "import time; time.sleep(0.5)"])
    assert len(ballast) and small["returncode"] == 0 and small["peak_rss_mb"] < 100


def test_benchmark_finds_corrected_logs_and_caches_generated_ones(tmp_path):
    sys.path.insert(0, str(ROOT / "tools"))
    import benchmark

    shared = _fake_shared(tmp_path)
    found = benchmark.corrected_logs(shared / "datasets")
    assert [(n, p.name) for n, p in found] == [("corner", "corner-corrected.log.gz")]
    args = argparse.Namespace(shared=shared, cache=tmp_path / "cache", sparse_seed=7, degrade_seed=1)
    clf, gt = benchmark.sparse_log(args, "corner", found[0][1])
    assert tmp_path / "cache" in clf.parents and clf.name == "corner.clf" and gt.name == "corner.gt.txt"
    t, poses, _ = read_tum(gt)
    assert len(t) == 100 and t[1] - t[0] == 0.5
    before = clf.stat().st_mtime_ns
    assert benchmark.sparse_log(args, "corner", found[0][1]) == (clf, gt) and clf.stat().st_mtime_ns == before
    args.sparse_seed = 8  # another seed: another cache folder, the first one kept
    clf8, _ = benchmark.sparse_log(args, "corner", found[0][1])
    assert clf8 != clf and clf.exists()
    deg = benchmark.degraded_log(args, "tiny")
    assert deg.exists() and deg.parent.parent.name.startswith("degrade-seed1-")
    assert len(list(open_source(deg))) == 100
    # the dropped-beams copy: its own folder beside it, the same scans with no-returns among their readings
    drop = benchmark.dropout_log(args, "tiny")
    assert drop.parent.parent == deg.parent.parent and drop.parent != deg.parent
    scans, clean = list(open_source(drop)), list(open_source(deg))
    assert len(scans) == 100
    dropped = np.mean([s.no_return.mean() - c.no_return.mean() for s, c in zip(scans, clean)])
    assert abs(dropped - benchmark.BEAM_DROPOUT) < 0.05


def test_benchmark_runs_every_suite_on_tiny_logs(tmp_path):
    shared = _fake_shared(tmp_path)
    out = tmp_path / "bench"
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "benchmark.py"), "--shared", str(shared),
                        "--cache", str(tmp_path / "cache"), "--out", str(out), "--markdown", str(tmp_path / "B.md"),
                        "--json", str(tmp_path / "b.json"), "--peers", "--speed-repeat", "2",
                        "--datasets", "tiny,corner,fr-clinic,fast"],  # of the simulated variants, the shortest
                       capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert r.returncode == 0, r.stderr
    md = (tmp_path / "B.md").read_text()
    for heading in ("## Relations logs", "## Degraded odometry", "## Dropped beams", "## Fewer scans", "## Harsh odometry",
                    "## Without odometry",
                    "## Sparse logs",
                    "## fr-clinic", "## Simulated sensors and robots"):
        assert heading in md
    b = json.loads((tmp_path / "b.json").read_text())
    assert [row["dataset"] for row in b["rows"]] == ["tiny"] and [row["dataset"] for row in b["degraded"]] == ["tiny"]
    assert [row["dataset"] for row in b["dropout"]] == ["tiny"] and "relations" in b["dropout"][0]["slam2d"]
    assert (out / "runs" / "dropout-tiny" / "trajectory.txt").exists()
    # one scan in five: its run against slam2d's run of the whole log, at every scan it keeps
    th = b["thinned"]
    assert [row["dataset"] for row in th] == ["tiny"] and th[0]["slam2d"]["scans"] == 20
    assert th[0]["slam2d"]["vs_full_log"]["pairs"] == 20 and "relations_exact" in th[0]["slam2d"]
    assert list((tmp_path / "cache").glob("degrade-seed1-*/tiny-every5/tiny.clf"))
    # the harsh copies: every log at every rate and seed, each against the whole log's run
    ha = b["harsh"]
    assert [(row["dataset"], row["keep_every"], row["seed"]) for row in ha] == [("tiny", 1, 4), ("tiny", 1, 5),
                                                                                   ("tiny", 3, 4), ("tiny", 3, 5)]
    assert [row["slam2d"]["scans"] for row in ha] == [100, 100, 33, 33]
    assert all(row["slam2d"]["vs_full_log"]["pairs"] == row["slam2d"]["scans"] for row in ha)
    assert all("relations_exact" in row["slam2d"] for row in ha)
    assert list((tmp_path / "cache").glob("degrade-seed5-*/tiny-harsh-every3/tiny.clf"))
    assert "## Harsh odometry" in md and "| tiny | 3 | 5 | slam2d" in md
    # the relations logs (the speed targets) are timed --speed-repeat times, the other suites once
    assert len(b["rows"][0]["slam2d"]["wall_s_runs"]) == 2 and len(b["degraded"][0]["slam2d"]["wall_s_runs"]) == 1
    assert "median wall time and largest peak of 2 runs" in md
    # the relations table's peak RSS shows its file-backed part where the sampled tree held the peak
    rel = b["rows"][0]["slam2d"]
    if rel["peak_rss_file_mb"] is not None:
        assert 0 < rel["peak_rss_file_mb"] < rel["peak_rss_mb"]
        assert f"| {rel['peak_rss_mb']:.0f} ({rel['peak_rss_file_mb']:.0f} file) |" in md
    # the same log without its odometry: the run says so (its config), and it is scored on the relations
    nod = b["no_odometry"]
    assert [row["dataset"] for row in nod] == ["tiny"] and "relations" in nod[0]["slam2d"] and "karto" not in nod[0]
    assert "use_odometry: false" in (out / "runs" / "no-odometry-tiny" / "config.yaml").read_text()
    assert [row["dataset"] for row in b["clinic"]] == ["fr-clinic"]
    sp = b["sparse"][0]["slam2d"]
    assert b["sparse"][0]["dataset"] == "corner" and sp["ate"]["matching"] == "scan_order" and sp["ate"]["pairs"] == 100
    assert set(sp["loops_vs_ground_truth"]) >= {"final_graph", "accepted", "recall", "tolerance"}
    assert "| corner | slam2d" in md and "≤ 0.15" in md
    # the same scans with the odometry of two more seeds (--sparse-spread, default 8,9): slam2d alone
    by_seed = sp["ate_rmse_by_seed"]
    assert list(by_seed) == ["7", "8", "9"] and by_seed["7"] == sp["ate"]["trans_m"]["rmse"]
    # and their loops against the ground truth, the other seeds' beside the first's in the table
    loops = sp["loops_vs_ground_truth_by_seed"]
    assert list(loops) == ["7", "8", "9"] and loops["7"] == sp["loops_vs_ground_truth"]["final_graph"]
    assert "; seeds 8, 9: " in md
    assert all((out / "runs" / f"sparse-corner-seed{s}" / "trajectory.txt").exists() for s in (8, 9))
    assert not (out / "runs" / "sparse-corner-seed8_karto.txt").exists()
    v = sorted(by_seed.values())
    assert f"{v[1]:.3f} ({v[0]:.3f}–{v[2]:.3f}) over 3" in md
    health = sp["health_by_seed"]
    assert list(health) == ["7", "8", "9"] and set(health.values()) <= {"OK", "WARN", "BROKEN"}
    for seed, status in health.items():  # a seed whose run is not OK is named in the table
        assert (f"seed {seed}: {by_seed[seed]:.3f}, {status}" in md) == (status != "OK")
    # the raw scans' free-space test at the run's poses and at the ground truth's, on the same scans
    c = sp["consistency_vs_ground_truth"]
    assert set(c) == {"slam2d", "ground_truth"} and c["slam2d"]["scans_checked"] == c["ground_truth"]["scans_checked"] > 0
    assert (f"{c['slam2d']['mean_violation']:.4f} / " in md and f"; {c['ground_truth']['mean_violation']:.4f} / " in md)
    for row in b["degraded"] + b["clinic"]:
        assert row["slam2d"]["peak_rss_mb"] > 0 and row["slam2d"]["wall_s"] > 0
    try:
        import karto_scanmatcher  # noqa: F401
    except ImportError:
        pass
    else:  # the peer runs beside slam2d on every FLASER log, never on fr-clinic
        assert "relations" in b["degraded"][0]["karto"] and "ate" in b["sparse"][0]["karto"]
        assert len(b["rows"][0]["karto"]["wall_s_runs"]) == 2  # alternating with slam2d
        assert "karto" not in b["clinic"][0]
    # a simulated variant: scored against the simulator's own ground truth, beside its odometry
    sim = b["simulated"]
    assert [row["dataset"] for row in sim] == ["fast"] and "karto" not in sim[0]
    assert sim[0]["slam2d"]["ate"]["pairs"] == sim[0]["slam2d"]["scans"]
    assert sim[0]["slam2d"]["ate"]["trans_m"]["rmse"] < sim[0]["odometry"]["ate"]["trans_m"]["rmse"]
    assert set(sim[0]["slam2d"]["loops_vs_ground_truth"]) >= {"final_graph", "accepted", "recall"}
    assert "| fast | speed 2, turn_rate 2.5 |" in md
    # beside the ATE, the similarity alignment's scale: a bias along the path the SE(2) ATE hides
    fast_row = next(line for line in md.splitlines() if line.startswith("| fast |"))
    a = sim[0]["slam2d"]["ate"]
    assert f"| {a['scale']:.4f}; {a['sim2_trans_m']['rmse']:.3f} |" in fast_row
    assert f"; {sim[0]['odometry']['ate']['scale']:.4f} |" in fast_row
    assert list((tmp_path / "cache").glob("simulator-seed0-*/fast-*/fast.mcap"))
    # the generated logs are in the cache, not in the output folder or the repository
    assert list((tmp_path / "cache").glob("make_sparse-seed7-*/corner/corner.clf"))
    assert list((tmp_path / "cache").glob("degrade-seed1-*/tiny/tiny.clf"))


def test_thinned_log_runs_are_held_against_the_whole_log_s_run(tmp_path):
    """``agreement_with``: a run of a thinned log against the run of the whole log, at the stamps both
    hold, after SE(2) alignment: a thinned run that is the whole run's poses (in another frame)
    agrees exactly; one turned by 10° after half its scans does not, and the table says so."""
    sys.path.insert(0, str(ROOT / "tools"))
    import benchmark
    from slam2d.geometry import compose
    from slam2d.io.trajectory import write_tum

    n = 200
    t = 1000.0 + 0.2 * np.arange(n)
    a = np.linspace(0.0, 3.0, n)
    full = np.c_[10.0 * np.cos(a), 6.0 * np.sin(a), a + np.pi / 2]
    stamps = [f"{x:.6f}" for x in t]
    write_tum(tmp_path / "full.txt", stamps, full)
    keep = np.arange(0, n, 5)
    moved = np.array([compose(np.array([3.0, -1.0, 0.4]), p) for p in full[keep]])
    write_tum(tmp_path / "thin.txt", [stamps[i] for i in keep], moved)
    g = benchmark.agreement_with(tmp_path / "thin.txt", tmp_path / "full.txt")
    assert g["pairs"] == len(keep) and g["trans_m"]["rmse"] < 1e-5 and g["rot_deg"]["rmse"] < 1e-4
    bent, h = moved.copy(), len(keep) // 2
    turned = compose(moved[h], np.array([0.0, 0.0, np.radians(10.0)]))  # a turn 10° wrong at the middle scan
    for i in range(h, len(keep)):
        bent[i] = compose(turned, between(moved[h], moved[i]))
    write_tum(tmp_path / "bent.txt", [stamps[i] for i in keep], bent)
    g2 = benchmark.agreement_with(tmp_path / "bent.txt", tmp_path / "full.txt")
    assert g2["trans_m"]["rmse"] > 0.3 and g2["rot_deg"]["max"] > 4.0
    write_tum(tmp_path / "none.txt", [f"{t[i] + 0.1:.6f}" for i in keep], moved)  # no stamp in common
    assert benchmark.agreement_with(tmp_path / "none.txt", tmp_path / "full.txt") is None
    s = {"scans": len(keep), "wall_s": 2.0, "peak_rss_mb": 300.0, "mode": "global", "vs_full_log": g2,
         "relations_exact": {"counts": {"exact": 3}, "abs_trans_m": {"mean": 0.05, "std": 0.01},
                             "abs_rot_deg": {"mean": 0.5, "std": 0.1}},
         "loop_closure": {"accepted": 5, "in_final_graph": 4, "candidates_searched": 9}, "health": {"status": "OK"}}
    line = benchmark.thinned_table([{"dataset": "fr079", "slam2d": s}]).splitlines()[2]
    assert (f"| {g2['trans_m']['rmse']:.3f} / {g2['trans_m']['max']:.3f} | {g2['rot_deg']['rmse']:.2f} | "
            "3; 0.0500 ± 0.0100; 0.500 | 5 / 4 / 9 | OK |") in line


def test_benchmark_tables_show_health_and_targets():
    sys.path.insert(0, str(ROOT / "tools"))
    import benchmark

    def row(wall, rss, health):
        s = {"scans": 10, "duration_s": 100.0, "wall_s": wall, "peak_rss_mb": rss, "mode": "global",
             "loop_closure": {"accepted": 5, "in_final_graph": 4, "candidates_searched": 9}}
        if health is not None:
            s["health"] = {"status": health, "share_agreeing": 0.97}
        return {"dataset": "fr-clinic", "slam2d": s}

    lines = benchmark.clinic_table([row(50.0, 800.0, "OK"), row(50.0, 800.0, "WARN"), row(50.0, 1500.0, "OK"),
                                    row(50.0, 800.0, None)]).splitlines()[2:]
    assert [line.split("|")[7].strip() for line in lines] == ["OK", "WARN", "OK", "—"]
    assert [line.split("|")[8].strip() for line in lines] == ["yes", "**no**", "**no**", "**no**"]
    assert all("5 / 4 / 9" in line for line in lines)
    sparse = row(5.0, 300.0, "BROKEN")
    sparse["dataset"] = "orebro"
    sparse["slam2d"]["ate"] = {"trans_m": {"rmse": 0.12}, "scale": 1.009, "sim2_trans_m": {"rmse": 0.0743}}
    sparse["slam2d"]["loops_vs_ground_truth"] = {
        "final_graph": {"true": 3, "false": 1, "unknown": 0, "precision": 0.75},
        "accepted": {"true": 3, "false": 2, "unknown": 0, "precision": 0.6}, "recall": {"episodes": 4, "closed": 2}}
    sparse["slam2d"]["consistency_vs_ground_truth"] = {
        "slam2d": {"mean_violation": 0.0327, "revisit_mean_violation": 0.0421},
        "ground_truth": {"mean_violation": 0.0381, "revisit_mean_violation": 0.0481, "disputes": {
            "with": "slam2d", "agree_only_here": 26, "agree_only_there": 60,
            "stretches": [{"scans": [1042, 1047], "nodes": 5, "agree_with": "there"},
                          {"scans": [490, 492], "nodes": 3, "agree_with": "here"}]}}}
    line = benchmark.sparse_table([sparse]).splitlines()[2]
    assert "| 0.120 | ≤ 0.15 | yes | 1.0090; 0.074 |" in line and "75.0 % of 4 (60.0 % of 5)" in line and "2 of 4" in line
    assert ("| 0.0327 / 0.0421; 0.0381 / 0.0481; disputed scans: 60 at slam2d's poses only (longest: scans "
            "1042–1047), 26 at the ground truth's only (longest: scans 490–492) |") in line
    assert line.rstrip().endswith("| BROKEN |")


def test_recovery_audit_scores_a_recovery_against_the_pose_it_replaced():
    """tools/recovery_audit.py: a 30° wheel slip injected into the bundled log makes local SLAM
    recover; the audit lists that scan, and the recovered pose lies near the simulator's ground
    truth while the replaced one (the real-time window's edge, or the prediction) does not. On
    the clean log there is nothing to list, and a run of the script says so."""
    import itertools
    import math

    from slam2d.geometry import compose

    sys.path.insert(0, str(ROOT / "tools"))
    from recovery_audit import audit

    scans = list(itertools.islice(open_source(BUNDLED), 260))
    k = 200
    jump = np.array([0.0, 0.0, math.radians(30.0)])
    for s in scans[k:]:
        s.odom_pose = compose(compose(scans[k - 1].odom_pose, jump), between(scans[k - 1].odom_pose, s.odom_pose))
    rows = audit(scans)
    at = [r for r in rows if r["scan"] == k]
    assert at, rows
    r = at[0]
    assert r["recovered_m"] < 0.1 and r["recovered_deg"] < 1.0, r
    assert r["replaced_deg"] > 5.0, r  # what it replaced carried much of the slip
    assert audit(itertools.islice(open_source(BUNDLED), 260)) == []
    out = subprocess.run([sys.executable, str(ROOT / "tools" / "recovery_audit.py"), str(BUNDLED)],
                         capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().endswith("0 recovered scans: 0 nearer the ground truth than the pose they replaced, 0 farther")


def test_dense_reference_places_each_sparse_scan_at_the_raw_run_pose_of_the_same_scan(tmp_path):
    """A sparse log's scans are raw scans with identical ranges and new stamps; the reference gives
    each the pose the raw log's run gave that scan, at the sparse stamp, and leaves out a scan the
    raw log does not hold."""
    sys.path.insert(0, str(ROOT / "tools"))
    import benchmark

    shared = _fake_shared(tmp_path)
    raw_log = shared / "datasets" / "tiny" / "tiny.clf.bz2"
    raw_lines = _flaser_lines(raw_log)
    raw = list(open_source(raw_log))
    rng = np.random.default_rng(3)
    poses = np.c_[rng.uniform(-5, 5, (len(raw), 2)), rng.uniform(-3, 3, len(raw))]
    stamps = np.array([s.timestamp for s in raw])
    with open(tmp_path / "dense.txt", "w") as f:  # the rows out of scan order: matched by stamp
        for i in rng.permutation(len(raw)):
            q = np.ravel(yaw_to_quaternion(poses[i, 2]))
            f.write(f"{stamps[i]:.6f} {poses[i, 0]:.6f} {poses[i, 1]:.6f} 0 {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")
    picked = _sparse_from_raw(raw_lines, tmp_path / "sparse.clf", every=3, changed=5)
    n = benchmark.dense_reference(tmp_path / "sparse.clf", raw_log, tmp_path / "dense.txt", tmp_path / "ref.txt")
    t, got, _ = read_tum(tmp_path / "ref.txt")
    want = [k for k in range(len(picked)) if k != 5]
    assert n == len(t) == len(want)
    np.testing.assert_allclose(t, [1e9 + 0.5 * k for k in want])
    expect = poses[[picked[k] for k in want]]
    np.testing.assert_allclose(got[:, :2], expect[:, :2], atol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (got[:, 2] - expect[:, 2]))), 0, atol=1e-6)


def _flaser_lines(log):
    import bz2

    with bz2.open(log, "rt") as f:
        return [line for line in f if line.startswith("FLASER")]


def _sparse_from_raw(raw_lines, path, every, changed=None) -> list[int]:
    """Write every ``every``-th raw FLASER line to ``path`` as make_sparse.py does (stamps from 1e9,
    0.5 s apart); the ``changed``-th kept scan gets one reading changed. Returns the raw indices kept."""
    picked = list(range(0, len(raw_lines), every))
    sparse = []
    for k, i in enumerate(picked):
        tok = raw_lines[i].split()
        if k == changed:  # a scan of no raw scan: one reading changed
            tok[2] = f"{float(tok[2]) + 0.5:.3f}"
        t = 1e9 + 0.5 * k
        tok[-3], tok[-1] = f"{t:.6f}", f"{t:.6f}"
        sparse.append(" ".join(tok) + "\n")
    Path(path).write_text("".join(sparse))
    return picked


def test_dense_reference_tool_judges_a_sparse_run_against_both_references(tmp_path):
    """``tools/dense_reference.py RUN GT RAW_LOG RAW_TRAJECTORY``: the reference for every sparse scan,
    the loop precision against the ground truth and against the raw log's run; a missing file is one
    line naming it and exit 2."""
    shared = _fake_shared(tmp_path)
    raw_log = shared / "datasets" / "tiny" / "tiny.clf.bz2"
    picked = _sparse_from_raw(_flaser_lines(raw_log), tmp_path / "sparse.clf", every=2)
    gt = [s.ground_truth for k, s in enumerate(open_source(BUNDLED)) if k % 6 == 0][:100]  # _fake_shared's scans
    with open(tmp_path / "sparse.gt.txt", "w") as f:
        for k, i in enumerate(picked):
            q = np.ravel(yaw_to_quaternion(gt[i][2]))
            f.write(f"{1e9 + 0.5 * k:.6f} {gt[i][0]:.6f} {gt[i][1]:.6f} 0 {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")
    for log, out in ((tmp_path / "sparse.clf", tmp_path / "run"), (raw_log, tmp_path / "raw_run")):
        r = subprocess.run([sys.executable, "-m", "slam2d.cli", "run", str(log), "--out", str(out), "--no-progress"],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
    tool = [sys.executable, str(ROOT / "tools" / "dense_reference.py")]
    args = [str(tmp_path / "run"), str(tmp_path / "sparse.gt.txt"), str(raw_log), str(tmp_path / "raw_run" / "trajectory.txt")]
    r = subprocess.run(tool + args, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].startswith(f"reference: {tmp_path / 'run' / 'dense_reference.txt'} ({len(picked)} scans")
    t, _, _ = read_tum(tmp_path / "run" / "dense_reference.txt")
    assert len(t) == len(picked)
    n = sum(1 for c in map(json.loads, open(tmp_path / "run" / "constraints.jsonl")) if c.get("in_final_graph"))
    assert lines[1].startswith("vs ground truth: ") and f" of {n} in the final graph" in lines[1]
    assert lines[2].startswith("vs raw log's run: ") and f" of {n} in the final graph" in lines[2]
    args[0] = str(tmp_path / "no-such-run")
    r = subprocess.run(tool + args, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip() == f"dense_reference: {tmp_path / 'no-such-run' / 'summary.json'}: no such file"
    # the benchmark's wiring: each seed's run judged against the raw log's run (``runs/NAME``)
    import shutil

    sys.path.insert(0, str(ROOT / "tools"))
    import benchmark

    runs = tmp_path / "runs"
    shutil.copytree(tmp_path / "raw_run", runs / "tiny")
    for label in ("sparse-tiny", "sparse-tiny-seed8"):
        shutil.copytree(tmp_path / "run", runs / label)
    (runs / "sparse-tiny-seed9").mkdir()  # a seed whose run left no constraints: left out
    row = {"dataset": "tiny", "slam2d": {},
           "seed_runs": {s: {"run": f"sparse-tiny{'' if s == '7' else '-seed' + s}", "log": str(tmp_path / "sparse.clf")}
                         for s in ("7", "8", "9")}}
    benchmark.loops_vs_dense_run(row, shared / "datasets", runs)
    by_seed = row["slam2d"]["loops_vs_dense_run_by_seed"]
    assert list(by_seed) == ["7", "8"] and by_seed["7"] == by_seed["8"] == row["slam2d"]["loops_vs_dense_run"]["final_graph"]
    assert by_seed["7"]["true"] + by_seed["7"]["false"] == n
    assert read_tum(runs / "sparse-tiny-seed8" / "dense_reference.txt")[0].tolist() == t.tolist()
