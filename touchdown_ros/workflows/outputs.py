"""Where a command writes: checked writable before the work, removed again if the command fails."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from types import TracebackType
from typing import Iterable


class OutputError(OSError):
    """An output place cannot be written (read-only, not a directory, ...); the message names it."""


def _nearest_existing(path: Path) -> Path:
    path = path.absolute()
    for candidate in (path, *path.parents):
        if os.path.lexists(candidate):
            return candidate
    return Path("/")


def check_writable(path: str | Path, directory: bool) -> None:
    """Raise OutputError unless `path` (a directory to fill, or a file to write) can be created
    or written: a file or directory in the way, a read-only place. Probes by creating and removing
    a temporary file where the output goes (permission bits alone do not stop root)."""
    path = Path(path)
    if directory and path.exists() and not path.is_dir():
        raise OutputError(f"{path}: exists and is not a directory")
    if not directory and path.is_dir():
        raise OutputError(f"{path}: is a directory; give a file name")
    place = path if directory and path.is_dir() else _nearest_existing(path.parent)
    if not place.is_dir():
        raise OutputError(f"{place}: is not a directory, cannot write {path} below it")
    try:
        handle, probe = tempfile.mkstemp(prefix=".touchdown_probe.", dir=place)
        os.close(handle)
        os.unlink(probe)
    except OSError as error:
        raise OutputError(f"{path}: cannot write there ({place}: {error.strerror or error})") from None


class OutputGuard:
    """Context: the given paths that do not exist on entry are removed again if the block fails,
    so that a failed command leaves nothing behind (an existing path is never touched)."""

    def __init__(self, paths: Iterable[str | Path], keep_on_interrupt: Iterable[str | Path] = ()):
        self.new = [Path(p) for p in paths if not os.path.lexists(p)]
        self.keep_on_interrupt = {Path(p) for p in keep_on_interrupt}

    def __enter__(self) -> "OutputGuard":
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        if kind is None:
            return
        for path in self.new:
            if kind is KeyboardInterrupt and path in self.keep_on_interrupt:
                continue
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            elif os.path.lexists(path):
                try:
                    path.unlink()
                except OSError:
                    pass
