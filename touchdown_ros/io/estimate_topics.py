"""The `/touchdown/*` estimate topics: one definition for the offline output bags, the live node and
the replayer's recording, so that a bag from any of them opens the same way.

Each topic takes a (n, 3) vector, and for the covariance types its (n, 3, 3) linear block, from a
set of per-row signals with the fields of `core.estimate.SignalSet` (`StreamOutput` has them too).
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np

from touchdown_ros.core.estimate import force_std
from touchdown_ros.io.bags import TopicSeries
from touchdown_ros.io.config import Topics


class EstimateTopic(NamedTuple):
    """One estimate topic: where its name is configured, its message type and its columns."""

    name: str  # the field of `io.config.Topics` holding the topic name
    msgtype: str  # geometry_msgs type, short name
    vector: Callable[[Any], np.ndarray]  # signals -> (n, 3)
    covariance: Callable[[Any], np.ndarray] | None = None  # signals -> (n, 3, 3), the *WithCovarianceStamped ones

    def series(self, signals: Any, stamps_ns: np.ndarray, topics: Topics) -> TopicSeries:
        """This topic's messages of `signals`, one per row stamped `stamps_ns` (n,) ns."""
        covariance = None if self.covariance is None else np.asarray(self.covariance(signals))
        return TopicSeries(getattr(topics, self.name), self.msgtype, stamps_ns, np.asarray(self.vector(signals)),
                           covariance, frame_id=topics.frame_id)


#: In publishing order (sample by sample, all topics, as a bag replays them).
ESTIMATE_TOPICS = (
    EstimateTopic("displacement_estimate", "PointStamped", lambda s: s.state[:, :3]),  # m
    EstimateTopic("velocity", "TwistWithCovarianceStamped", lambda s: s.state[:, 4:7],  # m/s
                  lambda s: s.state_cov[:, 4:7, 4:7]),
    EstimateTopic("acceleration", "AccelWithCovarianceStamped", lambda s: s.acceleration,  # m/s^2
                  lambda s: s.acceleration_cov),
    EstimateTopic("contact_force", "WrenchStamped", lambda s: s.force_xyz),  # N, sensor axes
    EstimateTopic("contact_force_std", "Vector3Stamped", lambda s: force_std(s.force_cov)),  # N, 1-sigma per axis
)


def estimate_series(signals: Any, stamps_ns: np.ndarray, topics: Topics) -> list[TopicSeries]:
    """Every estimate topic of `signals` (`ESTIMATE_TOPICS`)."""
    return [topic.series(signals, stamps_ns, topics) for topic in ESTIMATE_TOPICS]
