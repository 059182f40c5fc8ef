"""Coefficient files: round trip, rig check, schema, atomic write, bad files."""
import dataclasses
import os

import numpy as np
import pytest
import yaml

from touchdown_ros.core.types import EXACT_PAIR, Coefficients, ContactLaw
from touchdown_ros.io.coefficients import (
    CoefficientFileError,
    TrainingRecord,
    content_sha256,
    load_coefficients,
    save_coefficients,
    sha256_of,
)
from touchdown_ros.io.config import load_config, reference_rig_path
from touchdown_ros.workflows.offline import estimator_for

CONFIG = load_config()


def random_coeffs(seed=0):
    rng = np.random.default_rng(seed)
    zeros = Coefficients.zeros(CONFIG.kernel)
    return Coefficients(rng.standard_normal(zeros.alpha_R.shape), rng.standard_normal(zeros.alpha_Z.shape))


def test_round_trip_is_exact_and_records_training(tmp_path):
    coeffs = random_coeffs()
    record = TrainingRecord(bags=[{"path": "a", "sha256": "00"}], regularisation=1e-3, final_loss=3.5, steps=7)
    path = save_coefficients(tmp_path / "c.yaml", coeffs, CONFIG, record)
    loaded = load_coefficients(path, CONFIG)
    np.testing.assert_array_equal(loaded.coeffs.alpha_R, coeffs.alpha_R)
    np.testing.assert_array_equal(loaded.coeffs.alpha_Z, coeffs.alpha_Z)
    assert loaded.training.final_loss == 3.5 and loaded.training.steps == 7
    document = yaml.safe_load(path.read_text())
    assert document["schema_version"] == 2 and document["rig_fingerprint"] == CONFIG.fingerprint()
    assert set(document["coefficients"]) >= {"k_R", "c_R", "mu", "k_Z", "c_Z", "k_ZR"}
    assert document["training"]["bags"] == [{"path": "a", "sha256": "00"}]
    assert oct(path.stat().st_mode & 0o777) == oct(0o666 & ~current_umask())  # readable by a node of another user


def current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_file_carries_its_calibration(tmp_path):
    """Contact law and constants, kernel (centres and scales) and filter noise come from the file,
    not from the YAML that loads it: the YAML holds guesses."""
    law = ContactLaw.of("hertz", 1.5).with_friction(CONFIG.law.friction, CONFIG.law.slip_velocity)
    calibrated = CONFIG.calibrated(
        CONFIG.nominal._replace(k_R=3.0e11, c_Z=1.5e12),
        law,
        CONFIG.kernel._replace(scale_R=np.array([7e-6, 0.02]), T_Z=np.asarray(CONFIG.kernel.T_Z) + 0.5),
        CONFIG.noise._replace(
            measurement=np.array([1e-12, 2e-12, 3e-12]), process=np.asarray(CONFIG.noise.process) * 3
        ),
    )
    path = save_coefficients(tmp_path / "c.yaml", random_coeffs(), calibrated, TrainingRecord())
    other_guess = load_config(overrides={"contact.k_R": 5.0e8, "kernel.width": 2.0, "filter.measurement_noise": 9e-6})
    loaded = load_coefficients(path, other_guess).config(other_guess)
    assert loaded.law == law and loaded.model().law == loaded.law
    assert loaded.nominal == calibrated.nominal
    for field in ("T_R", "T_Z", "scale_R", "scale_Z"):
        np.testing.assert_array_equal(getattr(loaded.kernel, field), getattr(calibrated.kernel, field))
    assert loaded.kernel.width == CONFIG.kernel.width
    np.testing.assert_allclose(loaded.noise.measurement, [1e-12, 2e-12, 3e-12], rtol=1e-12)
    np.testing.assert_array_equal(loaded.noise.process, np.asarray(CONFIG.noise.process) * 3)
    document = yaml.safe_load(path.read_text())
    document["contact"]["k_R"] = -1.0
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(CoefficientFileError, match=r"contact\.k_R must be a finite number >= 0"):
        load_coefficients(path, CONFIG)


