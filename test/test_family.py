"""The rig family: the new contact options (exponent, Kelvin-Voigt law), the variants, their rig files and CLI."""
import dataclasses
from dataclasses import fields

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from touchdown_ros.cli import main
from touchdown_ros.io.bags import read_conditions, read_displacement
from touchdown_ros.io.config import ConfigError, config_from_parameters, load_config
from touchdown_ros.sim import physics
from touchdown_ros.sim.campaign import CAMPAIGN
from touchdown_ros.sim.family import (
    DRAWN_RANGES,
    REFERENCE,
    RIG_FILE,
    VARIANTS,
    NoTouchdownError,
    Variant,
    drawn_variant,
    drawn_variants,
    matched_stiffness,
    simulate_variant,
    variant,
    variant_config,
    write_rig_yaml,
)
from touchdown_ros.sim.params import (
    BALL_DEFAULTS, check_step_size, required_substeps, simulator_parameters, truth_constants,
)
from touchdown_ros.sim.simulator import RPM, simulate_drop

CONFIG = load_config()
NEW_KEYS = ("damping_law", "contact_exponent", "radial_viscous_damping", "axial_viscous_damping")


def assert_same_record(a, b):
    for f in fields(a):
        value, other = getattr(a, f.name), getattr(b, f.name)
        if isinstance(value, np.ndarray):
            assert np.array_equal(value, other), f.name
        else:
            assert value == other, f.name


@pytest.fixture(scope="module")
def reference_drop():
    return simulate_drop(CONFIG, CAMPAIGN[0], seed=1)


# --- The new options leave the reference rig as it was -----------------------------------------


def test_reference_output_unchanged_by_the_new_options(reference_drop):
    # Without the new keys in the rig file (the code's defaults) the drop is the same bit for bit.
    flat = {k: v for k, v in CONFIG.parameters.items() if not k.endswith(NEW_KEYS)}
    assert len(flat) == len(CONFIG.parameters) - 1 - 2 * 3  # damping_law + 3 keys per ball
    assert_same_record(simulate_drop(config_from_parameters(flat), CAMPAIGN[0], seed=1), reference_drop)
    # The random stream is the one before the options existed: theta_0 and the sensor noise of
    # the first samples (numpy only, in ADC steps of 0.1 um), recorded before the change.
    first = [1.1386689102448794e-06, -2.832913628831388e-06, 0.0]
    np.testing.assert_allclose(reference_drop.position[0], first, rtol=1e-12)
    np.testing.assert_array_equal(np.round(reference_drop.measured[:2] / 1e-7), [[26, -9, -8], [16, -29, 9]])


def test_default_force_is_the_former_hunt_crossley_law(monkeypatch, reference_drop):
    """The drop integrated with the law as written before the options (K d^1.5 (1 + D d_dot)) is identical."""

    def former(K, exponent, D, C, linear, deformation, rate):
        d = jnp.maximum(deformation, 0.0)
        return jnp.where(deformation > 0.0, jnp.maximum(K * d**1.5 * (1.0 + D * rate), 0.0), 0.0)

    monkeypatch.setattr(physics, "normal_force", former)
    jax.clear_caches()  # the compiled integrator holds the traced law
    try:
        assert_same_record(simulate_drop(CONFIG, CAMPAIGN[0], seed=1), reference_drop)
    finally:
        monkeypatch.undo()
        jax.clear_caches()


# --- The force laws by hand ---------------------------------------------------------------------


def axial_force(overrides, deformation, rate):
    """F_z (N) of the rig with `overrides` (no variation, rigid mount) at axial deformation (m) and rate (m/s)."""
    config = load_config(overrides={"simulator.variation": 0.0, "simulator.axial_mount_preload": 1e9, **overrides})
    params = simulator_parameters(config)
    truth = truth_constants(config, params, "ceramic", False, False, 0.02, np.random.default_rng(0))
    state = np.zeros(physics.STATE_SIZE)
    state[physics.Z], state[physics.VZ] = -(config.rig.axial_clearance + deformation), -rate
    c = physics.contact(physics.Truth(*(jnp.asarray(v, dtype=jnp.float64) for v in truth)), jnp.asarray(state))
    assert not bool(c.radial_contact) and bool(c.axial_contact)
    return float(c.F_z)


