"""What the streaming estimator needs besides the model: the input policy, the drop rule and its own limits."""
from __future__ import annotations

from dataclasses import dataclass

from touchdown_ros.core.estimate import DropDetector
from touchdown_ros.core.input_policy import InputPolicy


@dataclass(frozen=True)
class StreamSettings:
    """Settings of `StreamingEstimator`; SI units.

    The defaults here are the documented ones (docs/node.md); the live node's `node.*`
    parameters take theirs from these and from `InputPolicy`. `Config.stream_settings()`
    builds the settings of a rig YAML.
    """

    policy: InputPolicy  # sample grid, refused values, bridged holes and clock jumps (as offline)
    drop: DropDetector  # levitated window and drop onset (as offline)
    initial_samples: int = 5  # samples averaged for the initial position (as offline)
    resync_after: int = 20  # consecutive out-of-order / off-grid samples that re-anchor the grid
    relevitation_band: float = 20.0e-6  # m around the levitated mean (x, y and z)
    relevitation_window: float = 0.005  # s inside the band that ends a touchdown
    alarm_force: float = 5.0e4  # N, |contact force| that raises a force alarm
    chunk_sizes: tuple[int, ...] = (8, 16, 32, 64, 128, 256, 512)  # compiled EKF chunk lengths

    @property
    def sample_period(self) -> float:
        """s, the sensor grid."""
        return self.policy.sample_period

    @property
    def relevitation_samples(self) -> int:
        """Grid rows in the levitated band that end a touchdown."""
        return max(1, int(round(self.relevitation_window / self.sample_period)))
