"""`touchdown report`: what `touchdown train` found, from the coefficient file it wrote (a real training on a
family rig's simulated bag, not a hand-made file)."""
from __future__ import annotations

import pytest
import yaml

from touchdown_ros.cli import EXIT_BAD_INPUT, main
from touchdown_ros.sim.family import variant, write_rig_yaml, write_variant_bags

PNG = b"\x89PNG\r\n\x1a\n"
FIGURES = ("constants.png", "candidates.png", "convergence.png", "nis.png", "parameter_maps.png")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """soft_bearing's rig YAML and a coefficient file `touchdown train` wrote from one of its drops (two laws
    screened, a lambda path of two; the paper's friction and 30 ms of the drop, to keep it short)."""
    v = variant("soft_bearing")
    out = tmp_path_factory.mktemp("report")
    bags = write_variant_bags(v, out / "bags", n_drops=1, seed=3)
    rig = write_rig_yaml(v, out / "bags", overwrite=True)
    coeffs = out / "c.yaml"
    options = ["-p", "contact.friction:=paper", "-p", "training.contact_laws:=[linear, hertz:1.5]",
               "-p", "training.axial_support:=rigid", "-p", "training.regularisation:=[1.0, 1.0e-3]"]
    assert main(["train", str(bags[0]), "--config", str(rig), *options, "--duration", "0.03", "-o", str(coeffs)]) == 0
    return rig, coeffs


def test_train_records_each_fits_loss_per_step(trained):
    from touchdown_ros.io.config import load_config

    rig, coeffs = trained
    training = yaml.safe_load(coeffs.read_text())["training"]
    calibration, pkbkr = training["calibration"], training["pkbkr"]
    assert calibration["prior_width"] == load_config(rig).training.prior_width  # what the report's figure draws
    assert len(calibration["loss_history"]) == calibration["steps"] + 1
    assert calibration["loss_history"][0] == pytest.approx(calibration["initial_loss"])
    assert calibration["loss_history"][-1] == pytest.approx(calibration["final_loss"])
    for candidate in calibration["candidates"]:
        assert len(candidate["loss_history"]) == candidate["steps"] + 1
        assert candidate["loss_history"][-1] == pytest.approx(candidate["loss"])
    for tried in training["regularisation_path"]["tried"]:
        assert len(tried["loss_history"]) == tried["steps"] + 1 == len(tried["held_out_history"])
        assert tried["held_out_history"][tried["kept_step"]] == pytest.approx(tried["held_out_loss"])
    assert pkbkr["held_out_history"][pkbkr["kept_step"]] == pytest.approx(pkbkr["held_out_kept"])


@pytest.mark.parametrize("drops, screened", [(1, None), (2, 1)], ids=["all bags screened", "one of two screened"])
def test_stage_1s_record_counts_the_refinement_with_the_support_held(drops, screened, tmp_path, capsys):
    """A yielding fit is refined first with its support held, then free: the file's stage-1 record counts the steps,
    loss evaluations and losses of both runs (the campaign's refinement took 71 steps held and 3 free, and the
    record said 3). Where the laws are screened on fewer bags than all, the held run is on those: its steps and
    evaluations count, its losses (other bags') do not, and the reason says where it ran."""
    import re

    v = variant("soft_bearing")
    bags = write_variant_bags(v, tmp_path / "bags", n_drops=drops, seed=3)
    rig = write_rig_yaml(v, tmp_path / "bags", overwrite=True)
    coeffs = tmp_path / "c.yaml"
    options = ["-p", "contact.friction:=paper", "-p", "training.contact_laws:=[hertz:1.5]",
               "-p", "training.axial_support:=yielding"]
    if screened:
        options += ["-p", f"training.screening_bags:={screened}"]
    assert main(["train", *map(str, bags), "--config", str(rig), *options, "--duration", "0.03", "--steps", "0",
                 "-o", str(coeffs)]) == 0
    said = capsys.readouterr().err
    held = " with the support held" + (f" on the screening's {screened} bag" if screened else "")
    runs = {which: re.search(rf"\[calibrate \S+ n=1.5 \+ yielding support, refined{which}\] (?:NOT )?converged after "
                             r"(\d+) steps \((\d+) loss evaluations\)", said)
            for which in (held, "", " from the support grid[^]]*")}
    restarted = runs.pop(" from the support grid[^]]*")  # where the support grid's start was lower: counted too
    assert all(runs.values()), said[-3000:]
    steps, evaluations = (sum(int(run[i]) for run in [*runs.values(), restarted] if run) for i in (1, 2))
    calibration = yaml.safe_load(coeffs.read_text())["training"]["calibration"]
    assert int(runs[held][1]) > 0
    assert (calibration["steps"], calibration["evaluations"]) == (steps, evaluations), (calibration["steps"], runs)
    on_all = steps - (int(runs[held][1]) if screened else 0)
    assert len(calibration["loss_history"]) == on_all + 1
    assert held in calibration["reason"]
    first = re.search(r"\[calibrate \S+ n=1.5 \+ yielding support, refined step 0\] loss (\S+)", said)
    assert screened is None or calibration["loss_history"][0] == pytest.approx(float(first[1]), rel=1e-6)


