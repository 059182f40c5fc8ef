"""The paper's 21 touchdown experiments (Table 1) and running them all."""
from __future__ import annotations

from typing import Callable, Iterator

from touchdown_ros.io.config import Config
from touchdown_ros.sim.params import simulator_parameters
from touchdown_ros.sim.record import DropCondition, DropRecord
from touchdown_ros.sim.simulator import simulate_drop

_NO, _YES = False, True
# (brake, additional axial load, ball) for experiments 1..21, all at 5000 rpm (Table 1).
_TABLE_1 = (
    *[(_NO, _NO, "ceramic")] * 5,  # 1-5
    *[(_YES, _NO, "ceramic")] * 2,  # 6-7
    *[(_YES, _YES, "ceramic")] * 5,  # 8-12
    *[(_YES, _NO, "ceramic")] * 2,  # 13-14
    *[(_YES, _YES, "ceramic")] * 6,  # 15-20
    (_NO, _NO, "steel"),  # 21
)

CAMPAIGN: tuple[DropCondition, ...] = tuple(
    DropCondition(number=i + 1, speed_rpm=5000.0, brake=brake, axial_load=load, ball=ball)
    for i, (brake, load, ball) in enumerate(_TABLE_1)
)


def simulate_campaign(
    config: Config,
    seed: int = 0,
    progress: Callable[[int, int, DropCondition], None] | None = None,
    conditions: tuple[DropCondition, ...] = CAMPAIGN,
) -> Iterator[DropRecord]:
    """Yield one record per condition (default: all of Table 1); experiment N uses seed + N (as the CLI).

    `progress(done, total, condition)` is called before each experiment is simulated.
    """
    params = simulator_parameters(config)
    for done, condition in enumerate(conditions):
        if progress is not None:
            progress(done, len(conditions), condition)
        yield simulate_drop(config, condition, seed + condition.number, params=params)


__all__ = ["CAMPAIGN", "DropCondition", "simulate_campaign"]
