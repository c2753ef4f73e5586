#!/usr/bin/env python3
"""Benchmark slam2d on every dataset in ../shared/datasets and write BENCHMARKS.md + benchmarks.json.

  python tools/benchmark.py                      # all datasets, default config
  python tools/benchmark.py --peers              # also run the Karto peer (../shared/tools/peer_karto.py)
  python tools/benchmark.py --datasets intel --jobs 2 --config configs/default.yaml

Each run is a whole `slam2d run` process: wall time and peak memory are what the OS
reports for it (os.wait4). Numba's cache is warmed by a short run first, so compile time
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
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SHARED = ROOT.parent / "shared"
CARTOGRAPHER = {  # Hess et al. 2016: Table II (abs trans m, abs rot deg, mean ± std), Table V (wall s)
    "aces": {"trans": (0.0375, 0.0426), "rot": (0.373, 0.469), "wall_s": 41},
    "intel": {"trans": (0.0229, 0.0239), "rot": (0.453, 1.335), "wall_s": 179},
    "fr079": {"trans": (0.0452, 0.0354), "rot": (0.538, 0.718), "wall_s": 62},
}
REFERENCE_LOGS = {"intel": "intel.gfs.log", "aces": "aces-corrected.log.gz", "fr079": "freiburg-079-corrected.log.gz"}


def timed(cmd: list[str]) -> dict:
    """Run a process; wall time and its own peak RSS (MB)."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = "", ""
    _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    out, err = p.stdout.read(), p.stderr.read()
    p.returncode = os.waitstatus_to_exitcode(status)
    return {"wall_s": wall, "peak_rss_mb": usage.ru_maxrss / 1024.0, "returncode": p.returncode, "stdout": out,
            "stderr": err}


def relations_of(traj: Path, rel: Path) -> dict:
    from slam2d.eval.relations import read_relations, relations_metric
    from slam2d.io.trajectory import read_tum

    t, poses, _ = read_tum(traj)
    return relations_metric(t, poses, read_relations(rel))


