import json
import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from slam2d.eval.ate import align, ate, rpe
from slam2d.eval.loops import Thresholds, classify, read_constraints
from slam2d.eval.relations import Relations, read_relations, relations_metric
from slam2d.geometry import between, compose
from slam2d.io.trajectory import read_tum, write_tum

from conftest import SHARED, dataset, relations

ROOT = Path(__file__).resolve().parents[1]


def slam2d(*args):
    return subprocess.run([sys.executable, "-m", "slam2d.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=900)


def test_relations_hand_computed_case():
    # two poses: (0,0,0) and (1,0,90°); the relation claims (1.1, 0, 80°)
    times = np.array([1.0, 2.0])
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, math.pi / 2]])
    rel = Relations(np.array([1.0]), np.array([2.0]), np.array([[1.1, 0.0, math.radians(80)]]))
    m = relations_metric(times, poses, rel)
    # error = (1,0,90°) ∘ (1.1,0,80°)⁻¹: rotation 10°, translation (1,0) − R(10°)(1.1,0)
    tx = 1.0 - 1.1 * math.cos(math.radians(10))
    ty = -1.1 * math.sin(math.radians(10))
    assert m["abs_trans_m"]["mean"] == pytest.approx(math.hypot(tx, ty), abs=1e-12)
    assert m["abs_rot_deg"]["mean"] == pytest.approx(10.0, abs=1e-9)
    assert m["sq_rot_deg2"]["mean"] == pytest.approx(100.0, abs=1e-7)
    assert m["counts"]["evaluated"] == 1


def gtsam_relations(times, poses, rel):
    """Independent implementation of the same definition with gtsam.Pose2."""
    import gtsam

    lookup = {round(t, 6): gtsam.Pose2(*p) for t, p in zip(times, poses)}
    trans, rot = [], []
    for t1, t2, d in zip(rel.t1, rel.t2, rel.delta):
        a, b = lookup[round(t1, 6)], lookup[round(t2, 6)]
        err = a.between(b).compose(gtsam.Pose2(*d).inverse())
        trans.append(math.hypot(err.x(), err.y()))
        rot.append(abs(math.degrees(err.theta())))
    return np.array(trans), np.array(rot)


def test_relations_agree_with_gtsam_on_random_data():
    rng = np.random.default_rng(0)
    times = np.arange(200) * 0.5 + 1000.0
    poses = np.cumsum(rng.normal(0, 0.3, (200, 3)), axis=0)
    i = rng.integers(0, 200, 300)
    j = rng.integers(0, 200, 300)
    rel = Relations(times[i], times[j], rng.normal(0, 1.0, (300, 3)))
    m = relations_metric(times, poses, rel)
    tr, ro = gtsam_relations(times, poses, rel)
    assert m["abs_trans_m"]["mean"] == pytest.approx(tr.mean(), abs=1e-9)
    assert m["abs_trans_m"]["std"] == pytest.approx(tr.std(ddof=1), abs=1e-9)
    assert m["abs_rot_deg"]["mean"] == pytest.approx(ro.mean(), abs=1e-9)


def test_relations_interpolate_and_count_unmatched():
    times = np.array([0.0, 1.0, 2.0])
    poses = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    rel = Relations(np.array([0.5, 0.0, 5.0]), np.array([2.0, 1.0, 6.0]), np.array([[1.5, 0, 0], [1.0, 0, 0], [1, 0, 0]]))
    m = relations_metric(times, poses, rel)
    assert m["counts"] == {"relations": 3, "exact": 1, "interpolated": 1, "unmatched": 1, "evaluated": 2}
    assert m["abs_trans_m"]["max"] == pytest.approx(0.0, abs=1e-12)


def test_exact_relations_leave_out_the_interpolated_ones():
    """A trajectory that turned between its poses: a relation with an interpolated end carries the
    interpolation's error; ``exact`` scores only the relations whose two stamps are poses, and counts
    the others; the CLI's --exact gives the same."""
    times = np.array([0.0, 1.0, 2.0])
    poses = np.array([[0.0, 0, 0], [1.0, 0, math.pi / 2], [1.0, 1.0, math.pi / 2]])
    # truth: at t = 0.5 the robot stood at (1, 0, 0) (it drove, then turned); the interpolation says (0.5, 0, 45°)
    rel = Relations(np.array([0.0, 0.5, 0.0, 5.0]), np.array([1.0, 1.0, 2.0, 6.0]),
                    np.array([[1.0, 0, math.pi / 2], [0.0, 0, math.pi / 2], [1.0, 1.0, math.pi / 2], [1, 0, 0]]))
    every = relations_metric(times, poses, rel)
    exact = relations_metric(times, poses, rel, exact=True)
    assert every["counts"]["evaluated"] == 3 and every["abs_trans_m"]["max"] > 0.4  # the interpolated one is off
    assert exact["counts"] == {"relations": 4, "exact": 2, "interpolated": 0, "unmatched": 1, "not_exact": 1,
                               "evaluated": 2}
    assert exact["abs_trans_m"]["max"] == pytest.approx(0.0, abs=1e-12)
    assert exact["abs_rot_deg"]["max"] == pytest.approx(0.0, abs=1e-9)


