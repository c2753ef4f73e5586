#!/usr/bin/env python3
"""Benchmark slam2d on every dataset in ../shared/datasets and write BENCHMARKS.md + benchmarks.json.

  python tools/benchmark.py                      # every suite, default config
  python tools/benchmark.py --peers              # also run the Karto peer (../shared/tools/peer_karto.py)
  python tools/benchmark.py --datasets intel --jobs 2 --config configs/default.yaml
  python tools/benchmark.py --suite sparse --datasets orebro,belgioioso

Suites (issue 11), all in one run by default, `--suite` selects some:
  relations  intel / aces / fr079, relations metric on the dataset's `.relations`;
  degraded   the same logs with worse odometry (`../shared/tools/degrade.py IN OUT --seed 1`,
             its defaults), scored on the original `.relations`;
  dropout    the degraded logs with three readings in ten turned into no-returns as well
             (`degrade.py ... --beam-dropout 0.3`: dark, glossy and glass surfaces), relations;
  thinned    the degraded logs with one scan in five kept (`degrade.py ... --keep-every 5`: a fifth
             of the scan rate, tens of degrees between the scans of a fast turn); their agreement
             with slam2d's run of the whole raw log (the relations suite's), and the relations whose
             two stamps are both scans of the thinned log;
  harsh      odometry far worse than `degraded`'s (`degrade.py ... --rot-scale 0.5 --trans-scale 0.1`,
             seeds 4 and 5, every scan and one in three): where the default config stands beyond the
             logs it was measured on; scored as `thinned` is;
  no-odometry  the same logs run with `slam2d run --no-odometry` (odometry is optional), relations;
  sparse     `../shared/tools/make_sparse.py OUTDIR LOG --seed 7` of every corrected log found in
             ../shared/datasets (`*.gfs.log`, `*-corrected.log*`, any depth); ATE RMSE and loop
             precision/recall (`slam2d eval loops --ground-truth`) against the `.gt.txt` it writes,
             and for a log made from a relations log also against slam2d's run of the raw log;
             and the ATE's median and range over seeds 7, 8 and 9 (`--sparse-spread`: the same
             scans with other odometry noise, slam2d alone);
  clinic     fr-clinic (`datasets/fr-clinic/*.clf.bz2`): wall time, peak RSS, loop closures, health;
  simulated  the simulator with sensors and robots the real logs do not cover (`bench_logs.SIM_VARIANTS`:
             a 4 m scanner, a fast robot, bad odometry, a 1081-beam 20 Hz scanner, 240° / 5.6 m and
             180° / 8 m scanners); ATE and loop
             precision against its ground truth, beside the odometry's ATE.
`--datasets` names the dataset folders to keep (intel, aces, fr079, orebro, fr-clinic, ...).
Generated logs go to a cache folder outside the repository (`--cache`, default
`$XDG_CACHE_HOME/slam2d-benchmark` or `~/.cache/slam2d-benchmark`), in a subfolder keyed on the
seed and the generating tool's sha256, and are made again only when missing.
The Karto peer (`--peers`) runs beside slam2d on every CARMEN FLASER log (relations, degraded,
dropout, sparse); it cannot read fr-clinic's ROBOTLASER1 records. `bench_logs.py` makes and caches the
generated logs, `bench_tables.py` writes the tables.

Each run is a whole `slam2d run` process: wall time and peak memory are what the OS
reports for it (os.wait4). Numba's cache is warmed first (``warm_up``), so compile time
is not counted. Accuracy is the relations metric (Kümmerle et al. 2009) on the dataset's
`.relations`; the odometry baseline and Cartographer's published figures (Hess et al.
2016, Tables II and V, on a 6-core Xeon) stand beside it.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

sys.path.insert(0, str(ROOT / "tools"))

from bench_logs import (BEAM_DROPOUT, HARSH_KEEP_EVERY, HARSH_ODOMETRY, HARSH_SEEDS, KEEP_EVERY,  # noqa: E402
                        SIM_VARIANTS, corrected_logs, default_cache, degraded_log, dropout_log, harsh_log, sim_log,
                        sparse_log, thinned_log)
from bench_tables import (TARGETS, clinic_table, degraded_table, harsh_table, simulated_table, sparse_table,  # noqa: E402
                          table, thinned_table)

SHARED = ROOT.parent / "shared"
REFERENCE_LOGS = {"intel": "intel.gfs.log", "aces": "aces-corrected.log.gz", "fr079": "freiburg-079-corrected.log.gz"}
SUITES = ("relations", "degraded", "dropout", "thinned", "harsh", "no-odometry", "sparse", "clinic", "simulated")
LOOP_TOLERANCE = (0.3, 2.0)  # m, deg: slam2d eval loops --ground-truth defaults


def _tree_rss_mb(pid: int) -> tuple[float, float]:
    """Resident memory of a process and all its descendants now, and the file-backed part of it
    (MB; 0 once they are gone). The file-backed part is mostly shared libraries' code and data
    mapped from disk (numba's LLVM alone keeps tens of MB resident): how much of it a process has
    mapped depends on the page cache as well as on the process, and moves from hour to hour."""
    parent = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    parent[int(d)] = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    tree, todo = [], [pid]
    while todo:
        p = todo.pop()
        tree.append(p)
        todo.extend(c for c, pp in parent.items() if pp == p)
    rss_kb = file_kb = 0
    for p in tree:
        try:
            with open(f"/proc/{p}/status") as f:
                fields = dict(line.split(":", 1) for line in f if line.startswith(("VmRSS:", "RssFile:", "RssShmem:")))
            rss_kb += int(fields["VmRSS"].split()[0])
            file_kb += sum(int(fields[k].split()[0]) for k in ("RssFile", "RssShmem") if k in fields)
        except (OSError, IndexError, ValueError, KeyError):
            pass
    return rss_kb / 1024, file_kb / 1024


def timed(cmd: list[str]) -> dict:
    """Run a process; wall time and peak RSS (MB): the larger of its own peak and the peak of its
    resident memory summed with its child processes' (slam2d's pose-graph solver), sampled every 0.1 s;
    ``peak_rss_file_mb``: the file-backed part of that summed peak (None where its own peak is larger).
    Its own peak is its address space's high-water mark, read as it runs: the rusage figure would
    also hold this process's own peak, whose address space the child's exec replaced."""
    from slam2d.allocator import process_peak_mb

    with tempfile.TemporaryFile("w+") as fo, tempfile.TemporaryFile("w+") as fe:
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, stdout=fo, stderr=fe, text=True)
        tree_peak, tree_file, own = 0.0, 0.0, 0.0
        while True:
            pid, status, _ = os.wait4(p.pid, os.WNOHANG)
            if pid:
                break
            own = max(own, process_peak_mb(p.pid) or 0.0)
            rss, file_mb = _tree_rss_mb(p.pid)
            if rss > tree_peak:
                tree_peak, tree_file = rss, file_mb
            time.sleep(0.1)
        wall = time.perf_counter() - t0
        fo.seek(0)
        fe.seek(0)
        out, err = fo.read(), fe.read()
    p.returncode = os.waitstatus_to_exitcode(status)
    return {"wall_s": wall, "peak_rss_mb": max(own, tree_peak), "peak_rss_file_mb": tree_file if tree_peak >= own else None,
            "returncode": p.returncode, "stdout": out, "stderr": err}


def relations_of(traj: Path, rel: Path, exact: bool = False) -> dict:
    from slam2d.eval.relations import read_relations, relations_metric
    from slam2d.io.trajectory import read_tum

    t, poses, _ = read_tum(traj)
    return relations_metric(t, poses, read_relations(rel), exact=exact)


def agreement_with(traj: Path, full: Path) -> dict | None:
    """``ate_vs_ground_truth`` of a run of a thinned log against slam2d's run of the whole log (whose
    scans it keeps, stamps unchanged: matched by timestamp; ``pairs`` the scans compared). None
    without a common stamp."""
    from slam2d.errors import InputError

    try:
        return ate_vs_ground_truth(traj, full)
    except InputError:
        return None


def _median_run(runs: list[dict]) -> dict:
    """The run with the median wall time (the higher of the two middle ones), peak RSS the largest seen."""
    ok = [r for r in runs if r["returncode"] == 0] or runs
    pick = dict(sorted(ok, key=lambda r: r["wall_s"])[len(ok) // 2])
    top = max(ok, key=lambda r: r["peak_rss_mb"])
    pick["peak_rss_mb"], pick["peak_rss_file_mb"] = top["peak_rss_mb"], top.get("peak_rss_file_mb")
    return pick


def run_log(label: str, log: Path, args, outdir: Path, peer: bool = True, extra: tuple = (),
            repeat: int | None = None) -> dict:
    """slam2d on one log (and the Karto peer when asked and ``peer``), ``repeat`` (default ``--repeat``)
    times alternating.

    Returns {"slam2d": {...}, "karto": {...}?}; slam2d's run folder is ``outdir/label``, the
    peer's trajectory ``outdir/label_karto.txt``."""
    slam = [sys.executable, "-m", "slam2d.cli", "run", str(log), "--no-progress"]
    if args.config:
        slam += ["--config", str(args.config)]
    karto = outdir / f"{label}_karto.txt"
    peer_cmd = [sys.executable, str(args.shared / "tools" / "peer_karto.py"), str(log), "--out", str(karto)]
    peer = peer and args.peers
    # slam2d and the peer alternate --repeat times; each reports its median wall time, so a
    # machine whose speed drifts during the benchmark favours neither
    runs, peer_runs = [], []
    for _ in range(max(1, args.repeat if repeat is None else repeat)):
        runs.append(timed(slam + ["--out", str(outdir / label)] + list(extra) + args.extra))
        if runs[-1]["returncode"] != 0:
            raise SystemExit(f"{label}: slam2d run failed: {runs[-1]['stderr'].strip()}")
        if peer:
            peer_runs.append(timed(peer_cmd))
    r = _median_run(runs)
    summary = json.loads((outdir / label / "summary.json").read_text())
    own_end = summary.get("peak_rss_mb") or 0.0
    row: dict = {"dataset": label, "log": str(log)}
    row["slam2d"] = {"wall_s": r["wall_s"], "wall_s_runs": [round(x["wall_s"], 2) for x in runs],
                     # its own figure at its end as well: sampling every 0.1 s can miss the last moments
                     "peak_rss_mb": max(r["peak_rss_mb"], own_end),
                     "peak_rss_file_mb": r.get("peak_rss_file_mb") if r["peak_rss_mb"] >= own_end else None,
                     "scans": summary["scans"],
                     "duration_s": summary["duration_s"], "real_time_factor": summary["duration_s"] / r["wall_s"],
                     "timings": summary.get("timings", {}), "mode": summary.get("mode"),
                     "loop_closure": summary.get("loop_closure"), "health": summary.get("health")}
    if peer:
        p = _median_run(peer_runs)
        if p["returncode"] == 0:
            row["karto"] = {"wall_s": p["wall_s"], "peak_rss_mb": p["peak_rss_mb"],
                            "peak_rss_file_mb": p.get("peak_rss_file_mb"), "trajectory": str(karto),
                            "wall_s_runs": [round(x["wall_s"], 2) for x in peer_runs]}
        else:
            row["karto"] = {"error": p["stderr"].strip().splitlines()[-1] if p["stderr"].strip() else "failed"}
    return row


