"""Simulated drops as rosbag2 MCAP bags: the displacement topic, the truth topics and the drop's
Table 1 conditions, as a drop-test rig would record them."""
from __future__ import annotations

from pathlib import Path

from touchdown_ros.io.bags import CONDITION_PREFIX, TopicSeries, write_bag
from touchdown_ros.io.config import Config
from touchdown_ros.sim.record import DropCondition, DropRecord


def conditions_of(condition: DropCondition) -> dict[str, str]:
    """A Table 1 row as the bag's `condition.*` custom data (what an experimenter logs)."""
    return {
        f"{CONDITION_PREFIX}{name}": (str(value).lower() if isinstance(value, bool) else str(value))
        for name, value in vars(condition).items()
    }


def write_drop_bag(record: DropRecord, config: Config, out: Path, overwrite: bool = False) -> Path:
    """A simulated drop as a bag: `/amb/displacement` plus the `/truth/...` topics, and the
    experiment's conditions (brake, axial load, ball) in metadata.yaml (not for a bare .mcap)."""
    topics, frame, stamps = config.topics, config.topics.frame_id, record.stamps_ns
    write_bag(
        out,
        [
            TopicSeries(topics.displacement, "PointStamped", stamps, record.measured, frame_id=frame),
            TopicSeries(topics.truth_velocity, "Vector3Stamped", stamps, record.velocity, frame_id=frame),
            TopicSeries(topics.truth_acceleration, "Vector3Stamped", stamps, record.acceleration, frame_id=frame),
            TopicSeries(topics.truth_contact_force, "WrenchStamped", stamps, record.contact_force, frame_id=frame),
        ],
        overwrite=overwrite,
        custom_data=None if Path(out).suffix == ".mcap" else conditions_of(record.condition),
    )
    return out