def test_exact_relations_on_the_command_line(tmp_path):
    traj, rel = tmp_path / "t.txt", tmp_path / "r.relations"
    traj.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0.7071067811865476 0.7071067811865476\n")
    rel.write_text("0 1 1 0 0 0 0 1.5707963267948966\n0.5 1 0 0 0 0 0 1.5707963267948966\n")
    out = slam2d("eval", "relations", traj, rel, "--exact", "--json")
    assert out.returncode == 0, out.stderr
    m = json.loads(out.stdout)
    assert m["counts"]["evaluated"] == 1 and m["counts"]["not_exact"] == 1
    assert m["abs_trans_m"]["mean"] == pytest.approx(0.0, abs=1e-9)


def test_relations_on_intel_odometry(tmp_path):
    src = dataset("intel")
    out = tmp_path / "odo"
    assert slam2d("run", src, "--out", out, "--odometry-only", "--no-progress").returncode == 0
    r = slam2d("eval", "relations", out / "trajectory.txt", relations("intel"), "--json")
    m = json.loads(r.stdout)
    assert m["abs_trans_m"]["mean"] == pytest.approx(7.37, abs=0.01)
    t, poses, _ = read_tum(out / "trajectory.txt")
    rel = read_relations(relations("intel"))
    tr, ro = gtsam_relations(t, poses, rel)
    assert m["abs_trans_m"]["mean"] == pytest.approx(tr.mean(), abs=1e-6)
    assert m["abs_rot_deg"]["mean"] == pytest.approx(ro.mean(), abs=1e-6)
    # ATE against the GMapping-corrected log: every one of its 910 scans is found by its ranges
    r = slam2d("eval", "ate", out / "trajectory.txt", SHARED / "intel" / "intel.gfs.log", "--json",
               "--plot", tmp_path / "ate.png")
    a = json.loads(r.stdout)
    assert a["matched_scans"] == 910 and a["reference_scans"] == 910
    assert a["ate"]["trans_m"]["rmse"] > 1.0  # raw odometry is far off
    assert (tmp_path / "ate.png").exists() and (tmp_path / "ate_error.png").exists()


def test_ate_recovers_a_rigid_transform_exactly():
    rng = np.random.default_rng(1)
    ref = np.cumsum(rng.normal(0, 0.2, (300, 3)), axis=0)
    T = np.array([3.0, -2.0, 0.7])
    est = compose(T, ref)
    np.testing.assert_allclose(align(est, ref), np.column_stack([ref[:, :2], np.angle(np.exp(1j * ref[:, 2]))]),
                               atol=1e-9)
    m = ate(est, ref)
    assert m["trans_m"]["rmse"] < 1e-9
    noisy = est.copy()
    noisy[:, :2] += rng.normal(0, 0.05, (300, 2))
    assert 0.03 < ate(noisy, ref)["trans_m"]["rmse"] < 0.1
    r = rpe(est, ref, (1.0,))
    assert r["1m"]["trans_m"]["max"] < 1e-9
    assert m["scale"] == pytest.approx(1.0, abs=1e-12) and m["sim2_trans_m"]["rmse"] < 1e-9


def test_ate_reports_the_scale_of_a_uniformly_shrunk_trajectory():
    """A trajectory shrunk by 1 % as a whole (every step 1 % short) and moved: the SE(2) ATE sees
    the shrink as error, the similarity alignment recovers the factor and leaves none."""
    rng = np.random.default_rng(2)
    ref = np.cumsum(rng.normal(0, 0.5, (400, 3)), axis=0)
    est = compose(np.array([-4.0, 1.5, -0.4]), np.column_stack([0.99 * ref[:, :2], ref[:, 2]]))
    m = ate(est, ref)
    assert m["scale"] == pytest.approx(1 / 0.99, rel=1e-9)
    assert m["sim2_trans_m"]["rmse"] < 1e-9
    spread = np.sqrt(((ref[:, :2] - ref[:, :2].mean(axis=0)) ** 2).sum(axis=1).mean())
    assert m["trans_m"]["rmse"] == pytest.approx(0.01 * spread, rel=0.05)
    # headings are untouched by the scale
    np.testing.assert_allclose(align(est, ref, with_scale=True)[:, 2], align(est, ref)[:, 2])