def saved_with_law(path, law):
    """A coefficient file of the reference rig calibrated with `law` (the filter noise of its friction's state),
    checked to load it back."""
    noise = CONFIG.with_friction(law.friction).noise
    path = save_coefficients(
        path, random_coeffs(), CONFIG.calibrated(CONFIG.nominal, law, CONFIG.kernel, noise), TrainingRecord()
    )
    assert load_coefficients(path, CONFIG).config(CONFIG).law == law
    return path


def test_file_carries_a_kelvin_voigt_law_and_its_units(tmp_path):
    path = saved_with_law(tmp_path / "c.yaml", ContactLaw.of("kelvin_voigt", 1.5))
    contact = yaml.safe_load(path.read_text())["contact"]
    assert (contact["law"], contact["exponent"]) == ("kelvin_voigt", 1.5)
    assert contact["units"].startswith("F = k d^1.5 + c d_dot") and "c_R, c_Z N s/m;" in contact["units"]


def test_file_carries_a_yielding_support_and_refuses_a_bad_one(tmp_path):
    saved_with_law(tmp_path / "c.yaml", ContactLaw.of("hertz", 1.5).with_support(3.6e4, 1.0e4))
    rigid = save_coefficients(tmp_path / "rigid.yaml", random_coeffs(), CONFIG, TrainingRecord())
    document = yaml.safe_load(rigid.read_text())
    assert document["contact"]["support_preload"] == float("inf")  # written as .inf
    del document["contact"]["support_preload"], document["contact"]["support_span"]  # a file of before: rigid
    rigid.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
    assert not load_coefficients(rigid, CONFIG).config(CONFIG).law.yields
    for preload, span in ((-1.0, 1e4), (3e4, 0.0), (3e4, float("nan")), ("x", 1e4)):
        document["contact"].update(support_preload=preload, support_span=span)
        rigid.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
        with pytest.raises(
            CoefficientFileError, match=r"contact\.support_preload and contact\.support_span must be numbers > 0"
        ):
            load_coefficients(rigid, CONFIG)


@pytest.mark.parametrize("key", ["support_log_covariance", "stribeck_log_covariance"])
def test_file_carries_a_pairs_covariance_and_refuses_a_bad_one(tmp_path, key):
    """The support's (ln preload, ln span) and the Stribeck drop's (ln drop, ln v_s) covariances from stage 1."""
    covariance = ((6.25, -57.5), (-57.5, 530.0))
    support, stribeck = (covariance, EXACT_PAIR) if key.startswith("support") else (EXACT_PAIR, covariance)
    law = ContactLaw.of("hertz", 1.5).with_support(3.6e4, 1.0e4, support)
    law = law.with_friction("spinning_ring", 0.01).with_stribeck(0.35, 0.04, stribeck)
    uncertain = "support_uncertain" if key.startswith("support") else "stribeck_uncertain"
    path = saved_with_law(tmp_path / "c.yaml", law)  # loads back equal, covariance included
    document = yaml.safe_load(path.read_text())
    assert document["contact"][key] == [[6.25, -57.5], [-57.5, 530.0]]
    assert getattr(load_coefficients(path, CONFIG).config(CONFIG).law, uncertain)
    del document["contact"][key]  # a file of before: the pair taken as exact
    path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
    assert not getattr(load_coefficients(path, CONFIG).config(CONFIG).law, uncertain)
    bad = ([[1.0, 2.0], [2.0, 1.0]], [[1.0, 0.5], [0.4, 1.0]], [[1.0, float("nan")], [0.0, 1.0]], [1.0, 2.0], "x")
    for covariance in bad:  # not positive semi-definite, not symmetric, not finite, not 2 x 2
        document["contact"][key] = covariance
        path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
        with pytest.raises(CoefficientFileError, match=rf"contact\.{key} must be"):
            load_coefficients(path, CONFIG)