def ate_vs_ground_truth(traj: Path, gt_path: Path) -> dict:
    """ATE (slam2d.eval.ate) of a TUM trajectory against a per-scan ground truth (``load_ground_truth``)."""
    from slam2d.eval.ate import ate
    from slam2d.eval.reference import load_ground_truth
    from slam2d.io.trajectory import read_tum

    t, poses, _ = read_tum(traj)
    gt = load_ground_truth(gt_path, t)
    out = ate(poses[gt.scan_indices], gt.poses[gt.scan_indices])
    out["matching"] = gt.matching
    return out


def loops_vs_ground_truth(run_dir: Path, gt_path: Path, check_scans: bool = True) -> dict | None:
    """``slam2d eval loops RUN_DIR --ground-truth GT --json``'s ``ground_truth`` object (None without loops);
    ``check_scans``: put the misses to the raw scans (``false_by_scans``)."""
    from slam2d.eval.loops import Thresholds, check_stamps, classify_ground_truth, disagreeing, read_constraints
    from slam2d.eval.reference import load_ground_truth
    from slam2d.io.trajectory import read_tum

    if not (run_dir / "constraints.jsonl").exists():
        return None
    from slam2d.eval.scan_check import check_run

    t, poses, _ = read_tum(run_dir / "trajectory.txt")
    cs = read_constraints(run_dir / "constraints.jsonl")
    check_stamps(cs, t, run_dir / "constraints.jsonl")
    gt = load_ground_truth(gt_path, t)
    out = {"matching": gt.matching, **classify_ground_truth(cs, gt.poses, gt.scan_indices, *LOOP_TOLERANCE, Thresholds())}
    checked = check_run(run_dir, cs, poses, gt.poses, agree=LOOP_TOLERANCE) if check_scans else None
    if checked is not None:  # where the ground truth calls a constraint false: which side the raw scans take
        out["final_graph"]["false_by_scans"] = checked
        out["disagreeing"] = disagreeing(cs, gt.poses)  # now with the verdicts
    return out


