"""What the tests share: simulated drop-test bags (the simulator's Table 1 experiments, truth included),
library effects by name, and a watch on XLA compilations."""
from __future__ import annotations

import gc
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


#: Memory maps of this process above which the compiled programs are let go after a test. XLA's CPU code stays
#: mapped while a jit cache holds it (three or more maps per compiled function); the kernel allows 65530 maps per
#: process (vm.max_map_count). The whole suite in one process grew past 37 000 maps and 10 GB inside
#: test_diagnose.py alone, and with the spinning ring's larger programs an XLA compilation aborted the process
#: half-way through the suite (2026-11-29).
MAPS_TO_LET_GO = 20_000


def pytest_configure(config) -> None:
    config.addinivalue_line(
        "markers",
        "acceptance: an issue's gate on the simulated rig family, minutes each (`make acceptance`; `make test` leaves "
        "them out to stay within CI's 90 minutes)",
    )


def _memory_maps() -> int:
    """Memory maps of this process (0 where /proc is not there)."""
    try:
        with open("/proc/self/maps") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return 0


def _let_go_of_compiled_programs() -> None:
    """Drop JAX's caches of compiled programs (their memory maps) but keep its traced and lowered ones: tracing the
    filter's programs again took about a third of a hidden-effect test's time (151 s of 468 s, 2026-12-03), and the
    same program compiles again from the run's on-disk cache (scripts/run_tests.py). Private JAX caches (0.10): where
    one is missing, all caches are cleared as `jax.clear_caches` does."""
    try:
        from jax._src import pjit
        from jax._src.interpreters import pxla
        from jax._src.lib import _jax

        compiled = (pjit._pjit_lower, pxla._cached_compilation)
        fast_paths = (pjit._cpp_pjit_cache_fun_only, pjit._cpp_pjit_cache_explicit_attributes)
        every_function = _jax.PjitFunctionCache
    except (ImportError, AttributeError):
        jax.clear_caches()
    else:
        for cache in compiled:
            cache.cache_clear()
        for cache in fast_paths:
            cache.clear()
        every_function.clear_all()
    gc.collect()


@pytest.fixture(autouse=True, scope="module")
def _compiled_programs_let_go_after_each_file():
    """Each test file's compiled programs are let go when it ends (`MAPS_TO_LET_GO`)."""
    yield
    _let_go_of_compiled_programs()


@pytest.fixture(autouse=True)
def _compiled_programs_let_go_after_a_test_past_the_limit():
    """Within a file, the compiled programs are let go after a test that leaves more than `MAPS_TO_LET_GO` maps."""
    yield
    if _memory_maps() > MAPS_TO_LET_GO:
        _let_go_of_compiled_programs()


def write_simulated_bag(path: Path, experiment: int, seed: int, config: Config | None = None,
                        params=None) -> DropRecord:
    """Simulate Table 1 experiment `experiment` (1-based) with `seed` on the rig `config` (the reference
    rig if None; simulator `params` if given) and write it as a drop bag at `path`; returns the record."""
    config = config or load_config()
    record = simulate_drop(config, CAMPAIGN[experiment - 1], seed=seed, params=params)
    write_drop_bag(record, config, path)
    return record


def compilations(watched: set[str], run: Callable[[], Any]) -> tuple[Any, list[tuple[str, str]]]:
    """run()'s result and the (program, thread) of each XLA compilation of a `watched` jit name by run(): in
    the calling thread or a thread started during it. A compilation an earlier test left under way in its
    background thread (`Ahead.close` lets it finish) is not run()'s, though it may end during it."""
    compiled: list[tuple[str, str]] = []
    earlier = set(threading.enumerate()) - {threading.current_thread()}

    def listener(event: str, duration: float, fun_name: str = "", **_) -> None:
        thread = threading.current_thread()
        if event == "/jax/core/compile/backend_compile_duration" and fun_name in watched and thread not in earlier:
            compiled.append((fun_name, thread.name))

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


def band_added_and_by_hand(exact, uncertain, state, P, rescaled_law, log_covariance):
    """((3, 3), (3, 3)) N^2: what the force covariance of `uncertain` (a model whose law carries `log_covariance`
    of two constants) adds to `exact`'s at `state` with covariance P (`core.estimate.signals`), and J C J^T with J
    the force's derivative by the two logarithms by central differences (`rescaled_law(log_scale)`: exact's law
    with the two constants times exp(log_scale))."""
    import jax.numpy as jnp

    from touchdown_ros.core.dynamics import contact_force_xyz, contact_forces
    from touchdown_ros.core.ekf import Belief
    from touchdown_ros.core.estimate import signals

    def force_xyz(log_scale):
        return contact_force_xyz(contact_forces(exact._replace(law=rescaled_law(log_scale)), jnp.asarray(state)))

    J = central_differences(force_xyz, np.zeros(2), [1e-6, 1e-6])
    belief = Belief(jnp.asarray(state)[None], jnp.asarray(P)[None])
    added = np.asarray(signals(uncertain, belief).force_cov - signals(exact, belief).force_cov)[0]
    return added, J @ np.asarray(log_covariance) @ J.T


def library_effects(names, values=None) -> fx.Effects:
    """Effects of the library (or dotted paths) by name, at their defaults overridden by `values`."""
    return fx.Effects(tuple(fx.resolve(n) for n in names)).with_values(values or {})


@pytest.fixture(scope="session")
def experiment_11_bag(tmp_path_factory) -> Path:
    """The reference rig's experiment 11 (brake and axial load) with seed 11, written once per test run."""
    path = tmp_path_factory.mktemp("simulated") / "exp_11"
    write_simulated_bag(path, 11, seed=11)
    return path
