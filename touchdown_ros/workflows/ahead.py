"""Programs compiled in a background thread while the work before their first call goes on.

XLA compiles a program on one core; `touchdown train` compiles stage 1's objective, then, a minute
later, the standard errors' and stage 2's programs, each while the other core waits. Their arguments'
shapes are known from the bags and the rig YAML before stage 1 starts, and the programs take the
calibrated values as arguments, so they can be compiled while stage 1's is: `jit(f).lower(...).compile()`
fills the same cache the later call looks in (JAX's, in memory, and the persistent one on disk).
`diagnose` does the same with its fits' measures and standard errors while the first fit compiles the loss.
"""
from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable

from touchdown_ros.workflows.progress import STDERR


#: Name (prefix) of the background thread.
THREAD_NAME = "touchdown-compile-ahead"
#: s; a wait for a compilation at least this long is reported (where the work waited instead of computing).
REPORTED_WAIT = 1.0


class Ahead:
    """A queue of compilations run one at a time in a background thread, in the order given (those queued
    with `compile_first` before the others), from `start`; one waited for before its turn is compiled at
    once in a second thread.

    Tracing a program is Python, which holds the interpreter's lock: begun while the caller's own
    Python work goes on (reading bags, the data's scales), it slows that work by as much. So the
    compilations wait for `start`, called where the caller itself compiles (and XLA releases the lock)."""

    def __init__(self, stream=STDERR):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=THREAD_NAME)
        # a job waited for while it is still queued behind others: compiled at once beside them
        self._needed = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"{THREAD_NAME}-needed")
        self._queued: dict[str, Callable[[], Any]] = {}
        self._jobs: dict[str, tuple[Future, Callable[[], Any]]] = {}
        self._stream = stream
        self._started = False

    def compile(self, name: str, jitted: Any, *args: Any, **kwargs: Any) -> None:
        """Queue `jitted.lower(*args, **kwargs).compile()` under `name`: the arguments as the later call
        passes them (positional or keyword alike; leaves strongly typed), their values unused."""
        self._queued[name] = lambda: jitted.lower(*args, **kwargs).compile()
        if self._started:
            self.start()

    def compile_first(self, name: str, jitted: Any, *args: Any, **kwargs: Any) -> None:
        """`compile`, but before the compilations queued so far (a program needed sooner), if `start` is
        still to come; after it, in turn like any other."""
        self.compile(name, jitted, *args, **kwargs)
        if name in self._queued:
            self._queued = {name: self._queued.pop(name), **self._queued}

    def start(self) -> None:
        """Begin the queued compilations (those queued later begin at once)."""
        self._started = True
        for name, build in self._queued.items():
            self._jobs[name] = (self._pool.submit(build), build)
        self._queued.clear()

    def wait(self, name: str) -> None:
        """Block until `name` is compiled (the later call then finds it instead of compiling it a second
        time beside the first); one never started is dropped (the call compiles it). One still waiting
        behind others in the queue is compiled at once, beside the one under way (the caller's core is
        idle meanwhile). A failure only means the call compiles it: a note says so, no error. A wait of
        REPORTED_WAIT or more is reported."""
        self._queued.pop(name, None)
        job, build = self._jobs.pop(name, (None, None))
        if job is None:
            return
        if job.cancel():  # still queued
            job = self._needed.submit(build)
        started = time.perf_counter()
        try:
            job.result()
        except Exception as error:  # noqa: BLE001 (an optimisation failed: the call compiles it itself)
            print(f"note: compiling {name} ahead failed ({type(error).__name__}: {error}); compiled when needed",
                  file=self._stream, flush=True)
            return
        waited = time.perf_counter() - started
        if waited >= REPORTED_WAIT:
            print(f"[compile] waited {waited:.1f} s for {name}", file=self._stream, flush=True)

    def close(self) -> None:
        """Drop the compilations not yet started; one under way finishes in the background."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._needed.shutdown(wait=False)

    def __enter__(self) -> "Ahead":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
