#!/usr/bin/env python3
"""How good is the GMapping-corrected reference? Score it with the relations metric.

`slam2d eval loops --reference` judges loop constraints against a corrected CARMEN log
(GMapping's key-scan poses; scans between key scans take the nearer key pose plus the raw
odometry increment). This tool scores that very reference, and a run's trajectory, against
the hand-verified relations (Kümmerle et al. 2009) with the same tolerance the loop check
uses (0.3 m / 2°), so one can see whether the reference can certify constraints at all.

  python tools/reference_check.py benchmarks/runs/intel ../shared/datasets/intel/intel.gfs.log
  python tools/reference_check.py benchmarks/runs/aces ../shared/datasets/aces/aces-corrected.log.gz

Prints one line per trajectory: relations evaluated, mean |t| / |θ|, and the share of
relations whose error exceeds 0.3 m or 2°; then the same restricted to relations whose
both ends are key scans of the reference (no odometry interpolation involved).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from slam2d.eval.reference import load_reference  # noqa: E402
from slam2d.eval.relations import Relations, read_relations, relation_errors  # noqa: E402
from slam2d.io.source import open_source  # noqa: E402
from slam2d.io.trajectory import read_tum  # noqa: E402


def score(times, poses, rel: Relations, max_t=0.3, max_deg=2.0) -> dict:
    err, _ = relation_errors(times, poses, rel)
    et = np.hypot(err[:, 0], err[:, 1])
    er = np.degrees(np.abs(err[:, 2]))
    bad = (et > max_t) | (er > max_deg)
    return {"relations": int(len(et)), "trans_m": round(float(et.mean()), 4), "rot_deg": round(float(er.mean()), 3),
            "over_tolerance_pct": round(100.0 * float(bad.mean()), 1),
            "over_2deg_pct": round(100.0 * float((er > max_deg).mean()), 1),
            "over_0.3m_pct": round(100.0 * float((et > max_t).mean()), 1), "max_rot_deg": round(float(er.max()), 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a run folder (trajectory.txt, summary.json)")
    ap.add_argument("reference", help="corrected CARMEN log (e.g. intel.gfs.log)")
    ap.add_argument("--relations", help="relations file (default: next to the run's input log)")
    ap.add_argument("--input", help="the raw log the run was made from (default: summary.json's input)")
    args = ap.parse_args(argv)
    run = Path(args.run)
    times, poses, _ = read_tum(run / "trajectory.txt")
    raw = args.input or json.loads((run / "summary.json").read_text())["input"]
    rel_path = args.relations or str(Path(raw).parent / (Path(raw).name.split(".")[0] + ".relations"))
    rel = read_relations(rel_path)
    ref = load_reference(args.reference, times, raw)
    odom = np.array([s.odom_pose for s in open_source(raw)])
    dense = ref.dense(odom)
    ok = ~np.isnan(dense[:, 0])
    keys = ref.scan_indices
    key_stamps = set(np.round(times[keys], 6))
    both = np.array([round(a, 6) in key_stamps and round(b, 6) in key_stamps for a, b in zip(rel.t1, rel.t2)])
    key_rel = Relations(rel.t1[both], rel.t2[both], rel.delta[both])
    rows = {"run": score(times, poses, rel), "reference (as eval loops uses it)": score(times[ok], dense[ok], rel)}
    if both.any():
        rows["run, key-key relations"] = score(times, poses, key_rel)
        rows["reference, key-key relations"] = score(times[keys], ref.poses, key_rel)
    for name, r in rows.items():
        print(f"{name:36s} n={r['relations']:5d}  {r['trans_m']:.4f} m  {r['rot_deg']:.3f}°  "
              f"over 0.3 m/2°: {r['over_tolerance_pct']:5.1f} % (2°: {r['over_2deg_pct']} %, 0.3 m: {r['over_0.3m_pct']} %)"
              f"  max {r['max_rot_deg']}°")
    return 0


if __name__ == "__main__":
    sys.exit(main())
