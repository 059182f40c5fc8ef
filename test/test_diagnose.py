"""`touchdown diagnose` end to end on bags with a hidden effect (issues #5 and #16), on rigs of the family.

(a) Library effects the paper's model lacks (an axial load, on the reference rig and a family rig, a sensor
    offset, a contact angle, a seal's cross-coupling, a z sensor gain, a residual magnetic stiffness): the
    tool must name each first by fitting it, size it within 10 % of the truth, and adding it must halve the
    k-step or the contact-force error.
(b) A once-per-revolution axial thrust that no library candidate models: the tool must call the missing
    force unexplained, and a user-written effect registered by dotted path in a rig YAML must be fitted
    to its size and make the error fall.

Bags are simulated here (short drops to stay fast), written and read back as rosbag2 MCAP.
"""
import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from conftest import write_simulated_bag

from touchdown_ros.cli import main
from touchdown_ros.core.diagnostics.breakdown import contact_phase
from touchdown_ros.core.diagnostics.frols import frols
from touchdown_ros.core.diagnostics.prediction import fit_percent
from touchdown_ros.core.diagnostics.residuals import cross_correlation, whiteness
from touchdown_ros.core.impacts import impact_numbers
from touchdown_ros.io.coefficients import load_coefficients
from touchdown_ros.io.config import load_config
from touchdown_ros.sim.campaign import CAMPAIGN
from touchdown_ros.sim.family import variant, variant_config, write_variant_bags
from touchdown_ros.sim.params import simulator_parameters, truth_constants
from touchdown_ros.workflows.offline import force_rmse_against_truth

DURATION = 0.06  # s simulated after the drop


def _calibrated(bags, out, *extra):
    """Stage 1 of `touchdown train` alone (--steps 0: no PKBKR): the rig identified from the bags,
    the constant model the workbench starts from (the YAML's contact constants are only a guess)."""
    assert main(["train", *map(str, bags), "-o", str(out), "--steps", "0", "--duration", "0.05", *extra]) == 0
    return out


def thrust(xi, p, rig):
    """User effect: a once-per-revolution axial force a cos(theta) + b sin(theta), N."""
    zero = 0.0 * xi[2]
    return jnp.stack([zero, zero, p["a"] * jnp.cos(xi[3]) + p["b"] * jnp.sin(xi[3])])


thrust.parameters = {"a": (100.0, "N", "cos(theta) amplitude"), "b": (100.0, "N", "sin(theta) amplitude")}


def _simulate(out, numbers, **simulator):
    """Bags exp_NN of Table 1 rows `numbers` (seed = number) and each one's truth constants."""
    overrides = {"simulator.drop_duration": DURATION, **{f"simulator.{k}": v for k, v in simulator.items()}}
    config = load_config(overrides=overrides)
    params = simulator_parameters(config)
    truths = {}
    for number in numbers:
        condition = CAMPAIGN[number - 1]
        record = write_simulated_bag(out / f"exp_{number:02d}", number, seed=number, config=config, params=params)
        # the simulator draws the experiment's constants first from this generator
        rng = np.random.default_rng(np.random.SeedSequence([number, number]))
        truths[f"exp_{number:02d}"] = truth_constants(
            config, params, condition.ball, condition.brake, condition.axial_load, record.drop_time, rng
        )
    return [out / f"exp_{n:02d}" for n in numbers], truths


def _family(out, name, axial_load=False, **simulator):
    """Two drops of the family's rig `name` with the loader on or off and simulator.* changed: the
    bags, the rig file and each drop's truth constants."""
    base = variant(name)
    rig = dataclasses.replace(
        base, axial_load=axial_load, overrides={**base.overrides, **{f"simulator.{k}": v for k, v in simulator.items()}}
    )
    bags = write_variant_bags(rig, out, n_drops=2)
    config = variant_config(rig)
    params = simulator_parameters(config)
    truths = []
    for number in (1, 2):
        condition = rig.condition(number)
        rng = np.random.default_rng(np.random.SeedSequence([number, number]))  # seed 0 + number, as simulate_variant
        truths.append(truth_constants(config, params, condition.ball, condition.brake, condition.axial_load, 0.0, rng))
    return bags, out / "rig.yaml", truths


def _diagnosis(out):
    return json.loads((out / "diagnosis.json").read_text())


@pytest.fixture(scope="module")
def load_bags(tmp_path_factory):
    """Experiments 9 and 11: brake + the additional axial load (about 2000 N)."""
    return _simulate(tmp_path_factory.mktemp("load"), (9, 11))


