"""Evaluation plots (matplotlib, PNG): trajectory vs reference, error over time, loop closures on the map."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path):
    """Write ``fig`` to ``path`` as PNG, its folder made first; a folder that cannot be made or written is
    the user's one-line error (``UsageError``), not a traceback."""
    from slam2d.errors import UsageError

    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    except OSError as e:
        raise UsageError(f"{path}: cannot write the plot ({e.strerror or e})") from None
    finally:
        plt.close(fig)


def plot_trajectories(path, est: np.ndarray, ref: np.ndarray | None = None, title="", labels=("slam2d", "reference")):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 7))
    if ref is not None:
        ax.plot(ref[:, 0], ref[:, 1], "-", color="0.6", lw=1.2, label=labels[1])
    ax.plot(est[:, 0], est[:, 1], "-", color="tab:blue", lw=0.8, label=labels[0])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.legend(loc="best")
    fig.tight_layout()
    _save(plt, fig, path)


def plot_error_over_time(path, t: np.ndarray, err: np.ndarray, ylabel="error [m]", title=""):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 3))
    ax.plot(t - t[0], err, ".", ms=2)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(plt, fig, path)


def read_map(run_dir: Path):
    """(image rows top-first, resolution, origin) of RUN_DIR/map.pgm + map.yaml, or None."""
    import yaml

    from slam2d.grid.map_export import read_pgm

    y = run_dir / "map.yaml"
    if not y.exists():
        return None
    meta = yaml.safe_load(y.read_text())
    img = read_pgm(run_dir / meta["image"])
    return img, float(meta["resolution"]), meta["origin"]


def plot_loops(path, run_dir: Path, poses: np.ndarray, constraints: list[dict], key: str, title=""):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 8))
    m = read_map(run_dir)
    if m is not None:
        img, res, origin = m
        h, w = img.shape
        ax.imshow(img, cmap="gray", vmin=0, vmax=255,
                  extent=(origin[0], origin[0] + w * res, origin[1], origin[1] + h * res))
    ax.plot(poses[:, 0], poses[:, 1], "-", color="tab:blue", lw=0.5, alpha=0.6)
    for c in constraints:
        if not c["accepted"]:
            continue
        ok = c.get(key)
        color = "tab:green" if ok else ("tab:red" if ok is False else "tab:orange")
        a, b = poses[c["from_scan"]], poses[c["to_scan"]]
        ax.plot([a[0], b[0]], [a[1], b[1]], "-", color=color, lw=0.8)
    ax.set_aspect("equal")
    ax.set_title(title or "loop closures (green true, red false)")
    fig.tight_layout()
    _save(plt, fig, path)


def plot_score_histogram(path, hist: dict, title=""):
    plt = _plt()
    bins = np.asarray(hist["bins"])
    centers = 0.5 * (bins[:-1] + bins[1:])
    width = bins[1] - bins[0]
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.bar(centers, hist["true"], width=width * 0.9, color="tab:green", label="true")
    ax.bar(centers, hist["false"], width=width * 0.9, bottom=hist["true"], color="tab:red", label="false")
    ax.set_xlabel("match score")
    ax.set_ylabel("constraints")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    _save(plt, fig, path)
