"""XLA settings of the core, applied when `touchdown_ros.core` is imported.

Both are process-wide and read once, when JAX starts its CPU backend: importing the
core adds them to XLA_FLAGS unless an option is already there (set it yourself to
keep XLA's default, e.g. the small-loop threshold to 1024), and has no effect if the
process used JAX before importing the core.

Small loops. The EKF runs in `lax.scan` loops whose bodies are small (7 x 7 matrices). XLA's CPU
backend runs a loop body operation by operation through its runtime unless the loop's
buffers are smaller than `xla_cpu_small_while_loop_byte_threshold` (default 1 KiB);
then it compiles the whole loop into one function, about 3x cheaper per EKF row here
and about half the compilation time of the training gradient (bench/ekf_cost.py,
bench/train_cost.py).

Host devices. XLA shows the CPU as one device unless asked for more; the trainer
splits the records of a batch over one device per usable core (`shard_map` in
`core.training`), each filtering its share in its own loop. Everything else runs on
the first device as before.
"""
from __future__ import annotations

import os

SMALL_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
SMALL_LOOP_BYTES = 1 << 30
HOST_DEVICES_OPTION = "--xla_force_host_platform_device_count"


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


def usable_cores() -> int:
    """Cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def configure() -> None:
    """Small-loop option and one host device per usable core in this process's XLA_FLAGS
    (before JAX starts its backend)."""
    flags = with_small_loop_flag(os.environ.get("XLA_FLAGS", ""))
    os.environ["XLA_FLAGS"] = with_host_devices(flags, usable_cores())
