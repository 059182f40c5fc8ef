"""Progress lines on stderr for long work: step, elapsed time, time left."""
from __future__ import annotations

import sys
import time
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")


class _CurrentStderr:
    """Writes to `sys.stderr` as it is at each write: a default argument `sys.stderr` would keep the
    stream of the moment the module was imported, past a caller's later redirection."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


#: The default progress stream of the workflows.
STDERR = _CurrentStderr()


def progress(items: Iterable[T], total: int, label: str, stream=STDERR) -> Iterator[T]:
    """Yield items, printing '[k/n] label: elapsed, ~left' after each one."""
    start = time.perf_counter()
    for done, item in enumerate(items, start=1):
        yield item
        elapsed = time.perf_counter() - start
        left = elapsed / done * (total - done)
        print(f"[{done}/{total}] {label}: {elapsed:.1f} s elapsed, ~{left:.0f} s left", file=stream, flush=True)
