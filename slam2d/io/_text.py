"""Opening plain, gzip and bzip2 text files with errors that name the file."""
from __future__ import annotations

import bz2
import gzip
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


def iter_lines(path: str | Path):
    """Yield (line_number, text) with decompression/decoding errors turned into InputError."""
    n = 0
    f = open_text(path)
    try:
        with f:
            for n, line in enumerate(f, start=1):
                yield n, line
    except DECOMPRESSION_ERRORS as e:
        what = "not valid UTF-8 text" if isinstance(e, UnicodeDecodeError) else f"corrupt or truncated file ({e})"
        raise InputError(path, what, line=n + 1) from None
