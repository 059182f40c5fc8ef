"""Rig YAML loading: the reference rig, ROS 2 parameter-file form, clear errors."""
import numpy as np
import pytest

from touchdown_ros.io.config import ConfigError, load_config, reference_rig_path


LAMBDAS = "regularisation: [1.0, 1.0e-1, 1.0e-2, 1.0e-3]"


def write(tmp_path, text):
    path = tmp_path / "rig.yaml"
    path.write_text(text)
    return path


def test_reference_rig_is_the_documented_rig():
    config = load_config()
    assert config.rig.mass == 240.0
    assert np.isclose(config.rig.speed, 5000 * 2 * np.pi / 60)
    assert config.rig.eccentricity == 10e-6
    assert config.rig.radial_clearance == config.rig.axial_clearance == 0.25e-3
    assert config.sample_period == 1e-4 and config.noise_rms == 2e-6
    assert config.kernel.T_R.shape == (25, 2) and config.kernel.T_Z.shape == (25, 2)
    assert config.topics.displacement == "/amb/displacement"
    assert np.allclose(config.noise.measurement, 4e-12)
    assert config.regularisation == (1.0, 0.1, 0.01, 0.001)
    assert load_config(overrides={"training.regularisation": 0.02}).regularisation == (0.02,)


def test_named_node_section_and_overrides(tmp_path):
    text = reference_rig_path().read_text().replace("/**:", "touchdown_estimator:")
    config = load_config(write(tmp_path, text), overrides={"rig.mass": 300.0})
    assert config.rig.mass == 300.0


@pytest.mark.parametrize(
    "edit, message",
    [
        (("mass: 240.0", "mass: -1.0"), "'rig.mass' must be > 0"),
        (("mass: 240.0", "mass: heavy"), "'rig.mass' must be a finite number"),
        (("k_R: 5.0e+8", "k_R: 5.0e8"),
         "got '5.0e8' \\(YAML reads a number as text unless it has a decimal point and a signed exponent: write "
         "1.0e\\+8 or 1.0e-5"),
        (("k_R: 5.0e+8", "k_R: 5e+8"), "got '5e\\+8' \\(YAML reads a number as text"),
        (("mass: 240.0", "mass: 240.0\n      colour: red"), "unknown parameter\\(s\\): rig.colour"),
        (("      mass: 240.0                     # kg\n", ""), "missing parameter 'rig.mass'"),
        (("measurement_noise: 2.0e-6", "measurement_noise: [1, 2]"), "'filter.measurement_noise' must be a finite"),
        (("process_noise: [", "process_noise: [1.0, "), "'filter.process_noise' must have 7 values"),
        (("process_noise: [", "process_noise: [1e-14, "),
         "'filter.process_noise' must be a non-empty list of finite numbers; entry 1 is '1e-14' \\(YAML reads"),
        (("realtime_priority: 0 ", "realtime_priority: 100 "), "'node.realtime_priority' must be an integer in 0..99"),
        (("receive: drain ", "receive: polled "), "'node.receive' must be one of"),
        (("receive: drain ", "worker: true "), "node.worker: replaced by node.receive"),
        (("regularisation: [1.0, ", "regularisation: [-1.0, "), "'training.regularisation' must not be negative"),
        ((LAMBDAS, "regularisation: []"), "'training.regularisation' must be a"),
        ((LAMBDAS, "regularisation: much"), "'training.regularisation' must be"),
        (("clearance_tolerance: 0.0 ", "clearance_tolerance: -1.0e-6 "), "'training.clearance_tolerance' must be >= 0"),
        (("adaptation_memory: 0.01 ", "adaptation_memory: 1.0e-5 "),
         "filter.adaptation_memory = 1e-05 s is shorter than one sample"),
        (("adaptation_max_scale: 64.0", "adaptation_max_scale: 0.5"),
         "filter.adaptation_max_scale = 0.5 must be at least 1"),
        (("adaptation_gain: 0.1", "adaptation_gain: -0.1"), "'filter.adaptation_gain' must be > 0"),
    ],
)
def test_bad_values_are_named(tmp_path, edit, message):
    text = reference_rig_path().read_text()
    assert edit[0] in text
    with pytest.raises(ConfigError, match=message):
        load_config(write(tmp_path, text.replace(edit[0], edit[1], 1)))


def test_not_a_parameter_file(tmp_path):
    with pytest.raises(ConfigError, match="ros__parameters"):
        load_config(write(tmp_path, "rig:\n  mass: 1.0\n"))
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(write(tmp_path, "a: [\n"))


def test_fingerprint_follows_the_rig_not_the_guesses(tmp_path):
    """A coefficient file carries its own calibrated contact constants, kernel and noise: the
    YAML's guesses of those do not tie it; the rotor and the sample period do."""
    base = load_config()
    for same in (
        {"topics.velocity": "/v"},
        {"contact.k_Z": 1.0},
        {"kernel.width": 2.0},
        {"filter.measurement_noise": 1e-6},
    ):
        assert load_config(overrides=same).fingerprint() == base.fingerprint(), same
    for other in ({"rig.mass": 200.0}, {"rig.radial_clearance": 0.3e-3}, {"sensor.sample_period": 2e-4}):
        assert load_config(overrides=other).fingerprint() != base.fingerprint(), other


