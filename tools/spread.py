"""Run-to-run spread of local SLAM: the same log with the whole world rotated by small angles.

Rotating every odometry pose about the origin changes nothing a relations metric can see,
but it moves every scan against the grid's cells, and local SLAM's result moves with it
(a chaotic system: tiny differences early decide which way later matches fall). One run
is one sample; this tool shows the distribution, so that a change is judged by its mean
and not by one lucky or unlucky run. Run 0 is the unrotated log (what `slam2d run` gives).

examples:
  python tools/spread.py ../shared/datasets/intel/intel.clf.bz2 ../shared/datasets/intel/intel.relations
  python tools/spread.py LOG RELATIONS --runs 10 --set submaps.num_range_data_without_loop_closure=300
"""
from __future__ import annotations

import argparse
import copy
import math
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _config(config_path, settings):
    from slam2d.config import config_from_dict, load_config
    from slam2d.errors import Slam2dError

    try:
        data = load_config(config_path).model_dump() if config_path else {}
        for item in settings:
            key, _, value = item.partition("=")
            section, _, name = key.partition(".")
            if not name:
                raise SystemExit(f"spread.py: error: --set wants section.key=value, got {item!r}")
            data.setdefault(section, {})[name] = yaml.safe_load(value)
        return config_from_dict(data, "--set")
    except Slam2dError as e:
        raise SystemExit(f"spread.py: error: {e}") from None


def _run(args):
    log, relations, config_path, settings, phi = args
    from slam2d.eval.relations import read_relations, relations_metric
    from slam2d.frontend import LocalSlam
    from slam2d.io.source import open_source

    cfg = _config(config_path, settings)
    slam = LocalSlam(cfg, loop_closure=False)
    c, s = math.cos(phi), math.sin(phi)
    times, poses = [], []
    for scan in open_source(log):
        if scan.odom_pose is not None:
            o = scan.odom_pose
            scan = copy.copy(scan)
            scan.odom_pose = np.array([c * o[0] - s * o[1], s * o[0] + c * o[1], o[2] + phi])
        times.append(scan.timestamp)
        poses.append(slam.add_scan(scan).local_pose)
    m = relations_metric(np.array(times), np.array(poses), read_relations(relations))
    return m["abs_trans_m"]["mean"], m["abs_rot_deg"]["mean"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", help="a log with wheel odometry (CARMEN or MCAP)")
    ap.add_argument("relations", help="its .relations file")
    ap.add_argument("--runs", type=int, default=6, help="number of runs (default 6)")
    ap.add_argument("--config", help="YAML config (default: the built-in defaults)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override one option (repeatable)")
    ap.add_argument("--jobs", type=int, default=2, help="parallel runs (default 2; each runs numba single-threaded)")
    args = ap.parse_args(argv)
    os.environ["NUMBA_NUM_THREADS"] = "1"  # inherited by the workers; results do not depend on it
    _config(args.config, args.set)  # fail early on a bad option
    from slam2d.errors import Slam2dError
    from slam2d.eval.relations import read_relations
    from slam2d.io.source import open_source

    try:  # and on a missing or unreadable input
        read_relations(args.relations)
        src = open_source(args.log)
        if hasattr(src, "num_scans"):
            src.num_scans()
    except Slam2dError as e:
        raise SystemExit(f"spread.py: error: {e}") from None
    angles = [0.0] + [math.radians(7.0 * k + 0.3) for k in range(1, args.runs)]
    jobs = [(args.log, args.relations, args.config, args.set, a) for a in angles]
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        results = list(pool.map(_run, jobs))
    trans = np.array([r[0] for r in results])
    rot = np.array([r[1] for r in results])
    for a, (t, r) in zip(angles, results):
        print(f"rotated {math.degrees(a):6.2f}°: {t:.4f} m  {r:.3f}°")
    print(f"translation mean {trans.mean():.4f} m (min {trans.min():.4f}, max {trans.max():.4f}); "
          f"rotation mean {rot.mean():.3f}°")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
