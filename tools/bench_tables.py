"""The markdown tables of BENCHMARKS.md: one per suite, issue 11's targets beside the results."""
from __future__ import annotations

import numpy as np

CARTOGRAPHER = {  # Hess et al. 2016: Table II (abs trans m, abs rot deg, mean ± std), Table V (wall s)
    "aces": {"trans": (0.0375, 0.0426), "rot": (0.373, 0.469), "wall_s": 41},
    "intel": {"trans": (0.0229, 0.0239), "rot": (0.453, 1.335), "wall_s": 179},
    "fr079": {"trans": (0.0452, 0.0354), "rot": (0.538, 0.718), "wall_s": 62},
}


TARGETS = {  # issue 11, "What it must show"
    "degraded_trans_m": {n: c["trans"][0] for n, c in CARTOGRAPHER.items()},  # Cartographer on the clean log
    "sparse_ate_rmse_m": 0.15,
    "clinic": {"peak_rss_mb": 1024.0, "wall_s": 60.0, "health": "OK"},
}


def fmt(ms):
    return f"{ms[0]:.4f} ± {ms[1]:.4f}"


def loops_txt(s) -> str:
    lc = s.get("loop_closure") or {}
    return f"{lc.get('accepted', '—')} / {lc.get('in_final_graph', '—')} / {lc.get('candidates_searched', '—')}" if lc else "—"


def health_txt(s) -> str:
    h = s.get("health")
    return str(h.get("status", "?")) if isinstance(h, dict) else "—"


def _rel(m) -> str:
    return f"{fmt((m['abs_trans_m']['mean'], m['abs_trans_m']['std']))} | {m['abs_rot_deg']['mean']:.3f} ± {m['abs_rot_deg']['std']:.3f}"


def _rss(run) -> str:
    """Peak RSS MB, with its file-backed part in brackets where the benchmark measured it."""
    f = run.get("peak_rss_file_mb")
    return f"{run['peak_rss_mb']:.0f}" + (f" ({f:.0f} file)" if f is not None else "")


def _pct(p) -> str:
    """'100.0 % of 12' from a precision record of slam2d.eval.loops; '— of 0' when none was judged."""
    n = p["true"] + p["false"]
    return f"{100 * p['precision']:.1f} % of {n}" if p["precision"] is not None else "— of 0"


def _met(ok) -> str:
    return "—" if ok is None else ("yes" if ok else "**no**")


