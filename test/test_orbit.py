"""The rotor's speed read from its orbit: a braked rotor's decay off the displacements, before any fit."""
import io

import numpy as np
import pytest
from conftest import write_simulated_bag

from touchdown_ros.core import effects as fx
from touchdown_ros.core.orbit import speed_effects_from_orbits, whirl_speeds
from touchdown_ros.core.selection import with_candidates
from touchdown_ros.io.config import load_config
from touchdown_ros.workflows.calibrate import started_from_orbits
from touchdown_ros.workflows.candidates import candidates_to_fit
from touchdown_ros.workflows.training_data import TrainingData, load_training_data

BRAKED = {"effects.active": ["brake_decay"], "effects.when.brake_decay": "brake"}


@pytest.fixture(scope="module")
def drops(tmp_path_factory):
    """Experiments 9 (braked, loaded), 6 (braked) and 1 (neither) of Table 1 as bags, with their records."""
    out = tmp_path_factory.mktemp("orbit")
    return {n: (out / f"exp_{n:02d}", write_simulated_bag(out / f"exp_{n:02d}", n, seed=n)) for n in (9, 6, 1)}


def _truth_rate(record, times: np.ndarray) -> float:
    """1/s: the simulator's rotor speed decay over `times` (s from the drop) as brake_decay's rate."""
    at = record.drop_index + np.round(times / record.sample_period).astype(int)
    slope = np.polyfit(times, record.omega[at], 1)[0]
    return -slope / record.omega[record.drop_index]


def test_the_orbit_of_a_rotor_whirling_on_the_bore_turns_at_the_rotors_speed(drops):
    config = load_config()
    for n in (9, 6):
        _, record = drops[n]
        orbit = whirl_speeds(record.measured[record.drop_index :], config.sample_period)
        assert len(orbit.times) >= 8, (n, orbit)
        speed = record.omega[record.drop_index + np.round(orbit.times / config.sample_period).astype(int)]
        np.testing.assert_allclose(orbit.speeds, speed, rtol=0.03, err_msg=f"experiment {n}")
        assert np.all(np.diff(orbit.speeds[:-1]) < 5.0), orbit.speeds  # decaying: the spin-up is left out


def test_brake_decay_starts_at_the_decay_the_orbits_show_and_only_in_the_braked_bags(drops):
    """started_from_orbits on the YAML's default rate (0.1 1/s): the braked bags' orbits put the start
    within 15 % of the simulator's decay; the unbraked bag, gated off, does not count."""
    config = load_config(overrides=BRAKED)
    data = load_training_data(config, [drops[n][0] for n in (9, 6, 1)])
    stream = io.StringIO()
    started = started_from_orbits(config, data, stream)
    rate = started.effects.values()["brake_decay"]["rate"]
    truth = np.mean([_truth_rate(drops[n][1], np.arange(0.1, 0.145, 0.005)) for n in (9, 6)])
    assert abs(rate - truth) < 0.15 * truth, (rate, truth)
    assert "brake_decay starts where its speed fits the orbit's" in stream.getvalue()
    assert "(was 0.1)" in stream.getvalue()


def test_a_conditional_speed_effect_is_not_read_from_bags_without_conditions(drops):
    """Records with no recorded conditions: brake_decay (when: brake) acts in none of them in training
    (`TrainingData.gates`), so their orbits do not start it either."""
    config = load_config(overrides=BRAKED)
    records = tuple(record.measured[record.drop_index :] for _, record in (drops[9], drops[6]))
    stream = io.StringIO()
    started = started_from_orbits(config, TrainingData((), records), stream)
    assert started.effects.values() == config.effects.values() and stream.getvalue() == ""
    unconditional = load_config(overrides={"effects.active": ["brake_decay"]})
    assert started_from_orbits(unconditional, TrainingData((), records), stream).effects.values() != (
        unconditional.effects.values()
    )


def test_an_unbraked_rotor_gives_no_decay_to_start_from(drops):
    config = load_config(overrides=BRAKED)
    path, record = drops[1]
    orbit = whirl_speeds(record.measured[record.drop_index :], config.sample_period)
    effects = config.effects
    started, moved = speed_effects_from_orbits(effects, config.rig, [record.measured[record.drop_index :]], [(1.0,)],
                                               config.sample_period)
    # its whirl spins up to the rotor's speed only at the end: too short a stretch to fit a decay to
    assert orbit.times.min() > 0.12 and moved == {} and started.values() == effects.values()


def test_candidates_start_where_given_and_at_their_defaults_otherwise():
    model_effects = fx.Effects((fx.LIBRARY["axial_load"],), ({"force": 1900.0},))
    combined = with_candidates(model_effects, [fx.LIBRARY["brake_decay"], fx.LIBRARY["radial_load"]],
                               {"brake_decay": {"rate": 0.74}})
    assert combined.values() == {
        "axial_load": {"force": 1900.0},
        "brake_decay": {"rate": 0.74},
        "radial_load": {"force_x": 100.0, "force_y": 100.0},
    }


def test_a_steady_whirl_shows_no_speed_change_to_start_from():
    """A rotor whirling on the bore at a constant speed (a synthetic orbit with the sensor's noise): the
    orbit speeds are read, but a decay fitted to their scatter explains too little of it to count."""
    config = load_config(overrides=BRAKED)
    h, speed = config.sample_period, config.rig.speed
    t = np.arange(1500) * h
    rng = np.random.default_rng(3)
    orbit = 2.6e-4 * np.stack([np.cos(1.01 * speed * t), np.sin(1.01 * speed * t), -np.ones_like(t)], axis=1)
    record = orbit + 2e-6 * rng.standard_normal(orbit.shape)
    read = whirl_speeds(record, h)
    assert len(read.times) >= 20 and np.allclose(read.speeds, 1.01 * speed, rtol=0.01)
    _, moved = speed_effects_from_orbits(config.effects, config.rig, [record], [(1.0,)], h)
    assert moved == {}


def test_diagnose_fits_a_speed_candidate_the_orbits_show_whatever_its_frols_rank():
    """FROLS's best `count` are fitted, and a speed candidate the orbits show is added when it ranks lower;
    one already among the best is not fitted twice, and one the orbits do not show is left to its rank."""
    order = ["radial_load", "sensor_gain_z", "brake_decay", "axial_load"]
    assert candidates_to_fit(order, 2, ["brake_decay"]) == ["radial_load", "sensor_gain_z", "brake_decay"]
    assert candidates_to_fit(order, 3, ["brake_decay"]) == ["radial_load", "sensor_gain_z", "brake_decay"]
    assert candidates_to_fit(order, 2, []) == ["radial_load", "sensor_gain_z"]
