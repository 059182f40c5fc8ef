"""One definition of an impact: every output that counts or numbers impacts agrees on the same contact flags."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from touchdown_ros.core.impacts import MERGE_GAP, ImpactCounter, impact_numbers, impact_spans
from touchdown_ros.core.metrics import impacts as force_impacts
from touchdown_ros.core.streaming.outputs import PACKED_WIDTH, unpack
from touchdown_ros.core.streaming.touchdown import TouchdownTally
from touchdown_ros.sim.features import axial_impacts


def chattering_contact(seed: int, n: int = 600) -> np.ndarray:
    """Contact runs of 1-40 samples with gaps of 1-30 samples: chatter (gaps under MERGE_GAP) and impacts."""
    rng = np.random.default_rng(seed)
    flags, touching = [], bool(rng.integers(2))
    while len(flags) < n:
        flags += [touching] * int(rng.integers(1, 40 if touching else 30))
        touching = not touching
    return np.array(flags[:n])


def test_spans_by_hand():
    contact = np.array([0, 1, 1, 0, 0, 1, 0, 0, 0, 0, 0, 1, 1, 0], bool)
    spans = impact_spans(contact, merge_gap=3)
    assert spans.start.tolist() == [1, 11] and spans.stop.tolist() == [6, 13]
    assert impact_numbers(contact, merge_gap=3).tolist() == [0, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 2, 2, 2]
    assert len(impact_spans(np.zeros(5, bool)).start) == 0 and impact_numbers(np.zeros(0, bool)).shape == (0,)


@pytest.mark.parametrize("seed", range(6))
def test_every_output_counts_the_same_impacts(seed):
    """The node's touchdown summary (streamed in pieces), diagnose's impact numbers, evaluate's and report's
    force impacts and the simulator's paper features: one count for one contact flag."""
    contact = chattering_contact(seed)
    expected = len(impact_spans(contact).start)
    assert 0 < expected < len(impact_spans(contact, merge_gap=1).start)  # the chatter is merged

    assert impact_numbers(contact).max() == expected
    force = np.where(contact, 1.0e3, 0.0)  # N
    assert len(force_impacts(force, threshold=500.0)) == expected
    record = SimpleNamespace(drop_index=0, axial_contact=contact, F_z=force, t=np.arange(len(contact)) * 1e-4)
    assert len(axial_impacts(record)) == expected

    tally = TouchdownTally(onset_stamp_ns=0)
    cuts = np.sort(np.random.default_rng(seed).integers(0, len(contact), 12))
    for rows in np.split(np.arange(len(contact)), cuts):
        packed = np.zeros((len(rows), PACKED_WIDTH))
        out = unpack(rows.astype(np.int64), np.zeros((len(rows), 3)), packed)
        tally.add(out._replace(axial_contact=contact[rows], radial_contact=contact[rows]))
    summary = tally.summary("end_of_stream")
    assert summary.axial_impacts == summary.radial_impacts == expected


def test_counter_in_pieces_equals_the_whole():
    contact = chattering_contact(42, n=2000)
    for piece in (1, 7, MERGE_GAP, 333):
        counter = ImpactCounter()
        for start in range(0, len(contact), piece):
            counter.add(contact[start : start + piece])
        assert counter.count == len(impact_spans(contact).start), piece