@pytest.mark.acceptance
def test_load_is_ranked_first_fitted_and_adding_it_halves_the_errors(load_bags, tmp_path):
    bags, truths = load_bags
    loads = {name: t.axial_load for name, t in truths.items()}
    mean_load = float(np.mean(list(loads.values())))
    assert all(1500.0 < f < 2500.0 for f in loads.values())

    calibrated = _calibrated(bags, tmp_path / "calibrated.yaml")
    coeffs = tmp_path / "with_load.yaml"
    code = main(
        ["train", *map(str, bags), "-o", str(coeffs), "-p", "effects.active:=[axial_load]", "--duration", "0.05"]
    )
    assert code == 0
    fitted = load_coefficients(coeffs, load_config()).effects.values()["axial_load"]["force"]
    assert abs(fitted - mean_load) < 0.1 * mean_load, fitted

    out = tmp_path / "diagnosis"
    assert (
        main(["diagnose", *map(str, bags), "--coeffs", str(calibrated), "--compare", str(coeffs), "--out", str(out)])
        == 0
    )
    document = _diagnosis(out)
    before, after = document["models"]
    assert (before["label"], after["label"]) == ("before", "after")
    # each model's calibration notes (stage 1's, from its file) qualify its diagnosis, in the json and the report
    for model, path in ((before, calibrated), (after, coeffs)):
        said = [f"Calibration: {note}" for note in load_coefficients(path, load_config()).calibration_notes]
        assert said and model["notes"][: len(said)] == said, (model["notes"], said)
        assert all(f"  - {note}" in (out / "diagnosis.md").read_text() for note in model["notes"])

    # before (the paper's constant model, calibrated): the load is what is missing, and how large it is
    verdict = before["verdict"]
    assert verdict["explained"], verdict["text"]
    assert verdict["candidates"][0]["candidate"] == "axial_load", [c["candidate"] for c in verdict["candidates"]]
    force = verdict["candidates"][0]["parameters"]["force"]
    for name, value in force["per_bag"].items():
        assert abs(value - loads[name]) < 0.1 * loads[name], (name, value, loads[name])
    assert abs(force["value"] - mean_load) < 0.1 * mean_load

    # after: the errors on the axis the load acts on fall at least by half; x, y do not get worse
    ratio = document["comparison"]
    assert ratio["k_step_rmse_per_axis"][2] <= 0.5, ratio
    assert ratio["contact_force_rmse_per_axis"][2] <= 0.5, ratio
    assert max(ratio["k_step_rmse_per_axis"][:2]) < 1.1 and max(ratio["contact_force_rmse_per_axis"][:2]) < 1.1, ratio
    assert ratio["k_step_rmse_norm"] < 1.0 and ratio["contact_force_rmse_norm"] < 1.0, ratio
    assert ratio["missing_force_rms"][2] < 0.5, ratio
    for name in ("diagnosis.md", "errors.csv", "ranking.csv", "figures/missing_force.png", "figures/ranking.png"):
        assert (out / name).stat().st_size > 200, name
    assert "after / before" in (out / "diagnosis.md").read_text()
    assert f"-o with_axial_load.yaml --start {calibrated} -p 'effects.active:=[axial_load]'" in (
        out / "diagnosis.md").read_text()


@pytest.fixture(scope="module")
def family_load_bags(tmp_path_factory):
    """The soft_bearing rig of the family (bearing 5x softer than the reference) with the loader on."""
    return _family(tmp_path_factory.mktemp("family_load"), "soft_bearing", axial_load=True)