def table(rows, args) -> str:
    lines = ["| dataset | system | scans | data s | wall s | wall ÷ peer | real-time × | peak RSS MB | add_scan p50 / p99 / max ms | trans abs m (mean ± std) | rot abs ° (mean ± std) | loops accepted / final / searched | precision (final graph) | health |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        n = row["dataset"]
        s = row["slam2d"]
        lo = row.get("loops")
        prec = "—"
        if lo:
            own = lo["own"]["final_graph"]["precision"]
            prec = f"{100 * own:.1f} % own" if own is not None else "—"
            refp = lo.get("reference", {}).get("final_graph", {}).get("precision")
            if refp is not None:
                prec += f", {100 * refp:.1f} % ref"
        k = row.get("karto", {})
        ratio = f"{s['wall_s'] / k['wall_s']:.1f}" if k.get("wall_s") else "—"
        lat = s.get("timings", {}).get("add_scan")
        lat_txt = f"{lat['p50_ms']:.1f} / {lat['p99_ms']:.1f} / {lat['max_ms']:.0f}" if lat else "—"
        lines.append(f"| {n} | slam2d ({s['mode']}) | {s['scans']} | {s['duration_s']:.1f} | {s['wall_s']:.1f} | {ratio} | "
                     f"{s['real_time_factor']:.1f} | {_rss(s)} | {lat_txt} | {_rel(s['relations'])} | "
                     f"{loops_txt(s)} | {prec} | {health_txt(s)} |")
        if "relations" in k:
            lines.append(f"| {n} | Karto peer (sequential) | {s['scans']} | {s['duration_s']:.1f} | {k['wall_s']:.1f} | 1.0 | "
                         f"{s['duration_s'] / k['wall_s']:.1f} | {_rss(k)} | | {_rel(k['relations'])} | — | — | |")
        om = row["odometry"]["relations"]
        lines.append(f"| {n} | raw odometry | {s['scans']} | | | | | | | {_rel(om)} | | | |")
        c = CARTOGRAPHER.get(n)
        if c:
            lines.append(f"| {n} | Cartographer (published, 6-core Xeon) | | | {c['wall_s']} | | | | | {fmt(c['trans'])} | "
                         f"{c['rot'][0]:.3f} ± {c['rot'][1]:.3f} | | | |")
    return "\n".join(lines)


def degraded_table(rows, kind: str = "degraded") -> str:
    lines = [f"| dataset ({kind}) | system | scans | wall s | peak RSS MB | trans abs m (mean ± std) | rot abs ° (mean ± std) | target: trans ≤ Cartographer clean | met | loops accepted / final / searched | health |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        n, s = row["dataset"], row["slam2d"]
        target = TARGETS["degraded_trans_m"].get(n)
        met = None if target is None else s["relations"]["abs_trans_m"]["mean"] <= target
        tt = f"{target:.4f} m" if target is not None else "—"
        lines.append(f"| {n} | slam2d ({s['mode']}) | {s['scans']} | {s['wall_s']:.1f} | {s['peak_rss_mb']:.0f} | "
                     f"{_rel(s['relations'])} | {tt} | {_met(met)} | {loops_txt(s)} | {health_txt(s)} |")
        k = row.get("karto", {})
        if "relations" in k:
            kmet = None if target is None else k["relations"]["abs_trans_m"]["mean"] <= target
            lines.append(f"| {n} | Karto peer (sequential) | {s['scans']} | {k['wall_s']:.1f} | {k['peak_rss_mb']:.0f} | "
                         f"{_rel(k['relations'])} | {tt} | {_met(kmet)} | — | |")
    return "\n".join(lines)


def _vs_full(a) -> str:
    """'0.026 / 0.077 | 0.34': a thinned log's run against slam2d's run of the whole log (ATE RMSE /
    max m | rotation RMSE °)."""
    if not a:
        return "— | —"
    return f"{a['trans_m']['rmse']:.3f} / {a['trans_m']['max']:.3f} | {a['rot_deg']['rmse']:.2f}"


def _rel_exact(m) -> str:
    """'56; 0.0482 ± 0.0312; 0.594': how many relations were scored and their mean errors (m; °)."""
    if not m:
        return "—"
    n = (m.get("counts") or {}).get("exact", 0)
    if not n:
        return "0"
    return f"{n}; {fmt((m['abs_trans_m']['mean'], m['abs_trans_m']['std']))}; {m['abs_rot_deg']['mean']:.3f}"


def thinned_table(rows) -> str:
    lines = ["| dataset (thinned) | system | scans | wall s | peak RSS MB | vs slam2d's run of the whole log: ATE RMSE / max m | its rot RMSE ° | relations at kept stamps: n; trans abs m (mean ± std); rot abs ° (mean) | loops accepted / final / searched | health |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        lines += _vs_full_rows(row["dataset"], row)
    return "\n".join(lines)


def _vs_full_rows(lead: str, row, rss: bool = True) -> list[str]:
    """A thinned or harsh copy's lines (slam2d's, then the peer's): ``lead``, the leading cells; the
    run against slam2d's run of the whole log, the relations at kept stamps, loops and health
    (``rss``: with a peak RSS column after the wall time)."""
    s, k = row["slam2d"], row.get("karto", {})

    def mid(r):
        return f"{r['wall_s']:.1f} | " + (f"{r['peak_rss_mb']:.0f} | " if rss else "") + \
            f"{_vs_full(r.get('vs_full_log'))} | {_rel_exact(r.get('relations_exact'))}"
    lines = [f"| {lead} | slam2d ({s['mode']}) | {s['scans']} | {mid(s)} | {loops_txt(s)} | {health_txt(s)} |"]
    if "trajectory" in k:
        lines.append(f"| {lead} | Karto peer (sequential) | {s['scans']} | {mid(k)} | — | |")
    return lines


def harsh_table(rows) -> str:
    """The harsh copies: one row per log, rate and seed (slam2d, then the peer), against slam2d's run
    of the whole raw log and on the relations whose two stamps the copy keeps."""
    lines = ["| dataset (harsh odometry) | one scan in | seed | system | scans | wall s | vs slam2d's run of the whole log: ATE RMSE / max m | its rot RMSE ° | relations at kept stamps: n; trans abs m (mean ± std); rot abs ° (mean) | loops accepted / final / searched | health |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        lines += _vs_full_rows(f"{row['dataset']} | {row['keep_every']} | {row['seed']}", row, rss=False)
    return "\n".join(lines)


def sparse_table(rows) -> str:
    target = TARGETS["sparse_ate_rmse_m"]
    lines = [f"| dataset (sparse) | system | scans | wall s | peak RSS MB | ATE RMSE m | target ≤ {target} m | met | scale (Sim(2)); ATE RMSE after it m | ATE RMSE over the seeds: median (min–max) m; seeds whose health is not OK | loops accepted / final / searched | loop precision vs ground truth, final graph (all accepted; the other seeds' final graphs) | its misses, by the raw scans: loop right / truth right / both fit / undecided | loop precision vs slam2d's run of the raw log, final graph (the other seeds') | recall (revisit episodes closed) | free-space violation, all scans / revisits: slam2d; ground truth; disputed scans | health |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        n, s = row["dataset"], row["slam2d"]
        d = s.get("loops_vs_dense_run")
        dense = _pct(d["final_graph"]) + _other_seeds(s.get("loops_vs_dense_run_by_seed")) if d else "—"
        rmse = s["ate"]["trans_m"]["rmse"]
        g = s.get("loops_vs_ground_truth")
        prec = rec = by_scans = "—"
        if g:
            prec = f"{_pct(g['final_graph'])} ({_pct(g['accepted'])}){_other_seeds(s.get('loops_vs_ground_truth_by_seed'))}"
            b = g["final_graph"].get("false_by_scans")
            if b is not None:
                by_scans = f"{b['constraint']} / {b['ground_truth']} / {b.get('both', '—')} / {b['undecided']}"
            rc = g["recall"]
            rec = f"{rc['closed']} of {rc['episodes']}"
        lines.append(f"| {n} | slam2d ({s['mode']}) | {s['scans']} | {s['wall_s']:.1f} | {s['peak_rss_mb']:.0f} | "
                     f"{rmse:.3f} | ≤ {target} | {_met(rmse <= target)} | {_scale(s['ate'])} | {_spread(s.get('ate_rmse_by_seed'), s.get('health_by_seed'))} | "
                     f"{loops_txt(s)} | {prec} | {by_scans} | {dense} | {rec} | {_consistency(s.get('consistency_vs_ground_truth'))} | "
                     f"{health_txt(s)} |")
        k = row.get("karto", {})
        if "ate" in k:
            kr = k["ate"]["trans_m"]["rmse"]
            lines.append(f"| {n} | Karto peer (sequential) | {s['scans']} | {k['wall_s']:.1f} | {k['peak_rss_mb']:.0f} | "
                         f"{kr:.3f} | ≤ {target} | {_met(kr <= target)} | {_scale(k['ate'])} | — | — | — | — | — | — | — | |")
    return "\n".join(lines)


def _scale(a: dict) -> str:
    """'1.0090; 0.743': the similarity alignment's scale (above 1: the run's map is too small) and
    the ATE RMSE left after it (``slam2d.eval.ate``)."""
    if "scale" not in a:
        return "—"
    return f"{a['scale']:.4f}; {a['sim2_trans_m']['rmse']:.3f}"


def _other_seeds(by_seed: dict | None) -> str:
    """'; seeds 8, 9: 98.0 % of 593, 98.4 % of 575': the final graph's precision of the runs after
    the first (the ``--sparse-spread`` seeds), or nothing."""
    rest = [(k, v) for k, v in list((by_seed or {}).items())[1:] if v is not None]
    if not rest:
        return ""
    return f"; seeds {', '.join(k for k, _ in rest)}: {', '.join(_pct(v) for _, v in rest)}"


def _consistency(c: dict | None) -> str:
    """'slam2d all / revisits; ground truth all / revisits' mean free-space violation shares, then the
    disputed scans: how many agree with their neighbours at slam2d's poses only, and at the ground
    truth's only, with the longest such stretch of each."""
    if not c or "slam2d" not in c or "ground_truth" not in c:
        return "—"

    def pair(x):
        return " / ".join("—" if x[k] is None else f"{x[k]:.4f}" for k in ("mean_violation", "revisit_mean_violation"))

    out = f"{pair(c['slam2d'])}; {pair(c['ground_truth'])}"
    d = c["ground_truth"].get("disputes")
    if d is not None:  # 'here' is the ground truth, 'there' slam2d (the first trajectory)
        def longest(side):
            s = next((s for s in d["stretches"] if s["agree_with"] == side), None)
            return f" (longest: scans {s['scans'][0]}–{s['scans'][1]})" if s and s["nodes"] > 1 else ""

        out += (f"; disputed scans: {d['agree_only_there']} at slam2d's poses only{longest('there')}, "
                f"{d['agree_only_here']} at the ground truth's only{longest('here')}")
    return out


def _spread(by_seed: dict | None, health: dict | None = None) -> str:
    """'median (min–max) over N seeds' of the ATE RMSE by make_sparse.py seed, and each seed whose
    run's health report is not OK with its ATE and status."""
    if not by_seed or len(by_seed) < 2:
        return "—"
    v = np.array(list(by_seed.values()), dtype=float)
    text = f"{np.median(v):.3f} ({v.min():.3f}–{v.max():.3f}) over {len(v)}"
    flagged = [f"seed {k}: {by_seed[k]:.3f}, {st}" for k, st in (health or {}).items() if st not in (None, "OK")]
    return text + (f"; {'; '.join(flagged)}" if flagged else "")


def simulated_table(rows) -> str:
    from bench_logs import SIM_VARIANTS

    lines = ["| variant | what differs | scans | wall s | peak RSS MB | ATE RMSE m | scale (Sim(2)); ATE RMSE after it m | odometry ATE RMSE m; its scale | loops accepted / final / searched | loop precision vs ground truth, final graph (all accepted) | health |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        n, s = row["dataset"], row["slam2d"]
        what = ", ".join(f"{k} {v:g}" for k, v in SIM_VARIANTS.get(n, {}).items())
        g = s.get("loops_vs_ground_truth")
        prec = f"{_pct(g['final_graph'])} ({_pct(g['accepted'])})" if g else "—"
        odo = row.get("odometry", {}).get("ate")
        odo_txt = "—" if not odo else f"{odo['trans_m']['rmse']:.3f}" + (f"; {odo['scale']:.4f}" if "scale" in odo else "")
        lines.append(f"| {n} | {what} | {s['scans']} | {s['wall_s']:.1f} | {s['peak_rss_mb']:.0f} | "
                     f"{s['ate']['trans_m']['rmse']:.3f} | {_scale(s['ate'])} | {odo_txt} | {loops_txt(s)} | {prec} | {health_txt(s)} |")
    return "\n".join(lines)


def clinic_table(rows) -> str:
    t = TARGETS["clinic"]
    lines = [f"| dataset | scans | data s | wall s (target ≤ {t['wall_s']:.0f}) | peak RSS MB (target ≤ {t['peak_rss_mb']:.0f}) | loops accepted / final / searched | health (target {t['health']}) | met |",
             "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        s = row["slam2d"]
        h = health_txt(s)
        met = s["wall_s"] <= t["wall_s"] and s["peak_rss_mb"] <= t["peak_rss_mb"] and h == t["health"]
        lines.append(f"| {row['dataset']} | {s['scans']} | {s['duration_s']:.1f} | {s['wall_s']:.1f} | {s['peak_rss_mb']:.0f} | "
                     f"{loops_txt(s)} | {h} | {_met(met)} |")
    return "\n".join(lines)

