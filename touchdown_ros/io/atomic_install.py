"""Putting a freshly written bag in place atomically: a new path is created in one rename, an existing
bag is swapped out in one step where Linux allows (renameat2), and never anything that is not a bag."""
from __future__ import annotations

import ctypes
import errno
import functools
import os
from pathlib import Path
from typing import Any


def _is_bag(path: Path) -> bool:
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or not any(path.iterdir())
    return path.suffix == ".mcap"


def check_target(path: Path, overwrite: bool) -> None:
    """Raise FileExistsError if path exists, unless overwrite and it is a bag (a bag directory or an .mcap file)."""
    if not (path.exists() or path.is_symlink()):
        return
    if not overwrite:
        raise FileExistsError(f"{path} exists; refusing to overwrite it (pass overwrite)")
    if path.is_symlink() or not _is_bag(path):
        raise FileExistsError(f"{path} exists and is not a rosbag2 directory or .mcap file; refusing to replace it")


def fsync(path: Path) -> None:
    """Flush a file or directory to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_tree(path: Path) -> None:
    """Flush a file, or a directory and everything below it, to disk."""
    for item in sorted(path.rglob("*")) if path.is_dir() else []:
        fsync(item)
    fsync(path)


_RENAME_NOREPLACE, _RENAME_EXCHANGE, _AT_FDCWD = 1, 2, -100


@functools.lru_cache(maxsize=1)
def _renameat2_function() -> Any:
    return getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)


def _renameat2(src: Path, dst: Path, flags: int) -> bool:
    """Linux renameat2(2); False when the C library or the file system does not support it."""
    function = _renameat2_function()
    if function is None:
        return False
    if function(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst), flags) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    if code == errno.EEXIST:
        raise FileExistsError(code, f"{dst} appeared while writing; refusing to overwrite it", str(dst))
    raise OSError(code, os.strerror(code), str(dst))


def install(built: Path, path: Path, overwrite: bool) -> None:
    """Move built to path; an existing bag is swapped out in one step where the OS allows
    (renameat2 RENAME_EXCHANGE) and left at built, inside the staging directory."""
    if not (path.exists() or path.is_symlink()):
        if not _renameat2(built, path, _RENAME_NOREPLACE):
            if path.exists():
                raise FileExistsError(f"{path} appeared while writing; refusing to overwrite it")
            os.rename(built, path)
        return
    check_target(path, overwrite)
    if not _renameat2(built, path, _RENAME_EXCHANGE):
        old = built.with_name(built.name + ".replaced")
        os.rename(path, old)
        try:
            os.rename(built, path)
        except BaseException:
            os.rename(old, path)  # put the old bag back before the staging directory is removed
            raise
