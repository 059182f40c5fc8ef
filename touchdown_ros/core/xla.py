"""XLA settings of the core, applied when `touchdown_ros.core` is imported.

All are process-wide and read once, when JAX starts its CPU backend: importing the
core adds them to XLA_FLAGS unless an option is already there (set it yourself to
keep XLA's default, e.g. the small-loop threshold to 1024), and has no effect if the
process used JAX before importing the core.

Small loops. The EKF runs in `lax.scan` loops whose bodies are small (7 x 7 matrices). XLA's CPU
backend runs a loop body operation by operation through its runtime unless the loop's
buffers are smaller than `xla_cpu_small_while_loop_byte_threshold` (default 1 KiB);
then it compiles the whole loop into one function, about 3x cheaper per EKF row here
and about half the compilation time of the training gradient (bench/ekf_cost.py,
bench/train_cost.py).

Small matrix products inline. XLA's CPU backend hands some dot products to its YNNPACK library
as calls of their own (8 x 8, as with a spinning ring's eighth state, but not 7 x 7), which takes
them out of the small loop's single function: the live chunk of 16 rows with the ring's state cost
about 1.9 ms instead of about 0.3 ms, and an 8 x 8 covariance product in a loop 1.5 us instead of
0.4 us. `LIBRARY_DOT_OPTIONS` switches that off (2026-11-26; /tmp-free reproduction in
bench/ekf_cost.py's `--friction`).

Host devices. XLA shows the CPU as one device unless asked for more; the trainer
splits the records of a batch over one device per usable core (`shard_map` in
`core.training`), each filtering its share in its own loop. Everything else runs on
the first device as before.

Collective timeouts. The records' shares meet in an all-reduce; XLA aborts the process (SIGABRT)
when a device waits there more than 40 s for the other. The campaign's `touchdown train` died so
on 2026-11-25 and, with the limit raised, hung at no CPU on a quiet machine: a deadlock, not
slowness. Stage 1 summed its record chunks on the devices, so the chunks' programs and the sums of
their results were in flight together (JAX dispatches asynchronously); a loop of that sum alone
hung after 74 calls on the campaign. `core.calibration.stage1_value_and_grad_over` now waits for
each chunk on every device and sums on the host (the loop then ran 600 calls). The limits stay
raised (`COLLECTIVE_TIMEOUTS`: a warning after 60 s, the abort after 10 min) so that a loaded
machine's slow thread is not mistaken for one.

Compilation cache. The trainer's losses take 15-30 s to compile; `use_compilation_cache`
(called by the `touchdown` command, and by the node for every program) keeps compiled programs on disk, so a
second run of the same shapes starts at once. `TOUCHDOWN_XLA_CACHE` names the folder
(default `$XDG_CACHE_HOME/touchdown_ros/xla`, i.e. ~/.cache/...; at most 1 GiB, the least
recently used dropped first); `off` switches it off.
"""
from __future__ import annotations

import os

SMALL_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
SMALL_LOOP_BYTES = 1 << 30
HOST_DEVICES_OPTION = "--xla_force_host_platform_device_count"
#: Dot products compiled inline, not handed to the YNNPACK library (empty: no YNNPACK fusions).
LIBRARY_DOT_OPTIONS = {"--xla_cpu_experimental_ynn_fusion_type": ""}
#: XLA's CPU collective limits (s): abort after, and warn after, this long in one all-reduce.
COLLECTIVE_TIMEOUTS = {
    "--xla_cpu_collective_call_terminate_timeout_seconds": 600,
    "--xla_cpu_collective_call_warn_stuck_timeout_seconds": 60,
}


def with_small_loop_flag(xla_flags: str) -> str:
    """XLA_FLAGS value with the small-loop option added (kept as it is if already set)."""
    if SMALL_LOOP_OPTION in xla_flags:
        return xla_flags
    option = f"{SMALL_LOOP_OPTION}={SMALL_LOOP_BYTES}"
    flags = xla_flags.split()
    for i, flag in enumerate(flags):  # one --xla_backend_extra_options holds all (comma-separated)
        if flag.startswith("--xla_backend_extra_options="):
            flags[i] = f"{flag},{option}"
            return " ".join(flags)
    return " ".join([*flags, f"--xla_backend_extra_options={option}"])


def with_host_devices(xla_flags: str, count: int) -> str:
    """XLA_FLAGS value asking for `count` CPU devices (kept as it is if a count is already set)."""
    if HOST_DEVICES_OPTION in xla_flags:
        return xla_flags
    return " ".join([*xla_flags.split(), f"{HOST_DEVICES_OPTION}={count}"])


def with_options(xla_flags: str, options: dict[str, object]) -> str:
    """XLA_FLAGS value with `options` added (each kept as it is if already set)."""
    flags = xla_flags.split()
    for option, value in options.items():
        if option not in xla_flags:
            flags.append(f"{option}={value}")
    return " ".join(flags)


def with_collective_timeouts(xla_flags: str) -> str:
    """XLA_FLAGS value with `COLLECTIVE_TIMEOUTS` added (each kept as it is if already set)."""
    return with_options(xla_flags, COLLECTIVE_TIMEOUTS)


def usable_cores() -> int:
    """Cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


CACHE_VARIABLE = "TOUCHDOWN_XLA_CACHE"
CACHE_BYTES = 1 << 30  # least recently used programs are dropped beyond this


def compilation_cache_dir(environ: dict[str, str] | None = None) -> str | None:
    """Folder of the persistent compilation cache from the environment (None: switched off):
    TOUCHDOWN_XLA_CACHE, else JAX's own JAX_COMPILATION_CACHE_DIR, else the default."""
    environ = os.environ if environ is None else environ
    chosen = environ.get(CACHE_VARIABLE, "") or environ.get("JAX_COMPILATION_CACHE_DIR", "")
    if chosen.lower() == "off":
        return None
    if chosen:
        return chosen
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "touchdown_ros", "xla")


def use_compilation_cache(min_compile_seconds: float = 1.0) -> str | None:
    """Keep programs that took at least `min_compile_seconds` to compile in
    `compilation_cache_dir()`; its path."""
    import jax

    directory = compilation_cache_dir()
    if directory is not None:
        jax.config.update("jax_compilation_cache_dir", directory)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_seconds)
        jax.config.update("jax_compilation_cache_max_size", CACHE_BYTES)
    return directory


def configure() -> None:
    """Small-loop option, inline dot products, one host device per usable core and the collective
    timeouts in this process's XLA_FLAGS (before JAX starts its backend)."""
    flags = with_options(with_small_loop_flag(os.environ.get("XLA_FLAGS", "")), LIBRARY_DOT_OPTIONS)
    os.environ["XLA_FLAGS"] = with_collective_timeouts(with_host_devices(flags, usable_cores()))