@pytest.mark.parametrize("deformation, rate", [(10e-6, 0.05), (30e-6, -0.02), (45e-6, 0.0)])
def test_force_laws_by_hand(deformation, rate):
    K, D, C = 3.0e11, 6.0, 5.0e4  # ceramic axial K (N/m^1.5), D (s/m), C (N s/m)
    hunt_crossley = K * deformation**1.5 * (1.0 + D * rate)
    assert axial_force({}, deformation, rate) == pytest.approx(hunt_crossley, rel=1e-12)
    kelvin_voigt = K * deformation**1.5 + C * rate
    assert axial_force({"simulator.damping_law": "linear"}, deformation, rate) == pytest.approx(kelvin_voigt, rel=1e-12)
    C2 = 2.0e5
    linear = {"simulator.damping_law": "linear", "simulator.ceramic.axial_viscous_damping": C2}
    assert axial_force(linear, deformation, rate) == pytest.approx(K * deformation**1.5 + C2 * rate, rel=1e-12)
    for n in (1.0, 10.0 / 9.0, 2.0):
        Kn = matched_stiffness(n)
        rig = {"simulator.ceramic.contact_exponent": n, "simulator.ceramic.axial_stiffness": Kn}
        expected = Kn * deformation**n * (1.0 + D * rate)
        assert axial_force(rig, deformation, rate) == pytest.approx(expected, rel=1e-12)
        assert axial_force({"simulator.ceramic.contact_exponent": n}, deformation, rate) != pytest.approx(hunt_crossley)
    if rate != 0.0:
        assert kelvin_voigt != pytest.approx(hunt_crossley, rel=1e-3)  # the laws do differ here


def test_force_laws_never_pull_and_vanish_out_of_contact():
    for law in ("hunt_crossley", "linear"):
        rig = {"simulator.damping_law": law, "simulator.ceramic.contact_exponent": 1.0,
               "simulator.ceramic.axial_stiffness": matched_stiffness(1.0)}
        assert axial_force(rig, 1e-6, -5.0) == 0.0  # separating fast: clipped at 0, not pulling
    assert matched_stiffness(1.0) * 45e-6 == pytest.approx(3.0e11 * 45e-6**1.5, rel=1e-3)


def test_new_law_changes_the_drop(reference_drop):
    linear = simulate_drop(load_config(overrides={"simulator.damping_law": "linear"}), CAMPAIGN[0], seed=1)
    assert np.abs(linear.F_z - reference_drop.F_z).max() > 1e3
    np.testing.assert_array_equal(linear.position[0], reference_drop.position[0])  # same theta_0


# --- Validation ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "key, value",
    [
        ("simulator.ceramic.contact_exponent", 0.5),
        ("simulator.ceramic.contact_exponent", 2.5),
        ("simulator.steel.contact_exponent", "1.5"),
        ("simulator.damping_law", "viscous"),
        ("simulator.damping_law", 1),
        ("simulator.ceramic.radial_viscous_damping", -1.0),
        ("simulator.steel.axial_viscous_damping", "5.0e4"),
    ],
)
def test_bad_new_values_name_the_key(key, value):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        simulate_drop(load_config(overrides={key: value}), CAMPAIGN[0], seed=0)


def test_too_stiff_a_contact_asks_for_substeps():
    overrides = {
        "simulator.regularisation_velocity": 1.0,  # the ring-rotor stick is no longer the stiffest mode
        "simulator.ceramic.contact_exponent": 1.0,
        "simulator.ceramic.axial_stiffness": 1.0e16,  # N/m: sqrt(K / m) ~ 6e6 1/s
    }
    expected = r"'simulator\.substeps' = 100 .*axial contact.*use at least \d+.*'simulator\.ceramic\.axial_stiffness'"
    with pytest.raises(ConfigError, match=expected):
        simulate_drop(load_config(overrides=overrides), CAMPAIGN[0], seed=0)


# --- The family ---------------------------------------------------------------------------------


def test_family_covers_the_brief():
    assert len(VARIANTS) >= 7 and len({v.name for v in VARIANTS}) == len(VARIANTS)
    settings = {(k, v) for var in VARIANTS for k, v in var.overrides.items()}
    K = 3.0e11
    for wanted in [
        ("simulator.ceramic.radial_stiffness", 0.2 * K), ("simulator.ceramic.axial_stiffness", 0.2 * K),
        ("simulator.ceramic.radial_stiffness", 5.0 * K), ("simulator.ceramic.axial_stiffness", 5.0 * K),
        ("simulator.damping_law", "linear"), ("simulator.ceramic.radial_damping", 60.0),
        ("simulator.ceramic.friction_kinetic", 0.05), ("simulator.ceramic.friction_kinetic", 0.3),
        ("simulator.ceramic.contact_exponent", 10.0 / 9.0), ("simulator.ceramic.contact_exponent", 1.0),
        ("rig.mass", 0.7 * 240.0), ("rig.mass", 1.3 * 240.0),
        ("sensor.noise_rms", 1.0e-6), ("sensor.noise_rms", 5.0e-6),
    ]:
        assert any(k == wanted[0] and v == pytest.approx(wanted[1]) for k, v in settings), wanted
    for v in VARIANTS:
        config = variant_config(v)
        assert config.nominal == CONFIG.nominal, v.name  # the trainer's starting guess
        np.testing.assert_array_equal(config.noise.measurement, CONFIG.noise.measurement)
        assert config.fingerprint() == CONFIG.fingerprint() or "rig.mass" in v.overrides
        assert variant(v.name) is v
    with pytest.raises(ValueError, match="soft_bearing"):
        variant("no_such_rig")
    with pytest.raises(ValueError, match="contact.k_R"):
        Variant("cheat", "truth-derived nominal constants", {"contact.k_R": 2.0e9})


