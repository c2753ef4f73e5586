"""Online SLAM with the slam2d library: feed scans one at a time, read the pose estimate as it comes.

    python examples/online_slam.py                         # the bundled simulated office
    python examples/online_slam.py LOG [OUT_DIR] [--every N]

Prints the estimate every N scans (the global pose moves when a loop closes), then the final
result, and writes the same files as ``slam2d run LOG --out OUT_DIR``.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import slam2d

BUNDLED = Path(__file__).resolve().parents[1] / "data" / "sim_office.mcap"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", nargs="?", default=str(BUNDLED), help="a log slam2d reads (default: the bundled dataset)")
    ap.add_argument("out", nargs="?", default="runs/online_example", help="output folder")
    ap.add_argument("--every", type=int, default=200, help="print the estimate every N scans")
    args = ap.parse_args(argv)

    slam = slam2d.Slam()  # the default config; slam2d.Slam.from_yaml("my.yaml") for your own
    for scan in slam2d.open_source(args.log):
        est = slam.add_scan(scan)
        if est.index % args.every == 0:
            x, y, th = est.global_pose
            print(f"scan {est.index:6d}  t={est.time:.3f}  global ({x:8.3f}, {y:8.3f}, {math.degrees(th):7.2f}°)  "
                  f"local match: {est.quality}")
    result = slam.finish()
    h = result.summary["health"]
    loops = result.summary.get("loop_closure", {}).get("in_final_graph", 0)
    print(f"{len(result.poses)} scans, {loops} loop closures, map {result.map.shape[1]}×{result.map.shape[0]} cells, "
          f"health {h['status']}")
    print(f"wrote {result.save(args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
