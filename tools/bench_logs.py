"""Logs the benchmark generates from ../shared/datasets (degraded and sparse copies), kept in a cache
folder outside the repository, one subfolder per generating tool, seed and tool sha256."""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path


def default_cache() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "slam2d-benchmark"


def _sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]


def cached(cache: Path, tool: Path, seed: int, name: str, source: Path, make) -> Path:
    """The folder ``cache/<tool>-seed<seed>-<tool sha256>/<name>``, filled by ``make(folder)`` when it
    is missing (or was made from a different source file) and reused otherwise."""
    d = Path(cache) / f"{tool.stem}-seed{seed}-{_sha(tool)}" / name
    st = Path(source).stat()
    key = {"tool": str(tool), "seed": seed, "source": str(source), "source_size": st.st_size,
           "source_mtime": st.st_mtime}
    done = d / "DONE.json"
    if done.exists() and json.loads(done.read_text()) == key:
        return d
    tmp = d.with_name(d.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    make(tmp)
    (tmp / "DONE.json").write_text(json.dumps(key))
    shutil.rmtree(d, ignore_errors=True)
    os.replace(tmp, d)
    return d


def _tool(cmd: list) -> None:
    r = subprocess.run([sys.executable, *map(str, cmd)], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"benchmark: {' '.join(map(str, cmd))} failed: {r.stderr.strip()}")


#: ``degrade.py --beam-dropout``: the share of readings the dropped-beams copies turn into no-returns
BEAM_DROPOUT = 0.3


#: ``degrade.py --keep-every``: the thinned copies keep one scan in this many
KEEP_EVERY = 5


def degraded_log(args, name: str, beam_dropout: float = 0.0, keep_every: int = 1, seed: int | None = None,
                 odometry: dict | None = None) -> Path:
    """``degrade.py IN OUT --seed 1`` (its default odometry model) of a relations log, cached; with
    ``beam_dropout``, also that share of readings replaced by the log's no-return value
    (``--beam-dropout``), with ``keep_every``, only every that many-th scan kept (``--keep-every``),
    with ``seed`` another seed than ``--degrade-seed``, with ``odometry`` (``HARSH_ODOMETRY``) its
    ``--rot-scale`` and ``--trans-scale``, each in a folder of its own."""
    tool = args.shared / "tools" / "degrade.py"
    log = args.shared / "datasets" / name / f"{name}.clf.bz2"
    seed = args.degrade_seed if seed is None else seed
    extra = ["--rot-scale", odometry["rot_scale"], "--trans-scale", odometry["trans_scale"]] if odometry else []
    extra += ["--beam-dropout", beam_dropout] if beam_dropout else []
    extra += ["--keep-every", keep_every] if keep_every > 1 else []
    folder = name + ("-harsh" if odometry else "") + (f"-dropout{round(beam_dropout * 100)}" if beam_dropout else "") + (
        f"-every{keep_every}" if keep_every > 1 else "")
    d = cached(args.cache, tool, seed, folder, log,
               lambda tmp: _tool([tool, log, tmp / f"{name}.clf", "--seed", seed, *extra]))
    return d / f"{name}.clf"


def dropout_log(args, name: str) -> Path:
    """The degraded copy with ``BEAM_DROPOUT`` of the readings dropped as well (dark, glossy and glass
    surfaces that return no echo)."""
    return degraded_log(args, name, BEAM_DROPOUT)


def thinned_log(args, name: str) -> Path:
    """The degraded copy with only every ``KEEP_EVERY``-th scan kept: a robot logging its scans at a
    fifth of the rate, so that a fast turn is tens of degrees between scans."""
    return degraded_log(args, name, keep_every=KEEP_EVERY)


#: the harsh copies: ``degrade.py``'s odometry model with these rotation and translation scales (its
#: defaults: 0.15 and 0.03), so that a turn's odometry can miss most of the turn, at each of these rates
#: (one scan in N kept) and seeds
HARSH_ODOMETRY = {"rot_scale": 0.5, "trans_scale": 0.1}
HARSH_KEEP_EVERY = (1, 3)
HARSH_SEEDS = (4, 5)


def harsh_log(args, name: str, seed: int, keep_every: int = 1) -> Path:
    """``degrade.py IN OUT --seed SEED --rot-scale 0.5 --trans-scale 0.1 [--keep-every N]`` of a relations
    log, cached: odometry far worse than the degraded copies' (a turn's rotation scaled by 1 + k, k of
    σ 0.5: a turn read as half of itself, or hardly at all), at the full rate or a lower one."""
    return degraded_log(args, name, keep_every=keep_every, seed=seed, odometry=HARSH_ODOMETRY)


def corrected_logs(datasets: Path) -> list[tuple[str, Path]]:
    """(dataset folder name, path) of every GMapping-corrected log under ``datasets``."""
    pat = re.compile(r"(\.gfs\.log|-corrected\.log(\.gz)?)$")
    return sorted((p.parent.name, p) for p in datasets.rglob("*") if p.is_file() and pat.search(p.name))


def sparse_log(args, name: str, corrected: Path, seed: int | None = None) -> tuple[Path, Path]:
    """(NAME.clf, NAME.gt.txt) that ``make_sparse.py OUTDIR LOG --seed SEED`` writes (default
    ``args.sparse_seed``, 7), cached."""
    tool = args.shared / "tools" / "make_sparse.py"
    seed = args.sparse_seed if seed is None else seed
    d = cached(args.cache, tool, seed, name, corrected, lambda tmp: _tool([tool, tmp, corrected, "--seed", seed]))
    clf, gt = sorted(d.glob("*.clf")), sorted(d.glob("*.gt.txt"))
    if len(clf) != 1 or len(gt) != 1:
        raise SystemExit(f"benchmark: {d}: expected one .clf and one .gt.txt from make_sparse.py")
    return clf[0], gt[0]


#: simulated sensors and robots the real logs do not cover (``slam2d.io.simulator.SimConfig`` fields
#: that differ from the bundled dataset's), each a log slam2d was not tuned on
SIM_VARIANTS = {
    "short-range": {"beams": 682, "max_range": 4.0, "rate_hz": 10.0},   # a 4 m scanner in 2.5 m corridors
    "fast": {"speed": 2.0, "turn_rate": 2.5},                            # 0.4 m and up to 29° between scans
    "bad-odometry": {"odom_scale_error": 0.08, "odom_rot_scale_error": 0.15, "odom_rot_sigma": 0.03},
    "dense": {"beams": 1081, "max_range": 30.0, "rate_hz": 20.0},      # a modern scanner at 20 Hz
    # scanners whose range ends inside the corridors and that see no wall behind: a 240°, 5.6 m one
    # (Hokuyo URG-04LX class) at 10 Hz, and a 180°, 1°, 8 m one with 3 cm noise at 5 Hz
    "fov-240": {"beams": 683, "fov_deg": 240.0, "max_range": 5.6, "rate_hz": 10.0},
    "fov-180": {"beams": 181, "fov_deg": 180.0, "max_range": 8.0, "range_sigma": 0.03},
}


def sim_log(args, name: str) -> Path:
    """The simulator's run with ``SIM_VARIANTS[name]`` as MCAP (its /ground_truth included), cached on
    the simulator's source."""
    from slam2d.io import simulator

    src = Path(simulator.__file__)

    def make(tmp):
        simulator.write_simulation(tmp / f"{name}.mcap", simulator.SimConfig(**SIM_VARIANTS[name]))

    params = hashlib.sha256(json.dumps(SIM_VARIANTS[name], sort_keys=True).encode()).hexdigest()[:8]
    d = cached(args.cache, src, 0, f"{name}-{params}", src, make)
    return d / f"{name}.mcap"