def test_the_reference_yamls_balls_are_the_simulators_defaults():
    """The named rigs' stiffnesses are matched to the default ceramic ball; the reference YAML must mean the same."""
    assert simulator_parameters(CONFIG).balls == BALL_DEFAULTS
    assert matched_stiffness(1.5) == BALL_DEFAULTS["ceramic"]["radial_stiffness"]


@pytest.mark.parametrize("v", VARIANTS, ids=lambda v: v.name)
def test_every_variant_touches_down(v, reference_drop):
    (record,) = simulate_variant(v, 1, seed=0)  # raises NoTouchdownError without radial and axial contact
    after = slice(record.drop_index, None)
    assert record.radial_contact[after].any() and record.axial_contact[after].any()
    assert np.isfinite(record.position).all() and np.isfinite(record.contact_force).all()
    radial = np.hypot(record.contact_force[:, 0], record.contact_force[:, 1])
    assert 1e3 < record.F_z.max() < 1e5 and 1e3 < radial.max() < 1e5  # kN to tens of kN
    config = variant_config(v)
    noise = (record.measured - record.position)[: record.drop_index]
    assert noise.std() == pytest.approx(config.noise_rms, rel=0.15)
    # the same condition and seed on the reference rig gives another drop
    assert record.condition == CAMPAIGN[0] and record.seed == reference_drop.seed
    assert np.abs(record.contact_force - reference_drop.contact_force).max() > 100.0


# --- Rigs drawn at random ----------------------------------------------------------------------


def test_drawn_rigs_span_the_ranges_in_every_quantity_at_once():
    rigs = drawn_variants(0, 40)
    assert [v.name for v in rigs[:2]] == ["drawn_0_1", "drawn_0_2"] and len({v.name for v in rigs}) == 40
    assert variant("drawn_0_7") == rigs[6] and drawn_variant(0, 7) == rigs[6]  # drawn again, the same rig
    assert drawn_variant(1, 7) != rigs[6]  # another seed, another rig
    ranges = DRAWN_RANGES
    factors = []
    for v in rigs:
        o = v.overrides
        n = o["simulator.ceramic.contact_exponent"]
        assert n in ranges["contact_exponent"] and o["simulator.damping_law"] in ranges["damping_law"]
        factor = o["simulator.ceramic.radial_stiffness"] / matched_stiffness(n)
        axial = o["simulator.ceramic.axial_stiffness"] / matched_stiffness(n)
        assert 0.199 <= min(factor, axial) and max(factor, axial) <= 5.01, v.name
        factors.append(factor)
        mu_k, mu_s = o["simulator.ceramic.friction_kinetic"], o["simulator.ceramic.friction_static"]
        assert 0.05 <= mu_k <= 0.30 and 1.09 * mu_k <= mu_s <= 1.41 * mu_k
        assert 0.7 * 240.0 <= o["rig.mass"] <= 1.3 * 240.0 and 1.0e-6 <= o["sensor.noise_rms"] <= 5.0e-6
        config = variant_config(v)
        assert config.nominal == CONFIG.nominal, v.name  # the estimator's guess stays the reference's
        np.testing.assert_array_equal(config.noise.measurement, CONFIG.noise.measurement)
        params = simulator_parameters(config)
        truth = truth_constants(config, params, "ceramic", False, False, 0.0, np.random.default_rng(0))
        assert params.substeps >= required_substeps(truth, 5000.0 * RPM, config.sample_period)
    # 40 draws reach both ends of the stiffness and friction ranges and every law and exponent
    assert min(factors) < 0.4 and max(factors) > 2.5
    assert {v.overrides["simulator.damping_law"] for v in rigs} == set(ranges["damping_law"])
    assert {v.overrides["simulator.ceramic.contact_exponent"] for v in rigs} == set(ranges["contact_exponent"])
    frictions = [v.overrides["simulator.ceramic.friction_kinetic"] for v in rigs]
    assert min(frictions) < 0.08 and max(frictions) > 0.27
    with pytest.raises(ValueError, match="index >= 1"):
        drawn_variant(0, 0)
    with pytest.raises(ValueError, match=r"drawn_<seed>_<index>"):
        variant("drawn_x_1")