def test_file_carries_its_friction_and_refuses_a_bad_one(tmp_path):
    path = saved_with_law(tmp_path / "c.yaml", ContactLaw.of("hertz", 1.5).with_friction("co_rotating_ring", 0.03))
    document = yaml.safe_load(path.read_text())
    assert document["contact"]["friction"] == "co_rotating_ring" and document["contact"]["slip_velocity"] == 0.03
    del document["contact"]["friction"], document["contact"]["slip_velocity"]  # a file of before: the paper's
    path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
    assert load_coefficients(path, CONFIG).config(CONFIG).law.friction == "paper"
    for friction, slip, message in (
        ("sticky", 0.01, "friction must be one of paper, co_rotating_ring"),
        ("paper", 0.0, "slip_velocity must be > 0"),
        ("paper", "fast", "slip_velocity must be a number"),
    ):
        document["contact"].update(friction=friction, slip_velocity=slip)
        path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
        with pytest.raises(CoefficientFileError, match=message):
            load_coefficients(path, CONFIG)


def test_file_carries_the_stribeck_drop_and_refuses_a_bad_one(tmp_path):
    law = ContactLaw.of("hertz", 1.5).with_friction("spinning_ring", 0.01).with_stribeck(0.35, 0.04)
    path = saved_with_law(tmp_path / "c.yaml", law)
    assert load_coefficients(path, CONFIG).config(CONFIG).law == law
    document = yaml.safe_load(path.read_text())
    del document["contact"]["friction_drop"], document["contact"]["stribeck_velocity"]  # a file of before: none
    path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
    assert load_coefficients(path, CONFIG).config(CONFIG).law.friction_drop == 0.0
    for drop, velocity, message in (
        (-0.2, 0.04, r"contact\.friction_drop / contact\.stribeck_velocity: friction_drop must be >= 0"),
        (0.2, 0.0, "stribeck_velocity must be > 0"),
        ("high", 0.04, r"contact\.friction_drop and contact\.stribeck_velocity must be numbers"),
    ):
        document["contact"].update(friction_drop=drop, stribeck_velocity=velocity)
        path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
        with pytest.raises(CoefficientFileError, match=message):
            load_coefficients(path, CONFIG)


def test_file_carries_the_smoothing_noise_scale_and_the_offline_estimate_uses_it(tmp_path):
    """The offline estimate filters and smooths with Q times the file's factor; the live node's Q
    (`noise`) stays the fitted one; a file of before has none (1); a bad one is refused."""
    calibrated = CONFIG.calibrated(CONFIG.nominal, CONFIG.law, CONFIG.kernel, CONFIG.noise, 0.37)
    path = save_coefficients(tmp_path / "c.yaml", random_coeffs(), calibrated, TrainingRecord())
    loaded = load_coefficients(path, CONFIG).config(CONFIG)
    assert loaded.smoothing_noise_scale == 0.37
    np.testing.assert_array_equal(loaded.noise.process, CONFIG.noise.process)
    np.testing.assert_array_equal(loaded.offline_noise().process, np.asarray(CONFIG.noise.process) * 0.37)
    smoothed, filtered = (estimator_for(loaded, answer=answer) for answer in ("smoothed", "filtered"))
    np.testing.assert_array_equal(smoothed.noise.process, np.asarray(CONFIG.noise.process) * 0.37)
    np.testing.assert_array_equal(filtered.noise.process, CONFIG.noise.process)  # the live node's Q
    document = yaml.safe_load(path.read_text())
    del document["filter"]["smoothing_noise_scale"]
    path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
    assert load_coefficients(path, CONFIG).config(CONFIG).smoothing_noise_scale == 1.0
    for bad in (0.0, -2.0, float("nan"), "x", True):
        document["filter"]["smoothing_noise_scale"] = bad
        path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
        with pytest.raises(CoefficientFileError, match=r"filter\.smoothing_noise_scale must be a number > 0"):
            load_coefficients(path, CONFIG)


