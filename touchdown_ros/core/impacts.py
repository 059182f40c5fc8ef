"""What counts as an impact: one definition for every output that numbers or counts them.

An impact is a run of contact samples (a contact flag, or a force above a threshold);
runs fewer than `MERGE_GAP` samples apart are one impact (contact chatter at the
switching instant). The node's touchdown summary, diagnose's impact numbers, evaluate's
per-impact peaks and the simulator's paper features all segment with `impact_spans`.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

#: Contact runs separated by fewer samples than this are one impact.
MERGE_GAP = 10


class ImpactSpans(NamedTuple):
    """Impacts as index ranges: samples start[i] to stop[i] - 1; the gaps inside are shorter than the merge gap."""

    start: np.ndarray  # (k,) int
    stop: np.ndarray  # (k,) int, exclusive


def contact_runs(contact: np.ndarray) -> ImpactSpans:
    """The runs of True in `contact` (n,), unmerged."""
    padded = np.concatenate([[False], np.asarray(contact, bool), [False]])
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return ImpactSpans(edges[::2], edges[1::2])


def impact_spans(contact: np.ndarray, merge_gap: int = MERGE_GAP, free_before: float = math.inf) -> ImpactSpans:
    """The impacts of a contact flag (n,): its runs, those fewer than `merge_gap` samples apart joined.

    `free_before`: samples without contact between an earlier contact and contact[0] (a record
    fed in pieces); a first run that close to it continues the earlier impact and is left out.
    """
    runs = contact_runs(contact)
    gaps = np.concatenate([runs.start[:1] + free_before, runs.start[1:] - runs.stop[:-1]])
    first = np.flatnonzero(gaps >= merge_gap)  # the first run of each impact
    last = np.concatenate([first[1:] - 1, [len(runs.start) - 1]]) if first.size else first
    return ImpactSpans(runs.start[first], runs.stop[last])


def impact_numbers(contact: np.ndarray, merge_gap: int = MERGE_GAP) -> np.ndarray:
    """Per sample: the number of the latest impact (the first = 1), 0 before the first."""
    numbers = np.zeros(len(contact), int)
    starts = impact_spans(contact, merge_gap).start
    np.add.at(numbers, starts, 1)
    return np.cumsum(numbers)


class ImpactCounter:
    """Counts the impacts of a contact flag fed in pieces: the same count as `impact_spans` of the whole."""

    def __init__(self, merge_gap: int = MERGE_GAP):
        self.merge_gap = merge_gap
        self.count = 0
        self._free = math.inf  # samples without contact since the last contact (inf: none yet)

    def add(self, contact: np.ndarray) -> None:
        """The next samples of the flag (n,)."""
        contact = np.asarray(contact, bool)
        if len(contact) == 0:
            return
        self.count += len(impact_spans(contact, self.merge_gap, self._free).start)
        touching = np.flatnonzero(contact)
        self._free = len(contact) - 1 - int(touching[-1]) if touching.size else self._free + len(contact)