@pytest.mark.acceptance
@pytest.mark.parametrize("friction", ["paper", "spinning_ring"])
def test_a_hidden_load_on_a_family_rig_is_chosen_by_fitting_it_and_sized_within_10_percent(
    family_load_bags, tmp_path, friction
):
    """With the ring's friction stage 1 takes up part of the hidden load in the friction (mu 0.88 for
    about 0.2): the load's fit from there stays in that basin (1159 N) while the magnetic stiffness's
    leaves it; fitted again from the best candidate's constants the load wins (2026-11-26)."""
    bags, rig, truths = family_load_bags
    loads = [t.axial_load for t in truths]
    assert all(1500.0 < f < 2500.0 for f in loads)
    calibrated = _calibrated(
        bags, tmp_path / "calibrated.yaml", "--config", str(rig), "--duration", "0.15",
        "-p", f"contact.friction:={friction}",
    )
    out = tmp_path / "diagnosis"
    assert (
        main(["diagnose", *map(str, bags), "--config", str(rig), "--coeffs", str(calibrated), "--out", str(out)]) == 0
    )
    verdict = _diagnosis(out)["models"][0]["verdict"]
    assert verdict["method"] == "fitted" and verdict["explained"] and verdict["best"] == "axial_load", verdict["text"]
    first, second = verdict["candidates"][:2]
    assert first["candidate"] == "axial_load" and first["fitted"] and second["fitted"], [
        c["candidate"] for c in verdict["candidates"]
    ]
    # better than no candidate with its parameter counted, and on the held-out samples
    assert first["criterion"] < 0.0 and first["held_out_nll_fall"] > 0.0 and first["k_step_fall"] > 0.2, first
    assert (
        verdict["margin_to_second"] == pytest.approx(second["criterion"] - first["criterion"])
        and verdict["margin_to_second"] > 0
    )
    # a load acts in free flight too, a contact term does not (0.43 against contact_exponent's 0.06 with the
    # co-rotating ring's friction, 2026-11-25)
    free_flight = {c["candidate"]: c.get("k_step_fall_by_phase", {}).get("free flight") for c in verdict["candidates"]}
    assert free_flight["axial_load"] > 0.3, free_flight
    if free_flight.get("contact_exponent") is not None:
        assert free_flight["axial_load"] > 3 * free_flight["contact_exponent"], free_flight

    force = first["parameters"]["force"]
    mean_load = float(np.mean(loads))
    assert abs(force["value"] - mean_load) < 0.1 * mean_load, (force, loads)
    assert 0.0 < force["std"] < 0.25 * mean_load
    for (bag, value), load in zip(sorted(force["per_bag"].items()), loads):
        assert abs(value - load) < 0.1 * load, (bag, value, load)
    # net of the sensor noise the coefficient file measured, the k-step error is the model's own: lower, and
    # the load's share of it larger
    held = verdict["held_out"]
    assert np.all(np.asarray(held["baseline_k_step_rmse_net_m"]) < np.asarray(held["baseline_k_step_rmse_m"]))
    # soft_bearing keeps the reference's sensor, 2 um rms, measured by training on the levitated samples
    np.testing.assert_allclose(held["measurement_noise_rms_m"], 2.0e-6, rtol=0.2)
    assert first["k_step_fall_net"] > first["k_step_fall"], first
    text = (out / "diagnosis.md").read_text()
    assert (
        "| candidate | criterion | held-out NLL fall | k-step error fall | net of sensor noise | fitted value +- sd "
        "| per bag |" in text
    )
    assert "missing effect: axial_load" in text


@pytest.mark.acceptance
def test_stage1_moves_an_effect_started_far_from_its_value(family_load_bags, tmp_path):
    """Issue 16 item 4: `touchdown train` with the loader's effect switched on from a start 200x too
    small (10 N for about 2000 N) fits it within 10 %. Stage 1 scales an effect's parameters by the
    force they move along the data, not by their start (which left it at 14 N)."""
    bags, rig, truths = family_load_bags
    mean_load = float(np.mean([t.axial_load for t in truths]))
    coeffs = _calibrated(
        bags, tmp_path / "with_load.yaml", "--config", str(rig), "--duration", "0.15",
        "-p", "effects.active:=[axial_load]", "-p", "effects.axial_load.force:=10.0",
    )
    fitted = yaml.safe_load(coeffs.read_text())["effects"]["axial_load"]["parameters"]["force"]
    assert abs(fitted - mean_load) < 0.1 * mean_load, (fitted, mean_load)