def _synthetic_run(tmp_path):
    rng = np.random.default_rng(3)
    n = 400
    poses = np.column_stack([np.cos(np.arange(n) / 40) * 5, np.sin(np.arange(n) / 40) * 5, np.arange(n) / 40 + math.pi / 2])
    write_tum(tmp_path / "trajectory.txt", [f"{i}.0" for i in range(n)], poses)
    truth = []
    with open(tmp_path / "constraints.jsonl", "w") as f:
        for k in range(60):
            i, j = sorted(rng.choice(n, 2, replace=False))
            rel = between(poses[i], poses[j])
            kind = k % 4
            if kind == 1:
                rel = rel + [0.5, 0.0, 0.0]  # false: 0.5 m off
            elif kind == 2:
                rel = rel + [0.0, 0.0, math.radians(3)]  # false: 3° off
            elif kind == 3:
                rel = rel + [0.1, 0.05, math.radians(0.5)]  # true: inside 0.2 m / 1°
            truth.append(kind in (0, 3))
            f.write(json.dumps({"from_scan": int(i), "to_scan": int(j), "relative_pose": list(map(float, rel)),
                                "score": 0.5 + 0.4 * (kind in (0, 3)), "accepted": True}) + "\n")
    return poses, truth


def test_loops_classifies_synthetic_constraints_exactly(tmp_path):
    poses, truth = _synthetic_run(tmp_path)
    cs = read_constraints(tmp_path / "constraints.jsonl")
    out = classify(cs, poses, poses.copy(), (np.arange(len(poses)), poses), Thresholds())
    assert [c["true_own"] for c in cs] == truth
    assert [c["true_ref"] for c in cs] == truth
    assert out["own"]["accepted"]["true"] == sum(truth)
    assert out["own"]["accepted"]["precision"] == pytest.approx(sum(truth) / len(truth))
    # 0.25 m is outside (a)'s 0.2 m but inside (b)'s 0.3 m
    c = {"from_scan": 0, "to_scan": 5, "relative_pose": list(between(poses[0], poses[5]) + [0.25, 0, 0]), "score": 0.7,
         "accepted": True}
    out = classify([c], poses, poses, None, Thresholds())
    assert c["true_own"] is False and c["true_ref"] is True


def test_loops_cli_with_ground_truth_reference(tmp_path):
    _synthetic_run(tmp_path)
    r = slam2d("eval", "loops", tmp_path, "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["accepted"] == 60
    assert (tmp_path / "loops_on_map.png").exists() and (tmp_path / "loop_scores.png").exists()
    assert sum(out["score_histogram"]["true"]) == 30
    # a plot folder that does not exist yet is made; one that cannot be is a one-line error
    r = slam2d("eval", "loops", tmp_path, "--plot-dir", tmp_path / "new" / "plots")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "new" / "plots" / "loops_on_map.png").exists()
    assert (tmp_path / "new" / "plots" / "loop_scores.png").exists()
    (tmp_path / "taken").write_text("a file, not a folder")
    r = slam2d("eval", "loops", tmp_path, "--plot-dir", tmp_path / "taken" / "plots")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "cannot write the plot" in r.stderr, r.stderr
    r = slam2d("eval", "ate", tmp_path / "trajectory.txt", tmp_path / "trajectory.txt", "--plot", tmp_path / "ate" / "a.png")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "ate" / "a.png").exists() and (tmp_path / "ate" / "a_error.png").exists()