def test_contact_law_and_training_settings(tmp_path):
    assert load_config().law.label == "linear"
    hertz = load_config(overrides={"contact.law": "hertz", "contact.exponent": 1.111})
    assert (hertz.law.name, hertz.law.exponent, hertz.model().law) == ("hertz", 1.111, hertz.law)
    assert load_config(overrides={"contact.law": "hertz"}).law.exponent == 1.5
    viscous = load_config(overrides={"contact.law": "kelvin_voigt"}).law
    assert (viscous.name, viscous.exponent, viscous.setting, viscous.label) == (
        "kelvin_voigt", 1.5, "kelvin_voigt:1.5", "kelvin_voigt n=1.5"
    )
    with pytest.raises(ConfigError, match=r"kelvin_voigt law's exponent must be in \(1, 3\]"):
        load_config(overrides={"contact.law": "kelvin_voigt", "contact.exponent": 1.0})
    with pytest.raises(ConfigError, match="contact.law"):
        load_config(overrides={"contact.law": "spring"})
    with pytest.raises(ConfigError, match="linear contact law has exponent 1"):
        load_config(overrides={"contact.exponent": 1.5})
    settings = load_config(
        overrides={"training.contact_laws": ["hertz:1.5", "linear", "kelvin_voigt:1.2"], "training.loss": "one_step"}
    ).training
    assert [law.setting for law in settings.contact_laws] == ["hertz:1.5", "linear", "kelvin_voigt:1.2"]
    assert settings.loss == "one_step"
    assert load_config(overrides={"training.contact_laws": []}).training.contact_laws == (load_config().law,)
    with pytest.raises(ConfigError, match="training.contact_laws"):
        load_config(overrides={"training.contact_laws": ["hertz:x"]})
    with pytest.raises(ConfigError, match="training.loss"):
        load_config(overrides={"training.loss": "mse"})
    ring = load_config(overrides={"contact.friction": "co_rotating_ring", "contact.slip_velocity": 0.02})
    assert (ring.law.friction, ring.law.slip_velocity, ring.model().law) == ("co_rotating_ring", 0.02, ring.law)
    assert {(law.friction, law.slip_velocity) for law in ring.training.contact_laws} == {("co_rotating_ring", 0.02)}
    assert load_config().law.friction == "spinning_ring"
    with pytest.raises(ConfigError, match="contact.friction"):
        load_config(overrides={"contact.friction": "sticky"})
    with pytest.raises(ConfigError, match="contact.slip_velocity"):
        load_config(overrides={"contact.slip_velocity": 0.0})


def test_config_reads_the_friction_models_stage_1_chooses_from_and_moves_a_rig_to_another():
    """training.friction_models: a list of FRICTION_MODELS (empty by default: contact.friction alone); a wrong
    one is refused naming the key. `Config.with_friction` gives the rig the YAML would with that contact.friction:
    its law, its candidate laws and the filter noise of its state (a spinning ring's speed is an eighth)."""
    assert load_config().training.friction_models == ()
    paper = load_config(overrides={"training.friction_models": ["paper", "spinning_ring", "paper"],
                                   "contact.friction": "paper", "filter.ring_process_noise": 2.0e-3,
                                   "contact.slip_velocity": 0.02})
    assert paper.training.friction_models == ("paper", "spinning_ring")
    for wrong in ("spinning_ring", ["paper", "ring"], [1]):
        with pytest.raises(ConfigError, match="training.friction_models"):
            load_config(overrides={"training.friction_models": wrong})
    ring = load_config(overrides={"contact.friction": "spinning_ring", "filter.ring_process_noise": 2.0e-3,
                                  "contact.slip_velocity": 0.02})
    for moved, read in ((paper.with_friction("spinning_ring"), ring), (ring.with_friction("paper"), paper)):
        assert moved.law == read.law and moved.training.contact_laws == read.training.contact_laws
        np.testing.assert_array_equal(moved.noise.process, read.noise.process)
        np.testing.assert_array_equal(moved.noise.initial, read.noise.initial)
    assert len(ring.noise.process) == 8 and ring.noise.process[-1] == 2.0e-3 and len(paper.noise.process) == 7


def test_deep_shared_memory_profile_is_a_fast_dds_profile():
    """config/fastdds_deep_shm.xml: well-formed XML (no '--' in its comments), the default
    participant profile using a shared-memory transport deeper than Fast DDS's 512 messages."""
    import xml.etree.ElementTree as ET

    path = reference_rig_path().parent / "fastdds_deep_shm.xml"
    ns = {"dds": "http://www.eprosima.com"}
    root = ET.parse(path).getroot()
    shm = [
        d for d in root.iterfind(".//dds:transport_descriptor", ns) if d.findtext("dds:type", namespaces=ns) == "SHM"
    ]
    assert len(shm) == 1 and int(shm[0].findtext("dds:port_queue_capacity", namespaces=ns)) > 512
    participant = root.find(".//dds:participant", ns)
    assert participant.get("is_default_profile") == "true"
    used = [t.text for t in participant.iterfind(".//dds:userTransports/dds:transport_id", ns)]
    assert shm[0].findtext("dds:transport_id", namespaces=ns) in used