def dense_reference(sparse_log: Path, raw_log: Path, dense_trajectory: Path, out: Path) -> int:
    """Write ``out``: a TUM reference for the scans of a sparse log that are scans of ``raw_log`` too
    (identical ranges, in order: ``make_sparse.py`` keeps a subset of a corrected log's scans), each
    at the pose a run of the raw log gave that scan (``dense_trajectory``, matched by the raw scan's
    stamp) and stamped with the sparse scan's own time. Returns how many scans it holds. The run of
    the raw log is scored on the hand-verified relations (its row in the relations table), so it is
    a second reference beside GMapping's `.gt.txt`, independent of the sparse run."""
    import numpy as np

    from slam2d.geometry import yaw_to_quaternion
    from slam2d.io.source import open_source
    from slam2d.io.trajectory import read_tum

    raw: dict[bytes, list[tuple[int, float]]] = {}
    for scan in open_source(raw_log):
        raw.setdefault(np.asarray(scan.ranges, dtype=np.float32).tobytes(), []).append((scan.index, scan.timestamp))
    t, poses, _ = read_tum(dense_trajectory)
    order = np.argsort(t, kind="stable")
    ts = t[order]
    lines, last = [], -1
    for s in open_source(sparse_log):
        later = [(i, stamp) for i, stamp in raw.get(np.asarray(s.ranges, dtype=np.float32).tobytes(), []) if i > last]
        if not later:
            continue
        last, stamp = later[0]
        j = int(np.searchsorted(ts, stamp))
        near = min((i for i in (j - 1, j) if 0 <= i < len(ts)), key=lambda i: abs(ts[i] - stamp), default=None)
        if near is not None and abs(ts[near] - stamp) < 1e-3:  # trajectory.txt may nudge a repeated stamp by 1 µs
            p = poses[order[near]]
            q = np.ravel(yaw_to_quaternion(p[2]))
            lines.append(f"{s.timestamp:.6f} {p[0]:.6f} {p[1]:.6f} 0 {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")
    out.write_text("".join(lines))
    return len(lines)


def loops_vs_dense_run(row: dict, datasets: Path, runs: Path) -> None:
    """For a sparse log made from a relations log that this benchmark also ran whole (``runs/NAME``):
    the loop precision of its run of every seed (``row["seed_runs"]``) against that run
    (``dense_reference``): the ``--sparse-seed`` run's record in ``row["slam2d"]["loops_vs_dense_run"]``,
    each seed's final graph in ``...["loops_vs_dense_run_by_seed"]``. GMapping's `.gt.txt` misses the
    hand-verified relations more often than slam2d's dense runs do (``tools/reference_check.py``), so
    this tells a wrong loop from a wrong ground truth where the scans alone cannot (``scan_check``)."""
    name = row["dataset"]
    raw, dense = datasets / name / f"{name}.clf.bz2", runs / name / "trajectory.txt"
    if not (raw.exists() and dense.exists()):
        return
    by_seed = {}
    for i, (seed, r) in enumerate(row.get("seed_runs", {}).items()):
        run_dir = runs / r["run"]
        if not (run_dir / "constraints.jsonl").exists():
            continue
        ref = run_dir / "dense_reference.txt"
        if dense_reference(Path(r["log"]), raw, dense, ref) == 0:
            continue
        out = loops_vs_ground_truth(run_dir, ref, check_scans=False)
        if out is None:
            continue
        by_seed[seed] = out["final_graph"]
        if i == 0:  # the --sparse-seed run
            out["reference"] = str(dense)
            row["slam2d"]["loops_vs_dense_run"] = out
    if by_seed:
        row["slam2d"]["loops_vs_dense_run_by_seed"] = by_seed