def test_file_carries_the_models_force_error_and_the_force_band_adds_it_in_contact(tmp_path):
    """filter.force_model_variance (N^2 per axis, measured by the trainer) is what the force band adds in
    contact, offline and for the node's filtered answer, in place of m^2 Q_v / h^2; a file without it keeps
    the latter; a bad one is refused."""
    variance = (4.0e4, 9.0e4, 2.5e3)
    calibrated = CONFIG.calibrated(CONFIG.nominal, CONFIG.law, CONFIG.kernel, CONFIG.noise, 1.0, variance)
    path = save_coefficients(tmp_path / "c.yaml", random_coeffs(), calibrated, TrainingRecord())
    loaded = load_coefficients(path, CONFIG).config(CONFIG)
    np.testing.assert_array_equal(loaded.model_variance(), variance)
    resting = np.tile([0.0, 0.0, -CONFIG.rig.axial_clearance - 2e-5], (200, 1))  # on the axial bearing
    stamps = np.arange(200) * int(CONFIG.sample_period * 1e9)
    q_as_force = CONFIG.rig.mass**2 * np.asarray(CONFIG.noise.process)[4:7] / CONFIG.sample_period**2
    for answer in ("smoothed", "filtered"):
        with_file = getattr(estimator_for(loaded, answer=answer)(stamps, resting), answer)
        # the same file without the variance (the same filter, the live one's Q adapted alike): m^2 Q_v / h^2
        without = getattr(estimator_for(dataclasses.replace(loaded, force_model_variance=None), answer=answer)(
            stamps, resting), answer)
        contact = np.asarray(with_file.axial_contact)
        assert contact[20:].all()
        added = np.diagonal(np.asarray(with_file.force_cov) - np.asarray(without.force_cov), axis1=1, axis2=2)
        expected = np.broadcast_to(np.subtract(variance, q_as_force), added[contact].shape)
        np.testing.assert_allclose(added[contact], expected, rtol=1e-6, atol=1e-6 * max(variance))
    document = yaml.safe_load(path.read_text())
    del document["filter"]["force_model_variance"]
    path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
    assert load_coefficients(path, CONFIG).config(CONFIG).model_variance() is None
    for bad in ([1.0, 2.0], [1.0, -2.0, 3.0], [1.0, float("nan"), 3.0], "x"):
        document["filter"]["force_model_variance"] = bad
        path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
        with pytest.raises(CoefficientFileError, match=r"filter\.force_model_variance must be"):
            load_coefficients(path, CONFIG)


def test_other_rig_is_refused_naming_the_difference(tmp_path):
    path = save_coefficients(tmp_path / "c.yaml", random_coeffs(), CONFIG, TrainingRecord())
    other = load_config(reference_rig_path(), overrides={"rig.mass": 250.0, "sensor.sample_period": 2.0e-4})
    with pytest.raises(CoefficientFileError, match=r"rig\.mass: file 240\.0, rig 250\.0") as error:
        load_coefficients(path, other)
    assert "sample_period: file 0.0001, rig 0.0002" in str(error.value)


@pytest.mark.parametrize(
    "content, message",
    [
        ("{unclosed", "not a readable YAML"),
        ("kind: something_else\n", "not a touchdown_ros coefficient file"),
        ("kind: touchdown_ros/pkbkr_coefficients\nschema_version: 99\n", "schema version 99"),
    ],
)
def test_bad_files_get_clear_errors(tmp_path, content, message):
    path = tmp_path / "bad.yaml"
    path.write_text(content)
    with pytest.raises(CoefficientFileError, match=message):
        load_coefficients(path, CONFIG)


