import os
from pathlib import Path

import pytest

os.environ.setdefault("RERUN_ANALYTICS", "0")

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "datasets"
BUNDLED = ROOT / "data" / "sim_office.mcap"


def dataset(name: str) -> Path:
    """Path to a shared benchmark log; skips the test (with the reason) where ../shared is absent."""
    p = SHARED / name / f"{name}.clf.bz2"
    if not p.exists():
        pytest.skip(f"real-data test: {p} not found (../shared/datasets is not beside the repo)")
    return p


def relations(name: str) -> Path:
    p = SHARED / name / f"{name}.relations"
    if not p.exists():
        pytest.skip(f"real-data test: {p} not found")
    return p


def indeterminate_graph(g):
    """Four nodes into the pose graph ``g`` (in-process or in the solver process), two of them held a
    thousand million times tighter to their neighbours than the rest (information spanning 1e16):
    iSAM2's undamped elimination calls this system indeterminate. Returns ``g``."""
    import numpy as np

    for j in range(4):
        g.add_node(j, [j, 0.1 * j, 0.05 * j])
    g.add_intra(0, 1, [1, 0, 0], np.diag([1e-16] * 3))
    g.add_intra(1, 2, [1, 0, 0], np.diag([1e-16] * 3))
    g.add_intra(0, 3, [3, 0, 0], np.eye(3))
    g.add_intra(2, 3, [1, 0, 0], np.eye(3))
    return g


@pytest.fixture
def flaser_line():
    def make(ranges, pose=(0.0, 0.0, 0.0), odom=None, ts="100.000000", logger="0.5"):
        odom = pose if odom is None else odom
        r = " ".join(f"{v}" for v in ranges)
        p = " ".join(f"{v:.6f}" for v in pose)
        o = " ".join(f"{v:.6f}" for v in odom)
        return f"FLASER {len(ranges)} {r} {p} {o} {ts} nohost {logger}\n"
    return make
