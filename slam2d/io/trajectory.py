"""TUM trajectory files (``timestamp x y z qx qy qz qw``), as evo reads them."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from slam2d.errors import InputError
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
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    ts, poses, texts = [], [], []
    with open(path) as f:
        for n, line in enumerate(f, start=1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            if len(parts) != 8:
                raise InputError(path, f"TUM line needs 8 fields (timestamp x y z qx qy qz qw), found {len(parts)}", line=n)
            try:
                v = [float(p) for p in parts]
            except ValueError:
                raise InputError(path, "non-numeric field in TUM line", line=n) from None
            if not all(math.isfinite(x) for x in v):
                raise InputError(path, "non-finite value in TUM line", line=n)
            ts.append(v[0])
            texts.append(parts[0])
            poses.append((v[1], v[2], float(quaternion_to_yaw(v[4], v[5], v[6], v[7]))))
    if not ts:
        raise InputError(path, "no poses in the trajectory file")
    return np.array(ts), np.array(poses, dtype=float).reshape(-1, 3), texts