def test_wrong_shape_and_missing_file(tmp_path):
    path = save_coefficients(tmp_path / "c.yaml", random_coeffs(), CONFIG, TrainingRecord())
    document = yaml.safe_load(path.read_text())
    document["coefficients"]["k_R"] = document["coefficients"]["k_R"][:-1]
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(CoefficientFileError, match=r"coefficients\.k_R must be 25 finite numbers"):
        load_coefficients(path, CONFIG)
    with pytest.raises(CoefficientFileError, match="not found"):
        load_coefficients(tmp_path / "missing.yaml", CONFIG)


def test_interrupted_write_leaves_old_file_and_no_temporary(tmp_path, monkeypatch):
    path = save_coefficients(tmp_path / "c.yaml", random_coeffs(0), CONFIG, TrainingRecord())
    before = path.read_bytes()

    def fail(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(KeyboardInterrupt):
        save_coefficients(path, random_coeffs(1), CONFIG, TrainingRecord())
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["c.yaml"]


def test_sha256_of_directory_changes_with_content(tmp_path):
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "a.mcap").write_bytes(b"123")
    first = sha256_of(bag)
    (bag / "a.mcap").write_bytes(b"124")
    assert sha256_of(bag) != first and len(first) == 64


def test_file_carries_the_calibrated_clearances_and_the_model_sees_them(tmp_path):
    """contact.radial_clearance / axial_clearance (stage 1 with training.clearance_tolerance > 0) are the clearances
    the model's contacts see; the rig's fingerprint stays the YAML's (the file still loads with it); a file without
    them keeps the YAML's; one of the two alone, or a bad value, is refused naming both."""
    clearances = (2.49e-4, 2.6e-4)
    calibrated = CONFIG.calibrated(CONFIG.nominal, CONFIG.law, CONFIG.kernel, CONFIG.noise, clearances=clearances)
    path = save_coefficients(tmp_path / "c.yaml", random_coeffs(), calibrated, TrainingRecord())
    loaded = load_coefficients(path, CONFIG)
    rig = loaded.model(CONFIG).rig
    assert (rig.radial_clearance, rig.axial_clearance) == (2.49e-4, 2.6e-4)
    assert loaded.config(CONFIG).rig == CONFIG.rig  # the YAML's, which the file is tied to
    document = yaml.safe_load(path.read_text())
    for name in ("radial_clearance", "axial_clearance"):
        del document["contact"][name]
    path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
    assert load_coefficients(path, CONFIG).model(CONFIG).rig == CONFIG.rig
    for bad in ({"axial_clearance": 2.6e-4}, {"radial_clearance": -1.0, "axial_clearance": 2.6e-4},
                {"radial_clearance": "x", "axial_clearance": 2.6e-4}):
        broken = {**document, "contact": {**document["contact"], **bad}}
        path.write_text(yaml.safe_dump({**broken, "content_sha256": content_sha256(broken)}))
        with pytest.raises(CoefficientFileError, match=r"contact\.radial_clearance and contact\.axial_clearance"):
            load_coefficients(path, CONFIG)


def test_a_file_trained_with_a_lead_is_refused_where_the_records_start_elsewhere(tmp_path):
    """amb_release's release is timed from the record's start, which `drop_detection.lead` moves: a file saved with a
    lead loads only with the same lead, and the refusal names it; without a lead the fingerprint is as before."""
    amb = {"effects.active": ["amb_release"], "rig.amb_stiffness": 2.0e6, "rig.amb_damping": 2.0e4}
    plain, led = load_config(overrides=amb), load_config(overrides={**amb, "drop_detection.lead": 3.0e-3})
    assert "drop_detection.lead" not in plain.model_identity() and plain.fingerprint() != led.fingerprint()
    path = save_coefficients(tmp_path / "c.yaml", random_coeffs(), led, TrainingRecord(bags=[]))
    assert load_coefficients(path, led).effects.params[0]["release"] == 3.0e-3
    with pytest.raises(CoefficientFileError, match=r"differs in: drop_detection.lead: file 0.003, rig None"):
        load_coefficients(path, plain)