def consistency_vs_ground_truth(run_dir: Path, gt_path: Path, log: Path) -> dict:
    """``slam2d eval consistency RUN_DIR/trajectory.txt --against GT``: the raw scans' free-space test
    at the run's poses and at the ground truth's, on the same scans (``slam2d/eval/consistency.py``)."""
    from slam2d.config import load_config
    from slam2d.eval.consistency import compare
    from slam2d.eval.reference import load_ground_truth
    from slam2d.io.source import open_source
    from slam2d.io.trajectory import read_tum

    t, poses, _ = read_tum(run_dir / "trajectory.txt")
    gt = load_ground_truth(gt_path, t)
    return compare(open_source(log), load_config(run_dir / "config.yaml"), {"slam2d": poses, "ground_truth": gt.poses})


def bench_degraded(name: str, log: Path, args, outdir: Path, kind: str = "degraded") -> dict:
    rel = args.shared / "datasets" / name / f"{name}.relations"
    row = run_log(f"{kind}-{name}", log, args, outdir)
    row["dataset"] = name
    row["slam2d"]["relations"] = relations_of(outdir / f"{kind}-{name}" / "trajectory.txt", rel)
    if "trajectory" in row.get("karto", {}):
        row["karto"]["relations"] = relations_of(Path(row["karto"]["trajectory"]), rel)
    return row


def bench_thinned(name: str, log: Path, args, outdir: Path, label: str | None = None) -> dict:
    """A thinned degraded log (run folder ``label``, default ``thinned-NAME``): the relations whose two
    stamps are both scans of it (interpolating across the dropped scans would measure the
    interpolation); its agreement with slam2d's run of the whole log is added once every run is
    done (``thinned_agreement``)."""
    rel = args.shared / "datasets" / name / f"{name}.relations"
    label = label or f"thinned-{name}"
    row = run_log(label, log, args, outdir)
    row.update({"dataset": name, "label": label})
    row["slam2d"]["relations_exact"] = relations_of(outdir / label / "trajectory.txt", rel, exact=True)
    if "trajectory" in row.get("karto", {}):
        row["karto"]["relations_exact"] = relations_of(Path(row["karto"]["trajectory"]), rel, exact=True)
    return row


def bench_harsh(name: str, log: Path, keep_every: int, seed: int, args, outdir: Path) -> dict:
    """A harsh copy (``harsh_log``), scored as a thinned one is (``bench_thinned``)."""
    row = bench_thinned(name, log, args, outdir, f"harsh-{name}-every{keep_every}-seed{seed}")
    row.update({"keep_every": keep_every, "seed": seed})
    return row


def thinned_agreement(row: dict, runs: Path) -> None:
    """A thinned (or harsh) log's runs (slam2d's, the peer's) against slam2d's run of the whole raw log
    in this benchmark (``runs/NAME``), where there is one."""
    full = runs / row["dataset"] / "trajectory.txt"
    if not full.exists():
        return
    row["slam2d"]["vs_full_log"] = agreement_with(runs / row["label"] / "trajectory.txt", full)
    if "trajectory" in row.get("karto", {}):
        row["karto"]["vs_full_log"] = agreement_with(Path(row["karto"]["trajectory"]), full)


def bench_no_odometry(name: str, args, outdir: Path) -> dict:
    """A relations log run with ``--no-odometry``: the odometry is optional, and the same default
    config must map the log from its scans alone (the prediction from the matches' velocity)."""
    rel = args.shared / "datasets" / name / f"{name}.relations"
    row = run_log(f"no-odometry-{name}", args.shared / "datasets" / name / f"{name}.clf.bz2", args, outdir,
                  peer=False, extra=("--no-odometry",))
    row["dataset"] = name
    row["slam2d"]["relations"] = relations_of(outdir / f"no-odometry-{name}" / "trajectory.txt", rel)
    return row


def bench_sparse(name: str, log: Path, gt: Path, args, outdir: Path, corrected: Path | None = None) -> dict:
    """The sparse log of ``--sparse-seed`` (slam2d and the peer), then slam2d alone on the same
    corrected log made with each ``--sparse-spread`` seed: the same scans with other odometry noise,
    whose ATEs show how much one seed's figure owes to luck."""
    row = run_log(f"sparse-{name}", log, args, outdir)
    row["dataset"], row["ground_truth"] = name, str(gt)
    row["slam2d"]["ate"] = ate_vs_ground_truth(outdir / f"sparse-{name}" / "trajectory.txt", gt)
    row["slam2d"]["loops_vs_ground_truth"] = loops_vs_ground_truth(outdir / f"sparse-{name}", gt)
    # is the ground truth, itself a SLAM solution, better supported by the raw scans than the run?
    row["slam2d"]["consistency_vs_ground_truth"] = consistency_vs_ground_truth(outdir / f"sparse-{name}", gt, log)
    if "trajectory" in row.get("karto", {}):
        row["karto"]["ate"] = ate_vs_ground_truth(Path(row["karto"]["trajectory"]), gt)
    by_seed = {str(args.sparse_seed): row["slam2d"]["ate"]["trans_m"]["rmse"]}
    health = {str(args.sparse_seed): (row["slam2d"].get("health") or {}).get("status")}
    g = row["slam2d"]["loops_vs_ground_truth"]
    loops = {str(args.sparse_seed): g["final_graph"] if g else None}
    row["seed_runs"] = {str(args.sparse_seed): {"run": f"sparse-{name}", "log": str(log)}}
    for seed in (args.sparse_spread if corrected is not None else []):
        if seed == args.sparse_seed:
            continue
        log_s, gt_s = sparse_log(args, name, corrected, seed=seed)
        label = f"sparse-{name}-seed{seed}"
        r = run_log(label, log_s, args, outdir, peer=False, repeat=1)
        by_seed[str(seed)] = ate_vs_ground_truth(outdir / label / "trajectory.txt", gt_s)["trans_m"]["rmse"]
        health[str(seed)] = (r["slam2d"].get("health") or {}).get("status")
        g = loops_vs_ground_truth(outdir / label, gt_s, check_scans=False)
        loops[str(seed)] = g["final_graph"] if g else None
        row["seed_runs"][str(seed)] = {"run": label, "log": str(log_s)}
    row["slam2d"]["ate_rmse_by_seed"] = by_seed
    row["slam2d"]["health_by_seed"] = health  # does the run's own report flag the seeds that failed?
    row["slam2d"]["loops_vs_ground_truth_by_seed"] = loops  # final graph
    return row


