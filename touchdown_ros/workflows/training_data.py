"""Training data: drop records read from bags, batched for the filter and spread over the host's devices."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from touchdown_ros.core.effects import Effects, gates_for
from touchdown_ros.core.estimate import to_grid
from touchdown_ros.core.input_policy import InputPolicy
from touchdown_ros.core.training import RECORDS, Batch, make_batch, pad_records
from touchdown_ros.io.bags import read_conditions, read_displacement
from touchdown_ros.io.config import Config
from touchdown_ros.workflows.offline import NoDropError


@dataclass(frozen=True)
class TrainingData:
    """Records from the drop onset on, with the bags they came from."""

    paths: tuple[Path, ...]
    records: tuple[np.ndarray, ...]  # each (N_b, 3) m, NaN rows for missing samples
    conditions: tuple[dict[str, str], ...] = ()  # each bag's recorded test conditions (condition.*)
    levitated: tuple[np.ndarray, ...] = ()  # each bag's samples before the drop onset, (M_b, 3) m

    def subset(self, keep: Sequence[int]) -> "TrainingData":
        """The bags at the indices `keep`, with all they carry."""
        pick = lambda items: tuple(items[i] for i in keep) if items else ()  # noqa: E731
        return TrainingData(pick(self.paths), pick(self.records), pick(self.conditions), pick(self.levitated))

    def gates(self, effects: Effects) -> list[tuple[float, ...]]:
        """Each record's gates of `effects` by its bag's conditions (none recorded: a conditional effect is off)."""
        return [gates_for(effects, c) for c in self.conditions or ({},) * len(self.records)]


def load_training_data(config: Config, paths: Sequence[str | Path], duration: float | None = None) -> TrainingData:
    """Read and validate every bag (all of them before any work), keep the samples after the drop
    and, apart, the levitated samples before it (for the sensor noise)."""
    records, conditions, levitated = [], [], []
    for path in paths:
        conditions.append(read_conditions(path))
        series = read_displacement(path, config.topics.displacement)
        grid = to_grid(
            series.stamps_ns, series.xyz, config.sample_period, policy=InputPolicy.from_config(config), source=str(path)
        )
        onset = config.drop_detector().onset(grid.etas[:, 2])
        if onset is None:
            raise NoDropError(f"{path}: no touchdown found, cannot train on it")
        record = grid.etas[onset:]
        if duration is not None:
            record = record[: int(round(duration / config.sample_period))]
        records.append(record)
        levitated.append(grid.etas[:onset])
    return TrainingData(tuple(Path(p) for p in paths), tuple(records), tuple(conditions), tuple(levitated))


def record_mesh() -> Mesh | None:
    """The host's XLA devices (one per usable core, `core.xla`) as one mesh axis over the
    records of a batch; None with a single device."""
    devices = jax.devices()
    return Mesh(np.array(devices), (RECORDS,)) if len(devices) > 1 else None


def place(batch: Batch, mesh: Mesh | None) -> Batch:
    """The batch padded to a multiple of the mesh size and split over its devices."""
    if mesh is None:
        return batch
    return jax.device_put(pad_records(batch, mesh.size), NamedSharding(mesh, P(RECORDS)))


def training_batch(
    config: Config, data: TrainingData, effects: Effects, length: int | None = None, size: int | None = None
) -> Batch:
    """The records as one batch on `record_mesh()`, each with its effects' gates; with `size`, padded
    to that many records (`pad_records`: the copies count nowhere)."""
    batch = make_batch(list(data.records), np.asarray(config.noise.initial), length, data.gates(effects))
    return place(batch if size is None else pad_records(batch, size), record_mesh())


def training_chunks(
    config: Config, data: TrainingData, effects: Effects, size: int, length: int | None = None
) -> tuple[Batch, ...]:
    """The records as `training_batch`es of `size` records each (the last padded) and one `length`:
    one compiled program serves every chunk."""
    length = length or max(len(r) for r in data.records)
    count = len(data.records)
    return tuple(
        training_batch(config, data.subset(range(first, min(first + size, count))), effects, length, size)
        for first in range(0, count, size)
    )


def note_ungated(effects: Effects, batches: Sequence[Batch], stream) -> None:
    """A note for each effect that acts in none of the records of the batches (its parameters cannot move)."""
    gates = np.concatenate([np.asarray(b.gates)[np.asarray(b.valid).any(axis=1)] for b in batches])
    for index, name in enumerate(effects.names):
        if not gates[:, index].any():
            print(
                f"note: effect {name} acts in none of the bags (it needs condition "
                f"{effects.effects[index].when!r}); its parameters stay at their starting values",
                file=stream,
            )