# Hidden library effects on family rigs (bench/workbench_family.py measures these and more; its table
# is in docs/workbench.md): the simulator keys, the library effect, the identifiable size of the truth
# from the drops' truth constants and the fitted parameters, and the held-out k-step ratio required on
# the axes where the effect acts (None: only named and sized).
HIDDEN_LIBRARY_EFFECTS = {
    "sensor offset": (
        "soft_bearing", {"sensor_offset_x": 3.0e-5}, "sensor_offset_x",
        lambda truth: 3.0e-5, lambda p: p["offset"], 0.1, [0], 0.5,
    ),
    "contact angle": (
        # tan(beta) times the model's own normal force in the bore (until 2026-12-07 tan_beta k_radial d, a linear
        # force whose two parameters acted only as their product)
        "linear_spring", {"contact_angle_tan": 0.2}, "contact_angle_coupling",
        lambda truth: truth.contact_angle_tan, lambda p: p["tan_beta"], 0.1, [2], 0.5,
    ),
    "cross-coupled stiffness": (
        # stage 1 ran down to almost no friction (mu 0.002 for 0.05) and q came out +12-18 %; the friction restart
        # from a lubricated contact's 0.05 finds the rig's (2026-12-03)
        "slippery", {"cross_coupled_stiffness": 5.0e5}, "cross_coupled_stiffness",
        lambda truth: 5.0e5, lambda p: p["q"], 0.1, [0, 1], 0.5,
    ),
    "z sensor gain": (
        # stage 1 takes the gain up in contact (a face six times too soft, mu above any bearing's): found from
        # the rig's friction, where every candidate starts again (2026-12-02), and on to convergence (60 steps
        # left it at 1.044 +- 0.001 on these drops, 2026-12-03); sized by its deviation from 1
        "lossy_contact", {"sensor_gain_z": 1.05}, "sensor_gain_z",
        lambda truth: 0.05, lambda p: p["gain"] - 1.0, 0.1, [2], 0.5,
    ),
}
#: Cases the gate is not met on yet, with what was measured (strict: one that passes fails the run, to be moved back).
NOT_MET_YET: dict[str, str] = {}


def _named_and_sized(case, tmp_path):
    """One case of HIDDEN_LIBRARY_EFFECTS: its bags, stage 1 on them, diagnose; asserts the effect is named first with
    a negative criterion and sized within the case's tolerance. The bags, the calibrated file and the verdict."""
    rig_name, simulator, effect, true_size, fitted_size, tolerance, _, _ = HIDDEN_LIBRARY_EFFECTS[case]
    bags, rig, truths = _family(tmp_path / "bags", rig_name, **simulator)
    calibrated = _calibrated(bags, tmp_path / "calibrated.yaml", "--config", str(rig), "--duration", "0.15")
    out = tmp_path / "diagnosis"
    assert (
        main(["diagnose", *map(str, bags), "--config", str(rig), "--coeffs", str(calibrated), "--out", str(out)]) == 0
    )
    verdict = _diagnosis(out)["models"][0]["verdict"]
    assert verdict["explained"] and verdict["best"] == effect, verdict["text"]
    first = verdict["candidates"][0]
    assert first["candidate"] == effect and first["criterion"] < 0.0 and first["held_out_nll_fall"] > 0.0, first
    truth = float(np.mean([true_size(t) for t in truths]))
    fitted = fitted_size({k: v["value"] for k, v in first["parameters"].items()})
    assert abs(fitted - truth) < tolerance * abs(truth), (fitted, truth)
    return bags, rig, calibrated, verdict


def _lowers_the_error(case, bags, rig, calibrated, verdict, tmp_path):
    """The gate's last part for one case: its held-out k-step error on its axes, net of the sensor noise (the model's
    own error, as bench/workbench_family.py judges "halved"; docs/workbench.md, "The k-step error net of the sensor
    noise"), below the case's share of the baseline's, or else (the gate's "k-step or contact-force error at most
    half") the contact force error against the truth at most half once it is trained."""
    _, _, effect, _, _, _, axes, k_step_ratio = HIDDEN_LIBRARY_EFFECTS[case]
    before = np.asarray(verdict["held_out"]["baseline_k_step_rmse_net_m"])[axes]
    after = np.asarray(verdict["candidates"][0]["held_out_k_step_rmse_net_m"])[axes]
    if np.linalg.norm(after) < (k_step_ratio or 1.0) * np.linalg.norm(before):
        return
    assert k_step_ratio, (before, after)
    with_it = _calibrated(bags, tmp_path / "with.yaml", "--config", str(rig), "--duration", "0.15",
                          "-p", f"effects.active:=[{effect}]", "--start", str(calibrated))
    config = load_config(rig)
    forces = [force_rmse_against_truth(config, c, bags) for c in (calibrated, with_it)]
    assert forces[1] <= 0.5 * forces[0], (before, after, forces)


@pytest.mark.acceptance
@pytest.mark.parametrize("case", [
    pytest.param(case, marks=pytest.mark.xfail(reason=NOT_MET_YET[case], strict=True)) if case in NOT_MET_YET else case
    for case in sorted(set(HIDDEN_LIBRARY_EFFECTS) - {"contact angle"})
])
def test_a_hidden_library_effect_on_a_family_rig_is_named_sized_and_lowers_the_error(case, tmp_path):
    """Issue 16's gate for one hidden effect: named first with a negative criterion, sized within the tolerance, and
    the error lowered (`_lowers_the_error`)."""
    _lowers_the_error(case, *_named_and_sized(case, tmp_path), tmp_path)


