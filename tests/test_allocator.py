"""``slam2d.allocator``: with the mmap threshold fixed, freed large blocks leave the process."""
import subprocess
import sys

import pytest

from slam2d import allocator

pytestmark = pytest.mark.skipif(allocator._glibc() is None, reason="not glibc: the allocator module does nothing")

# A long run in miniature: one large block freed (glibc then raises its threshold past the blocks
# that follow), 64 blocks of 512 KiB, every other one freed. RSS dropped by the frees is printed (MB).
_PROBE = r"""
import sys
import numpy as np
from slam2d import allocator
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2 ** 20
if sys.argv[1] == "fixed":
    assert allocator.map_large_blocks()
big = np.ones(8 << 20, dtype=np.uint8)
del big
blocks = [np.ones(512 << 10, dtype=np.uint8) for _ in range(64)]
before = rss()
del blocks[::2]
print(before - rss())
"""


def _dropped(mode: str) -> float:
    p = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return float(p.stdout)


def test_fixed_threshold_returns_freed_blocks_the_adaptive_one_keeps():
    fixed, adaptive = _dropped("fixed"), _dropped("adaptive")
    assert fixed >= 12.0  # 32 blocks of 0.5 MB unmapped
    assert adaptive <= fixed - 8.0  # the same blocks left as holes in the heap

