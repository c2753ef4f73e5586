"""CARMEN log reader (``.clf``/``.log``, plain, ``.gz``, ``.bz2``).

Message formats (CARMEN 0.7 logger):

* ``FLASER n r1..rn x y theta odom_x odom_y odom_theta ipc_ts host logger_ts``: ``n``
  beams spread over 180°, first beam on the right (−90°); 180/360 beams step π/n, 181/361
  beams step π/(n−1). ``x y theta`` is the laser pose, ``odom_*`` the robot pose, both in
  the odometry frame; their difference is the laser mount.
* ``ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode n r1..rn
  m i1..im laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv fwd side turn
  ipc_ts host logger_ts``.
* ``RAWLASER1`` … ``RAWLASER4 type start_angle fov resolution max_range accuracy remission_mode n
  r1..rn m i1..im ipc_ts host logger_ts``: a laser without a pose. Read only when the log holds
  none of the messages above (a log holds both for the same scans when the robot module ran),
  then from the one laser with the most lines; the robot pose at each scan is the ``ODOM``
  pose interpolated at its timestamp (held at the first / last ``ODOM`` before / after them; no
  ``ODOM``: no odometry), and the laser is taken to sit at the robot's origin (the line carries no
  mount, and the ``robot_*laser_offset`` parameters disagree with the mounts of the Freiburg logs).
* ``ODOM x y theta tv rv accel ipc_ts host logger_ts``, ``PARAM name value ...``, ``#`` comments;
  other messages (TRUEPOS, NEFF, SYNC, ...) are skipped.

The scan timestamp is ``ipc_ts`` (the Freiburg benchmark relations use it); a log whose timestamps
are unusable (a 32-bit wrap, negative stamps) is read with ``scan_period``: every scan stamped that
many seconds after the one before it, in file order. Readings at
or above the sensor's no-return threshold are flagged invalid and never become hits. The
threshold is a fact of the data, decided by a first pass (``NoReturnSurvey``): a laser that
sees nothing writes one fixed number, so a no-return value shows up as a *spike* in the
histogram of readings near the log's maximum — one exact value far more frequent than the
readings around it (81.83 m on Intel, 50.0 m on ACES; fr-clinic has two, 81.83 and 81.91).
The maximum range stated in a ROBOTLASER1 line is a no-return value too. The lowest of
these is the threshold.

slam2d maps with one laser. A log with more than one laser message that carries poses (a front
and a rear laser, ``FLASER`` and ``RLASER``; or one laser logged both as ``FLASER`` and as
``ROBOTLASER1``) is read from the one with the most lines (ties: ``ROBOTLASER1``, ``FLASER``,
``RLASER``), as a log of ``RAWLASERn`` lines is, and says which it skipped. Two lasers read as
one stream of scans look to local SLAM like a robot whose odometry stalls at every other scan
(the rear scan carries the front scan's odometry): on the simulator split into a front and a
rear laser, 0.048 m ATE with the front alone, 0.60 m with both. Each laser message is surveyed
on its own (``LaserFacts``): the one read is judged by its own readings, not by another
model's maximum. The first pass keeps the parsed records for
the second pass in memory up to ``RECORD_MEMORY_BUDGET`` bytes and in an unnamed temporary
file beyond, so memory stays bounded however long the log is.
"""
from __future__ import annotations

import logging
import math
import pickle
import tempfile
from array import array
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slam2d._kernels import classify_readings, survey_band
from slam2d.errors import InputError
from slam2d.geometry import between
from slam2d.io._text import iter_lines
from slam2d.types import MAX_TIME_GAP, MAX_TIME_REVERSAL, Scan

log = logging.getLogger(__name__)

#: a finite reading beyond this [m], or a pose coordinate beyond MAX_COORDINATE, is corrupt data
MAX_READING = 1e5
MAX_COORDINATE = 1e9
#: beams may span this share more than a full turn (a resolution printed with 6 decimals, 0.008727 for
#: 0.5°, adds up over 721 beams); a resolution in degrees read as radians spans 57 times as much
FULL_TURN_SLACK = 1e-3
#: a repeated reading near the top is a no-return value when at least this share of beams has it
SATURATION_MIN_SHARE = 1e-4
SATURATION_MIN_COUNT = 5
#: ... it lies within this fraction of the log's maximum reading
SPIKE_BAND = 0.9
#: ... and it is this many times more frequent than the typical value within ±SPIKE_NEIGHBOURHOOD m
SPIKE_RATIO = 20.0
SPIKE_NEIGHBOURHOOD = 1.0

