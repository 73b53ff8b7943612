"""Paths a user hands daemodel to write to, checked before the work that produces the file.

A typo in a directory should cost a second, not a training run or a whole comparison: every
place that writes a user-named file or directory checks it here first.
"""

from __future__ import annotations

import os
from pathlib import Path

from daemodel.errors import InvalidOptionError


def writable_file(path, argument: str) -> Path:
    """``path`` (``~`` expanded) if a file can be written there, else an :class:`InvalidOptionError`
    naming ``argument``, the path and the fix."""
    if not isinstance(path, str | os.PathLike):
        raise InvalidOptionError(f"{argument} must be a file path (str or Path); got {type(path).__name__}")
    path = Path(path).expanduser()
    if path.is_dir():
        raise InvalidOptionError(f"{argument} = '{path}' is a directory; give a file name in it")
    if not path.parent.is_dir():
        raise InvalidOptionError(
            f"{argument} = '{path}': the directory '{path.parent}' does not exist; create it first or write elsewhere"
        )
    if not os.access(path.parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise InvalidOptionError(f"{argument} = '{path}' is not writable; write elsewhere")
    return path


def writable_directory(path, argument: str) -> Path:
    """``path`` (``~`` expanded), created if missing, with a probe file written and removed in it;
    else an :class:`InvalidOptionError` naming ``argument``, the path and the reason."""
    if not isinstance(path, str | os.PathLike):
        raise InvalidOptionError(f"{argument} must be a directory path (str or Path); got {type(path).__name__}")
    path = Path(path).expanduser()
    if path.exists() and not path.is_dir():
        raise InvalidOptionError(f"{argument} {path} is an existing file, not a directory; give a directory")
    probe = path / f".daemodel-write-check-{os.getpid()}"
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe.write_text("")
        probe.unlink()
    except OSError as error:
        reason = error.strerror or str(error)
        where = f" ({error.filename})" if error.filename and str(error.filename) != str(path) else ""
        raise InvalidOptionError(
            f"{argument} {path} cannot be created or written: {reason}{where}; give a writable directory"
        ) from None
    return path