@pytest.mark.acceptance
def test_a_contact_angle_a_spinning_rings_friction_took_up_is_found_from_the_rigs_friction(tmp_path):
    """Issue 16's gate for a hidden contact angle (linear_spring, whose rig YAML has the spinning ring's friction).
    Against a spinning ring the bore's friction opposes axial sliding, so stage 1 can let a large mu act as
    the axial force a hidden contact angle makes in radial contact (mu 1.49 on these drops); train's note says
    the friction is above any bearing contact's, and diagnose's fits start again from a bearing's friction (the
    rig YAML's until 2026-12-04, the friction grid's best pair since): the contact angle is named well ahead,
    sized within 10 % with a bearing's mu, and lowers the z error (2026-11-28: 242.6 ahead, +1.2 %, mu 0.22, z
    0.80x; from the calibrated friction alone mu 1.44, 49.2 ahead, z 0.87x). A strict xfail from 2026-12-04 (97.4
    ahead, force 0.56x) until the ring's implicit update was solved on its root (2026-12-05: 360.5 ahead, -0.8 %,
    held-out k-step error -47 %)."""
    from touchdown_ros.workflows.calibrate import HIGH_FRICTION

    bags, rig, calibrated, verdict = _named_and_sized("contact angle", tmp_path)
    notes = yaml.safe_load(calibrated.read_text())["training"]["calibration"]["notes"]
    assert any("above any bearing contact's" in note for note in notes), notes
    assert verdict["margin_to_second"] > 100.0, verdict["margin_to_second"]
    assert verdict["candidates"][0]["nominal"]["mu"] < HIGH_FRICTION, verdict["candidates"][0]["nominal"]
    _lowers_the_error("contact angle", bags, rig, calibrated, verdict, tmp_path)


@pytest.mark.acceptance
def test_a_hidden_magnetic_stiffness_is_named_sized_and_halves_the_force_error(tmp_path):
    """The whole gate for one more library effect: a residual negative magnetic stiffness of 1e7 N/m
    (radial and axial) on soft_bearing is named, its diagnose fit and `touchdown train` with it are
    within 10 % of the truth, and the contact force error against the truth falls to at most half."""
    bags, rig, _ = _family(
        tmp_path / "bags", "soft_bearing", magnetic_stiffness_radial=1.0e7, magnetic_stiffness_axial=1.0e7
    )
    calibrated = _calibrated(bags, tmp_path / "calibrated.yaml", "--config", str(rig), "--duration", "0.15")
    out = tmp_path / "diagnosis"
    assert (
        main(["diagnose", *map(str, bags), "--config", str(rig), "--coeffs", str(calibrated), "--out", str(out)]) == 0
    )
    verdict = _diagnosis(out)["models"][0]["verdict"]
    assert verdict["explained"] and verdict["best"] == "magnetic_stiffness", verdict["text"]
    first = verdict["candidates"][0]
    for name, value in first["parameters"].items():
        assert abs(value["value"] - 1.0e7) < 1.0e6, (name, value)
    with_it = _calibrated(
        bags, tmp_path / "with.yaml", "--config", str(rig), "--duration", "0.15",
        "-p", "effects.active:=[magnetic_stiffness]",
    )
    fitted = yaml.safe_load(with_it.read_text())["effects"]["magnetic_stiffness"]["parameters"]
    assert all(abs(v - 1.0e7) < 1.0e6 for v in fitted.values()), fitted
    config = load_config(rig)
    before, after = (force_rmse_against_truth(config, c, bags) for c in (calibrated, with_it))
    assert after <= 0.5 * before, (before, after)


@pytest.fixture(scope="module")
def family_thrust_bags(tmp_path_factory):
    """The lossy_contact rig of the family (Hunt-Crossley damping x3) with a hidden 500 N
    once-per-revolution axial thrust (larger ones unsettle the levitated rotor before the drop)."""
    return _family(tmp_path_factory.mktemp("family_thrust"), "lossy_contact", axial_thrust=500.0)


@pytest.fixture(scope="module")
def family_thrust_calibrated(family_thrust_bags, tmp_path_factory):
    """Stage 1 on the thrust drops: the constant model the workbench starts from."""
    bags, rig, _ = family_thrust_bags
    out = tmp_path_factory.mktemp("family_thrust_calibrated") / "calibrated.yaml"
    return _calibrated(bags, out, "--config", str(rig), "--duration", "0.15")


