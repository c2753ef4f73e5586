"""``slam2d eval relations | ate | loops | consistency``."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

EXAMPLES = """examples:
  slam2d eval relations runs/intel/trajectory.txt ../shared/datasets/intel/intel.relations
  slam2d eval relations runs/thin/trajectory.txt ../shared/datasets/intel/intel.relations --exact
  slam2d eval ate runs/intel/trajectory.txt ../shared/datasets/intel/intel.gfs.log --plot runs/intel/ate.png
  slam2d eval loops runs/intel --reference ../shared/datasets/intel/intel.gfs.log
  slam2d eval loops runs/orebro --ground-truth sparse/orebro.gt.txt
  slam2d eval loops runs/sim --ground-truth data/sim_office.mcap
  slam2d eval consistency runs/orebro/trajectory.txt --against sparse/orebro.gt.txt
"""


#: what ``--plot`` writes (matplotlib's formats a viewer opens)
PLOT_SUFFIXES = (".png", ".svg", ".pdf", ".jpg")


def add_eval_parser(sub):
    p = sub.add_parser("eval", help="evaluate a trajectory (relations metric, ATE/RPE, loop closures, free-space consistency)",
                       epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    es = p.add_subparsers(dest="eval_command", metavar="METRIC")

    r = es.add_parser("relations", help="Kümmerle et al. 2009 relations metric (as Cartographer reports it)")
    r.add_argument("trajectory", help="TUM trajectory (e.g. RUN_DIR/trajectory.txt)")
    r.add_argument("relations", help="relations file: t1 t2 x y z roll pitch yaw per line")
    r.add_argument("--tolerance", type=float, default=1e-4, help="timestamp match tolerance [s] (default 1e-4)")
    r.add_argument("--exact", action="store_true",
                   help="score only the relations whose two stamps are both poses of the trajectory (no interpolation: "
                        "for a log thinned by degrade.py --keep-every, where interpolating across dropped scans makes most of the error)")
    r.add_argument("--json", action="store_true")

    a = es.add_parser("ate", help="absolute trajectory error (SE(2) Umeyama alignment; also the scale of the best similarity alignment and the error left after it) and RPE")
    a.add_argument("trajectory")
    a.add_argument("reference", help="TUM file, MCAP with /ground_truth, or CARMEN corrected log (*.gfs.log, *-corrected.log*)")
    a.add_argument("--run-input", default=None, help="the log the run read (default: 'input' in summary.json beside the trajectory)")
    a.add_argument("--distances", default="1,5,10", help="RPE travelled distances [m], comma-separated")
    a.add_argument("--plot", default=None, help="write trajectory-vs-reference PNG here (and *_error.png)")
    a.add_argument("--json", action="store_true")

    lp = es.add_parser("loops", help="loop-closure precision/recall from RUN_DIR/constraints.jsonl")
    lp.add_argument("run_dir")
    lp.add_argument("--reference", default=None, help="TUM file, MCAP with /ground_truth, or CARMEN corrected log")
    lp.add_argument("--run-input", default=None)
    lp.add_argument("--own-trans", type=float, default=0.2, help="(a) own-solution threshold [m] (default 0.2)")
    lp.add_argument("--own-rot", type=float, default=1.0, help="(a) own-solution threshold [deg] (default 1)")
    lp.add_argument("--ref-trans", type=float, default=0.3, help="(b) reference threshold [m] (default 0.3)")
    lp.add_argument("--ref-rot", type=float, default=2.0, help="(b) reference threshold [deg] (default 2)")
    lp.add_argument("--ground-truth", default=None,
                    help="ground truth independent of the run: TUM file with one pose per scan (matched in scan order "
                         "when the counts are equal, else by timestamp), or an MCAP with /ground_truth")
    lp.add_argument("--tolerance-trans", type=float, default=0.3, help="ground-truth tolerance [m] (default 0.3)")
    lp.add_argument("--tolerance-rot", type=float, default=2.0, help="ground-truth tolerance [deg] (default 2)")
    lp.add_argument("--revisit-distance", type=float, default=1.0, help="recall: a revisit comes this close [m]")
    lp.add_argument("--plot-dir", default=None, help="write loops_on_map.png and loop_scores.png here (default RUN_DIR)")
    lp.add_argument("--json", action="store_true")

    c = es.add_parser("consistency",
                      help="free-space consistency of the raw scans at a trajectory's poses (no reference needed), "
                           "and at other trajectories' for comparison")
    c.add_argument("trajectory", help="TUM trajectory with one pose per scan (e.g. RUN_DIR/trajectory.txt)")
    c.add_argument("--against", action="append", default=[], metavar="TUM",
                   help="another trajectory of the same log, tested on the same scans; may be repeated: TUM or MCAP "
                        "with /ground_truth (matched to the scans as eval loops --ground-truth does), or a corrected "
                        "CARMEN log (*.gfs.log, *-corrected.log*: its key scans, matched by their ranges)")
    c.add_argument("--run-input", default=None, help="the log (default: 'input' in summary.json beside the trajectory)")
    c.add_argument("--config", default=None,
                   help="config whose range filter and motion filter pick the scans (default: config.yaml beside the "
                        "trajectory, else the defaults)")
    c.add_argument("--json", action="store_true")
    return p


def _print(obj, as_json):
    if as_json:
        print(json.dumps(obj, indent=2))
        return
    def walk(o, prefix=""):
        for k, v in o.items():
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            elif not isinstance(v, list):
                print(f"{prefix}{k}: {v:.6g}" if isinstance(v, float) else f"{prefix}{k}: {v}")
    walk(obj)


def run_eval(args) -> int:
    from slam2d.errors import UsageError

    if args.eval_command is None:
        raise UsageError("eval: choose a metric: relations, ate, loops or consistency (see slam2d eval --help)")
    return {"relations": _relations, "ate": _ate, "loops": _loops, "consistency": _consistency}[args.eval_command](args)


def _relations(args) -> int:
    from slam2d.eval.relations import read_relations, relations_metric
    from slam2d.io.trajectory import read_tum

    from slam2d.errors import InputError, UsageError

    if not 0 <= args.tolerance < 1.0:
        raise UsageError(f"--tolerance must lie in [0, 1) s, not {args.tolerance}")
    t, poses, _ = read_tum(args.trajectory)
    m = relations_metric(t, poses, read_relations(args.relations), args.tolerance, args.exact)
    if not m["counts"]["evaluated"]:
        raise InputError(args.relations, f"none of its relations falls within the trajectory's stamps "
                         f"({t.min():.3f} to {t.max():.3f} s): another log's relations?")
    m["trajectory"], m["relations_file"] = args.trajectory, args.relations
    _print(m, args.json)
    return 0


def _ate(args) -> int:
    from slam2d.errors import UsageError
    from slam2d.eval.ate import align, ate, rpe
    from slam2d.eval.reference import load_reference, run_input_of
    from slam2d.io.trajectory import read_tum

    if args.plot:
        from slam2d.cli import writable_file

        if Path(args.plot).suffix.lower() not in PLOT_SUFFIXES:
            raise UsageError(f"--plot {args.plot}: the picture must end in {', '.join(PLOT_SUFFIXES)}")
        writable_file(args.plot, "plot")
    t, poses, _ = read_tum(args.trajectory)
    ref = load_reference(args.reference, t, run_input_of(Path(args.trajectory), args.run_input))
    if ref.scan_indices.max() >= len(poses):
        raise UsageError(f"{args.reference}: matches scan {ref.scan_indices.max()} but the trajectory has {len(poses)} poses")
    est = poses[ref.scan_indices]
    try:
        dists = [float(d) for d in args.distances.split(",") if d]
    except ValueError:
        raise UsageError(f"--distances: not a list of numbers: {args.distances!r}") from None
    out = {"reference_kind": ref.kind, "reference_scans": ref.total_reference_scans,
           "matched_scans": int(len(ref.scan_indices)), "ate": ate(est, ref.poses), "rpe": rpe(est, ref.poses, dists)}
    if args.plot:
        from slam2d.eval.plots import plot_error_over_time, plot_trajectories

        al = align(est, ref.poses)
        plot_trajectories(args.plot, al, ref.poses, title=f"ATE RMSE {out['ate']['trans_m']['rmse']:.3f} m")
        err = np.hypot(*(al[:, :2] - ref.poses[:, :2]).T)
        plot_error_over_time(str(Path(args.plot).with_name(Path(args.plot).stem + "_error.png")), t[ref.scan_indices], err,
                             "ATE [m]")
    _print(out, args.json)
    return 0


def _loops(args) -> int:
    from slam2d.eval.loops import (Thresholds, check_stamps, classify, classify_ground_truth, disagreeing,
                                   read_constraints, score_histogram)
    from slam2d.eval.plots import plot_loops, plot_score_histogram
    from slam2d.eval.reference import load_ground_truth, load_reference, run_input_of
    from slam2d.io.trajectory import read_tum

    run_dir = Path(args.run_dir)
    t, poses, _ = read_tum(run_dir / "trajectory.txt")
    constraints = read_constraints(run_dir / "constraints.jsonl")
    check_stamps(constraints, t, run_dir / "constraints.jsonl")
    th = Thresholds(args.own_trans, args.own_rot, args.ref_trans, args.ref_rot, args.revisit_distance)
    ref_dense = ref_key = None
    if args.reference:
        run_input = run_input_of(run_dir / "trajectory.txt", args.run_input)
        ref = load_reference(args.reference, t, run_input)
        odom = _odometry(run_input, len(t)) if ref.kind == "corrected_carmen" else None
        ref_dense = ref.dense(odom) if odom is not None else ref.dense(None)
        if len(ref_dense) < len(t):
            ref_dense = np.vstack([ref_dense, np.full((len(t) - len(ref_dense), 3), np.nan)])
        ref_key = (ref.scan_indices, ref.poses)
    out = classify(constraints, poses, ref_dense, ref_key, th)
    key = "true_ref" if ref_dense is not None else "true_own"
    if args.ground_truth:
        gt = load_ground_truth(args.ground_truth, t)
        out["ground_truth"] = {"file": str(args.ground_truth), "matching": gt.matching,
                               "poses": gt.total_ground_truth_poses, "matched_scans": int(len(gt.scan_indices)),
                               **classify_ground_truth(constraints, gt.poses, gt.scan_indices, args.tolerance_trans,
                                                       args.tolerance_rot, th)}
        key = "true_gt"
        out["score_histogram"] = score_histogram(constraints, key)
        from slam2d.eval.scan_check import check_run

        checked = check_run(run_dir, constraints, poses, gt.poses, args.run_input,
                            (args.tolerance_trans, args.tolerance_rot))
        if checked is not None:  # where the ground truth calls a constraint false, which side the scans take
            out["ground_truth"]["final_graph"]["false_by_scans"] = checked
            out["ground_truth"]["disagreeing"] = disagreeing(constraints, gt.poses)  # now with the verdicts
    plot_dir = Path(args.plot_dir) if args.plot_dir else run_dir
    plot_loops(plot_dir / "loops_on_map.png", run_dir, poses, constraints, key)
    plot_score_histogram(plot_dir / "loop_scores.png", out["score_histogram"], "loop-closure scores")
    out.pop("score_histogram") if not args.json else None
    _print(out, args.json)
    if not args.json:
        for d in out.get("ground_truth", {}).get("disagreeing", []):
            check = d.get("scan_check", {})
            says = f"; the raw scans: {check['verdict']} ({check['share_constraint']} vs {check['share_ground_truth']} " \
                   f"of the hits on the place{', then registered' if check.get('by') else ''})" if check else ""
            print(f"ground_truth.disagreeing: submap {d['submap']}, scans {d['from_scan']} -> {d['to_scan']}, "
                  f"{d['off_m']} m / {d['off_deg']} deg off the ground truth, score {d['score']}{says}")
    return 0


def _consistency(args) -> int:
    from slam2d.config import load_config
    from slam2d.errors import UsageError
    from slam2d.eval.consistency import compare
    from slam2d.eval.reference import check_scan_order, recording_stamps, run_input_of
    from slam2d.io.source import open_source
    from slam2d.io.trajectory import read_tum

    traj = Path(args.trajectory)
    t, poses, _ = read_tum(traj)
    log = run_input_of(traj, args.run_input)
    if log is None:
        raise UsageError(f"{traj}: no summary.json beside it names the log; give it with --run-input")
    cfg_path = Path(args.config) if args.config else traj.parent / "config.yaml"
    cfg = load_config(cfg_path if (args.config or cfg_path.exists()) else None)
    trajectories = {str(traj): poses}
    for other in args.against:
        trajectories[other] = _poses_of(other, t, log)
    stamps = []
    out = compare(recording_stamps(open_source(log), stamps), cfg, trajectories)
    check_scan_order(t, np.array(stamps), log)  # a trajectory of another log, or re-sorted, scores nonsense
    if len(t) > len(stamps):
        raise UsageError(f"{traj}: {len(t)} poses for the {len(stamps)} scans of {log}: not a trajectory of this log")
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    for name, c in out.items():
        print(f"{name}: {c['scans_checked']} scans, {c['scans_agreeing']} agreeing, mean violation {c['mean_violation']}; "
              f"revisits {c['revisits_checked']}, {c['revisits_agreeing']} agreeing, mean violation "
              f"{c['revisit_mean_violation']}")
        d = c.get("disputes")
        if d is not None:  # the scans that agree with their neighbours at one of the two trajectories only
            whose = {"here": "these", "there": "the first's"}
            where = ", ".join(f"scans {s['scans'][0]}-{s['scans'][1]} ({s['nodes']} at {whose[s['agree_with']]})"
                              for s in d["stretches"])
            print(f"  disputed with the first: {d['agree_only_here']} scans agree with their neighbours only at these "
                  f"poses, {d['agree_only_there']} only at the first's{'; longest: ' + where if where else ''}")
    return 0


def _poses_of(path, stamps, run_input) -> np.ndarray:
    """One pose per scan of the run (NaN where ``path`` has none): a corrected CARMEN log's key scans,
    else a ground truth as ``load_ground_truth`` reads it."""
    from slam2d.eval.reference import is_carmen, load_ground_truth, load_reference

    if is_carmen(Path(path)) or Path(path).name.lower().endswith(".gfs.log"):
        return load_reference(path, stamps, run_input).dense(None)
    return load_ground_truth(path, stamps).poses


def _odometry(run_input, n):
    from slam2d.io.source import open_source

    odom = [s.odom_pose for s in open_source(run_input)]
    if not odom or any(o is None for o in odom):
        return None
    return np.array(odom[:n])