_LASER_TYPES = ("FLASER", "RLASER", "ROBOTLASER1")
#: lasers without a pose, read when a log holds none of ``_LASER_TYPES`` (module docstring)
_RAW_TYPES = ("RAWLASER1", "RAWLASER2", "RAWLASER3", "RAWLASER4")
_KINDS = _LASER_TYPES + _RAW_TYPES
#: of several laser messages with as many lines, the one read (module docstring)
_PREFERRED = ("ROBOTLASER1", "FLASER", "RLASER")
#: parsed laser records beyond this many bytes go to a temporary file (``_RecordStore``)
RECORD_MEMORY_BUDGET = 256 * 1024 * 1024


#: records per block of the in-memory store; a pass frees each block once it has handed it on
RECORD_BLOCK = 1024
_SCALARS = 10  # timestamp, angle_min, angle_increment, laser pose (3), robot pose (3), max_range (NaN: none)


class _Block:
    """Parsed laser records packed into a few flat buffers (``array.array``, one allocation each):
    per-record numpy arrays and strings would scatter small long-lived objects among the parser's
    short-lived ones, and the allocator could then give little of the parse's memory back."""

    __slots__ = ("ranges", "range_end", "intensities", "intensity_start", "scalars", "lineno", "kind", "text",
                 "text_end")

    def __init__(self):
        self.ranges, self.range_end = array("d"), array("q")
        self.intensities, self.intensity_start = array("f"), array("q")  # start -1: no intensities
        self.scalars, self.lineno, self.kind = array("d"), array("q"), array("b")
        self.text, self.text_end = bytearray(), array("q")

    def __len__(self):
        return len(self.lineno)

    def append(self, lineno: int, p: "_Parsed"):
        self.ranges.frombytes(np.ascontiguousarray(p.ranges, dtype=np.float64).tobytes())
        self.range_end.append(len(self.ranges))
        if p.intensities is None:
            self.intensity_start.append(-1)
        else:
            self.intensity_start.append(len(self.intensities))
            self.intensities.frombytes(np.ascontiguousarray(p.intensities, dtype=np.float32).tobytes())
        self.scalars.extend((p.timestamp, p.angle_min, p.angle_increment, *map(float, p.laser_pose),
                             *map(float, p.robot_pose), math.nan if p.max_range is None else p.max_range))
        self.lineno.append(lineno)
        self.kind.append(_KINDS.index(p.kind))
        self.text += p.timestamp_text.encode()
        self.text_end.append(len(self.text))

    def record(self, i: int) -> tuple[int, "_Parsed"]:
        r0 = self.range_end[i - 1] if i else 0
        n = self.range_end[i] - r0
        ranges = np.frombuffer(self.ranges, dtype=np.float64, count=n, offset=8 * r0).copy()
        i0 = self.intensity_start[i]  # a line's remissions are kept only when there is one per reading
        inten = None if i0 < 0 else np.frombuffer(self.intensities, dtype=np.float32, count=n, offset=4 * i0).copy()
        v = self.scalars[_SCALARS * i:_SCALARS * (i + 1)]
        t0 = self.text_end[i - 1] if i else 0
        return self.lineno[i], _Parsed(_KINDS[self.kind[i]], v[0], self.text[t0:self.text_end[i]].decode(), ranges,
                                       v[1], v[2], np.array(v[3:6]), np.array(v[6:9]),
                                       None if math.isnan(v[9]) else v[9], inten)