def bench_simulated(name: str, log: Path, args, outdir: Path) -> dict:
    """A simulated variant: ATE and loops against the MCAP's own ground truth, and the odometry's ATE."""
    row = run_log(f"sim-{name}", log, args, outdir, peer=False)
    row["dataset"] = name
    row["slam2d"]["ate"] = ate_vs_ground_truth(outdir / f"sim-{name}" / "trajectory.txt", log)
    row["slam2d"]["loops_vs_ground_truth"] = loops_vs_ground_truth(outdir / f"sim-{name}", log)
    odo = outdir / f"sim-{name}_odometry"
    timed([sys.executable, "-m", "slam2d.cli", "run", str(log), "--no-progress", "--odometry-only", "--out", str(odo)])
    row["odometry"] = {"ate": ate_vs_ground_truth(odo / "trajectory.txt", log)}
    return row


def warm_up(log: Path, out: Path) -> None:
    """Compile numba's kernels into its cache before anything is timed: the first log's start (its
    sensor's code paths), the bundled dataset whole (loop search, optimization, final refinement),
    and the bundled dataset with every match untrusted (local recovery, which a short clean start
    rarely reaches; otherwise the first real log to recover pays the compile)."""
    bundled = ROOT / "data" / "sim_office.mcap"
    distrust = out / "distrust.yaml"
    out.mkdir(parents=True, exist_ok=True)
    distrust.write_text("real_time_matcher:\n  min_relative_score: 0.999\n")
    runs = [[str(log), "--max-scans", "300"], [str(bundled)], [str(bundled), "--max-scans", "200", "--config", str(distrust)]]
    for i, extra in enumerate(runs):
        subprocess.run([sys.executable, "-m", "slam2d.cli", "run", extra[0], "--out", str(out / str(i)), "--no-progress",
                        *extra[1:]], check=True, capture_output=True)


def bench_clinic(log: Path, args, outdir: Path) -> dict:
    row = run_log(f"clinic-{log.name.split('.')[0]}", log, args, outdir, peer=False)  # the peer reads FLASER only
    row["dataset"] = log.parent.name
    return row


