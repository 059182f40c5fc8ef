"""The `/touchdown/*` estimate topics: one definition for the offline output bags, the live node and
the replayer's recording, so that a bag from any of them opens the same way.

Each topic takes a (n, 3) vector, and for the covariance types its (n, 3, 3) block, from a set of
per-row signals with the fields of `core.estimate.SignalSet` (`StreamOutput` has them too). The
vector fills the message's linear part, or its angular part for a rotation rate (the ring's speed).
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np

from touchdown_ros.core.estimate import force_std
from touchdown_ros.core.types import ContactLaw
from touchdown_ros.io.bags import TopicSeries
from touchdown_ros.io.config import Topics


class EstimateTopic(NamedTuple):
    """One estimate topic: where its name is configured, its message type and its columns."""

    name: str  # the field of `io.config.Topics` holding the topic name
    msgtype: str  # geometry_msgs type, short name
    vector: Callable[[Any], np.ndarray]  # signals -> (n, 3)
    covariance: Callable[[Any], np.ndarray] | None = None  # signals -> (n, 3, 3), the *WithCovarianceStamped ones
    angular: bool = False  # the vector fills the angular part (twist.angular, rad/s), the linear part zero
    ring: bool = False  # published only when the friction model has the ring's speed as a state

    def series(self, signals: Any, stamps_ns: np.ndarray, topics: Topics) -> TopicSeries:
        """This topic's messages of `signals`, one per row stamped `stamps_ns` (n,) ns."""
        covariance = None if self.covariance is None else np.asarray(self.covariance(signals))
        return TopicSeries(getattr(topics, self.name), self.msgtype, stamps_ns, np.asarray(self.vector(signals)),
                           covariance, frame_id=topics.frame_id, angular=self.angular)


def about_z(rate: np.ndarray) -> np.ndarray:
    """(n, 3) rad/s: rotation rates (n,) about the sensor z axis as angular velocity vectors."""
    rate = np.asarray(rate, dtype=np.float64)
    return np.stack([np.zeros_like(rate), np.zeros_like(rate), rate], axis=-1)


def about_z_covariance(std: np.ndarray) -> np.ndarray:
    """(n, 3, 3) (rad/s)^2: the covariance of `about_z`'s vectors, the variance std^2 (std (n,) rad/s) on z."""
    std = np.asarray(std, dtype=np.float64)
    covariance = np.zeros((len(std), 3, 3))
    covariance[:, 2, 2] = std**2
    return covariance


#: In publishing order (sample by sample, all topics, as a bag replays them).
ESTIMATE_TOPICS = (
    EstimateTopic("displacement_estimate", "PointStamped", lambda s: s.state[:, :3]),  # m
    EstimateTopic("velocity", "TwistWithCovarianceStamped", lambda s: s.state[:, 4:7],  # m/s
                  lambda s: s.state_cov[:, 4:7, 4:7]),
    EstimateTopic("acceleration", "AccelWithCovarianceStamped", lambda s: s.acceleration,  # m/s^2
                  lambda s: s.acceleration_cov),
    EstimateTopic("contact_force", "WrenchStamped", lambda s: s.force_xyz),  # N, sensor axes
    EstimateTopic("contact_force_std", "Vector3Stamped", lambda s: force_std(s.force_cov)),  # N, 1-sigma per axis
    EstimateTopic("ring_speed", "TwistWithCovarianceStamped", lambda s: about_z(s.ring_speed),  # rad/s about z
                  lambda s: about_z_covariance(s.ring_speed_std), angular=True, ring=True),
)


def published_topics(law: ContactLaw) -> tuple[EstimateTopic, ...]:
    """The estimate topics under a contact law: `ESTIMATE_TOPICS`, the ring's speed only when the
    law's friction model makes it a state (spinning_ring)."""
    has_ring = law.spins_ring
    return tuple(topic for topic in ESTIMATE_TOPICS if has_ring or not topic.ring)


def estimate_series(signals: Any, stamps_ns: np.ndarray, topics: Topics, law: ContactLaw) -> list[TopicSeries]:
    """Every estimate topic of `signals` under `law` (`published_topics`)."""
    return [topic.series(signals, stamps_ns, topics) for topic in published_topics(law)]