class _RecordStore:
    """The first pass's parsed laser records: in memory (packed in blocks) up to a byte budget, then
    spilled to an unnamed temporary file (the disk, not memory, grows with the log)."""

    def __init__(self, budget: int | None = None):
        self.budget = RECORD_MEMORY_BUDGET if budget is None else budget
        self.blocks: list[_Block | None] = []
        self.consumed = False
        self.nbytes = 0
        self.count = 0
        self.file = None
        self._dump = None

    def append(self, lineno: int, p: "_Parsed"):
        self.count += 1
        if self.file is None:
            if not self.blocks or len(self.blocks[-1]) >= RECORD_BLOCK:
                self.blocks.append(_Block())
            self.blocks[-1].append(lineno, p)
            self.nbytes += p.ranges.size * 8 + 100 + (0 if p.intensities is None else p.intensities.size * 4)
            if self.nbytes > self.budget:
                self._spill()
            return
        self._write(lineno, p)

    def _memory_records(self, hand_on: bool = False):
        """The in-memory records in order; ``hand_on``: each block leaves the store as it is reached."""
        for b in range(len(self.blocks)):
            block = self.blocks[b]
            if hand_on:
                self.blocks[b] = None  # its memory serves the run once passed
            for i in range(len(block)):
                yield block.record(i)

    def _spill(self):
        self.file = tempfile.TemporaryFile()
        self._dump = pickle.Pickler(self.file, protocol=pickle.HIGHEST_PROTOCOL)
        for lineno, p in self._memory_records():
            self._write(lineno, p)
        self.blocks = []

    def _write(self, lineno, p):
        self._dump.dump((lineno, p.kind, p.timestamp, p.timestamp_text, p.ranges.tobytes(), p.angle_min,
                         p.angle_increment, tuple(p.laser_pose), tuple(p.robot_pose), p.max_range,
                         None if p.intensities is None else p.intensities.tobytes()))
        self._dump.clear_memo()

    def in_memory(self) -> int:
        """Records still held in memory."""
        return sum(len(b) for b in self.blocks if b is not None)

    def __iter__(self):
        self.consumed = True  # a pass hands each in-memory block on once (see CarmenLog._laser_records)
        if self.file is None:
            yield from self._memory_records(hand_on=True)
            return
        self.file.seek(0)
        load = pickle.Unpickler(self.file)
        for _ in range(self.count):
            ln, kind, t, text, r, a0, da, lp, rp, mr, inten = load.load()
            yield ln, _Parsed(kind, t, text, np.frombuffer(r, dtype=np.float64), a0, da, np.array(lp), np.array(rp), mr,
                              None if inten is None else np.frombuffer(inten, dtype=np.float32))

    def close(self):
        self.blocks = []
        if self.file is not None:
            self.file.close()


@dataclass
class _Parsed:
    kind: str
    timestamp: float
    timestamp_text: str
    ranges: np.ndarray
    angle_min: float
    angle_increment: float
    laser_pose: np.ndarray
    robot_pose: np.ndarray
    max_range: float | None  # from the line itself (ROBOTLASER1)
    intensities: np.ndarray | None = None