def bench_dataset(name: str, args, outdir: Path) -> dict:
    d = args.shared / "datasets" / name
    log = d / f"{name}.clf.bz2"
    rel = d / f"{name}.relations"
    slam = [sys.executable, "-m", "slam2d.cli", "run", str(log), "--no-progress"]
    if args.config:
        slam += ["--config", str(args.config)]
    row = run_log(name, log, args, outdir, repeat=max(args.repeat, args.speed_repeat))
    r = row["slam2d"]
    r["relations"] = relations_of(outdir / name / "trajectory.txt", rel)
    if args.rerun:
        rrd = outdir / f"{name}.rrd"
        rv = timed(slam + ["--out", str(outdir / f"{name}_rerun"), "--rerun", str(rrd)] + args.extra)
        if rv["returncode"] == 0:
            row["rerun"] = {"wall_s": rv["wall_s"], "peak_rss_mb": rv["peak_rss_mb"], "rrd_mb": rrd.stat().st_size / 2 ** 20,
                            "overhead": rv["wall_s"] / r["wall_s"] - 1.0}
    timed(slam + ["--out", str(outdir / f"{name}_odometry"), "--odometry-only"])
    row["odometry"] = {"relations": relations_of(outdir / f"{name}_odometry" / "trajectory.txt", rel)}
    if "trajectory" in row.get("karto", {}):
        row["karto"]["relations"] = relations_of(Path(row["karto"]["trajectory"]), rel)
    ref = d / REFERENCE_LOGS.get(name, "")
    if (outdir / name / "constraints.jsonl").exists():
        cmd = [sys.executable, "-m", "slam2d.cli", "eval", "loops", str(outdir / name), "--json", "--run-input", str(log)]
        if ref.is_file():
            cmd += ["--reference", str(ref)]
        lp = subprocess.run(cmd, capture_output=True, text=True)
        if lp.returncode == 0:
            row["loops"] = json.loads(lp.stdout)
            for p in ("loops_on_map.png", "loop_scores.png"):
                src = outdir / name / p
                if src.exists():
                    os.replace(src, outdir / f"{name}_{p}")
                    row.setdefault("plots", []).append(f"{name}_{p}")
    if ref.is_file():
        plot = outdir / f"{name}_trajectory.png"
        a = subprocess.run([sys.executable, "-m", "slam2d.cli", "eval", "ate", str(outdir / name / "trajectory.txt"),
                            str(ref), "--run-input", str(log), "--plot", str(plot), "--json"],
                           capture_output=True, text=True)
        if a.returncode == 0:
            row["slam2d"]["ate_vs_corrected_log"] = json.loads(a.stdout)["ate"]
            row.setdefault("plots", []).extend([plot.name, plot.with_name(plot.stem + "_error.png").name])
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", default=",".join(SUITES), help=f"comma-separated suites (default: all of {','.join(SUITES)})")
    ap.add_argument("--datasets", default=None,
                    help="comma-separated dataset folder names to keep in every suite (default: all found)")
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--peers", action="store_true", help="also run ../shared/tools/peer_karto.py (needs karto-scanmatcher)")
    ap.add_argument("--rerun", action="store_true", help="also time each relations run with --rerun (recording cost and size)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="time slam2d (and the peer) this many times, alternating, and report the median wall time")
    ap.add_argument("--speed-repeat", type=int, default=3,
                    help="the relations logs, whose wall time against the peer's is a target, are timed at least "
                         "this many times, alternating with the peer, and the medians compared (default 3: the "
                         "machines here are noisy)")
    ap.add_argument("--jobs", type=int, default=1, help="logs run in parallel (default 1: timings undisturbed)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks"), help="folder for runs and plots")
    ap.add_argument("--cache", default=None,
                    help="folder for generated (degraded, sparse) logs (default $XDG_CACHE_HOME/slam2d-benchmark "
                         "or ~/.cache/slam2d-benchmark)")
    ap.add_argument("--shared", default=str(SHARED), help="folder holding datasets/ and tools/ (default ../shared)")
    ap.add_argument("--degrade-seed", type=int, default=1, help="degrade.py --seed (default 1, issue 11)")
    ap.add_argument("--sparse-seed", type=int, default=7, help="make_sparse.py --seed (default 7, issue 11)")
    ap.add_argument("--sparse-spread", default="8,9",
                    help="more make_sparse.py seeds each sparse log is run with (slam2d alone, comma-separated; "
                         "'' for none): the table gives the ATE's median and range over them and --sparse-seed, "
                         "since a single seed's figure can be luck (default 8,9)")
    ap.add_argument("--title", default="Benchmarks", help="heading of the markdown file")
    ap.add_argument("--markdown", default=str(ROOT / "BENCHMARKS.md"))
    ap.add_argument("--json", default=str(ROOT / "benchmarks.json"))
    ap.add_argument("--extra", default="", help="extra arguments for slam2d run, e.g. '--no-loop-closure' (use --extra=...)")
    args = ap.parse_args(argv)
    args.extra = args.extra.split()
    try:
        args.sparse_spread = [int(x) for x in args.sparse_spread.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--sparse-spread: comma-separated seeds expected, not {args.sparse_spread!r}")
    args.shared = Path(args.shared).resolve()
    args.cache = Path(args.cache) if args.cache else default_cache()
    suites = [x for x in args.suite.split(",") if x]
    unknown = sorted(set(suites) - set(SUITES))
    if unknown:
        ap.error(f"--suite: unknown {', '.join(unknown)} (choose from {', '.join(SUITES)})")
    datasets = args.shared / "datasets"
    if not datasets.is_dir():
        print(f"benchmark: {datasets} not found", file=sys.stderr)
        return 2
    keep = set(args.datasets.split(",")) if args.datasets else None
    wanted = (lambda n: keep is None or n in keep)
    relation_names = sorted(p.name for p in datasets.iterdir()
                            if (p / f"{p.name}.clf.bz2").exists() and (p / f"{p.name}.relations").exists() and wanted(p.name))
    outdir = Path(args.out)
    runs = outdir / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    # every job: (suite, log, thunk); generated logs are made (or found in the cache) first
    jobs: list[tuple[str, Path, object]] = []
    if "relations" in suites:
        jobs += [("relations", datasets / n / f"{n}.clf.bz2", lambda n=n: bench_dataset(n, args, runs))
                 for n in relation_names]
    if "degraded" in suites:
        for n in relation_names:
            log = degraded_log(args, n)
            jobs.append(("degraded", log, lambda n=n, log=log: bench_degraded(n, log, args, runs)))
    if "dropout" in suites:
        for n in relation_names:
            log = dropout_log(args, n)
            jobs.append(("dropout", log, lambda n=n, log=log: bench_degraded(n, log, args, runs, "dropout")))
    if "thinned" in suites:
        for n in relation_names:
            log = thinned_log(args, n)
            jobs.append(("thinned", log, lambda n=n, log=log: bench_thinned(n, log, args, runs)))
    if "harsh" in suites:
        for n in relation_names:
            for every in HARSH_KEEP_EVERY:
                for seed in HARSH_SEEDS:
                    log = harsh_log(args, n, seed, every)
                    jobs.append(("harsh", log, lambda n=n, log=log, k=every, sd=seed: bench_harsh(n, log, k, sd, args, runs)))
    if "no-odometry" in suites:
        jobs += [("no-odometry", datasets / n / f"{n}.clf.bz2", lambda n=n: bench_no_odometry(n, args, runs))
                 for n in relation_names]
    if "sparse" in suites:
        for n, corrected in corrected_logs(datasets):
            if wanted(n):
                log, gt = sparse_log(args, n, corrected)
                jobs.append(("sparse", log, lambda n=n, log=log, gt=gt, c=corrected: bench_sparse(n, log, gt, args, runs, c)))
    if "clinic" in suites:
        jobs += [("clinic", log, lambda log=log: bench_clinic(log, args, runs))
                 for log in sorted((datasets / "fr-clinic").glob("*.clf.bz2")) if wanted("fr-clinic")]
    if "simulated" in suites:
        for n in SIM_VARIANTS:
            if wanted(n):
                log = sim_log(args, n)
                jobs.append(("simulated", log, lambda n=n, log=log: bench_simulated(n, log, args, runs)))
    if not jobs:
        print("benchmark: nothing to run (check --suite and --datasets)", file=sys.stderr)
        return 2
    warm_up(jobs[0][1], runs / "warmup")
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        done = list(ex.map(lambda j: (j[0], j[2]()), jobs))
    by_suite = {s: [row for k, row in done if k == s] for s in SUITES}
    for row in by_suite["sparse"]:
        loops_vs_dense_run(row, datasets, runs)
    for row in by_suite["thinned"] + by_suite["harsh"]:
        thinned_agreement(row, runs)
    rows = by_suite["relations"]
    for row in rows:
        for p in row.get("plots", []):
            if (runs / p).exists():
                os.replace(runs / p, outdir / p)
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
            "python": platform.python_version(), "config": os.path.relpath(args.config, ROOT),
            "extra_args": args.extra, "jobs": args.jobs, "repeat": args.repeat,
            "speed_repeat": args.speed_repeat, "suites": suites,
            "degrade_seed": args.degrade_seed, "sparse_seed": args.sparse_seed, "sparse_spread": args.sparse_spread,
            "cache": str(args.cache),
            "targets": TARGETS}
    Path(args.json).write_text(json.dumps({"meta": meta, "rows": rows, "degraded": by_suite["degraded"],
                                           "dropout": by_suite["dropout"], "thinned": by_suite["thinned"], "harsh": by_suite["harsh"],
                                           "no_odometry": by_suite["no-odometry"], "sparse": by_suite["sparse"], "clinic": by_suite["clinic"],
                                           "simulated": by_suite["simulated"]},
                                          indent=2, default=float) + "\n")
    flags = "".join(f" --{f}" for f in ("peers", "rerun") if getattr(args, f))
    flags += f" --repeat {args.repeat}" if args.repeat > 1 else ""
    flags += f" --speed-repeat {args.speed_repeat}" if args.speed_repeat != 3 else ""
    speed_runs = max(args.repeat, args.speed_repeat)
    flags += f" --suite {args.suite}" if suites != list(SUITES) else ""
    flags += f" --datasets {args.datasets}" if args.datasets else ""
    md = [f"# {args.title}", "",
          f"`python tools/benchmark.py{flags}` on {meta['date']} ({meta['machine']}, "
          f"Python {meta['python']}), config `{meta['config']}`{', slam2d run ' + ' '.join(args.extra) if args.extra else ''}. "
          "Wall time and peak RSS are those of the whole process; peak RSS is the larger of its own peak and "
          "the peak of its resident memory summed with its child processes' (the pose-graph solver), sampled every 0.1 s"
          + (f" (median of {args.repeat} runs, slam2d and the peer alternating)" if args.repeat > 1 else "")
          + (f"; the relations logs' wall time and peak RSS: median wall time and largest peak of {speed_runs} runs, "
             "slam2d and the peer alternating, so that the ratio is not one run's noise" if speed_runs > max(1, args.repeat) else "")
          + "; in the relations table, in brackets, the file-backed part of that peak (shared libraries' code and data "
          "mapped from disk, numba's LLVM most of it: how much of it a process maps moves with the page cache, tens of "
          "MB from hour to hour with the same code)"
          + ". 'loops' are the loop-closure constraints accepted / left in the final graph / searched "
          "(summary.json); 'health' is summary.json's `health.status` where the run writes one. "
          "Targets are those of issue 11.", ""]
    if "relations" in suites:
        md += ["## Relations logs", "",
               "Accuracy is the relations metric "
               "(Kümmerle et al. 2009) on each dataset's `.relations`. Cartographer's rows are its published figures "
               "(Hess et al. 2016, Tables II and V; wall clock on a 6-core Xeon). Loop-closure precision counts the "
               "constraints left in the final graph: 'own' against slam2d's final poses (0.2 m / 1°, Cartographer's Table IV "
               "criterion), 'ref' against the GMapping-corrected log (0.3 m / 2°; scans between its key scans take the key "
               "pose plus raw odometry).", "", table(rows, args), ""]
    if "degraded" in suites:
        md += ["## Degraded odometry", "",
               f"`degrade.py IN OUT --seed {args.degrade_seed}` (its default odometry model) of each relations log, scored "
               "on the original `.relations`; the target is Cartographer's published figure for the clean log.", "",
               degraded_table(by_suite["degraded"]), ""]
    if "dropout" in suites:
        md += ["## Dropped beams", "",
               f"`degrade.py IN OUT --seed {args.degrade_seed} --beam-dropout {BEAM_DROPOUT}` of each relations log: "
               "the degraded odometry above, and three readings in ten replaced by the log's no-return value, "
               "as dark, glossy and glass surfaces give no echo. Scored on the original `.relations`; the target is "
               "Cartographer's published figure for the clean log.", "",
               degraded_table(by_suite["dropout"], "dropped beams"), ""]
    if "thinned" in suites:
        md += ["## Fewer scans", "",
               f"`degrade.py IN OUT --seed {args.degrade_seed} --keep-every {KEEP_EVERY}` of each relations log: the "
               f"degraded odometry, and one scan in {KEEP_EVERY} kept, as a robot logging at a fifth of the rate (a fast "
               "turn is then tens of degrees between scans). Each run against slam2d's run of the whole raw log above "
               "(its scans keep their stamps; ATE after SE(2) alignment over the scans the thinned log keeps), and the "
               "relations metric over the relations whose two stamps are both scans of the thinned log (few: "
               "interpolating across the dropped scans would measure the interpolation, not the SLAM).", "",
               thinned_table(by_suite["thinned"]), ""]
    if "harsh" in suites:
        md += ["## Harsh odometry", "",
               f"`degrade.py IN OUT --seed S --rot-scale {HARSH_ODOMETRY['rot_scale']} --trans-scale "
               f"{HARSH_ODOMETRY['trans_scale']} [--keep-every N]` of each relations log, seeds "
               f"{', '.join(map(str, HARSH_SEEDS))}, every scan and one in {', '.join(map(str, HARSH_KEEP_EVERY[1:]))}: "
               "odometry far worse than the degraded copies' (each turn's rotation scaled by 1 + k, k drawn with "
               f"σ {HARSH_ODOMETRY['rot_scale']}: a turn read as half of itself, or hardly at all), as a robot whose "
               "wheels slip in fast turns. No targets: where the default config stands beyond the logs it was "
               "measured on, and whether the health report says so where it fails. Each run against slam2d's run "
               "of the whole raw log above (ATE after SE(2) alignment over the scans the copy keeps), and the "
               "relations metric over the relations whose two stamps are both scans of the copy.", "",
               harsh_table(by_suite["harsh"]), ""]
    if "no-odometry" in suites:
        md += ["## Without odometry", "",
               "The relations logs run with `--no-odometry` (the log's wheel odometry ignored; each scan predicted "
               "from the velocity of the recent trusted matches), scored on the `.relations`; the target is "
               "Cartographer's published figure for the log *with* odometry.", "",
               degraded_table(by_suite["no-odometry"], "without odometry"), ""]
    if "sparse" in suites:
        md += ["## Sparse logs", "",
               f"`make_sparse.py OUTDIR LOG --seed {args.sparse_seed}` of every corrected log in `../shared/datasets` "
               "(scans ~1 m apart, noisy synthetic odometry). ATE RMSE after SE(2) alignment against the `.gt.txt` it "
               "writes, and the scale of the best similarity alignment (above 1: the run's map is too small as a whole) "
               "with the ATE RMSE left after it; loop precision is `slam2d eval loops --ground-truth` (0.3 m / 2°) over the constraints in the "
               "final graph (in brackets: over all accepted ones), recall over the ground truth's revisit episodes. The "
               "ground truth is GMapping's solution and has errors of its own: each constraint it calls false is put "
               "to the raw scans (`slam2d/eval/scan_check.py`: the share of the scan's hits within 2 cells of the hits "
               "recorded around the other end, as the loop places it and as the ground truth does; a side wins with "
               "twice the other's share and at least 30 %). Where the sparse log comes from a relations log, the same "
               "constraints (of every seed's run) are also judged (0.3 m / 2°) against slam2d's run of that raw log in this benchmark "
               "(its row in the relations table; each sparse scan is a raw scan with identical ranges), a reference "
               "the hand-verified relations check: GMapping's corrected logs miss those relations by 0.3 m / 2° "
               "more often than slam2d's runs do (`tools/reference_check.py RUN CORRECTED_LOG`; "
               "`tools/dense_reference.py` judges any run the same way). "
               "The same corrected logs made with the seeds "
               f"{', '.join(str(x) for x in args.sparse_spread) or '(none)'} as well (`--sparse-spread`: the same "
               "scans, other odometry noise; slam2d alone) give the ATE's median and range over the seeds: one "
               "seed's figure can be luck. Where the ATE is large, is the run wrong or the ground truth? The raw "
               "scans' free-space test of the map health report, put to both trajectories on the same scans "
               "(`slam2d eval consistency RUN/trajectory.txt --against GT`): the mean share of a scan's hits inside "
               "its neighbours' free space, over all scans and over the revisits (neighbours from other passes); "
               "lower is better supported. Then the scans each trajectory alone places where they agree with their "
               "neighbours (disputed scans; the command lists the longest stretches): a run's own failure shows "
               "among the ground truth's, a jump of the ground truth among slam2d's.", "",
               sparse_table(by_suite["sparse"]), ""]
    if "clinic" in suites:
        md += ["## fr-clinic", "", "No ground truth: wall time, peak RSS, loop closures and the run's own health report.",
               "", clinic_table(by_suite["clinic"]), ""]
    if "simulated" in suites:
        md += ["## Simulated sensors and robots", "",
               "The simulator's world and path with what the real logs do not cover (`tools/bench_logs.py`, "
               "`SIM_VARIANTS`). ATE RMSE after SE(2) alignment and loop precision (0.3 m / 2°) against the "
               "simulator's ground truth; the odometry's ATE for scale. The scale of the best similarity alignment "
               "(above 1: the map is too small as a whole) shows a bias along the path that the SE(2) ATE mixes "
               "with everything else; the odometry's is beside its ATE. No targets: these show where the default "
               "config stands on sensors it was not tuned on.", "", simulated_table(by_suite["simulated"]), ""]
    if any("rerun" in row for row in rows):
        md += ["Cost of `--rerun` (same run, recording to an .rrd):", "",
               "| dataset | wall s without | wall s with --rerun | overhead | .rrd MB | peak RSS MB with |", "|---|---|---|---|---|---|"]
        for row in rows:
            if "rerun" in row:
                rv = row["rerun"]
                md.append(f"| {row['dataset']} | {row['slam2d']['wall_s']:.1f} | {rv['wall_s']:.1f} | {100 * rv['overhead']:+.0f} % | "
                          f"{rv['rrd_mb']:.0f} | {rv['peak_rss_mb']:.0f} |")
        md.append("")
    for row in rows:
        a = row["slam2d"].get("ate_vs_corrected_log")
        if a:
            md.append(f"- {row['dataset']}: ATE against the GMapping-corrected log: RMSE {a['trans_m']['rmse']:.3f} m "
                      f"over {a['pairs']} key scans; timings p50/p99 per scan: "
                      + ", ".join(f"{k} {v['p50_ms']:.2f}/{v['p99_ms']:.2f} ms" for k, v in row['slam2d']['timings'].items()
                                  if isinstance(v, dict) and k in ('frontend', 'match', 'refine', 'insert')))
        t = row["slam2d"].get("timings", {})
        if "cpu_s" in t.get("add_scan", {}):
            worker = t.get("global_worker_cpu_s")
            md.append(f"  add_scan: {t['add_scan']['total_s']:.1f} s in all, {t['add_scan']['cpu_s']:.1f} s of it on the "
                      f"caller's CPU (the rest it waited, mostly for the interpreter lock)"
                      + (f"; global SLAM's worker thread: {worker:.1f} s CPU" if worker is not None else ""))
        lo = row.get("loops", {}).get("reference", {})
        if lo.get("recall"):
            rc = lo["recall"]
            md.append(f"  loop-closure recall against the reference's revisits: {rc['closed']} of {rc['episodes']} episodes")
        for p in row.get("plots", []):
            md.append(f"  ![{p}]({os.path.relpath(outdir / p, Path(args.markdown).parent)})")
    Path(args.markdown).write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
