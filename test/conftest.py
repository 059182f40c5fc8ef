"""What the tests share: simulated drop-test bags (the simulator's Table 1 experiments, truth included),
library effects by name, and a watch on XLA compilations."""
from __future__ import annotations

import threading
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np
import pytest

from touchdown_ros.core import effects as fx
from touchdown_ros.io.config import Config, load_config
from touchdown_ros.sim.bags import write_drop_bag
from touchdown_ros.sim.campaign import CAMPAIGN
from touchdown_ros.sim.record import DropRecord
from touchdown_ros.sim.simulator import simulate_drop


def write_simulated_bag(path: Path, experiment: int, seed: int, config: Config | None = None,
                        params=None) -> DropRecord:
    """Simulate Table 1 experiment `experiment` (1-based) with `seed` on the rig `config` (the reference
    rig if None; simulator `params` if given) and write it as a drop bag at `path`; returns the record."""
    config = config or load_config()
    record = simulate_drop(config, CAMPAIGN[experiment - 1], seed=seed, params=params)
    write_drop_bag(record, config, path)
    return record


def compilations(watched: set[str], run: Callable[[], Any]) -> tuple[Any, list[tuple[str, str]]]:
    """run()'s result and the (program, thread) of each XLA compilation of a `watched` jit name during it."""
    compiled: list[tuple[str, str]] = []

    def listener(event: str, duration: float, fun_name: str = "", **_) -> None:
        if event == "/jax/core/compile/backend_compile_duration" and fun_name in watched:
            compiled.append((fun_name, threading.current_thread().name))

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        return run(), compiled
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def central_differences(f, x, scales):
    """(len(f(x)), len(x)) Jacobian of f at x by central differences, step scales[j] along x_j."""
    x = np.asarray(x, dtype=float)
    columns = []
    for j, scale in enumerate(scales):
        step = np.zeros_like(x)
        step[j] = scale
        columns.append((np.asarray(f(x + step)) - np.asarray(f(x - step))) / (2 * scale))
    return np.stack(columns, axis=1)


def library_effects(names, values=None) -> fx.Effects:
    """Effects of the library (or dotted paths) by name, at their defaults overridden by `values`."""
    return fx.Effects(tuple(fx.resolve(n) for n in names)).with_values(values or {})


@pytest.fixture(scope="session")
def experiment_11_bag(tmp_path_factory) -> Path:
    """The reference rig's experiment 11 (brake and axial load) with seed 11, written once per test run."""
    path = tmp_path_factory.mktemp("simulated") / "exp_11"
    write_simulated_bag(path, 11, seed=11)
    return path