class NoReturnSurvey:
    """Histogram of the readings near the log's maximum, to find its no-return values.

    Exact values are counted only in the band above ``SPIKE_BAND / 2`` of the running maximum
    (values below it are pruned when the histogram is compacted), so memory stays small
    whatever the log's length. The maximum is the ``TOP``-th largest finite reading, not the
    largest: a stray reading (a corrupt token such as 500 in a log whose returns end at 80 m) would
    otherwise lift the band above the no-return value and hide it. ``TOP`` is the count a no-return
    value needs at least (``SATURATION_MIN_COUNT``): a maximum fewer readings reach could not be one.
    """

    COMPACT_EVERY = 1 << 20  # readings buffered before the histogram is compacted
    BATCH = 1 << 16  # readings surveyed by one kernel call (per scan, the call would cost more than the work)
    TOP = SATURATION_MIN_COUNT  # the maximum is the TOP-th largest reading (the largest in a log of fewer)

    def __init__(self):
        self._top = np.empty(0)  # the TOP largest finite readings so far, ascending
        self.values = np.empty(0)
        self.counts = np.empty(0, dtype=np.int64)
        self._pending: list[np.ndarray] = []
        self._pending_n = 0
        self._batch: list[np.ndarray] = []
        self._batch_n = 0

    @property
    def max_reading(self) -> float:
        """The log's maximum for the spike search: the ``TOP``-th largest finite reading surveyed so
        far (the largest, in a log of fewer; -inf before any)."""
        self._survey_batch()
        if self._top.size == self.TOP:
            return float(self._top[0])
        return float(self._top[-1]) if self._top.size else -math.inf

    @property
    def largest(self) -> float:
        """The largest finite reading surveyed (-inf before any)."""
        self._survey_batch()
        return float(self._top[-1]) if self._top.size else -math.inf

    def _floor_max(self) -> float:
        """What the band is cut against while readings come: the ``TOP``-th largest so far, which only
        rises toward the final one, and -inf (everything kept) until there are ``TOP`` readings."""
        return float(self._top[0]) if self._top.size == self.TOP else -math.inf

    def add(self, ranges: np.ndarray):
        self._batch.append(ranges)
        self._batch_n += ranges.size
        if self._batch_n >= self.BATCH:
            self._survey_batch()

    def _survey_batch(self):
        """Survey the buffered scans at once. The band is cut at ``SPIKE_BAND / 2`` of ``_floor_max``,
        which is never above its final value, and the final compaction prunes against that: so a
        batch keeps at least what the histogram ends with, and the histogram ends the same however
        the readings were batched."""
        if not self._batch:
            return
        ranges = self._batch[0] if len(self._batch) == 1 else np.concatenate(self._batch)
        self._batch, self._batch_n = [], 0
        finite = ranges[np.isfinite(ranges)].astype(np.float64)
        if finite.size > self.TOP:
            finite = np.partition(finite, finite.size - self.TOP)[-self.TOP:]
        self._top = np.sort(np.concatenate([self._top, finite]))[-self.TOP:]
        band = survey_band(ranges, 0.5 * SPIKE_BAND * self._floor_max())
        if band.size:
            self._pending.append(band)
            self._pending_n += band.size
            if self._pending_n >= self.COMPACT_EVERY:
                self._compact()

    def _compact(self):
        self._survey_batch()
        if not self._pending:
            return
        vals = np.concatenate([self.values, *self._pending])
        weights = np.concatenate([self.counts, np.ones(self._pending_n, dtype=np.int64)])
        self._pending, self._pending_n = [], 0
        uniq, inv = np.unique(vals, return_inverse=True)
        cnt = np.bincount(inv, weights=weights).astype(np.int64)
        keep = uniq >= 0.5 * SPIKE_BAND * self._floor_max()
        self.values, self.counts = uniq[keep], cnt[keep]

    def spikes(self, num_readings: int) -> list[dict]:
        """The no-return values, each with its count and the typical count of the values around it."""
        self._compact()
        vals, cnts = self.values, self.counts
        need = max(SATURATION_MIN_COUNT, SATURATION_MIN_SHARE * num_readings)
        out = []
        frequent = (cnts >= need) & (vals >= SPIKE_BAND * self.max_reading)
        for i in np.flatnonzero(frequent):
            # the background: values around it that are not frequent themselves (two no-return
            # values side by side, as in fr-clinic, must not hide each other)
            lo, hi = np.searchsorted(vals, [vals[i] - SPIKE_NEIGHBOURHOOD, vals[i] + SPIKE_NEIGHBOURHOOD], side="left")
            near = cnts[lo:hi][~frequent[lo:hi]]
            typical = float(np.median(near)) if near.size else 1.0
            if cnts[i] >= SPIKE_RATIO * typical:
                out.append({"value": float(vals[i]), "count": int(cnts[i]), "typical_count_nearby": typical})
        return out


def odom_at(odom: np.ndarray, t: float) -> np.ndarray | None:
    """The robot pose at time ``t`` from ``ODOM`` rows (timestamp, x, y, θ) sorted by time: linear
    between the two around it (θ along the shorter arc), the first / last pose before / after
    them; None without any."""
    if len(odom) == 0:
        return None
    k = int(np.searchsorted(odom[:, 0], t, side="right"))
    if k == 0:
        return odom[0, 1:].copy()
    if k == len(odom):
        return odom[-1, 1:].copy()
    (t0, x0, y0, a0), (t1, x1, y1, a1) = odom[k - 1], odom[k]
    u = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
    return np.array([x0 + u * (x1 - x0), y0 + u * (y1 - y0), math.remainder(a0 + u * math.remainder(a1 - a0, 2 * math.pi),
                                                                               2 * math.pi)])