def _median_run(runs: list[dict]) -> dict:
    """The run with the median wall time (the higher of the two middle ones), peak RSS the largest seen."""
    ok = [r for r in runs if r["returncode"] == 0] or runs
    pick = dict(sorted(ok, key=lambda r: r["wall_s"])[len(ok) // 2])
    pick["peak_rss_mb"] = max(r["peak_rss_mb"] for r in ok)
    return pick


def bench_dataset(name: str, args, outdir: Path) -> dict:
    d = SHARED / "datasets" / name
    log = d / f"{name}.clf.bz2"
    rel = d / f"{name}.relations"
    slam = [sys.executable, "-m", "slam2d.cli", "run", str(log), "--no-progress"]
    if args.config:
        slam += ["--config", str(args.config)]
    row: dict = {"dataset": name}
    peer = SHARED / "tools" / "peer_karto.py"
    out = outdir / f"{name}_karto.txt"
    peer_cmd = [sys.executable, str(peer), str(log), "--out", str(out)]
    # slam2d and the peer alternate --repeat times; each reports its median wall time, so a
    # machine whose speed drifts during the benchmark favours neither
    runs, peer_runs = [], []
    for _ in range(max(1, args.repeat)):
        runs.append(timed(slam + ["--out", str(outdir / name)] + args.extra))
        if runs[-1]["returncode"] != 0:
            raise SystemExit(f"{name}: slam2d run failed: {runs[-1]['stderr'].strip()}")
        if args.peers:
            peer_runs.append(timed(peer_cmd))
    r = _median_run(runs)
    summary = json.loads((outdir / name / "summary.json").read_text())
    m = relations_of(outdir / name / "trajectory.txt", rel)
    row["slam2d"] = {"wall_s": r["wall_s"], "wall_s_runs": [round(x["wall_s"], 2) for x in runs],
                     "peak_rss_mb": r["peak_rss_mb"], "scans": summary["scans"],
                     "duration_s": summary["duration_s"], "real_time_factor": summary["duration_s"] / r["wall_s"],
                     "relations": m, "timings": summary.get("timings", {}), "mode": summary.get("mode"),
                     "loop_closure": summary.get("loop_closure")}
    if args.rerun:
        rrd = outdir / f"{name}.rrd"
        rv = timed(slam + ["--out", str(outdir / f"{name}_rerun"), "--rerun", str(rrd)] + args.extra)
        if rv["returncode"] == 0:
            row["rerun"] = {"wall_s": rv["wall_s"], "peak_rss_mb": rv["peak_rss_mb"], "rrd_mb": rrd.stat().st_size / 2 ** 20,
                            "overhead": rv["wall_s"] / r["wall_s"] - 1.0}
    timed(slam + ["--out", str(outdir / f"{name}_odometry"), "--odometry-only"])
    row["odometry"] = {"relations": relations_of(outdir / f"{name}_odometry" / "trajectory.txt", rel)}
    if args.peers:
        p = _median_run(peer_runs)
        if p["returncode"] == 0:
            row["karto"] = {"wall_s": p["wall_s"], "peak_rss_mb": p["peak_rss_mb"], "relations": relations_of(out, rel),
                            "wall_s_runs": [round(x["wall_s"], 2) for x in peer_runs]}
        else:
            row["karto"] = {"error": p["stderr"].strip().splitlines()[-1] if p["stderr"].strip() else "failed"}
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


def fmt(ms):
    return f"{ms[0]:.4f} ± {ms[1]:.4f}"


def table(rows, args) -> str:
    lines = ["| dataset | system | scans | data s | wall s | real-time × | peak RSS MB | trans abs m (mean ± std) | rot abs ° (mean ± std) | loop closures (final / searched) | precision (final graph) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        n = row["dataset"]
        s = row["slam2d"]
        m = s["relations"]
        lc = s.get("loop_closure") or {}
        lo = row.get("loops")
        prec = "—"
        if lo:
            own = lo["own"]["final_graph"]["precision"]
            prec = f"{100 * own:.1f} % own" if own is not None else "—"
            refp = lo.get("reference", {}).get("final_graph", {}).get("precision")
            if refp is not None:
                prec += f", {100 * refp:.1f} % ref"
        lc_txt = f"{lc.get('in_final_graph', '—')} of {lc.get('candidates_searched', '—')}" if lc else "—"
        lines.append(f"| {n} | slam2d ({s['mode']}) | {s['scans']} | {s['duration_s']:.1f} | {s['wall_s']:.1f} | "
                     f"{s['real_time_factor']:.1f} | {s['peak_rss_mb']:.0f} | "
                     f"{fmt((m['abs_trans_m']['mean'], m['abs_trans_m']['std']))} | "
                     f"{m['abs_rot_deg']['mean']:.3f} ± {m['abs_rot_deg']['std']:.3f} | "
                     f"{lc_txt} | {prec} |")
        if "karto" in row and "relations" in row["karto"]:
            k = row["karto"]
            km = k["relations"]
            lines.append(f"| {n} | Karto peer (sequential) | {s['scans']} | {s['duration_s']:.1f} | {k['wall_s']:.1f} | "
                         f"{s['duration_s'] / k['wall_s']:.1f} | {k['peak_rss_mb']:.0f} | "
                         f"{fmt((km['abs_trans_m']['mean'], km['abs_trans_m']['std']))} | "
                         f"{km['abs_rot_deg']['mean']:.3f} ± {km['abs_rot_deg']['std']:.3f} | — | — |")
        om = row["odometry"]["relations"]
        lines.append(f"| {n} | raw odometry | {s['scans']} | | | | | {fmt((om['abs_trans_m']['mean'], om['abs_trans_m']['std']))} | "
                     f"{om['abs_rot_deg']['mean']:.3f} ± {om['abs_rot_deg']['std']:.3f} | | |")
        c = CARTOGRAPHER.get(n)
        if c:
            lines.append(f"| {n} | Cartographer (published, 6-core Xeon) | | | {c['wall_s']} | | | {fmt(c['trans'])} | "
                         f"{c['rot'][0]:.3f} ± {c['rot'][1]:.3f} | | |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", default=None, help="comma-separated names (default: every folder in ../shared/datasets)")
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--peers", action="store_true", help="also run ../shared/tools/peer_karto.py (needs karto-scanmatcher)")
    ap.add_argument("--rerun", action="store_true", help="also time each run with --rerun (recording cost and size)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="time slam2d (and the peer) this many times, alternating, and report the median wall time")
    ap.add_argument("--jobs", type=int, default=1, help="datasets run in parallel (default 1: timings undisturbed)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks"), help="folder for runs and plots")
    ap.add_argument("--title", default="Benchmarks", help="heading of the markdown file")
    ap.add_argument("--markdown", default=str(ROOT / "BENCHMARKS.md"))
    ap.add_argument("--json", default=str(ROOT / "benchmarks.json"))
    ap.add_argument("--extra", default="", help="extra arguments for slam2d run, e.g. '--no-loop-closure' (use --extra=...)")
    args = ap.parse_args(argv)
    args.extra = args.extra.split()
    if not (SHARED / "datasets").is_dir():
        print(f"benchmark: {SHARED / 'datasets'} not found", file=sys.stderr)
        return 2
    names = args.datasets.split(",") if args.datasets else sorted(
        p.name for p in (SHARED / "datasets").iterdir() if (p / f"{p.name}.clf.bz2").exists())
    outdir = Path(args.out)
    (outdir / "runs").mkdir(parents=True, exist_ok=True)
    # warm numba's cache so compile time is not timed
    first = SHARED / "datasets" / names[0] / f"{names[0]}.clf.bz2"
    subprocess.run([sys.executable, "-m", "slam2d.cli", "run", str(first), "--out", str(outdir / "runs" / "warmup"),
                    "--max-scans", "300", "--no-progress"], check=True, capture_output=True)
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        rows = list(ex.map(lambda n: bench_dataset(n, args, outdir / "runs"), names))
    for row in rows:
        for p in row.get("plots", []):
            if (outdir / "runs" / p).exists():
                os.replace(outdir / "runs" / p, outdir / p)
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
            "python": platform.python_version(), "config": os.path.relpath(args.config, ROOT),
            "extra_args": args.extra, "jobs": args.jobs,
            "repeat": args.repeat}
    Path(args.json).write_text(json.dumps({"meta": meta, "rows": rows}, indent=2, default=float) + "\n")
    flags = "".join(f" --{f}" for f in ("peers", "rerun") if getattr(args, f))
    flags += f" --repeat {args.repeat}" if args.repeat > 1 else ""
    md = [f"# {args.title}", "",
          f"`python tools/benchmark.py{flags}` on {meta['date']} ({meta['machine']}, "
          f"Python {meta['python']}), config `{meta['config']}`{', slam2d run ' + ' '.join(args.extra) if args.extra else ''}. "
          "Wall time and peak RSS are those of the whole process"
          + (f" (median of {args.repeat} runs, slam2d and the peer alternating)" if args.repeat > 1 else "")
          + "; accuracy is the relations metric "
          "(Kümmerle et al. 2009) on each dataset's `.relations`. Cartographer's rows are its published figures "
          "(Hess et al. 2016, Tables II and V; wall clock on a 6-core Xeon). Loop-closure precision counts the "
          "constraints left in the final graph: 'own' against slam2d's final poses (0.2 m / 1°, Cartographer's Table IV "
          "criterion), 'ref' against the GMapping-corrected log (0.3 m / 2°; scans between its key scans take the key "
          "pose plus raw odometry).", "", table(rows, args), ""]
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