@pytest.mark.acceptance
def test_a_hidden_thrust_no_candidate_models_stays_unexplained_on_a_family_rig(
    family_thrust_bags, family_thrust_calibrated, tmp_path
):
    bags, rig, truths = family_thrust_bags
    assert all(t.axial_thrust == 500.0 and t.axial_load == 0.0 for t in truths)
    out = tmp_path / "diagnosis"
    assert (
        main(["diagnose", *map(str, bags), "--config", str(rig), "--coeffs", str(family_thrust_calibrated),
              "--out", str(out)]) == 0
    )
    model = _diagnosis(out)["models"][0]
    verdict = model["verdict"]
    assert verdict["method"] == "fitted" and not verdict["explained"], verdict["text"]
    assert verdict["text"].startswith("unexplained") and all(c["fitted"] for c in verdict["candidates"][:3])
    z = model["signature"]["axes"]["z"]
    assert z["rms_N"] > 200.0 and z["mean_by_phase_N"]["free flight"] > 200.0, z  # lifts the rotor: not a load


@pytest.mark.acceptance
def test_a_user_effect_by_dotted_path_fits_the_unmodelled_thrust_at_its_phase_and_the_axial_force_error_falls(
    family_thrust_bags, family_thrust_calibrated, tmp_path
):
    """Issue 16 item 5: the thrust no candidate models, written by the user as a plain jnp function
    (`thrust` above) and registered by dotted path in the rig file, is fitted by stage 1 at its phase (the
    truth is 500 cos(theta) N: a = 500, b = 0) and the axial contact-force error against the truth falls when
    it is added. Its size through the filter is loose: 0.78-1.41x the truth on seven truths with the paper's
    friction (phases up to 97 deg off), 1.36-1.62x at the right phase with a spinning ring's (docs/workbench.md,
    "The user's thrust", 2026-11-29); on this rig 516 N with the paper's friction, 719 N with the ring's. So the
    size is asserted to its order (half to twice), the phase to 0.2 rad: the start, a = b = 300 N, is 45 deg off."""
    bags, rig, truths = family_thrust_bags
    parameters = yaml.safe_load(rig.read_text())
    parameters["/**"]["ros__parameters"]["effects"] = {
        "active": ["thrust"], "user": {"thrust": f"{__name__}:thrust"}, "thrust": {"a": 300.0, "b": 300.0},
    }
    rig_with_thrust = tmp_path / "rig_with_thrust.yaml"
    rig_with_thrust.write_text(yaml.safe_dump(parameters))
    with_thrust = _calibrated(
        bags, tmp_path / "with_thrust.yaml", "--config", str(rig_with_thrust), "--duration", "0.15"
    )
    fitted = load_coefficients(with_thrust, load_config(rig_with_thrust)).effects.values()["thrust"]
    amplitude, phase = float(np.hypot(fitted["a"], fitted["b"])), float(np.arctan2(fitted["b"], fitted["a"]))
    truth = float(np.mean([t.axial_thrust for t in truths]))
    assert 0.5 * truth < amplitude < 2.0 * truth and abs(phase) < 0.2, fitted

    out = tmp_path / "diagnosis"
    assert (
        main(["diagnose", *map(str, bags), "--config", str(rig), "--coeffs", str(family_thrust_calibrated),
              "--compare", str(with_thrust), "--out", str(out), "--fit", "0"]) == 0
    )
    ratio = _diagnosis(out)["comparison"]
    assert ratio["contact_force_rmse_per_axis"][2] < 0.9, ratio


def test_a_cross_coupling_named_under_the_papers_friction_is_qualified():
    """The verdict's notes: the file's calibration notes, then, only where the paper's friction meets a
    verdict for cross_coupled_stiffness, that it may stand in for a turning ring's friction."""
    from touchdown_ros.workflows.diagnose import verdict_notes

    named = {"explained": True, "best": "cross_coupled_stiffness"}
    notes = verdict_notes(["friction: mu 0.0004 ..."], "paper", named)
    assert notes[0] == "Calibration: friction: mu 0.0004 ..." and len(notes) == 2
    assert notes[1].startswith("cross_coupled_stiffness also stands in") and "spinning_ring" in notes[1]
    assert verdict_notes([], "spinning_ring", named) == []
    assert verdict_notes([], "paper", {"explained": True, "best": "radial_load"}) == []
    assert verdict_notes([], "paper", {"explained": False, "best": "cross_coupled_stiffness"}) == []