@dataclass
class LaserFacts:
    """What the first pass learns of one laser message (``FLASER``, ``RLASER``, ...): a log with a front
    and a rear laser holds two sensors, and each has its own no-return values."""

    kind: str
    num_scans: int = 0
    num_readings: int = 0
    #: how many lines state each max_range (ROBOTLASER1, RAWLASERn; a value of 0 or less states none)
    line_max_ranges: dict = field(default_factory=dict)
    survey: NoReturnSurvey = field(default_factory=NoReturnSurvey)

    @property
    def line_max_range(self) -> float | None:
        """The max_range most lines state (the smallest of equally common ones): one corrupt line's
        field does not become the threshold of the whole log."""
        if not self.line_max_ranges:
            return None
        return min(self.line_max_ranges, key=lambda v: (-self.line_max_ranges[v], v))

    @property
    def no_return_evidence(self) -> list[dict]:
        """Why each of this laser's no-return values was chosen."""
        out = [dict(s, why="a repeated reading near the laser's maximum (a spike over the readings around it)")
               for s in self.survey.spikes(self.num_readings)]
        value = self.line_max_range
        if value is not None:
            n, total = self.line_max_ranges[value], sum(self.line_max_ranges.values())
            why = f"the max_range field of the {self.kind} lines" + ("" if n == total else f" ({n} of {total} lines)")
            out.append({"value": value, "why": why})
        return out

    @property
    def no_return_value(self) -> float | None:
        """Every reading at or above it is a no-return (the lowest no-return value)."""
        cands = [e["value"] for e in self.no_return_evidence]
        return min(cands) if cands else None


@dataclass
class CarmenFacts:
    """What a first pass over the log learns."""

    num_scans: int = 0
    num_odom: int = 0
    #: the laser message read (``FLASER``/``RLASER``/``ROBOTLASER1`` lines carry poses; a
    #: ``RAWLASERn`` is read only in a log without them) and where the robot pose comes from
    laser_messages: str = ""
    odometry: str = "the pose fields of the laser lines"
    #: ``ODOM`` (timestamp, x, y, θ), kept to interpolate the robot pose of ``RAWLASERn`` scans
    odom: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    params: dict = field(default_factory=dict)
    #: per laser message, in the order first seen; after the first pass, only the one read
    lasers: dict = field(default_factory=dict)
    #: laser messages with poses that were not read (slam2d maps with one laser): lines of each
    skipped_lasers: dict = field(default_factory=dict)

    def laser(self, kind: str) -> LaserFacts:
        got = self.lasers.get(kind)
        if got is None:
            got = self.lasers[kind] = LaserFacts(kind)
        return got

    @property
    def laser_kind(self) -> str:
        """The laser message read."""
        return next(iter(self.lasers))

    @property
    def no_return_evidence(self) -> list[dict]:
        """Why each no-return value was chosen (``slam2d info`` prints it)."""
        return self.lasers[self.laser_kind].no_return_evidence if self.lasers else []

    @property
    def no_return_value(self) -> float | None:
        """The no-return threshold of the laser read: every reading at or above it is a no-return."""
        return self.lasers[self.laser_kind].no_return_value if self.lasers else None


def _floats(path, lineno, tokens, what):
    try:
        return [float(t) for t in tokens]
    except ValueError:
        for t in tokens:
            try:
                float(t)
            except ValueError:
                raise InputError(path, f"non-numeric {what} {t!r}", line=lineno) from None
        raise


def _float_array(path, lineno, tokens, what, dtype=np.float64) -> np.ndarray:
    """``tokens`` as an array (numpy parses strings as ``float`` does, in one C loop: the readings
    of a long log are most of its parsing time); errors as ``_floats``."""
    try:
        return np.array(tokens, dtype=np.float64).astype(dtype, copy=False)
    except ValueError:
        return np.array(_floats(path, lineno, tokens, what), dtype=dtype)


