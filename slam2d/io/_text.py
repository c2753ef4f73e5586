"""Opening plain, gzip and bzip2 text files with errors that name the file."""
from __future__ import annotations

import bz2
import gzip
import math
import lzma
import zlib
from pathlib import Path

from slam2d.errors import InputError

#: exceptions a corrupt compressed stream raises while being read
DECOMPRESSION_ERRORS = (OSError, EOFError, zlib.error, lzma.LZMAError, UnicodeDecodeError)


def open_text(path: str | Path):
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    if path.is_dir():
        raise InputError(path, "is a directory, not a log file")
    name = path.name.lower()
    try:
        if name.endswith(".bz2"):
            return bz2.open(path, "rt", encoding="utf-8", errors="strict")
        if name.endswith(".gz"):
            return gzip.open(path, "rt", encoding="utf-8", errors="strict")
        return open(path, "rt", encoding="utf-8", errors="strict")
    except OSError as e:
        raise InputError(path, f"cannot open: {e.strerror or e}") from None


def _threaded_lines(f, block=1 << 20):
    """Lines of a text stream whose reading (decompression) runs in a background thread.

    bz2/gzip decompression releases the GIL, so it overlaps with the parsing done by the
    caller on the other core. Errors raised while reading are re-raised here, in order.
    """
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=8)
    stop = threading.Event()

    def reader():
        try:
            while not stop.is_set():
                chunk = f.read(block)
                q.put(chunk)
                if not chunk:
                    return
        except BaseException as e:  # handed to the consumer
            q.put(e)

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    rest = ""
    try:
        while True:
            chunk = q.get()
            if isinstance(chunk, BaseException):
                raise chunk
            if not chunk:
                if rest:
                    yield rest
                return
            lines = (rest + chunk).split("\n")
            rest = lines.pop()
            for line in lines:
                yield line + "\n"
    finally:
        stop.set()
        while t.is_alive():
            try:
                q.get_nowait()
            except queue.Empty:
                t.join(0.01)


def iter_lines(path: str | Path):
    """Yield (line_number, text) with decompression/decoding errors turned into InputError."""
    n = 0
    f = open_text(path)
    try:
        with f:
            lines = _threaded_lines(f) if str(path).lower().endswith((".bz2", ".gz")) else f
            for n, line in enumerate(lines, start=1):
                yield n, line
    except DECOMPRESSION_ERRORS as e:
        what = "not valid UTF-8 text" if isinstance(e, UnicodeDecodeError) else f"corrupt or truncated file ({e})"
        raise InputError(path, what, line=n + 1) from None


def read_numeric_table(path, fields: int, layout: str, what: str):
    """Rows of ``fields`` finite numbers from a whitespace-separated text file ('#' comments).

    Returns (rows as lists of floats, the first token of each row as written). Errors name the
    file and line: wrong field count (``layout`` describes the fields), non-numeric, non-finite.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    if path.is_dir():
        raise InputError(path, f"is a folder, not a file of {what}s")
    try:
        return _numeric_rows(path, fields, layout, what)
    except UnicodeDecodeError:
        raise InputError(path, f"not a text file of {what}s (it holds bytes that are not UTF-8; compressed?)") from None


def _numeric_rows(path, fields, layout, what):
    rows, firsts = [], []
    with open(path) as f:
        for n, line in enumerate(f, start=1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            if len(parts) != fields:
                raise InputError(path, f"{what} needs {fields} fields ({layout}), found {len(parts)}", line=n)
            try:
                v = [float(p) for p in parts]
            except ValueError:
                raise InputError(path, f"non-numeric field in {what}", line=n) from None
            if not all(math.isfinite(x) for x in v):
                raise InputError(path, f"non-finite value in {what}", line=n)
            rows.append(v)
            firsts.append(parts[0])
    if not rows:
        raise InputError(path, f"no {what}s in the file")
    return rows, firsts