@pytest.mark.parametrize("name", ["drawn_0_1", "drawn_0_2"])
def test_a_drawn_rig_touches_down_and_its_rig_file_loads_back(name, tmp_path):
    v = variant(name)
    (record,) = simulate_variant(v, 1, seed=0)  # the substeps are enough, or the simulator refuses them
    after = slice(record.drop_index, None)
    assert record.radial_contact[after].any() and record.axial_contact[after].any()
    assert np.isfinite(record.contact_force).all()
    path = write_rig_yaml(v, tmp_path)
    assert dict(load_config(path).parameters) == dict(variant_config(v).parameters)
    assert v.description in path.read_text()


def test_required_substeps_is_the_step_size_check_s_limit():
    config = load_config(overrides=variant("stiff_quiet").overrides)
    params = simulator_parameters(config)
    truth = truth_constants(config, params, "ceramic", False, False, 0.0, np.random.default_rng(0))
    speed, period = 5000.0 * RPM, config.sample_period
    needed = required_substeps(truth, speed, period)
    check_step_size(dataclasses.replace(params, substeps=needed), truth, speed, period)
    with pytest.raises(ConfigError, match=f"use at least {needed}"):
        check_step_size(dataclasses.replace(params, substeps=needed - 1), truth, speed, period)


def test_a_drop_without_touchdown_is_refused():
    too_short = Variant("too_short", "stops before the rotor reaches the bearing", {"simulator.drop_duration": 0.005})
    with pytest.raises(NoTouchdownError, match="too_short experiment 1: no radial and no axial contact"):
        simulate_variant(too_short, 1)


def test_drops_of_a_variant_differ():
    v = variant("lossy_contact")
    short = Variant(v.name, v.description, {**v.overrides, "simulator.drop_duration": 0.06})
    first, second = simulate_variant(short, 2, seed=7)
    assert [first.condition.number, second.condition.number] == [1, 2] and [first.seed, second.seed] == [8, 9]
    assert not np.array_equal(first.position[0], second.position[0])  # another theta_0


@pytest.mark.parametrize("v", (REFERENCE, *VARIANTS), ids=lambda v: v.name)
def test_variant_rig_file_loads_back(v, tmp_path):
    path = write_rig_yaml(v, tmp_path)
    assert path.name == RIG_FILE and path.read_text().startswith(f"# touchdown_ros rig variant '{v.name}'")
    loaded, expected = load_config(path), variant_config(v)
    assert dict(loaded.parameters) == dict(expected.parameters)
    assert list(loaded.parameters) == list(CONFIG.parameters)  # the reference rig's layout
    assert loaded.fingerprint() == expected.fingerprint()
    assert dict(loaded.simulator) == dict(expected.simulator)
    write_rig_yaml(v, tmp_path)  # the same rig again is fine, another one is not
    other = VARIANTS[1] if v is VARIANTS[0] else VARIANTS[0]
    with pytest.raises(FileExistsError, match="rig.yaml"):
        write_rig_yaml(other, tmp_path)


# --- touchdown simulate --variant -------------------------------------------------------------


def test_cli_writes_variant_bags_and_rig(tmp_path, capsys):
    out = tmp_path / "bags"
    assert main(["simulate", "--variant", "linear_spring", "--experiment", "2", "-o", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["linear_spring_02", RIG_FILE]
    series = read_displacement(out / "linear_spring_02")
    (expected,) = simulate_variant(variant("linear_spring"), seed=0, numbers=[2])
    np.testing.assert_array_equal(series.stamps_ns, expected.stamps_ns)
    np.testing.assert_array_equal(series.xyz, expected.measured)
    assert read_conditions(out / "linear_spring_02")["ball"] == "ceramic"
    assert dict(load_config(out / RIG_FILE).parameters) == dict(variant_config(variant("linear_spring")).parameters)
    capsys.readouterr()

    assert main(["simulate", "--variant", "linear_spring", "--experiment", "2", "-o", str(out)]) == 3
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert main(["simulate", "--variant", "glass_bearing", "-o", str(out)]) == 3
    error = capsys.readouterr().err
    assert "no rig variant named 'glass_bearing'" in error and all(v.name in error for v in VARIANTS)
    assert main(["simulate", "--variant", "slippery", "--config", str(out / RIG_FILE), "-o", str(out)]) == 3
    assert "--variant brings its own rig" in capsys.readouterr().err
    assert main(["simulate", "-o", str(out)]) == 3
    assert "--variant NAME" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["linear_spring_02", RIG_FILE]


def test_cli_help_lists_the_variants(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert all(v.name in text for v in VARIANTS)
