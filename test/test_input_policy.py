"""Bad input through the real `touchdown` command: one policy (core.input_policy), one clear answer.

Bags are the simulator's experiment 11, damaged and written back with `write_bag`; every
call goes through `touchdown_ros.cli.main`. Nothing is mocked.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from touchdown_ros.cli import main
from touchdown_ros.core.types import Coefficients
from touchdown_ros.io.bags import TopicSeries, read_displacement, read_truth, read_vector_topic, write_bag
from touchdown_ros.io.coefficients import TrainingRecord, save_coefficients
from touchdown_ros.io.config import load_config

CONFIG = load_config()
PERIOD_NS = int(round(CONFIG.sample_period * 1e9))
EXIT_BAD_INPUT, EXIT_OUTPUT = 3, 5  # docs/input_policy.md


def policy_module():
    """core.input_policy and the reference rig's policy (imported here so that the CLI tests run,
    and fail for what they check, against a tree without the module)."""
    from touchdown_ros.core import input_policy

    return input_policy, input_policy.InputPolicy.from_config(CONFIG)


# ---------------------------------------------------------------------------------------------- the policy itself
def test_jump_kinds_follow_the_limits():
    ip, POLICY = policy_module()
    steps = np.array([1, 2, POLICY.bridge_rows + 1, POLICY.bridge_rows + 2, 501, 10**9, -501, -3])
    assert ip.jump_kind(steps, POLICY).tolist() == [
        ip.CONTIGUOUS, ip.BRIDGED, ip.BRIDGED, ip.GAP, ip.CLOCK_JUMP_FORWARD, ip.CLOCK_JUMP_FORWARD,
        ip.CLOCK_JUMP_BACKWARD, ip.CONTIGUOUS,
    ]


def test_saturated_and_pinned_values_are_refused_across_calls():
    ip, POLICY = policy_module()
    values = np.full((30, 3), 1.0e-6)
    values[:, 0] += 1e-9 * np.arange(30)  # never pinned: it changes
    values[:, 1] += 1e-9 * np.arange(30)
    values[5, 2] = -CONFIG.node.sensor_range  # at the range: saturated
    values[10:30, 2] = -0.7e-3  # pinned at a rail inside the range
    first = ip.value_flags(values[:15], POLICY)
    second = ip.value_flags(values[15:], POLICY, first.rail_run, first.last)
    saturated = np.concatenate([first.saturated, second.saturated])
    pinned_from = 10 + POLICY.rail_samples - 1
    assert saturated[5] and saturated[pinned_from:].all() and not saturated[10:pinned_from].any()
    assert not ip.value_flags(np.zeros((50, 3)), POLICY).saturated.any()  # a constant zero is no rail


def test_runs_of_unusable_rows_are_bridged_then_restart_the_filter_row_by_row_as_at_once():
    ip, POLICY = policy_module()
    usable = np.ones(100, bool)
    usable[10:15] = False
    usable[40:40 + POLICY.bridge_rows + 5] = False
    whole = ip.bridge_rows(usable, POLICY)
    parts, carried = [], 0
    for start in range(0, 100, 7):
        part = ip.bridge_rows(usable[start : start + 7], POLICY, carried)
        parts.append(part)
        carried = part.run
    assert np.array_equal(np.concatenate([p.keep for p in parts]), whole.keep)
    assert np.array_equal(np.concatenate([p.restart for p in parts]), whole.restart)
    assert whole.keep[10:15].all() and np.flatnonzero(whole.restart).tolist() == [40 + POLICY.bridge_rows + 5]
    assert np.count_nonzero(~whole.keep) == 5


def test_an_hour_long_clock_jump_allocates_nothing():
    ip, POLICY = policy_module()
    stamps = np.arange(200, dtype=np.int64) * PERIOD_NS
    stamps[100:] += 3600 * 10**9
    record = ip.split_record(stamps, np.full((200, 3), 1e-6), POLICY)
    assert [len(s.stamps_ns) for s in record.segments] == [100, 100]
    assert record.counts["clock_jump_forward"] == 1


# ---------------------------------------------------------------------------------------------- bags
@pytest.fixture(scope="module")
def exp_11(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bags")
    assert main(["simulate", "--experiment", "11", "-o", str(out)]) == 0
    return out / "exp_11"


def damaged(source: Path, target: Path, change) -> Path:
    """A copy of `source` with its displacement (and truth) changed by change(stamps, xyz) -> (stamps, xyz, keep)."""
    series = read_displacement(source, CONFIG.topics.displacement)
    truth = read_truth(source)
    stamps, xyz, keep = change(series.stamps_ns.copy(), series.xyz.copy())
    topics = CONFIG.topics
    write_bag(
        target,
        [
            TopicSeries(topics.displacement, "PointStamped", stamps[keep], xyz[keep], frame_id=topics.frame_id),
            TopicSeries(topics.truth_velocity, "Vector3Stamped", stamps[keep], truth.velocity[keep]),
            TopicSeries(topics.truth_acceleration, "Vector3Stamped", stamps[keep], truth.acceleration[keep]),
            TopicSeries(topics.truth_contact_force, "WrenchStamped", stamps[keep], truth.contact_force[keep]),
        ],
    )
    return target


def onset_sample(source: Path) -> int:
    z = read_displacement(source).xyz[:, 2]
    return int(np.argmax(z < np.mean(z[:50]) - CONFIG.drop.threshold))


def estimate(bag: Path, out: Path, *extra: str) -> dict:
    assert main(["estimate", str(bag), "--filtered", "--no-figures", "-o", str(out), *extra]) == 0
    return json.loads((out / "summary.json").read_text())["bags"][str(bag)]


def test_a_50_ms_gap_in_the_touchdown_restarts_the_filter_and_says_so(exp_11, tmp_path):
    start = onset_sample(exp_11) + 100

    def gap(stamps, xyz):
        keep = np.ones(len(stamps), bool)
        keep[start : start + 500] = False  # 50 ms without samples
        return stamps, xyz, keep

    bag = damaged(exp_11, tmp_path / "gap", gap)
    summary = estimate(bag, tmp_path / "out")
    clean = estimate(exp_11, tmp_path / "clean")
    report = summary["input"]
    assert report["filter_restarts"] == 1 and len(report["breaks"]) == 1
    assert summary["samples"] <= clean["samples"] - 500  # the gap is not estimated as predicted rows
    assert abs(summary["truth"]["peak_radial_force_error"]) < 0.3, summary["truth"]
    assert "filter restarts" in (tmp_path / "out" / "summary.md").read_text()


def test_a_short_gap_is_bridged_flagged_and_left_out_of_the_peaks(exp_11, tmp_path):
    start = onset_sample(exp_11) + 100

    def gap(stamps, xyz):
        keep = np.ones(len(stamps), bool)
        keep[start : start + 10] = False  # 1 ms: bridged
        return stamps, xyz, keep

    summary = estimate(damaged(exp_11, tmp_path / "gap", gap), tmp_path / "out")
    assert summary["input"]["bridged_gaps"] == 1 and summary["input"]["filter_restarts"] == 0
    assert summary["predicted_only_samples"] == 10
    assert "10 predict-only rows" in (tmp_path / "out" / "summary.md").read_text()
    marked = read_vector_topic(tmp_path / "out" / "gap_estimate", "/touchdown/predicted_only")
    assert len(marked.stamps_ns) == 10 and (marked.values == 1.0).all()


def test_z_saturated_for_100_samples_is_treated_as_missing(exp_11, tmp_path):
    start = onset_sample(exp_11) + 100

    def saturate(stamps, xyz):
        xyz[start : start + 100, 2] = -CONFIG.node.sensor_range
        return stamps, xyz, np.ones(len(stamps), bool)

    summary = estimate(damaged(exp_11, tmp_path / "saturated", saturate), tmp_path / "out")
    assert summary["input"]["saturated"] == 100 and summary["input"]["filter_restarts"] == 1
    # the first axial impact falls in the saturated stretch: it is missed (and said so), never invented
    assert summary["truth"]["peak_axial_force_error"] < 0.1, summary["truth"]
    assert "100 saturated or pinned samples" in (tmp_path / "out" / "summary.md").read_text()


@pytest.mark.parametrize("jump_s", [10, 3600])
def test_a_clock_jump_is_never_allocated_as_samples(exp_11, tmp_path, jump_s):
    start = onset_sample(exp_11) + 300

    def jump(stamps, xyz):
        stamps[start:] += jump_s * 10**9
        return stamps, xyz, np.ones(len(stamps), bool)

    bag = damaged(exp_11, tmp_path / "jump", jump)
    summary = estimate(bag, tmp_path / "out")
    assert summary["input"]["clock_jump_forward"] == 1 and summary["input"]["filter_restarts"] == 1
    assert summary["samples"] < len(read_displacement(bag).stamps_ns)
    assert sum(f.stat().st_size for f in (tmp_path / "out").rglob("*.mcap")) < 20e6


def test_train_refuses_a_clock_jump_naming_bag_and_sample_and_leaves_nothing(exp_11, tmp_path, capsys):
    start = onset_sample(exp_11) + 300

    def jump(stamps, xyz):
        stamps[start:] += 10 * 10**9
        return stamps, xyz, np.ones(len(stamps), bool)

    bag = damaged(exp_11, tmp_path / "jump", jump)
    out = tmp_path / "c.yaml"
    assert main(["train", str(bag), "-o", str(out)]) == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert str(bag) in error and f"sample {start}" in error and "Traceback" not in error
    assert len(error.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["jump"]


def test_train_refuses_a_long_saturated_stretch_before_the_work(exp_11, tmp_path, capsys):
    start = onset_sample(exp_11) + 100

    def saturate(stamps, xyz):
        xyz[start : start + 100, 2] = -CONFIG.node.sensor_range
        return stamps, xyz, np.ones(len(stamps), bool)

    bag = damaged(exp_11, tmp_path / "saturated", saturate)
    assert main(["train", str(bag), "-o", str(tmp_path / "c.yaml")]) == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert str(bag) in error and "without a usable value" in error and len(error.strip().splitlines()) == 1
    assert not (tmp_path / "c.yaml").exists()


def test_off_grid_and_sample_period_errors_name_the_file(exp_11, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["estimate", str(exp_11), "-o", str(out), "-p", "sensor.sample_period:=3.0e-4"]) == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert str(exp_11) in error and "sample" in error and "sample_period" in error
    assert not out.exists()


def test_a_refused_bag_leaves_no_output_directory(exp_11, tmp_path, capsys):
    def millimetres(stamps, xyz):
        return stamps, xyz * 1000.0, np.ones(len(stamps), bool)

    bad = damaged(exp_11, tmp_path / "mm", millimetres)
    out = tmp_path / "out"
    assert main(["estimate", str(exp_11), str(bad), "--no-figures", "-o", str(out)]) == EXIT_BAD_INPUT
    assert str(bad) in capsys.readouterr().err
    assert not out.exists()  # not even the good bag's estimate: every bag is checked first
    assert main(["estimate", str(exp_11), "--no-figures", "-o", str(out)]) == 0  # the rerun is not refused


def test_output_on_a_read_only_place_is_refused_before_the_work(exp_11, tmp_path, capsys):
    # root ignores permission bits, so a read-only place is a file system mounted read-only: /proc
    out = Path("/proc/touchdown_out")
    assert main(["estimate", str(exp_11), "--no-figures", "-o", str(out)]) == EXIT_OUTPUT
    error = capsys.readouterr().err
    assert "/proc/touchdown_out" in error and "Traceback" not in error and len(error.strip().splitlines()) == 1
    coefficient_file = save_coefficients(tmp_path / "c.yaml", Coefficients.zeros(CONFIG.kernel), CONFIG,
                                         TrainingRecord())
    for command in (["train", str(exp_11), "-o", "/proc/touchdown_c.yaml"],
                    ["evaluate", str(exp_11), "--coeffs", str(coefficient_file), "--no-cv", "-o", str(out)]):
        assert main(command) == EXIT_OUTPUT  # before the work: train and evaluate return at once
        error = capsys.readouterr().err
        assert "/proc/touchdown" in error and "Traceback" not in error and len(error.strip().splitlines()) == 1
    # a file where the output directory goes
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main(["estimate", str(exp_11), "--no-figures", "-o", str(blocker / "out")]) == EXIT_OUTPUT
    assert "a_file" in capsys.readouterr().err


def test_a_full_disk_is_a_message_and_leaves_nothing(exp_11, tmp_path, capsys):
    """A tmpfs of 64 KiB: the probe file fits, the estimate bag does not."""
    mount = tmp_path / "small"
    mount.mkdir()
    if os.system(f"mount -t tmpfs -o size=64k tmpfs {mount} 2>/dev/null") != 0:
        pytest.skip("cannot mount a small tmpfs here")
    try:
        out = mount / "out"
        assert main(["estimate", str(exp_11), "--no-figures", "-o", str(out)]) == EXIT_OUTPUT
        error = capsys.readouterr().err
        assert "No space left" in error and "Traceback" not in error and len(error.strip().splitlines()) == 1
        assert not out.exists() and not any(mount.iterdir())
    finally:
        os.system(f"umount {mount}")


def test_coefficient_path_that_is_a_directory_is_a_message(exp_11, tmp_path, capsys):
    assert main(["estimate", str(exp_11), "--coeffs", str(tmp_path), "-o", str(tmp_path / "out")]) == EXIT_BAD_INPUT
    assert "is a directory" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def edited(tmp_path: Path, change) -> Path:
    path = save_coefficients(tmp_path / "c.yaml", Coefficients.zeros(CONFIG.kernel), CONFIG, TrainingRecord())
    document = yaml.safe_load(path.read_text())
    change(document)
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d["training"].update(regularisation="abc"), "training.regularisation must be a finite number"),
        (lambda d: d.pop("rig_fingerprint"), "no rig_fingerprint"),
        (lambda d: d["model"]["rig"].update(mass=300.0), "model section does not match"),
        (lambda d: d["contact"].update(k_R=d["contact"]["k_R"] * 2), "was edited after training"),
        (lambda d: d["coefficients"]["k_R"].__setitem__(0, 0.5), "was edited after training"),
        (lambda d: d.pop("content_sha256"), "no content_sha256"),
    ],
)
def test_edited_coefficient_files_are_refused_with_what_differs(exp_11, tmp_path, capsys, change, message):
    path = edited(tmp_path, change)
    for command in (["estimate", str(exp_11), "--coeffs", str(path), "-o", str(tmp_path / "out")],
                    ["evaluate", str(exp_11), "--coeffs", str(path), "-o", str(tmp_path / "eval")]):
        assert main(command) == EXIT_BAD_INPUT
        error = capsys.readouterr().err
        assert message in error and str(path) in error and "Traceback" not in error
    assert not (tmp_path / "out").exists() and not (tmp_path / "eval").exists()


def test_coefficient_files_are_readable_by_everyone(tmp_path):
    path = save_coefficients(tmp_path / "c.yaml", Coefficients.zeros(CONFIG.kernel), CONFIG, TrainingRecord())
    assert path.stat().st_mode & 0o644 == 0o644


def test_demo_help_says_how_long_it_takes(capsys):
    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--quick: about 10 s" in text and "about 12 min on 2 cores" in text and "about 6 min" in text


def test_evaluation_md_says_which_coefficients_how_held_out_and_what_the_means_are(exp_11, tmp_path):
    coefficient_file = save_coefficients(tmp_path / "c.yaml", Coefficients.zeros(CONFIG.kernel), CONFIG,
                                         TrainingRecord())
    out = tmp_path / "eval"
    assert main(["evaluate", str(exp_11), "--coeffs", str(coefficient_file), "--no-cv", "-o", str(out)]) == 0
    heading = (out / "evaluation.md").read_text().split("| bag |")[0]
    assert heading.startswith("# Evaluation") and str(coefficient_file) in heading
    assert "in-sample" in heading and "absolute value" in heading


def test_a_levitated_window_too_noisy_for_the_threshold_names_the_threshold_that_would_do(exp_11, tmp_path, capsys):
    """The levitated z wobbling 8 um rms (a thrust's, a noisy sensor's): train refuses the bag before the work,
    naming it and the drop_detection.threshold that takes it; estimate with that threshold finds the drop. Two such
    bags, the second wobbling more (drawn_1_1's thrust, 2026-12-07: 7.11 and 8.07 um): both named at once, and the
    threshold that takes both."""
    onset = onset_sample(exp_11)

    def wobbling(amplitude):
        def wobble(stamps, xyz):
            xyz[: onset - 20, 2] += amplitude * np.sin(2 * np.pi * 150.0 * np.arange(onset - 20) * CONFIG.sample_period)
            return stamps, xyz, np.ones(len(stamps), bool)
        return wobble

    bag = damaged(exp_11, tmp_path / "wobbling", wobbling(1.13e-5))
    assert main(["train", str(bag), "-o", str(tmp_path / "c.yaml")]) == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert str(bag) in error and "is not clean" in error and len(error.strip().splitlines()) == 1
    suggested = error.split("-p drop_detection.threshold:=")[1].split(")")[0]
    assert 2.2e-5 <= float(suggested) <= 2.6e-5, suggested
    assert not (tmp_path / "c.yaml").exists()

    more = damaged(exp_11, tmp_path / "wobbling_more", wobbling(1.3e-5))
    assert main(["train", str(more), "-o", str(tmp_path / "c.yaml")]) == EXIT_BAD_INPUT
    alone = capsys.readouterr().err.split("-p drop_detection.threshold:=")[1].split(")")[0]
    assert float(alone) > float(suggested)
    assert main(["train", str(bag), str(exp_11), str(more), "-o", str(tmp_path / "c.yaml")]) == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert "2 of 3 bags cannot be used: (1) " in error and len(error.strip().splitlines()) == 1, error
    first, second = error.split("(1) ")[1].split(" (2) ")
    assert str(bag) in first and str(more) in second and "is not clean" in first and "is not clean" in second
    assert str(exp_11) not in error.replace(str(bag), "").replace(str(more), "")
    assert "The 2 levitated windows too noisy for drop_detection.threshold are all taken by" in second
    both = second.split("are all taken by")[1].split("-p drop_detection.threshold:=")[1].split(")")[0]
    assert both == alone
    assert not (tmp_path / "c.yaml").exists()
    summary = estimate(more, tmp_path / "out", "-p", f"drop_detection.threshold:={both}")
    assert summary["samples"] > 1000 and summary["input"]["filter_restarts"] == 0, summary
