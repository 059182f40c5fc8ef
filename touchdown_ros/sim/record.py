"""What one simulated drop test is run under and what it produces."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DropCondition:
    """One row of the paper's Table 1."""

    number: int  # experiment number, 1-based
    speed_rpm: float  # rotor speed at the drop, rpm
    brake: bool  # drive-motor brake applied at the drop
    axial_load: bool  # additional axial load (about 2000 N downward) from the axial loader
    ball: str  # auxiliary-bearing ball material: "ceramic" or "steel"


@dataclass(frozen=True, eq=False)
class DropRecord:
    """One simulated drop at the sensor rate: measurements and the truth behind them (SI units)."""

    condition: DropCondition
    stamps_ns: np.ndarray  # (N,) int64, absolute sample times, ns since the Unix epoch
    t: np.ndarray  # (N,) s from the first sample
    drop_time: float  # s, instant the AMB force starts to decay, same time base as t
    measured: np.ndarray  # (N, 3) m, sensor output: position + noise, quantised
    position: np.ndarray  # (N, 3) m, true geometric-centre displacement
    velocity: np.ndarray  # (N, 3) m/s
    acceleration: np.ndarray  # (N, 3) m/s^2, second derivative of position (all forces)
    contact_force: np.ndarray  # (N, 3) N, force of the bearing on the rotor, sensor x/y/z
    F_n: np.ndarray  # (N,) N, radial component, positive towards the centre
    F_t: np.ndarray  # (N,) N, component along (sin a, -cos a)
    F_z: np.ndarray  # (N,) N, axial component, positive up
    radial_contact: np.ndarray  # (N,) bool, r > r0
    axial_contact: np.ndarray  # (N,) bool, z < -z0
    omega: np.ndarray  # (N,) rad/s, rotor spin speed
    omega_ring: np.ndarray  # (N,) rad/s, auxiliary-bearing inner-ring spin speed
    seed: int = 0

    @property
    def sample_period(self) -> float:
        """s between samples."""
        return float(self.t[1] - self.t[0])

    @property
    def drop_index(self) -> int:
        """Index of the first sample at or after the drop."""
        return int(np.searchsorted(self.t, self.drop_time - 1e-12))
