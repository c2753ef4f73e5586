"""Per-scan arrays kept on disk while the run goes on (issue 11: memory grows with the mapped area,
not with the number of scans).

What a run keeps of every scan until ``Slam.finish`` (a node's range data for the map and the
health report, the points each scan matched for the final refinement) is written to an unnamed
temporary file as it comes, not held in memory: hours of scans grow the disk, not the process,
and the pose-graph solver's peak, which comes at the end of the scan loop, no longer lands on
top of them. The records come back once, at the end, as views into one buffer read in one go
(no object per array until then, nor after).
"""
from __future__ import annotations

import tempfile
from array import array

import numpy as np

#: the dtypes a record's arrays may have (their index is what the index keeps)
DTYPES = (np.dtype(np.float32), np.dtype(np.float64), np.dtype(np.uint16), np.dtype(np.int64))
#: per array: byte offset, first dimension, second dimension (-1: a 1-D array), dtype index (-1: None)
_FIELDS = 4
#: arrays start at multiples of this many bytes in the file and in the buffer read back
_ALIGN = 8


class ArraySpill:
    """Records of ``arity`` arrays (each 1-D or 2-D, one of ``DTYPES``, or None) appended in order."""

    def __init__(self, arity: int):
        self.arity = int(arity)
        self._file = None
        self._size = 0
        self._index = array("q")

    def append(self, *arrays) -> None:
        if len(arrays) != self.arity:
            raise ValueError(f"a record has {self.arity} arrays, not {len(arrays)}")
        for a in arrays:
            if a is None:
                self._index.extend((0, 0, 0, -1))
                continue
            a = np.ascontiguousarray(a)
            if a.ndim not in (1, 2):
                raise ValueError(f"arrays of 1 or 2 dimensions only, not {a.ndim}")
            if self._file is None:
                self._file = tempfile.TemporaryFile()
            self._file.write(a.data)
            pad = -a.nbytes % _ALIGN  # every array starts aligned for any of ``DTYPES`` (numba's kernels take aligned ones)
            if pad:
                self._file.write(bytes(pad))
            self._index.extend((self._size, a.shape[0], a.shape[1] if a.ndim == 2 else -1, DTYPES.index(a.dtype)))
            self._size += a.nbytes + pad

    def __len__(self) -> int:
        return len(self._index) // (_FIELDS * self.arity)

    def records(self) -> list[tuple]:
        """Every record so far, in order, as tuples of views into one buffer (aligned, writeable: the
        arrays the kernels took before); more may be appended afterwards."""
        buf = np.empty(self._size, dtype=np.uint8)
        if self._size:
            self._file.flush()
            self._file.seek(0)
            self._file.readinto(memoryview(buf))
            self._file.seek(0, 2)
        idx = np.frombuffer(self._index, dtype=np.int64).reshape(-1, self.arity, _FIELDS)
        out = []
        for rec in idx.tolist():
            arrays = []
            for off, n, m, d in rec:
                if d < 0:
                    arrays.append(None)
                    continue
                dt = DTYPES[d]
                count = n * (m if m >= 0 else 1)
                a = buf[off:off + count * dt.itemsize].view(dt)
                arrays.append(a.reshape(n, m) if m >= 0 else a)
            out.append(tuple(arrays))
        return out

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


__all__ = ["ArraySpill", "DTYPES"]