def test_without_stribeck_fit_is_the_rig_with_no_drop_given():
    """What `train` fits first with training.friction_drop: fitted (for the process noise): the same rig with
    no drop, in its law and every candidate law, and the drop given; the rest as it was."""
    fitted = load_config(overrides={"contact.friction_drop": 0.3, "contact.stribeck_velocity": 0.03,
                                    "training.friction_drop": "fitted"})
    plain = fitted.without_stribeck_fit()
    assert fitted.fits_stribeck_drop and not plain.fits_stribeck_drop
    assert not fitted.with_friction("paper").fits_stribeck_drop  # no slip for a drop to act on
    assert plain.training.friction_drop == "given"
    assert all(law.friction_drop == 0.0 for law in (plain.law, *plain.training.contact_laws))
    assert plain.law == fitted.law.with_stribeck(0.0, 0.03) and plain.noise is fitted.noise
    assert len(plain.training.contact_laws) == len(fitted.training.contact_laws) > 1


def test_config_reads_the_stribeck_drop_and_refuses_to_fit_one_it_cannot():
    """contact.friction_drop and stribeck_velocity reach the law and every candidate law; training.friction_drop:
    fitted needs a ring's friction and a guess of the drop > 0, each refused by name."""
    given = load_config(overrides={"contact.friction_drop": 0.3, "contact.stribeck_velocity": 0.03})
    assert (given.law.friction_drop, given.law.stribeck_velocity) == (0.3, 0.03)
    assert all((c.friction_drop, c.stribeck_velocity) == (0.3, 0.03) for c in given.training.contact_laws)
    assert given.training.friction_drop == "given" and load_config().law.friction_drop == 0.0
    fitted = load_config(overrides={"contact.friction_drop": 0.3, "training.friction_drop": "fitted"})
    assert fitted.training.friction_drop == "fitted"
    for overrides, message in (
        ({"contact.friction_drop": -0.1}, "contact.friction_drop' must be >= 0"),
        ({"contact.stribeck_velocity": 0.0}, "contact.stribeck_velocity' must be > 0"),
        ({"training.friction_drop": "fitted"}, "contact.friction_drop .* must then be > 0"),
        ({"training.friction_drop": "fitted", "contact.friction": "paper"}, "fitted needs friction against a ring"),
        ({"training.friction_drop": "guessed"}, "training.friction_drop"),
        ({"contact.friction_drop": 0.3, "contact.friction": "paper"}, "the drop would be ignored"),
    ):
        with pytest.raises(ConfigError, match=message):
            load_config(overrides=overrides)


def test_a_lead_starts_the_record_in_levitation_and_needs_the_ambs_force():
    """drop_detection.lead moves the onset back by its rows in every tool (the detector's fall rows) and starts
    amb_release's release there; without a clocked force effect it is refused by name, as is a negative one."""
    amb = {"effects.active": ["amb_release"], "rig.amb_stiffness": 2.0e6, "rig.amb_damping": 2.0e4}
    plain, led = load_config(overrides=amb), load_config(overrides={**amb, "drop_detection.lead": 3.0e-3})
    assert led.drop_detector().fall_samples == plain.drop_detector().fall_samples + 30
    assert led.stream_settings().drop == led.drop_detector()  # the live node's onset is the offline tools'
    assert led.effects.params[0]["release"] == 3.0e-3 and plain.effects.params[0]["release"] == 0.0
    given = load_config(overrides={**amb, "drop_detection.lead": 3.0e-3, "effects.amb_release.release": 2.0e-3})
    assert given.effects.params[0]["release"] == 2.0e-3
    with pytest.raises(ConfigError, match=r"drop_detection.lead = 0.003 s .* \(effects.active: \[amb_release\]"):
        load_config(overrides={"drop_detection.lead": 3.0e-3})
    with pytest.raises(ConfigError, match="drop_detection.lead' must be >= 0"):
        load_config(overrides={**amb, "drop_detection.lead": -1.0e-3})


def test_the_live_filters_adaptive_q_from_the_yaml():
    """filter.adaptive_process_noise and its settings: the leak per sample is the period over the memory; off: None;
    the live filter adapts a fitted Q only."""
    adaptation = load_config(overrides={"filter.adaptation_memory": 0.002, "filter.adaptation_gain": 0.3}).adaptation
    assert adaptation.leak == pytest.approx(1.0e-4 / 0.002) and adaptation.gain == 0.3
    assert adaptation.max_scale == 64.0
    assert load_config(overrides={"filter.adaptive_process_noise": False}).adaptation is None
    # live only where Q was fitted on training bags (a coefficient file's), not on the YAML's guess
    guess = load_config()
    assert guess.live_adaptation is None
    fitted = guess.calibrated(guess.nominal, guess.law, guess.kernel, guess.noise)
    assert fitted.live_adaptation == guess.adaptation is not None
