"""Exception hierarchy. The CLI turns every `Slam2dError` into one line and a non-zero exit."""
from __future__ import annotations


class Slam2dError(Exception):
    """Base of every error slam2d reports to a user as one line."""

    exit_code = 1


class InputError(Slam2dError):
    """Bad input data: names the file, the line or record, and what is wrong."""

    exit_code = 2

    def __init__(self, path, message: str, line: int | None = None, record: int | None = None):
        self.path = str(path)
        self.line = line
        self.record = record
        self.message = message
        where = self.path
        if line is not None:
            where += f":{line}"
        elif record is not None:
            where += f": record {record}"
        super().__init__(f"{where}: {message}")


class ConfigError(Slam2dError):
    """A bad configuration file or value; names the key."""

    exit_code = 2


class UsageError(Slam2dError):
    """A command-line usage mistake not caught by argparse (e.g. an output that cannot be written)."""

    exit_code = 2
