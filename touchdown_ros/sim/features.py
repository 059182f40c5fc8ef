"""Paper features of a drop record (Section 5.3): axial impacts, first radial contact, force peaks, whirl."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from touchdown_ros.core.impacts import impact_spans
from touchdown_ros.sim.record import DropRecord


@dataclass(frozen=True)
class AxialImpact:
    """One axial impact (`core.impacts`: samples with z < -z0, runs closer than its merge gap joined)."""

    start: float  # s, first sample in contact (record time base)
    time: float  # s, sample of the peak
    peak: float  # N, largest F_z in the episode


@dataclass(frozen=True)
class DropFeatures:
    """What the paper reports about a drop (Section 5.3, Figures 6-8)."""

    impacts: tuple[AxialImpact, ...]  # axial impacts after the drop, in time order
    first_radial_contact: float | None  # s, first sample with r > r0 after the drop (record time base)
    peak_F_n: float  # N, largest radial force after the drop
    peak_F_z: float  # N, largest axial force after the drop
    bounces_before_radial: int  # axial impacts that start before the first radial contact
    largest_impact: int  # 0-based index into `impacts` of the largest axial impact
    force_ratio: float  # peak_F_n / peak_F_z
    whirl_direction: float  # mean sign of the orbit angular velocity after the first radial contact (+1 forward)
    radial_contact_share: float  # share of samples in radial contact after the first radial contact

    def describe(self) -> str:
        """One line for logs and reports."""
        first = "none" if self.first_radial_contact is None else f"{self.first_radial_contact:.4f} s"
        return (
            f"{len(self.impacts)} axial impacts, {self.bounces_before_radial} before radial contact ({first}); "
            f"largest #{self.largest_impact + 1} {self.peak_F_z / 1e3:.1f} kN; peak F_n {self.peak_F_n / 1e3:.1f} kN "
            f"(ratio {self.force_ratio:.2f}); whirl {self.whirl_direction:+.2f}, "
            f"clinging {self.radial_contact_share:.2f}"
        )


def axial_impacts(record: DropRecord, min_peak: float = 0.0) -> tuple[AxialImpact, ...]:
    """Axial impacts after the drop (`core.impacts.impact_spans`) whose peak F_z exceeds min_peak (N)."""
    start = record.drop_index
    flags, F_z, t = record.axial_contact[start:], record.F_z[start:], record.t[start:]
    impacts = []
    for a, b in zip(*impact_spans(flags)):
        k = a + int(np.argmax(F_z[a:b]))
        if F_z[k] > min_peak:
            impacts.append(AxialImpact(start=float(t[a]), time=float(t[k]), peak=float(F_z[k])))
    return tuple(impacts)


def drop_features(record: DropRecord) -> DropFeatures:
    """Extract the paper's features from the truth of a record."""
    start = record.drop_index
    impacts = axial_impacts(record)
    radial = np.flatnonzero(record.radial_contact[start:])
    first = float(record.t[start + radial[0]]) if radial.size else None
    before = sum(1 for i in impacts if first is None or i.start < first)
    peak_F_n = float(np.max(record.F_n[start:]))
    peak_F_z = float(np.max(record.F_z[start:]))
    largest = int(np.argmax([i.peak for i in impacts])) if impacts else -1
    whirl, share = 0.0, 0.0
    if radial.size:
        k = start + radial[0]
        x, y = record.position[k:, 0], record.position[k:, 1]
        vx, vy = record.velocity[k:, 0], record.velocity[k:, 1]
        whirl = float(np.mean(np.sign(x * vy - y * vx)))
        share = float(np.mean(record.radial_contact[k:]))
    return DropFeatures(
        impacts=impacts,
        first_radial_contact=first,
        peak_F_n=peak_F_n,
        peak_F_z=peak_F_z,
        bounces_before_radial=before,
        largest_impact=largest,
        force_ratio=peak_F_n / peak_F_z if peak_F_z > 0 else float("nan"),
        whirl_direction=whirl,
        radial_contact_share=share,
    )
