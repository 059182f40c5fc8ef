"""The rotor's speed read from its orbit: a braked rotor's decay off the displacements, before any fit."""
import io

import numpy as np
import pytest
from conftest import write_simulated_bag

from touchdown_ros.core import effects as fx
from touchdown_ros.core.orbit import orbit_centre, sensor_offsets_from_orbits, speed_effects_from_orbits, whirl_speeds
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


def _whirl(centre: tuple[float, float], span: float, seed: int, samples: int = 1500) -> np.ndarray:
    """A record (samples, 3) m of a rotor going `span` rad round a 260 um bore about `centre` (m) as the
    sensors read it, with 5 um of sensor noise and 10 um of bouncing, after 300 levitated samples."""
    rng = np.random.default_rng(seed)
    angle = np.linspace(0.0, span, samples)
    radius = 2.6e-4 + 1e-5 * np.abs(np.sin(37.0 * angle))
    on_bore = np.stack([centre[0] + radius * np.cos(angle), centre[1] + radius * np.sin(angle),
                        -np.full(samples, 2e-4)], axis=1)
    record = np.concatenate([np.zeros((300, 3)), on_bore])
    return record + 5e-6 * rng.standard_normal(record.shape)


def test_a_sensor_offset_starts_at_the_centre_the_orbit_goes_round_and_only_where_it_shows():
    """Synthetic whirls: about (30, -12) um both offsets start within 1.5 um; about the sensors' zero, or a
    rotor resting on one side of the bore (a quarter turn), none; one not asked for is not started."""
    names = ["sensor_offset_x", "sensor_offset_y", "sensor_offset_z"]
    off = [_whirl((3e-5, -1.2e-5), 40.0, seed) for seed in (1, 2)]
    started = sensor_offsets_from_orbits(names, off)
    assert set(started) == {"sensor_offset_x", "sensor_offset_y"}, started
    np.testing.assert_allclose([started[n]["offset"] for n in names[:2]], [3e-5, -1.2e-5], atol=1.5e-6)
    assert sensor_offsets_from_orbits(["sensor_offset_y"], off).keys() == {"sensor_offset_y"}
    assert sensor_offsets_from_orbits(names, [_whirl((0.0, 0.0), 40.0, seed) for seed in (1, 2)]) == {}
    assert orbit_centre([_whirl((3e-5, -1.2e-5), np.pi / 2, seed) for seed in (1, 2)]) is None
    assert sensor_offsets_from_orbits(names, [_whirl((3e-5, -1.2e-5), np.pi / 2, 1)]) == {}


def test_a_sensor_offset_the_drops_show_starts_at_their_orbits_centre(tmp_path):
    """Table 1's experiments 1 and 2 simulated with a 30 um x sensor offset: train's stage 1 starts
    sensor_offset_x within 5 um of it (from the YAML's 0) and says so; y shows none; the same drops without
    the offset start neither."""
    config = load_config(overrides={"effects.active": ["sensor_offset_x", "sensor_offset_y"]})
    offset = load_config(overrides={"simulator.sensor_offset_x": 3e-5})
    paths = [tmp_path / f"exp_{n:02d}" for n in (1, 2)]
    for n, path in zip((1, 2), paths):
        write_simulated_bag(path, n, seed=n, config=offset)
    stream = io.StringIO()
    started = started_from_orbits(config, load_training_data(config, paths), stream).effects.values()
    assert abs(started["sensor_offset_x"]["offset"] - 3e-5) < 5e-6, started
    assert started["sensor_offset_y"]["offset"] == 0.0
    assert "sensor_offset_x starts at the orbit's centre" in stream.getvalue() and "(was 0)" in stream.getvalue()
    plain = [write_simulated_bag(tmp_path / f"plain_{n:02d}", n, seed=n) for n in (1, 2)]
    records = [record.measured[record.drop_index :] for record in plain]
    assert sensor_offsets_from_orbits(["sensor_offset_x", "sensor_offset_y"], records) == {}