def test_the_report_says_how_to_add_the_named_effect_from_the_diagnosed_file():
    """diagnosis.md's next step under a verdict that names an effect: `train --start` from the diagnosed file with the
    effects it kept beside the new one, then the comparison; none where the verdict names none."""
    from touchdown_ros.workflows.report.diagnosis import CONSTANT_MODEL, next_step

    named = {"explained": True, "best": "brake_decay"}
    model = {"coefficients": "fits/c.yaml", "effects": {"axial_load": {"force": 1900.0}}, "verdict": named}
    assert next_step(model) == (
        "To add it: `touchdown train BAG... -o with_brake_decay.yaml --start fits/c.yaml -p "
        "'effects.active:=[axial_load, brake_decay]'`, then `touchdown diagnose BAG... --coeffs fits/c.yaml --compare "
        "with_brake_decay.yaml` (docs/workbench.md).")
    constant = next_step({**model, "coefficients": CONSTANT_MODEL, "effects": {}})
    assert "--start" not in constant and "--coeffs" not in constant and "[brake_decay]" in constant
    assert next_step({**model, "verdict": {"explained": False, "best": "brake_decay"}}) is None


def test_the_report_says_how_tightly_the_drops_pin_the_named_effects_size():
    """diagnosis.md under a verdict: each fitted parameter of the named effect with its 95 % interval relative to
    its value, and where one is wider than +- 10 %, about how many drops like these would pin it (n (w / 10 %)^2);
    and the terms of the fit a parameter shares half its variance or more with (r^2 >= 0.5), each pair once."""
    from touchdown_ros.workflows.report.diagnosis import how_well_sized

    def parameter(value: float, std: float) -> dict:  # as `candidates.candidate_rows` writes it
        return {"value": value, "std": std, "ci95": [value - 1.96 * std, value + 1.96 * std], "unit": "N s/m",
                "per_bag": {"a": value, "b": value}}

    drag = {"candidate": "viscous_friction", "fitted": True,
            "parameters": {"c_radial": parameter(2983.0, 45.0), "c_axial": parameter(4595.0, 900.0)}}
    other = {"candidate": "radial_load", "fitted": True, "parameters": {"force_x": parameter(300.0, 100.0)}}
    verdict = {"explained": True, "best": "viscous_friction", "candidates": [other, drag]}

    def diagnosed(**changes) -> dict:  # a model of diagnosis.json, its two bags diagnosed
        return {"bags": {"a": {}, "b": {}}, "verdict": {**verdict, **changes}}

    wide = {**drag, "parameters": {"c_axial": parameter(1000.0, 800.0)}}
    assert "c_axial 1000 N s/m +- 157 %" in how_well_sized(diagnosed(candidates=[wide]))
    assert how_well_sized(diagnosed()) == (
        "How tightly 2 drops pin its size (95 % intervals): c_radial 2983 N s/m +- 3 %, c_axial 4595 N s/m +- 38 %. "
        "c_axial is not pinned to +- 10 %: about 30 drops like these would be (the interval narrows as "
        "1 / sqrt(drops)). The intervals are the fit's scatter; a bias from a force the model lacks does not narrow.")
    pinned = {**drag, "parameters": {"c_radial": parameter(2983.0, 45.0)}}
    assert how_well_sized(diagnosed(candidates=[pinned])).endswith("c_radial 2983 N s/m +- 3 %.")
    at_bound = {**drag, "parameters": {"c_radial": parameter(0.0, 45.0), "c_axial": parameter(3000.0, 150.0)}}
    assert how_well_sized(diagnosed(candidates=[at_bound])) == (
        "How tightly 2 drops pin its size (95 % intervals): c_radial 0 +- 88 N s/m, c_axial 3000 N s/m +- 9.8 %.")
    assert how_well_sized(diagnosed(explained=False)) is None
    assert how_well_sized(diagnosed(candidates=[other])) is None  # the named effect was not fitted
    # a parameter that shares half its variance or more with another coordinate of its fit: which, and what it means;
    # a pair within the effect once; a dimensionless parameter without a unit
    traded = {**drag, "parameters": {
        "c_radial": {**parameter(2983.0, 45.0), "correlated_with": {"coordinate": "k_ZR", "r": 0.30}},
        "c_axial": {**parameter(3000.0, 150.0), "correlated_with": {"coordinate": "c_Z", "r": -0.75}},
    }}
    assert how_well_sized(diagnosed(candidates=[traded])) == (
        "How tightly 2 drops pin its size (95 % intervals): c_radial 2983 N s/m +- 3 %, c_axial 3000 N s/m +- 9.8 %. "
        "Its size moves with another term of the fit: c_axial with c_Z, the face contact's damping (posterior "
        "correlation -0.75). The drops tell such a pair's joint effect better than either, and where the model's form "
        "of the one differs from the rig's, the other's size makes up for it.")
    magnet = {"candidate": "magnetic_stiffness", "fitted": True, "parameters": {
        "k_radial": {**parameter(6.4e5, 6e3), "unit": "N/m",
                     "correlated_with": {"coordinate": "magnetic_stiffness.k_axial", "r": 0.97}},
        "k_axial": {**parameter(9.0e5, 9e3), "unit": "N/m",
                    "correlated_with": {"coordinate": "magnetic_stiffness.k_radial", "r": 0.97}},
    }}
    assert how_well_sized({"bags": {"a": {}}, "verdict": {**verdict, "best": "magnetic_stiffness",
                                                          "candidates": [magnet]}}) == (
        "How tightly 1 drop pins its size (95 % intervals): k_radial 6.4e+05 N/m +- 1.8 %, k_axial 9e+05 N/m +- 2 %. "
        "Its size moves with another term of the fit: k_radial with its k_axial (posterior correlation +0.97). The "
        "drops tell such a pair's joint effect better than either, and where the model's form of the one differs from "
        "the rig's, the other's size makes up for it.")


