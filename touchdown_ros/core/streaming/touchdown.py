"""Running figures of the touchdown in progress, summarised when it ends."""
from __future__ import annotations

import math

import numpy as np

from touchdown_ros.core.impacts import ImpactCounter
from touchdown_ros.core.streaming.outputs import StreamOutput, TouchdownSummary


class TouchdownTally:
    """Running figures of the touchdown in progress."""

    def __init__(self, onset_stamp_ns: int):
        self.onset_stamp_ns = onset_stamp_ns
        self.end_stamp_ns = onset_stamp_ns
        self.samples = self.missing = 0
        self.axial_impacts, self.radial_impacts = ImpactCounter(), ImpactCounter()
        self.peak_axial = self.peak_radial = -math.inf
        self.nis_sum, self.nis_count = 0.0, 0
        self.scale_sum, self.scale_max = 0.0, math.nan  # the filter's factor on Q over the rows
        self.restarts = 0

    def add(self, out: StreamOutput) -> None:
        n = len(out.stamps_ns)
        if n == 0:
            return
        used = out.used
        n_used = int(np.count_nonzero(used))
        self.samples += n
        self.missing += n - n_used
        self.end_stamp_ns = int(out.stamps_ns[-1])
        self.axial_impacts.add(out.axial_contact)
        self.radial_impacts.add(out.radial_contact)
        self.scale_sum += float(out.process_scale.sum())
        self.scale_max = float(np.fmax(self.scale_max, out.process_scale.max()))  # fmax: past the initial NaN
        if n_used:  # predict-only rows (gaps, refused values) are left out of the peaks, as offline
            self.peak_axial = max(self.peak_axial, float(out.F_z[used].max()))
            fx, fy = out.force_xyz[used, 0], out.force_xyz[used, 1]
            self.peak_radial = max(self.peak_radial, math.sqrt(float((fx * fx + fy * fy).max())))
        if n_used:  # NIS is NaN exactly where the measurement was not used
            self.nis_sum += float(out.nis[used].sum())
            self.nis_count += n_used

    def summary(self, end_reason: str) -> TouchdownSummary:
        return TouchdownSummary(
            onset_stamp_ns=self.onset_stamp_ns,
            end_stamp_ns=self.end_stamp_ns,
            samples=self.samples,
            missing_samples=self.missing,
            axial_impacts=self.axial_impacts.count,
            radial_impacts=self.radial_impacts.count,
            peak_axial_force=self.peak_axial if self.nis_count else math.nan,
            peak_radial_force=self.peak_radial if self.nis_count else math.nan,
            mean_nis=self.nis_sum / self.nis_count if self.nis_count else math.nan,
            end_reason=end_reason,
            filter_restarts=self.restarts,
            process_scale_mean=self.scale_sum / self.samples if self.samples else math.nan,
            process_scale_max=self.scale_max,
        )
