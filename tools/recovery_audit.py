"""Did each recovery of local SLAM help? Every recovered pose against the pose it replaced, on ground truth.

Local SLAM's recovery (``LocalSlam._recover``) replaces a scan's pose: the real-time window's
match, or the prediction when there was none (``MatchingResult.replaced``). For every such
scan this tool places the ground truth in local SLAM's frame from the last trusted scan before
it (that scan's local pose moved by the ground truth's step since it, so earlier drift cancels)
and prints how far the recovered pose and the replaced one lie from it. A recovery that helps
lands nearer than what it replaced; one that jumped to a look-alike place lands farther.

Local SLAM runs as under global SLAM (``LocalSlam(cfg, loop_closure=True)``: the same submaps),
without the pose graph, which does not change local poses.

examples:
  python tools/recovery_audit.py data/sim_office.mcap
  python tools/recovery_audit.py ~/.cache/slam2d-benchmark/make_sparse-seed7-*/orebro/orebro.clf \\
      --ground-truth ~/.cache/slam2d-benchmark/make_sparse-seed7-*/orebro/orebro.gt.txt
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def audit(scans, cfg=None, ground_truth: np.ndarray | None = None) -> list[dict]:
    """One row per recovered scan: its index and quality, and the distance (m) and heading error
    (deg) to the ground truth of the recovered pose and of the replaced one. ``ground_truth``:
    (N, 3), one pose per scan in input order, NaN where there is none (``load_ground_truth``);
    else each scan's own ``ground_truth``. Scans before the first trusted one, or without ground
    truth, are skipped."""
    from slam2d.config import config_from_dict
    from slam2d.frontend import LocalSlam
    from slam2d.geometry import between, compose

    slam = LocalSlam(cfg or config_from_dict({}), loop_closure=True)
    rows, anchor = [], None
    for i, scan in enumerate(scans):
        res = slam.add_scan(scan)
        gt = scan.ground_truth if ground_truth is None else ground_truth[i]
        if gt is None or not np.all(np.isfinite(gt)):
            continue
        gt = np.asarray(gt, dtype=float)
        if res.replaced is not None and anchor is not None:
            truth = compose(anchor[0], between(anchor[1], gt))

            def off(pose):
                return (math.hypot(pose[0] - truth[0], pose[1] - truth[1]),
                        abs(math.degrees(math.remainder(pose[2] - truth[2], 2 * math.pi))))

            (d_new, r_new), (d_old, r_old) = off(res.local_pose), off(res.replaced)
            rows.append({"scan": int(scan.index), "quality": res.quality, "recovered_m": d_new,
                         "recovered_deg": r_new, "replaced_m": d_old, "replaced_deg": r_old})
        if res.quality == "trusted":
            anchor = (np.asarray(res.local_pose, dtype=float), gt)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", help="any input slam2d reads (CARMEN, MCAP, ROS bag)")
    ap.add_argument("--ground-truth", help="TUM file with one pose per scan (in scan order when the counts are "
                                           "equal, else by timestamp) or an MCAP with /ground_truth, as for "
                                           "`slam2d eval loops` (default: the input's own ground truth)")
    ap.add_argument("--config", help="YAML config (default: the built-in defaults)")
    args = ap.parse_args(argv)
    from slam2d.config import load_config
    from slam2d.errors import Slam2dError
    from slam2d.eval.reference import load_ground_truth
    from slam2d.io.source import open_source

    try:
        cfg = load_config(args.config) if args.config else None
        scans = list(open_source(args.log))
        gt = None
        if args.ground_truth:
            gt = load_ground_truth(args.ground_truth, np.array([s.timestamp for s in scans])).poses
        rows = audit(scans, cfg, gt)
    except Slam2dError as e:
        raise SystemExit(f"recovery_audit.py: error: {e}") from None
    for r in rows:
        verdict = "nearer" if r["recovered_m"] < r["replaced_m"] else "farther"
        print(f"scan {r['scan']:6d} {r['quality']:9s} recovered {r['recovered_m']:.3f} m {r['recovered_deg']:5.2f}°, "
              f"replaced {r['replaced_m']:.3f} m {r['replaced_deg']:5.2f}°: {verdict}")
    nearer = sum(r["recovered_m"] < r["replaced_m"] for r in rows)
    print(f"{len(rows)} recovered scans: {nearer} nearer the ground truth than the pose they replaced, "
          f"{len(rows) - nearer} farther")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
