"""TUM trajectory files (``timestamp x y z qx qy qz qw``), as evo reads them."""
from __future__ import annotations

import math

import numpy as np

from slam2d.io._text import read_numeric_table
from slam2d.geometry import quaternion_to_yaw


def format_tum_line(stamp_text: str, pose) -> str:
    x, y, th = (float(v) for v in pose)
    return f"{stamp_text} {x:.6f} {y:.6f} 0 0 0 {math.sin(th / 2):.9f} {math.cos(th / 2):.9f}\n"


def write_tum(path, stamps: list[str], poses: np.ndarray) -> None:
    with open(path, "w") as f:
        for s, p in zip(stamps, poses):
            f.write(format_tum_line(s, p))


def read_tum(path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(timestamps (N,), poses (N, 3), timestamp strings)."""
    rows, texts = read_numeric_table(path, 8, "timestamp x y z qx qy qz qw", "TUM line")
    ts = [v[0] for v in rows]
    poses = [(v[1], v[2], float(quaternion_to_yaw(v[4], v[5], v[6], v[7]))) for v in rows]
    return np.array(ts), np.array(poses, dtype=float).reshape(-1, 3), texts
