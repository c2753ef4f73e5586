"""TUM trajectory files (``timestamp x y z qx qy qz qw``), as evo reads them.

evo (``PoseTrajectory3D.check()``) accepts a trajectory only when its timestamps strictly
ascend, yet a log's stamps may go back (Intel: 631 scans up to 0.9 s) or repeat (logs whose
stamps are all 0). slam2d still writes one line for every scan, by this rule:

- lines are sorted by stamp; scans with equal stamps keep their input order (stable sort);
- a stamp written exactly as the source wrote it, except where it is not later than the line
  before (a repeated stamp, or one within float64 resolution): then it is written as that
  line's stamp + 1 µs, in fixed-point with at least 6 decimals (more where the source had
  more), so a nudged stamp never lands on another;
- when the lines are not in input order, a first comment line ``# scans 0-1233 1235 1234 …``
  gives the input scan index of every line, in line order (ranges ``a-b`` ascending). evo and
  other TUM readers skip ``#`` lines; `read_tum` uses it to give rows back in scan order.

A file without that comment (any other TUM file, or a run whose stamps ascend) is in scan order.
"""
from __future__ import annotations

import math
from decimal import Decimal

import numpy as np

from slam2d.errors import InputError
from slam2d.geometry import quaternion_to_yaw
from slam2d.io._text import read_numeric_table

#: the step a repeated stamp is moved by [s]
NUDGE = Decimal("0.000001")
SCANS_COMMENT = "# scans "


def format_tum_line(stamp_text: str, pose) -> str:
    x, y, th = (float(v) for v in pose)
    return f"{stamp_text} {x:.6f} {y:.6f} 0 0 0 {math.sin(th / 2):.9f} {math.cos(th / 2):.9f}\n"


def _decimals(d: Decimal) -> int:
    return max(0, -d.as_tuple().exponent)


def ascending_stamps(stamps: list[str]) -> tuple[list[int], list[str]]:
    """(input index of each line, the stamp text each line is written with), by the module's rule."""
    values = [Decimal(s) for s in stamps]
    order = sorted(range(len(stamps)), key=lambda i: values[i])
    texts: list[str] = []
    prev: Decimal | None = None
    for i in order:
        d, text = values[i], stamps[i]
        if prev is not None and float(text) <= float(prev):
            places = Decimal(1).scaleb(-max(6, _decimals(d)))
            d = prev + NUDGE
            while float(d) <= float(prev):  # beyond ~8e9 s a microsecond is below float64 resolution
                d += NUDGE
            text = format(d.quantize(places), "f")
        texts.append(text)
        prev = d
    return order, texts


def scans_comment(order: list[int]) -> str:
    """``# scans`` + the order as ascending runs (``0-1233 1235 1234 1236-13630``)."""
    parts, k = [], 0
    while k < len(order):
        j = k
        while j + 1 < len(order) and order[j + 1] == order[j] + 1:
            j += 1
        parts.append(str(order[k]) if j == k else f"{order[k]}-{order[j]}")
        k = j + 1
    return SCANS_COMMENT + " ".join(parts) + "\n"


def parse_scans_comment(path, line: str, n: int) -> np.ndarray:
    """The input scan index of each of the ``n`` lines, from a ``# scans`` comment."""
    out: list[int] = []
    try:
        for part in line[len(SCANS_COMMENT):].split():
            a, _, b = part.partition("-")
            out.extend(range(int(a), int(b or a) + 1))
    except ValueError:
        raise InputError(path, f"malformed {SCANS_COMMENT.strip()!r} comment", line=1) from None
    order = np.array(out, dtype=int)
    if len(order) != n or not np.array_equal(np.sort(order), np.arange(n)):
        raise InputError(path, f"the {SCANS_COMMENT.strip()!r} comment does not list each of the {n} lines once",
                         line=1)
    return order


def write_tum(path, stamps: list[str], poses: np.ndarray) -> None:
    """One line per scan, by the module's rule (evo's ``check()`` passes)."""
    order, texts = ascending_stamps(list(stamps))
    with open(path, "w") as f:
        if order != list(range(len(order))):
            f.write(scans_comment(order))
        for i, text in zip(order, texts):
            f.write(format_tum_line(text, poses[i]))


def read_tum(path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(timestamps (N,), poses (N, 3), timestamp strings), in scan order: file order unless a
    ``# scans`` comment gives each line's scan (then row i is scan i)."""
    rows, texts = read_numeric_table(path, 8, "timestamp x y z qx qy qz qw", "TUM line")
    q = np.array([v[4:8] for v in rows], dtype=float).reshape(-1, 4)
    off = np.flatnonzero(np.abs(np.linalg.norm(q, axis=1) - 1.0) > 0.01)
    if off.size:  # an 8-column file that is no trajectory (a .relations file: t1 t2 x y z roll pitch yaw)
        raise InputError(path, f"not a TUM trajectory: the quaternion of pose {off[0]} ({', '.join(f'{v:g}' for v in q[off[0]])}) "
                         "is not of unit length")
    ts = np.array([v[0] for v in rows])
    poses = np.array([(v[1], v[2], float(quaternion_to_yaw(v[4], v[5], v[6], v[7]))) for v in rows],
                     dtype=float).reshape(-1, 3)
    with open(path) as f:
        first = f.readline()
    if not first.startswith(SCANS_COMMENT):
        return ts, poses, texts
    order = parse_scans_comment(path, first, len(rows))
    back = np.empty_like(order)
    back[order] = np.arange(len(order))
    return ts[back], poses[back], [texts[k] for k in back]