def _is_number(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _int(path, lineno, token, what):
    try:
        return int(token)
    except ValueError:
        raise InputError(path, f"{what} must be an integer, found {token!r}", line=lineno) from None


def flaser_geometry(n: int) -> tuple[float, float]:
    """(angle_min, angle_increment) of an n-beam FLASER line over 180°."""
    step = math.pi / (n - 1) if n % 2 == 1 and n > 1 else math.pi / n
    return -math.pi / 2, step


def _parse_laser(path, lineno, parts) -> _Parsed:
    kind = parts[0]
    if kind in ("FLASER", "RLASER"):
        if len(parts) < 2:
            raise InputError(path, f"truncated {kind} line: no beam count", line=lineno)
        n = _int(path, lineno, parts[1], "beam count")
        if n <= 0:
            raise InputError(path, f"beam count must be positive, found {n}", line=lineno)
        need = 2 + n + 7
        if len(parts) >= 11 and not _is_number(parts[-2]) and len(parts) - 11 != n:
            raise InputError(path, f"beam count mismatch: {kind} declares {n} readings but the line holds "
                             f"{len(parts) - 11}", line=lineno)
        if len(parts) < need or len(parts) > need + 2:
            raise InputError(path, f"{kind} declares {n} readings, so it needs {need}..{need + 2} fields; "
                             f"the line has {len(parts)} (beam count mismatch or truncated line)", line=lineno)
        ranges = _float_array(path, lineno, parts[2:2 + n], "range reading")
        tail = _floats(path, lineno, parts[2 + n:2 + n + 7], "pose/timestamp field")
        a0, da = flaser_geometry(n)
        return _Parsed(kind, tail[6], parts[2 + n + 6], ranges, a0, da,
                       np.array(tail[0:3]), np.array(tail[3:6]), None)
    # ROBOTLASER1 and RAWLASERn share the header; RAWLASERn has no pose fields
    if len(parts) < 9:
        raise InputError(path, f"truncated {kind} line", line=lineno)
    head = _floats(path, lineno, parts[2:8], f"{kind} header field")
    start, _fov, res, max_range = head[0], head[1], head[2], head[3]
    n = _int(path, lineno, parts[8], "beam count")
    if n <= 0:
        raise InputError(path, f"beam count must be positive, found {n}", line=lineno)
    if len(parts) < 9 + n + 1:
        raise InputError(path, f"{kind} declares {n} readings but the line is truncated", line=lineno)
    ranges = _float_array(path, lineno, parts[9:9 + n], "range reading")
    m = _int(path, lineno, parts[9 + n], "remission count")
    base = 10 + n + m
    fields = 1 if kind in _RAW_TYPES else 12  # ipc_ts; or laser pose, robot pose, 5 velocities/safety, ipc_ts
    need = base + fields
    if m < 0 or len(parts) < need or len(parts) > need + 2:
        raise InputError(path, f"{kind} with {n} readings and {m} remissions needs {need}..{need + 2} fields; "
                         f"the line has {len(parts)}", line=lineno)
    rem = _float_array(path, lineno, parts[10 + n:base], "remission", np.float32) if m == n else None
    tail = _floats(path, lineno, parts[base:base + fields], "pose/timestamp field")
    if not (res > 0 and math.isfinite(res)):
        raise InputError(path, f"angular resolution must be positive, found {res}", line=lineno)
    if not math.isfinite(start):
        raise InputError(path, f"start angle must be a number, found {start}", line=lineno)
    if (n - 1) * res > 2 * math.pi * (1 + FULL_TURN_SLACK):
        raise InputError(path, f"{n} beams {res} rad apart span {math.degrees((n - 1) * res):.0f}°, more than a full "
                         "turn (is the angular resolution in degrees?)", line=lineno)
    if kind in _RAW_TYPES:  # the robot pose comes from the ODOM lines (``CarmenLog._to_scan``)
        return _Parsed(kind, tail[0], parts[base], ranges, start, res, np.full(3, np.nan), np.full(3, np.nan),
                       max_range if max_range > 0 else None, rem)
    return _Parsed(kind, tail[11], parts[base + 11], ranges, start, res, np.array(tail[0:3]),
                   np.array(tail[3:6]), max_range if max_range > 0 else None, rem)


class CarmenLog:
    """Lazy iterator over the scans of a CARMEN log. ``scan_period`` [s]: ignore the log's timestamps and
    stamp scan k at k × ``scan_period`` (module docstring)."""

    def __init__(self, path: str | Path, scan_period: float | None = None):
        self.path = Path(path)
        if scan_period is not None and not (math.isfinite(scan_period) and scan_period > 0):
            raise InputError(path, f"--scan-period must be a positive number of seconds, not {scan_period}")
        self.scan_period = scan_period
        self._facts: CarmenFacts | None = None
        # the first pass keeps its parsed laser records (memory up to a budget, then a temporary
        # file), so the second pass neither decompresses nor parses again
        self._spool: _RecordStore | None = None
        self._far_warned = False

    def _largest_reading(self) -> float:
        """The read laser's largest finite reading (1 m in a log without any), the range_max of a scan
        that has no reading of its own."""
        las = self.facts().lasers[self.facts().laser_kind]
        top = min(las.survey.largest, MAX_READING)
        return top if top > 0 else 1.0

    def num_scans(self) -> int:
        return self.facts().num_scans

    # ---- first pass
    def facts(self) -> CarmenFacts:
        if self._facts is None:
            self._facts = self._survey()
        return self._facts

    def _survey(self, raw: str | None = None) -> CarmenFacts:
        """The first pass. ``raw``: read that ``RAWLASERn`` message as the laser (a second survey,
        made when the first found no laser message with a pose)."""
        f = CarmenFacts()
        spool = _RecordStore()
        raw_counts = dict.fromkeys(_RAW_TYPES, 0)
        odom = array("d")
        for lineno, kind, parts in self._records():
            if kind == "PARAM":
                if len(parts) >= 3:
                    f.params[parts[1]] = parts[2]
                continue
            if kind == "ODOM":
                vals = self._parse_odom(lineno, parts)
                if raw is not None:  # kept only for the RAWLASER scans' poses
                    odom.extend(vals)
                f.num_odom += 1
                continue
            if kind in _RAW_TYPES:
                raw_counts[kind] += 1
                if kind != raw:
                    continue
            elif raw is not None:
                continue
            p = _parse_laser(self.path, lineno, parts)
            spool.append(lineno, p)
            las = f.laser(kind)
            las.num_scans += 1
            las.num_readings += p.ranges.size
            if p.max_range is not None:
                las.line_max_ranges[p.max_range] = las.line_max_ranges.get(p.max_range, 0) + 1
            las.survey.add(p.ranges)
        if not f.lasers:
            spool.close()
            best = max(_RAW_TYPES, key=lambda k: raw_counts[k])  # the first of the most frequent
            if raw is None and raw_counts[best]:
                return self._survey(best)
            raise InputError(self.path, "no laser scans (FLASER, RLASER, ROBOTLASER1 or RAWLASER1-4 lines) in the file")
        if len(f.lasers) > 1:  # one laser is read (module docstring)
            chosen = max(f.lasers, key=lambda k: (f.lasers[k].num_scans, -_PREFERRED.index(k)))
            f.skipped_lasers = {k: las.num_scans for k, las in f.lasers.items() if k != chosen}
            log.warning("%s: reading %s (%d lines); skipping %s: slam2d maps with one laser", self.path, chosen,
                     f.lasers[chosen].num_scans, ", ".join(f"{k} ({n} lines)" for k, n in f.skipped_lasers.items()))
            f.lasers = {chosen: f.lasers[chosen]}
        f.num_scans = f.lasers[f.laser_kind].num_scans
        f.laser_messages = f.laser_kind
        if raw is not None:
            o = np.frombuffer(odom, dtype=np.float64).reshape(-1, 7)
            f.odom = np.ascontiguousarray(o[np.argsort(o[:, 6], kind="stable")][:, [6, 0, 1, 2]])
            f.odometry = ("the ODOM lines, interpolated at each scan's timestamp" if len(f.odom) else
                          "none (no ODOM lines beside the RAWLASER lines)")
            others = [f"{k} ({raw_counts[k]} lines)" for k in _RAW_TYPES if k != raw and raw_counts[k]]
            if others:
                log.info("%s: reading %s, the laser with the most lines; skipping %s", self.path, raw, ", ".join(others))
        self._spool = spool
        return f

    def _laser_records(self):
        """(line number, parsed laser record) kept by the first pass; a second pass over a log whose
        records were kept in memory (and handed on) reads the file again."""
        self.facts()
        if self._spool.consumed and self._spool.file is None:
            self._spool.close()
            self._facts = None
            self.facts()
        yield from self._spool

    def _records(self):
        for lineno, line in iter_lines(self.path):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            kind = parts[0]
            if kind in _KINDS or kind in ("ODOM", "PARAM"):
                yield lineno, kind, parts

    def _parse_odom(self, lineno, parts):
        if len(parts) < 8:
            raise InputError(self.path, f"truncated ODOM line: {len(parts)} fields, needs at least 8", line=lineno)
        vals = _floats(self.path, lineno, parts[1:8], "ODOM field")
        if not all(math.isfinite(v) for v in vals):
            raise InputError(self.path, "ODOM line has a non-finite value", line=lineno)
        return vals

    # ---- second pass
    def __iter__(self):
        facts = self.facts()
        no_return = facts.no_return_value
        kind = facts.laser_kind  # the one laser read (module docstring)
        period = self.scan_period
        if period is not None and kind in _RAW_TYPES and len(facts.odom):
            raise InputError(self.path, "--scan-period cannot be used here: this log's scans have no pose of their own "
                             "(RAWLASER lines), and their odometry comes from the ODOM lines by timestamp")
        prev = None  # (the latest timestamp so far, its line)
        gap_warned = False
        for index, (lineno, p) in enumerate((lineno, p) for lineno, p in self._laser_records() if p.kind == kind):
            if p.kind in _RAW_TYPES:  # no pose in the line: the robot's from the ODOM lines, the laser at its origin
                p.robot_pose = p.laser_pose = odom_at(facts.odom, p.timestamp)
            if period is not None:  # the log's stamps are unusable: file order, ``period`` apart
                p.timestamp = index * period
                p.timestamp_text = f"{p.timestamp:.6f}"
            yield self._to_scan(p, lineno, index, no_return, prev)
            if prev is not None and p.timestamp > prev[0] + MAX_TIME_GAP and not gap_warned:
                gap_warned = True
                log.warning("%s:%d: timestamp %s jumps %.6g s ahead of the scan of line %d (a broken stamp?)", self.path,
                            lineno, p.timestamp_text, p.timestamp - prev[0], prev[1])
            if prev is None or p.timestamp > prev[0]:
                prev = (p.timestamp, lineno)

    def _to_scan(self, p: _Parsed, lineno: int, index: int, no_return, prev) -> Scan:
        """``prev``: (the latest timestamp of the scans before, its line), None for the first."""
        path = self.path
        if not math.isfinite(p.timestamp):
            raise InputError(path, f"timestamp {p.timestamp_text!r} is not finite", line=lineno)
        if prev is not None and p.timestamp < prev[0] - MAX_TIME_REVERSAL:
            raise InputError(path, f"timestamp {p.timestamp_text} goes back {prev[0] - p.timestamp:.6g} s "
                             f"(more than {MAX_TIME_REVERSAL} s) behind the scan of line {prev[1]}; if the log's "
                             f"timestamps are unusable, --scan-period S stamps the scans S seconds apart in file order",
                             line=lineno)
        if p.robot_pose is not None and not (np.all(np.isfinite(p.laser_pose)) and np.all(np.isfinite(p.robot_pose))):
            raise InputError(path, "pose field is not finite", line=lineno)
        if p.robot_pose is not None and max(np.abs(p.laser_pose).max(), np.abs(p.robot_pose).max()) > MAX_COORDINATE:
            raise InputError(path, f"pose field beyond {MAX_COORDINATE:g} m", line=lineno)
        r = p.ranges
        valid = np.empty(r.shape, dtype=np.bool_)
        no_ret = np.empty(r.shape, dtype=np.bool_)
        if p.max_range is not None:  # a line's own max_range holds for its readings (the log's may be another's)
            no_return = p.max_range if no_return is None else min(no_return, p.max_range)
        negative, all_nan = classify_readings(r, math.nan if no_return is None else float(no_return), valid, no_ret)
        if negative >= 0:  # -inf included
            raise InputError(path, f"negative range reading {r[negative]} (beam {negative})", line=lineno)
        if all_nan:
            raise InputError(path, "every range reading is NaN", line=lineno)
        with np.errstate(invalid="ignore"):
            far = np.flatnonzero(valid & (r > MAX_READING))
        if far.size:  # no laser measures that far: a no-return value too rare to show as a spike, or corrupt
            valid[far] = False
            no_ret[far] = True
            if not self._far_warned:
                self._far_warned = True
                log.warning("%s:%d: range reading %g (beam %d) beyond %g m read as a no-return (so is any such reading)",
                            path, lineno, r[far[0]], far[0], MAX_READING)
        if no_return is not None:
            range_max = float(no_return)
        else:  # the scan's farthest reading; one without any reading takes the log's farthest
            finite = r[np.isfinite(r) & (r <= MAX_READING)]
            range_max = float(finite.max()) if finite.size and finite.max() > 0 else self._largest_reading()
        with np.errstate(over="ignore"):  # a no-return value beyond float32 (1e300) reads as inf, a no-return too
            r32 = r.astype(np.float32)
        return Scan(
            timestamp=p.timestamp,
            timestamp_text=p.timestamp_text,
            ranges=r32,
            angle_min=p.angle_min,
            angle_increment=p.angle_increment,
            range_min=0.0,
            range_max=range_max,
            valid=valid,
            no_return=no_ret,
            index=index,
            intensities=p.intensities,
            odom_pose=p.robot_pose,
            laser_offset=np.zeros(3) if p.robot_pose is None else between(p.robot_pose, p.laser_pose),
        )