def test_loops_refuses_a_constraint_to_a_scan_the_run_does_not_have(tmp_path):
    """An unstamped record naming a scan past the trajectory's end was an IndexError; it is one line."""
    _synthetic_run(tmp_path)
    lines = (tmp_path / "constraints.jsonl").read_text().splitlines()
    rec = json.loads(lines[0])
    rec.pop("from_stamp", None), rec.pop("to_stamp", None)
    rec["from_scan"] = 999999
    (tmp_path / "constraints.jsonl").write_text("\n".join([json.dumps(rec)] + lines[1:]) + "\n")
    r = slam2d("eval", "loops", tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "constraints.jsonl:1: from_scan 999999 is not a scan of trajectory.txt" in r.stderr


def test_ate_against_a_corrected_log_refuses_a_trajectory_out_of_scan_order(tmp_path, flaser_line):
    """A corrected CARMEN reference is matched to the run input's scans by position: a trajectory
    re-sorted or reversed (evo re-saves by stamp, without the '# scans' line) was scored against the
    wrong poses, silently."""
    log = tmp_path / "in.clf"
    log.write_text("".join(flaser_line([1.0 + 0.1 * i, 2.0, 3.0], pose=(0.5 * i, 0, 0), odom=(0.5 * i, 0, 0),
                                       ts=f"{100 + i}.0") for i in range(6)))
    stamps = [f"{100 + i}.0" for i in range(6)]
    poses = np.array([[0.5 * i, 0.0, 0.0] for i in range(6)])
    write_tum(tmp_path / "ok.txt", stamps, poses)
    r = subprocess.run([sys.executable, "-m", "slam2d.cli", "eval", "ate", str(tmp_path / "ok.txt"), str(log),
                        "--run-input", str(log), "--json"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["ate"]["trans_m"]["rmse"] == pytest.approx(0.0, abs=1e-9)
    write_tum(tmp_path / "rev.txt", stamps[::-1], poses[::-1])
    r = subprocess.run([sys.executable, "-m", "slam2d.cli", "eval", "ate", str(tmp_path / "rev.txt"), str(log),
                        "--run-input", str(log)], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "scan 0 is stamped 100.000000 but the trajectory's pose 0 105.000000" in r.stderr


def test_loops_reads_corrected_carmen_reference(tmp_path):
    src = dataset("intel")
    run = tmp_path / "run"
    assert slam2d("run", src, "--out", run, "--odometry-only", "--no-progress", "--max-scans", "3000").returncode == 0
    t, poses, _ = read_tum(run / "trajectory.txt")
    # constraints made from the corrected log's own relative poses are true against it
    from slam2d.eval.reference import load_reference

    ref = load_reference(SHARED / "intel" / "intel.gfs.log", t, str(src))
    k = ref.scan_indices
    with open(run / "constraints.jsonl", "w") as f:
        for a, b in [(0, 10), (5, 50), (20, 120)]:
            rel = between(ref.poses[a], ref.poses[b])
            f.write(json.dumps({"from_scan": int(k[a]), "to_scan": int(k[b]), "relative_pose": list(map(float, rel)),
                                "score": 0.8, "accepted": True}) + "\n")
            f.write(json.dumps({"from_scan": int(k[a]), "to_scan": int(k[b]),
                                "relative_pose": list(map(float, rel + [1.0, 0, 0])), "score": 0.6,
                                "accepted": True}) + "\n")
    r = slam2d("eval", "loops", run, "--reference", SHARED / "intel" / "intel.gfs.log", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["reference"]["accepted"]["true"] == 3 and out["reference"]["accepted"]["false"] == 3


def test_eval_bad_inputs_are_one_line(tmp_path):
    (tmp_path / "t.txt").write_text("1.0 2.0 3.0\n")
    r = slam2d("eval", "relations", tmp_path / "t.txt", tmp_path / "missing.relations")
    assert r.returncode != 0 and r.stderr.count("\n") == 1 and "t.txt:1" in r.stderr
    (tmp_path / "c").mkdir()
    write_tum(tmp_path / "c" / "trajectory.txt", ["1.0"], np.zeros((1, 3)))
    (tmp_path / "c" / "constraints.jsonl").write_text("{not json\n")
    r = slam2d("eval", "loops", tmp_path / "c")
    assert r.returncode != 0 and "constraints.jsonl:1" in r.stderr and r.stderr.count("\n") == 1


def _gt_run(tmp_path, stamps=None):
    """A run whose own poses are wrong after scan 200 (a 1 m shift), its ground truth, and
    constraints whose truth is known: true, false, and one that agrees with the wrong own poses."""
    n = 400
    gt = np.column_stack([np.cos(np.arange(n) / 40) * 5, np.sin(np.arange(n) / 40) * 5, np.arange(n) / 40 + math.pi / 2])
    own = gt.copy()
    own[200:, 0] += 1.0
    stamps = [f"{1e9 + 0.5 * i:.6f}" for i in range(n)] if stamps is None else stamps
    write_tum(tmp_path / "trajectory.txt", stamps, own)
    cases = [  # (from, to, offset, in_final_graph, truly true)
        (10, 260, [0.0, 0.0, 0.0], True, True),                      # exact
        (20, 270, [0.2, 0.1, math.radians(1.5)], True, True),        # inside 0.3 m / 2°
        (30, 280, [0.35, 0.0, 0.0], True, False),                    # 0.35 m off
        (40, 290, [0.0, 0.0, math.radians(2.5)], True, False),       # 2.5° off
        (50, 300, [0.0, 0.0, 0.0], False, True),                     # true but removed from the graph
        (60, 310, [1.0, 0.0, 0.0], False, False),                    # false, removed
    ]
    with open(tmp_path / "constraints.jsonl", "w") as f:
        for i, j, off, final, _ in cases:
            rel = between(gt[i], gt[j]) + off
            f.write(json.dumps({"submap": 0, "from_scan": i, "to_scan": j, "from_stamp": stamps[i], "to_stamp": stamps[j],
                                "relative_pose": list(map(float, rel)), "score": 0.7, "accepted": True,
                                "reason": "accepted", "in_final_graph": final}) + "\n")
        # false against the ground truth, but the run's own (wrong) poses agree with it exactly
        rel = between(own[100], own[350])
        f.write(json.dumps({"submap": 1, "from_scan": 100, "to_scan": 350, "relative_pose": list(map(float, rel)),
                            "score": 0.9, "accepted": True, "reason": "accepted", "in_final_graph": True}) + "\n")
        f.write(json.dumps({"submap": 1, "from_scan": 100, "to_scan": 360, "relative_pose": None, "score": None,
                            "accepted": False, "reason": "no match", "in_final_graph": False}) + "\n")
    truth = [c[4] for c in cases] + [False, None]
    return gt, own, truth


def test_loops_ground_truth_classifies_exactly(tmp_path):
    from slam2d.eval.loops import classify_ground_truth

    gt, own, truth = _gt_run(tmp_path)
    cs = read_constraints(tmp_path / "constraints.jsonl")
    classify(cs, own, None, None)
    out = classify_ground_truth(cs, gt, np.arange(len(gt)), 0.3, 2.0)
    assert [c["true_gt"] for c in cs] == truth
    assert cs[6]["true_own"] is True and cs[6]["true_gt"] is False  # own check fooled, ground truth not
    assert out["final_graph"] == {"true": 2, "false": 3, "unknown": 0, "precision": 0.4}
    assert out["accepted"] == {"true": 3, "false": 4, "unknown": 0, "precision": 3 / 7}
    # the false ones of the final graph, each with how far it lies off the ground truth
    off = {(d["from_scan"], d["to_scan"]): (d["off_m"], d["off_deg"]) for d in out["disagreeing"]}
    assert set(off) == {(30, 280), (40, 290), (100, 350)}
    assert off[(30, 280)] == (pytest.approx(0.35, abs=1e-3), pytest.approx(0.0, abs=0.01))
    assert off[(40, 290)] == (pytest.approx(0.0, abs=1e-3), pytest.approx(2.5, abs=0.01))
    assert off[(100, 350)][0] == pytest.approx(1.0, abs=0.05)  # the run's own shift of 1 m
    # the circle of radius 5 m is 31 m round: scans ~250 onwards revisit the start
    assert out["recall"]["episodes"] >= 1 and out["recall"]["closed"] >= 1
    # a looser tolerance turns the 0.35 m and 2.5° ones true
    assert classify_ground_truth(cs, gt, np.arange(len(gt)), 0.4, 3.0)["final_graph"]["true"] == 4


def test_loops_cli_ground_truth_in_scan_order_and_by_timestamp(tmp_path):
    gt, _, _ = _gt_run(tmp_path)
    n = len(gt)
    stamps = [f"{1e9 + 0.5 * i:.6f}" for i in range(n)]
    # the same count: matched in scan order, whatever the stamps say
    write_tum(tmp_path / "order.gt.txt", [f"{i}.0" for i in range(n)], gt)
    r = slam2d("eval", "loops", tmp_path, "--ground-truth", tmp_path / "order.gt.txt", "--json")
    assert r.returncode == 0, r.stderr
    g = json.loads(r.stdout)["ground_truth"]
    assert g["matching"] == "scan_order" and g["matched_scans"] == n
    assert g["final_graph"]["precision"] == pytest.approx(0.4) and g["tolerance"] == {"trans_m": 0.3, "rot_deg": 2.0}
    # without --json, a line names each false constraint of the final graph
    r = slam2d("eval", "loops", tmp_path, "--ground-truth", tmp_path / "order.gt.txt")
    lines = [x for x in r.stdout.splitlines() if x.startswith("ground_truth.disagreeing: ")]
    assert len(lines) == 3 and "scans 30 -> 280, 0.35 m / 0.0 deg off the ground truth" in lines[0], r.stdout
    # every other pose, shuffled: matched by timestamp; constraints on scans without a pose are unknown
    keep = np.random.default_rng(0).permutation(np.arange(0, n, 2))
    write_tum(tmp_path / "half.gt.txt", [stamps[i] for i in keep], gt[keep])
    r = slam2d("eval", "loops", tmp_path, "--ground-truth", tmp_path / "half.gt.txt", "--json",
               "--tolerance-trans", "0.4", "--tolerance-rot", "3")
    assert r.returncode == 0, r.stderr
    g = json.loads(r.stdout)["ground_truth"]
    assert g["matching"] == "timestamp" and g["matched_scans"] == n // 2
    # scans 10..60 and 260..310 are even; 350 too: only the loosened ones change
    assert g["final_graph"] == {"true": 4, "false": 1, "unknown": 0, "precision": 0.8}
    assert set(json.loads(r.stdout)) >= {"constraints", "accepted", "in_final_graph", "own", "ground_truth"}


def test_loops_ground_truth_bad_inputs_are_one_line(tmp_path):
    gt, _, _ = _gt_run(tmp_path)
    lines = [f"{1e9 + 0.5 * i:.6f} {p[0]} {p[1]} 0 0 0 0 1\n" for i, p in enumerate(gt)]
    lines[7] = "1000000003.5 1.0 2.0 0 0 0\n"
    (tmp_path / "bad.gt.txt").write_text("".join(lines))
    r = slam2d("eval", "loops", tmp_path, "--ground-truth", tmp_path / "bad.gt.txt")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "bad.gt.txt:8" in r.stderr
    (tmp_path / "far.gt.txt").write_text("5.0 0 0 0 0 0 0 1\n6.0 0 0 0 0 0 0 1\n")
    r = slam2d("eval", "loops", tmp_path, "--ground-truth", tmp_path / "far.gt.txt")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "far.gt.txt" in r.stderr and "timestamp" in r.stderr
    r = slam2d("eval", "loops", tmp_path, "--ground-truth", tmp_path / "missing.gt.txt")
    assert r.returncode == 2 and "missing.gt.txt: no such file" in r.stderr
    # constraints from another run: their stamps are not the trajectory's
    (tmp_path / "o").mkdir()
    write_tum(tmp_path / "o" / "trajectory.txt", [f"{i}.0" for i in range(len(gt))], gt)
    (tmp_path / "o" / "constraints.jsonl").write_text((tmp_path / "constraints.jsonl").read_text())
    r = slam2d("eval", "loops", tmp_path / "o")
    assert r.returncode == 2 and "constraints.jsonl:1" in r.stderr and r.stderr.count("\n") == 1


def test_loops_ground_truth_of_the_simulator(tmp_path):
    from conftest import BUNDLED

    run = tmp_path / "sim"
    r = slam2d("run", BUNDLED, "--out", run, "--no-progress")
    assert r.returncode == 0, r.stderr
    r = slam2d("eval", "loops", run, "--ground-truth", BUNDLED, "--json")
    assert r.returncode == 0, r.stderr
    g = json.loads(r.stdout)["ground_truth"]
    assert g["matching"] == "mcap_scan_index" and g["matched_scans"] == json.loads((run / "summary.json").read_text())["scans"]
    assert g["final_graph"]["unknown"] == 0 and g["recall"]["episodes"] >= 1
    # every constraint the ground truth calls false is put to the raw scans (the log read again)
    fb = g["final_graph"]["false_by_scans"]
    assert set(fb) == {"constraint", "ground_truth", "both", "undecided"} and sum(fb.values()) == g["final_graph"]["false"]
    assert len(g["disagreeing"]) == g["final_graph"]["false"] and all("scan_check" in d for d in g["disagreeing"])


def test_loops_on_a_run_whose_stamps_go_back_and_repeat(tmp_path):
    """trajectory.txt is sorted by stamp (evo's rule); eval matches its lines to scans by its
    '# scans' comment, so constraints, own poses and the ground truth line up as before."""
    n = 400
    stamps = [f"{1e9 + 0.5 * i:.6f}" for i in range(n)]
    stamps[260], stamps[261] = stamps[261], stamps[260]  # a constraint's end stamped after its successor
    stamps[271] = stamps[270]  # a repeated stamp at another constraint's end
    gt, own, truth = _gt_run(tmp_path, stamps)
    assert (tmp_path / "trajectory.txt").read_text().startswith("# scans 0-259 261 260 262-399\n")
    t, poses, _ = read_tum(tmp_path / "trajectory.txt")
    np.testing.assert_allclose(poses[:, :2], own[:, :2], atol=2e-6)
    write_tum(tmp_path / "order.gt.txt", [f"{i}.0" for i in range(n)], gt)
    r = slam2d("eval", "loops", tmp_path, "--ground-truth", tmp_path / "order.gt.txt", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["ground_truth"]["final_graph"]["precision"] == pytest.approx(0.4)
    assert out["own"]["accepted"]["true"] >= 1


def _bent(poses, k, degrees):
    """``poses`` with everything from scan ``k`` on turned by ``degrees`` about scan k's position."""
    out = np.array(poses, dtype=float)
    turn = compose(compose(np.r_[out[k, :2], 0.0], np.array([0.0, 0.0, math.radians(degrees)])), np.r_[-out[k, :2], 0.0])
    for i in range(k, len(out)):
        out[i] = compose(turn, out[i])
    return out


def test_consistency_prefers_the_true_trajectory_on_the_simulator():
    """The raw scans at the simulator's true poses agree with each other; the same trajectory bent by
    1° halfway (a wrong turn that no loop repaired) puts walls into free space where the robot comes
    back, and scores worse, on the same scans."""
    from conftest import BUNDLED

    from slam2d.config import load_config
    from slam2d.eval.consistency import compare, scan_nodes
    from slam2d.io.source import open_source

    truth = np.array([s.ground_truth for s in open_source(BUNDLED)], dtype=float)
    cfg = load_config(None)
    bent = _bent(truth, len(truth) // 2, 1.0)
    out = compare(open_source(BUNDLED), cfg, {"truth": truth, "bent": bent})
    t, b = out["truth"], out["bent"]
    assert t["scans_checked"] == b["scans_checked"] > 100 and t["revisits_checked"] > 0
    assert t["scans_agreeing"] >= 0.95 and t["mean_violation"] < 0.02
    assert b["revisit_mean_violation"] > 2 * t["revisit_mean_violation"] and b["revisits_agreeing"] < 0.95
    assert b["mean_violation"] > t["mean_violation"]
    # the scans are those the motion filter passes along the first trajectory, each with its range data
    nodes = scan_nodes(open_source(BUNDLED), cfg, truth)
    assert len(nodes) >= t["scans_checked"]  # a scan no neighbour sees is not checked
    assert all(np.linalg.norm(nodes[i + 1].local_pose[:2] - nodes[i].local_pose[:2]) > cfg.motion_filter.max_distance
               or abs(math.remainder(nodes[i + 1].local_pose[2] - nodes[i].local_pose[2], 2 * math.pi))
               > math.radians(cfg.motion_filter.max_angle_deg)
               or nodes[i + 1].time - nodes[i].time > cfg.motion_filter.max_time for i in range(len(nodes) - 1))
    # a trajectory without a pose for some scans: those scans are left out for every trajectory
    holes = bent.copy()
    holes[::2] = np.nan
    part = compare(open_source(BUNDLED), cfg, {"truth": truth, "holes": holes})
    assert part["truth"]["scans_checked"] == part["holes"]["scans_checked"] < t["scans_checked"]


def test_consistency_disputes_point_at_the_scans_one_trajectory_misplaces():
    """The simulator's true poses against the same poses with scans 300-319 moved 0.5 m sideways (a
    reference that jumps for a stretch): the scans of that stretch agree with their neighbours only
    at the true poses, the disputed scans side with the truth, and the longest disputed stretch lies
    inside the moved one; the truth against itself has no dispute."""
    from conftest import BUNDLED

    from slam2d.config import load_config
    from slam2d.eval.consistency import compare, disputes
    from slam2d.io.source import open_source

    truth = np.array([s.ground_truth for s in open_source(BUNDLED)], dtype=float)
    cfg = load_config(None)
    moved = truth.copy()
    moved[300:320] = [compose(p, np.array([0.0, 0.5, 0.0])) for p in truth[300:320]]
    d = compare(open_source(BUNDLED), cfg, {"truth": truth, "moved": moved})["moved"]["disputes"]
    assert d["with"] == "truth"
    assert d["agree_only_there"] >= 5 and d["agree_only_here"] <= 1, d
    longest = d["stretches"][0]
    assert longest["agree_with"] == "there" and 300 <= longest["scans"][0] <= longest["scans"][1] < 320, d
    assert compare(open_source(BUNDLED), cfg, {"a": truth, "b": truth.copy()})["b"]["disputes"]["stretches"] == []
    # the verdict per node, by hand: disputed where exactly one side agrees; NaN (unchecked) is no dispute
    nodes = [SimpleNamespace(scan_index=i) for i in range(6)]
    here = np.array([0.0, 0.5, 0.5, 0.0, np.nan, 0.5])
    there = np.array([0.0, 0.0, 0.0, 0.5, 0.5, 0.0])
    d = disputes(nodes, here, there)
    assert (d["agree_only_here"], d["agree_only_there"]) == (1, 3)
    assert d["stretches"] == [{"scans": [1, 2], "nodes": 2, "agree_with": "there"},
                              {"scans": [3, 3], "nodes": 1, "agree_with": "here"},
                              {"scans": [5, 5], "nodes": 1, "agree_with": "there"}]


def test_consistency_cli(tmp_path):
    from conftest import BUNDLED

    run = tmp_path / "sim"
    r = slam2d("run", BUNDLED, "--out", run, "--no-progress", "--max-scans", "400")
    assert r.returncode == 0, r.stderr
    r = slam2d("eval", "consistency", run / "trajectory.txt", "--against", BUNDLED, "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert list(out) == [str(run / "trajectory.txt"), str(BUNDLED)]
    assert out[str(BUNDLED)]["scans_checked"] == out[str(run / "trajectory.txt")]["scans_checked"] > 0
    assert "disputes" in out[str(BUNDLED)] and "disputes" not in out[str(run / "trajectory.txt")]
    r = slam2d("eval", "consistency", run / "trajectory.txt", "--against", BUNDLED)
    assert r.returncode == 0 and r.stdout.count("\n") == 3 and "disputed with the first" in r.stdout, r.stdout
    r = slam2d("eval", "consistency", run / "trajectory.txt")
    assert r.returncode == 0 and r.stdout.count("\n") == 1 and "agreeing" in r.stdout
    # a trajectory with no run folder beside it: the log must be named
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "trajectory.txt").write_text((run / "trajectory.txt").read_text())
    r = slam2d("eval", "consistency", tmp_path / "t" / "trajectory.txt")
    assert r.returncode != 0 and r.stderr.count("\n") == 1 and "--run-input" in r.stderr
    r = slam2d("eval", "consistency", tmp_path / "t" / "trajectory.txt", "--run-input", BUNDLED)
    assert r.returncode == 0, r.stderr


def test_consistency_against_a_corrected_carmen_log(tmp_path):
    """A corrected CARMEN log's key scans (matched to the run's scans by their ranges) against raw
    odometry: the scans support GMapping's poses better than the odometry's, on the same scans."""
    src = dataset("intel")
    run = tmp_path / "run"
    assert slam2d("run", src, "--out", run, "--odometry-only", "--no-progress", "--max-scans", "3000").returncode == 0
    r = slam2d("eval", "consistency", run / "trajectory.txt", "--against", SHARED / "intel" / "intel.gfs.log", "--json")
    assert r.returncode == 0, r.stderr
    odo, ref = json.loads(r.stdout).values()
    from slam2d.eval.reference import load_reference

    t, _, _ = read_tum(run / "trajectory.txt")
    keys = len(load_reference(SHARED / "intel" / "intel.gfs.log", t, str(src)).scan_indices)
    assert 0 < odo["scans_checked"] == ref["scans_checked"] <= keys
    assert ref["mean_violation"] < odo["mean_violation"] and ref["scans_agreeing"] > odo["scans_agreeing"]


def test_ground_truth_on_the_run_s_clock_in_another_order_is_matched_by_stamp(tmp_path):
    """Matched by position when it has a pose per scan: reversed (or sorted by time, where the run's
    stamps go back), its poses were paired with the wrong scans and precision read 0 instead of 0.96.
    On the run's clock the stamps now pair them; on another clock (make_sparse's) position is all there is."""
    from slam2d.eval.reference import load_ground_truth

    stamps = [f"{100 + 0.5 * i:.1f}" for i in range(8)]
    poses = np.array([[0.3 * i, 0.0, 0.1 * i] for i in range(8)])
    run_t = np.array([float(s) for s in stamps])
    write_tum(tmp_path / "gt.txt", stamps, poses)
    assert load_ground_truth(tmp_path / "gt.txt", run_t).matching == "scan_order"
    write_tum(tmp_path / "other_clock.txt", [f"{1e9 + i:.1f}" for i in range(8)], poses)
    got = load_ground_truth(tmp_path / "other_clock.txt", run_t)
    np.testing.assert_allclose(got.poses, poses, atol=1e-6)
    rev = tmp_path / "rev.txt"
    rev.write_text("".join(line for line in reversed((tmp_path / "gt.txt").read_text().splitlines(True))
                           if not line.startswith("#")))
    got = load_ground_truth(rev, run_t)
    assert got.matching == "timestamp"
    np.testing.assert_allclose(got.poses, poses, atol=1e-6)


def test_a_run_made_with_scan_period_is_evaluated_against_its_log(tmp_path, flaser_line):
    """Its stamps are k × period, not the log's (broken) ones: the order check must not refuse it (the
    sparse logs of ../shared are all run so)."""
    log = tmp_path / "wrap.clf"
    log.write_text("".join(flaser_line([1.0 + 0.1 * i, 2.0, 3.0], pose=(0.5 * i, 0, 0), odom=(0.5 * i, 0, 0),
                                       ts="4294967296.0") for i in range(12)))
    stamps = [f"{0.2 * i:.6f}" for i in range(12)]
    write_tum(tmp_path / "t.txt", stamps, np.array([[0.5 * i, 0.0, 0.0] for i in range(12)]))
    r = subprocess.run([sys.executable, "-m", "slam2d.cli", "eval", "ate", str(tmp_path / "t.txt"), str(log),
                        "--run-input", str(log), "--json"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["matched_scans"] == 12