def test_report_shows_the_calibration_the_lambda_path_and_figures(trained, tmp_path, capsys):
    rig, coeffs = trained
    out = tmp_path / "report"
    assert main(["report", str(coeffs), "--config", str(rig), "-o", str(out)]) == 0
    training = yaml.safe_load(coeffs.read_text())["training"]
    calibration = training["calibration"]
    text = (out / "training.md").read_text()
    assert text in capsys.readouterr().out
    assert f"Chosen: **{calibration['law']}**" in text
    for name, value in calibration["calibrated"].items():
        guess = calibration["guess"][name]
        assert f"| {name} | {guess:.4g} | {value:.4g} | {value / guess:.4g} |" in text
    for candidate in calibration["candidates"]:
        assert f"| {candidate['law']} | {candidate['loss']:.4g} |" in text
    chosen = training["regularisation_path"]["chosen"]
    for tried in training["regularisation_path"]["tried"]:
        row = f"| {tried['regularisation']:.4g} | {tried['steps']} | {tried['kept_step']} |"
        mark = "yes |" if tried["regularisation"] == chosen else "no |"
        assert row in text and text.split(row)[1].split("\n")[0].endswith(mark)
    for bag, nis in training["mean_nis"].items():
        assert f"| {bag.rsplit('/', 1)[-1]} | {nis:.4g} |" in text
    for figure in FIGURES:
        assert (out / "figures" / figure).read_bytes()[:8] == PNG, figure
    assert "Figures in `figures/`: " + ", ".join(FIGURES) + "." in text


def test_report_refuses_a_file_of_another_rig_and_writes_nothing(trained, tmp_path, capsys):
    rig, coeffs = trained
    out = tmp_path / "report"
    heavier = ["--config", str(rig), "-p", "rig.mass:=300.0"]
    assert main(["report", str(coeffs), *heavier, "-o", str(out)]) == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert "made for another rig" in error and "mass" in error
    assert not out.exists()


def test_report_of_a_file_without_a_training_record_says_so(tmp_path):
    from touchdown_ros.core.types import Coefficients
    from touchdown_ros.io.coefficients import TrainingRecord, save_coefficients
    from touchdown_ros.io.config import load_config

    config = load_config()
    coeffs = save_coefficients(tmp_path / "c.yaml", Coefficients.zeros(config.kernel), config, TrainingRecord())
    out = tmp_path / "report"
    assert main(["report", str(coeffs), "-o", str(out)]) == 0
    assert "No stage-1 record in this file" in (out / "training.md").read_text()
    assert sorted(p.name for p in (out / "figures").iterdir()) == ["parameter_maps.png"]


def test_report_says_where_the_learned_functions_are_lowest_and_highest(tmp_path):
    """One coefficient of k_R at the kernel's corner centre (80 um, +100 mm/s): k_R reaches 1 + alpha there and is the
    constant to 1e-18 at the opposite corner, eight widths away (a function moved at one end only is still shown
    moved, with both places); the other five are the constants. Zero coefficients: said so."""
    import numpy as np

    from touchdown_ros.core.types import Coefficients
    from touchdown_ros.io.coefficients import TrainingRecord, save_coefficients
    from touchdown_ros.io.config import load_config

    config = load_config(overrides={"kernel.radial_deformation_centres": [float(i) for i in range(9)]})
    kernel = config.kernel
    T, scale = np.asarray(kernel.T_R), np.asarray(kernel.scale_R)
    corner = int(np.flatnonzero((T[:, 0] == T[:, 0].max()) & (T[:, 1] == T[:, 1].max()))[0])
    zeros = Coefficients.zeros(kernel)
    alpha_R = np.array(zeros.alpha_R)
    alpha_R[0, corner] = 0.3
    out = tmp_path / "report"
    coeffs = save_coefficients(tmp_path / "c.yaml", zeros._replace(alpha_R=alpha_R), config, TrainingRecord())
    assert main(["report", str(coeffs), "-o", str(out)]) == 0
    text = (out / "training.md").read_text()
    top = f"{T[corner, 0] * scale[0] * 1e6:.3g} / {T[corner, 1] * scale[1] * 1e3:+.3g}"
    bottom = f"{0.0:.3g} / {T[:, 1].min() * scale[1] * 1e3:+.3g}"
    assert f"| k_R | 1 | {bottom} | 1.3 | {top} |" in text, text
    for name in ("c_R", "mu", "k_Z", "c_Z", "k_ZR"):
        assert f"| {name} | 1 | - | 1 | - |" in text

    unmoved = save_coefficients(tmp_path / "zero.yaml", zeros, config, TrainingRecord())
    assert main(["report", str(unmoved), "-o", str(tmp_path / "zero")]) == 0
    said = (tmp_path / "zero" / "training.md").read_text()
    assert "The learned functions are the calibrated constants everywhere" in said and "| k_R |" not in said
