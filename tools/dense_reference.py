#!/usr/bin/env python3
"""Judge a sparse run's loops against a run of the raw log its scans came from.

`make_sparse.py` keeps a subset of a corrected log's scans with their real ranges, and writes
GMapping's corrected poses as the ground truth (`.gt.txt`). Where the corrected log belongs to a
raw log with hand-verified relations (intel, aces, fr079), a run of that raw log is a second
reference: the relations check it, and it misses them less often than GMapping's corrected log
does (`tools/reference_check.py`). This writes that reference (each sparse scan at the pose the
raw log's run gave the raw scan with identical ranges) and prints the final graph's loop
precision at 0.3 m / 2° against both references, as the benchmark's sparse table does.

  python tools/dense_reference.py benchmarks/runs/sparse-fr079-seed8 \\
      ~/.cache/slam2d-benchmark/make_sparse-seed8-*/fr079/freiburg-079.gt.txt \\
      ../shared/datasets/fr079/fr079.clf.bz2 benchmarks/runs/fr079/trajectory.txt

The sparse log is the run's input (its summary.json); `--out` keeps the reference (default: the
run folder's dense_reference.txt).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from benchmark import dense_reference, loops_vs_ground_truth  # noqa: E402

from slam2d.errors import InputError  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="the sparse log's run folder (trajectory.txt, constraints.jsonl, summary.json)")
    ap.add_argument("ground_truth", help="the .gt.txt make_sparse.py wrote for the sparse log")
    ap.add_argument("raw_log", help="the raw log the corrected log belongs to")
    ap.add_argument("raw_trajectory", help="a run of the raw log: its trajectory.txt")
    ap.add_argument("--out", help="where to write the reference (TUM)")
    args = ap.parse_args(argv)
    try:
        return _judge(args)
    except InputError as e:
        print(f"dense_reference: {e}", file=sys.stderr)
        return 2


def _judge(args) -> int:
    run = Path(args.run)
    for p in (run / "summary.json", run / "trajectory.txt", Path(args.ground_truth), Path(args.raw_log),
              Path(args.raw_trajectory)):
        if not p.is_file():
            raise InputError(p, "no such file")
    try:
        sparse_log = Path(json.loads((run / "summary.json").read_text())["input"])
    except (ValueError, KeyError, TypeError):
        raise InputError(run / "summary.json", "not a run's summary (no 'input')") from None
    out = Path(args.out) if args.out else run / "dense_reference.txt"
    n = dense_reference(sparse_log, Path(args.raw_log), Path(args.raw_trajectory), out)
    if n == 0:
        print(f"{sparse_log}: no scan of it is a scan of {args.raw_log}", file=sys.stderr)
        return 1
    print(f"reference: {out} ({n} scans of {sparse_log.name})")
    for name, ref, check in (("ground truth", Path(args.ground_truth), True), ("raw log's run", out, False)):
        g = loops_vs_ground_truth(run, ref, check_scans=check)
        if g is None:
            print("no constraints.jsonl in the run")
            return 1
        f = g["final_graph"]
        extra = f"; misses by the raw scans {f['false_by_scans']}" if "false_by_scans" in f else ""
        prec = "—" if f["precision"] is None else f"{100 * f['precision']:.1f} %"
        print(f"vs {name}: {f['false']} false of {f['true'] + f['false']} in the final graph (precision {prec}){extra}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