def test_the_fitted_candidates_table_prints_each_value_with_its_unit_and_a_dimensionless_one_bare():
    """diagnosis.md's table of fitted candidates: `name = value +- sd unit`, no unit "1" after a gain."""
    from touchdown_ros.workflows.report.diagnosis import fitted_markdown

    def row(candidate: str, name: str, value: float, std: float, unit: str) -> dict:
        return {"candidate": candidate, "fitted": True, "criterion": -40.0, "held_out_nll_fall": 0.01,
                "k_step_fall": -0.3, "k_step_fall_net": -0.5, "k_step_fall_by_phase": {"free flight": -0.2},
                "parameters": {name: {"value": value, "std": std, "unit": unit, "per_bag": {"a": value},
                                      "per_bag_std": {"a": std}}}}

    held = {"block_samples": 250, "every": 5, "measurement_noise_rms_m": [2e-6] * 3,
            "baseline_k_step_rmse_m": [4e-6] * 3, "baseline_k_step_rmse_net_m": [3e-6] * 3}
    lines = fitted_markdown({"held_out": held, "candidates": [row("sensor_gain_z", "gain", 1.05, 0.00069, "1"),
                                                              row("axial_load", "force", 1917.0, 42.0, "N")]})
    gain = next(line for line in lines if line.startswith("| sensor_gain_z | -40.0"))
    load = next(line for line in lines if line.startswith("| axial_load | -40.0"))
    assert "| gain = 1.05 +- 0.00069 | a 1.05 +- 0.00069 |" in gain
    assert "| force = 1917 +- 42 N | a 1917 +- 42 |" in load


def test_residual_tests_see_white_and_coloured_sequences():
    rng = np.random.default_rng(0)
    white = rng.standard_normal(4000)
    coloured = np.convolve(white, np.ones(10) / 10, mode="same")
    assert whiteness(white, 50)["outside_share"] < 0.05
    assert whiteness(coloured, 50)["outside_share"] > 0.1
    lags, r, band = cross_correlation(np.roll(white, 3), white, 10)
    assert lags[np.argmax(r)] == 3 and r.max() > 0.9 and band < 0.05


def test_frols_finds_the_true_block_and_its_value_despite_forced_terms():
    rng = np.random.default_rng(1)
    n = 3000
    forced = rng.standard_normal((n, 4))
    blocks = {"a": rng.standard_normal((n, 1)), "b": rng.standard_normal((n, 2)), "c": rng.standard_normal((n, 1))}
    y = forced @ np.array([1.0, -2.0, 0.5, 3.0]) + 2.5 * blocks["b"][:, 1] + 0.1 * rng.standard_normal(n)
    ranking = frols(y, blocks, forced)
    best = ranking.candidates[0]
    assert best.name == "b" and best.err > 0.99
    np.testing.assert_allclose(best.values, [0.0, 2.5], atol=0.02)
    assert ranking.forced_err > 0.5 and ranking.order[0][0] == "b"
    assert fit_percent(y[:, None], y[:, None])[0] == 100.0


def test_phases_and_impact_numbers():
    radial = np.array([0, 0, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 1], bool)
    axial = np.array([0, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1], bool)
    np.testing.assert_array_equal(contact_phase(radial, axial)[:5], [0, 1, 3, 2, 0])
    numbers = impact_numbers(radial | axial, merge_gap=5)
    assert numbers[0] == 0 and numbers[2] == 1 and numbers[-1] == 2
