"""Drop-test simulator: the paper's features over Table 1, physics sanity, sensor, seeding, parameters."""
from dataclasses import fields, replace
from datetime import datetime, timezone

import numpy as np
import pytest

from touchdown_ros.io.config import ConfigError, load_config
from touchdown_ros.sim.campaign import CAMPAIGN, simulate_campaign
from touchdown_ros.sim.features import axial_impacts, drop_features
from touchdown_ros.sim.record import DropCondition, DropRecord
from touchdown_ros.sim.simulator import simulate_drop

CONFIG = load_config()
RIG = CONFIG.rig
SETTLED = 0.03  # s at the end of a record taken as settled


@pytest.fixture(scope="module")
def campaign() -> list[DropRecord]:
    return list(simulate_campaign(CONFIG, seed=0))


@pytest.fixture(scope="module")
def features(campaign):
    return [drop_features(r) for r in campaign]


def after_drop(record: DropRecord, seconds: float) -> int:
    return record.drop_index + int(round(seconds / record.sample_period))


# --- Table 1 and record layout -------------------------------------------------------------


def test_campaign_is_table_1():
    assert [c.number for c in CAMPAIGN] == list(range(1, 22))
    assert all(c.speed_rpm == 5000.0 for c in CAMPAIGN)
    assert [c.number for c in CAMPAIGN if not c.brake] == [1, 2, 3, 4, 5, 21]
    assert [c.number for c in CAMPAIGN if c.axial_load] == [8, 9, 10, 11, 12, 15, 16, 17, 18, 19, 20]
    assert [c.number for c in CAMPAIGN if c.ball == "steel"] == [21]
    assert {c.ball for c in CAMPAIGN} == {"ceramic", "steel"}


def test_record_layout(campaign):
    period = CONFIG.sample_period
    n = int(round((0.02 + 0.15) / period))
    start = datetime(2026, 1, 1, tzinfo=timezone.utc).timestamp()
    for number, record in enumerate(campaign, start=1):
        assert record.condition.number == number
        assert record.stamps_ns.dtype == np.int64 and record.stamps_ns.shape == (n,)
        assert np.all(np.diff(record.stamps_ns) == int(round(period * 1e9)))
        assert record.stamps_ns[0] == int(start * 1e9) + (number - 1) * 600 * 10**9
        assert record.t[0] == 0.0 and np.allclose(np.diff(record.t), period)
        assert record.drop_time == pytest.approx(0.02)
        for name in ("measured", "position", "velocity", "acceleration", "contact_force"):
            assert getattr(record, name).shape == (n, 3), name
        for name in ("F_n", "F_t", "F_z", "omega", "omega_ring"):
            assert getattr(record, name).shape == (n,), name
        assert record.radial_contact.dtype == bool and record.axial_contact.dtype == bool
        assert all(np.isfinite(getattr(record, f.name)).all() for f in fields(record) if f.name in ("measured", "F_z"))


def test_levitated_before_the_drop(campaign):
    for record in campaign:
        lev = slice(0, record.drop_index)
        radius = np.hypot(record.position[lev, 0], record.position[lev, 1])
        assert 0.5e-6 < radius.max() < 6e-6  # a few um of residual unbalance orbit
        assert np.abs(record.position[lev, 2]).max() < 1e-7  # gravity (and load) compensated
        assert not record.radial_contact[lev].any() and not record.axial_contact[lev].any()
        assert np.all(record.contact_force[lev] == 0.0)


# --- The paper's features (Section 5.3, Figures 6-8) for every experiment ---------------------


def test_paper_features_every_experiment(campaign, features):
    problems = []
    for record, f in zip(campaign, features):
        n = record.condition.number
        if f.first_radial_contact is None:
            problems.append(f"#{n}: no radial contact")
            continue
        if f.bounces_before_radial < 3:
            problems.append(f"#{n}: only {f.bounces_before_radial} axial bounces before the first radial contact")
        if f.largest_impact not in (0, 1):
            problems.append(f"#{n}: largest axial impact is #{f.largest_impact + 1}")
        if not 1 / 3 <= f.force_ratio <= 1 / 2:
            problems.append(f"#{n}: max F_n / max F_z = {f.force_ratio:.3f}")
        if not 5e3 < f.peak_F_z < 1e5:
            problems.append(f"#{n}: peak F_z {f.peak_F_z:.0f} N")
        if f.impacts[0].peak <= f.impacts[-1].peak:
            problems.append(f"#{n}: axial impacts do not decrease")
        first = int(np.searchsorted(record.t, f.first_radial_contact))
        if np.abs(record.F_n[record.drop_index : first]).max() > 0.1 * f.peak_F_z:
            problems.append(f"#{n}: radial force not negligible before the first radial contact")
    assert not problems, "\n".join(problems)


def test_rotor_clings_and_whirls_forward_sinusoidally(campaign, features):
    problems = []
    for record, f in zip(campaign, features):
        n = record.condition.number
        if f.whirl_direction < 0.8:
            problems.append(f"#{n}: whirl direction {f.whirl_direction:+.2f} (forward whirl expected)")
        if f.radial_contact_share < 0.7:
            problems.append(f"#{n}: in radial contact only {f.radial_contact_share:.0%} after the first contact")
        tail = slice(len(record.t) - int(0.04 / record.sample_period), None)
        radius = np.hypot(record.position[tail, 0], record.position[tail, 1])
        if not (radius > 0.9 * RIG.radial_clearance).all():
            problems.append(f"#{n}: rotor leaves the bearing at the end")
        for axis in (0, 1):
            signal = record.position[tail, axis] - record.position[tail, axis].mean()
            power = np.abs(np.fft.rfft(signal * np.hanning(signal.size))) ** 2
            k = int(np.argmax(power))
            if power[max(k - 2, 0) : k + 3].sum() < 0.9 * power.sum():
                problems.append(f"#{n}: radial displacement {'xy'[axis]} is not sinusoidal")
    assert not problems, "\n".join(problems)


# --- Physics sanity ---------------------------------------------------------------------------


def test_free_fall_after_amb_decay():
    """With a fast AMB decay, z follows z1 + v1 t - g t^2 / 2 exactly until the first axial contact."""
    overrides = {"rig.eccentricity": 0.0, "simulator.variation": 0.0, "simulator.amb_decay_time": 1e-4}
    record = simulate_drop(load_config(overrides=overrides), CAMPAIGN[0], seed=5)
    k0 = after_drop(record, 0.0015)  # AMB force below 1e-6 of its level
    k1 = int(np.searchsorted(record.t, axial_impacts(record)[0].start)) - 1
    assert k1 - k0 > 40
    t = record.t[k0:k1] - record.t[k0]
    z1, v1 = record.position[k0, 2], record.velocity[k0, 2]
    free_fall = z1 + v1 * t - 0.5 * RIG.gravity * t**2
    assert np.abs(record.position[k0:k1, 2] - free_fall).max() < 1e-4 * RIG.axial_clearance
    np.testing.assert_allclose(record.acceleration[k0:k1, 2], -RIG.gravity, rtol=1e-5)
    assert 2.0 * np.polyfit(t, record.position[k0:k1, 2], 2)[0] == pytest.approx(-RIG.gravity, rel=1e-5)


def test_campaign_falls_freely_before_the_first_impact(campaign):
    for record in campaign[:9]:  # unloaded and loaded experiments
        g_eff = RIG.gravity + (2000.0 / RIG.mass if record.condition.axial_load else 0.0)
        k1 = int(np.searchsorted(record.t, axial_impacts(record)[0].start)) - 1
        window = slice(k1 - 10, k1)  # the last millisecond of the fall: the AMB force has decayed
        assert record.acceleration[window, 2] == pytest.approx(-g_eff, rel=0.02)
        assert record.velocity[k1, 2] < -0.05  # hits the bearing at several cm/s


def test_truth_is_kinematically_consistent(campaign):
    """Acceleration and velocity truth are the derivatives of the position truth.

    At 10 kHz the finite differences themselves err near the contact onsets (the Hertz
    force has an unbounded jerk there), hence percent-level tolerances on RMS errors.
    """

    def relative_rms(error: np.ndarray, reference: np.ndarray) -> float:
        return float(np.sqrt(np.mean(error**2) / np.mean(reference**2)))

    for record in campaign[::5]:
        h, x, v, a = record.sample_period, record.position, record.velocity, record.acceleration
        a_num = (x[2:] - 2.0 * x[1:-1] + x[:-2]) / h**2
        assert relative_rms(a_num - a[1:-1], a[1:-1]) < 2e-2
        simpson = lambda f: h / 3.0 * (f[:-2] + 4.0 * f[1:-1] + f[2:])  # noqa: E731
        assert relative_rms(v[2:] - v[:-2] - simpson(a), v[2:] - v[:-2]) < 1e-2
        assert relative_rms(x[2:] - x[:-2] - simpson(v), x[2:] - x[:-2]) < 1e-3


def test_contact_force_matches_its_components(campaign):
    for record in campaign[::4]:
        a = np.arctan2(record.position[:, 1], record.position[:, 0])
        fx = -record.F_n * np.cos(a) + record.F_t * np.sin(a)
        fy = -record.F_n * np.sin(a) - record.F_t * np.cos(a)
        np.testing.assert_allclose(record.contact_force[:, 0], fx, atol=1e-6 * np.abs(record.F_z).max())
        np.testing.assert_allclose(record.contact_force[:, 1], fy, atol=1e-6 * np.abs(record.F_z).max())
        np.testing.assert_array_equal(record.contact_force[:, 2], record.F_z)
        # Forces only where there is contact; the bearing pushes the rotor up and inwards.
        none = ~record.radial_contact & ~record.axial_contact
        assert np.all(record.contact_force[none] == 0.0)
        assert record.F_z[record.axial_contact & ~record.radial_contact].min() >= 0.0


def test_axial_energy_conserved_without_dissipation():
    """Centred rotor (e = 0), no damping, friction or mount yield: the axial bounce is conservative."""
    config = load_config(
        overrides={
            "rig.eccentricity": 0.0,
            "simulator.variation": 0.0,
            "simulator.axial_mount_preload": 1e9,
            "simulator.ceramic.axial_damping": 0.0,
            "simulator.ceramic.friction_static": 0.0,
            "simulator.ceramic.friction_kinetic": 0.0,
        }
    )
    record = simulate_drop(config, CAMPAIGN[0], seed=3)
    K, m, g, z0 = 3.0e11, RIG.mass, RIG.gravity, RIG.axial_clearance
    d = np.maximum(-(record.position[:, 2] + z0), 0.0)
    energy = 0.5 * m * record.velocity[:, 2] ** 2 + m * g * record.position[:, 2] + 0.4 * K * d**2.5
    after = energy[after_drop(record, 0.015) :]  # AMB force < 1e-6 of its level
    assert np.all(np.hypot(record.position[:, 0], record.position[:, 1]) < 1e-9)
    assert len(axial_impacts(record)) >= 5
    assert np.ptp(after) < 1e-6 * (m * g * z0)
    # With the contact damping back, every bounce loses energy.
    damped = simulate_drop(load_config(overrides={"rig.eccentricity": 0.0, "simulator.variation": 0.0}), CAMPAIGN[0], 3)
    apex = [i.start for i in axial_impacts(damped)]
    z_top = [damped.position[(damped.t > a) & (damped.t < b), 2].max() for a, b in zip(apex[:-1], apex[1:])]
    assert np.all(np.diff(z_top[:5]) < 0.0)


def test_integration_converged():
    coarse = simulate_drop(CONFIG, CAMPAIGN[3], seed=4)
    fine = simulate_drop(load_config(overrides={"simulator.substeps": 200}), CAMPAIGN[3], seed=4)
    assert np.abs(coarse.position - fine.position).max() < 1e-9
    assert np.abs(coarse.contact_force - fine.contact_force).max() < 1.0


# --- Conditions: brake, axial load, balls -----------------------------------------------------


def test_brake_lowers_the_speed(campaign):
    for record in campaign:
        omega0 = record.condition.speed_rpm * 2 * np.pi / 60
        assert record.omega[record.drop_index] == pytest.approx(omega0)
        if record.condition.brake:
            assert record.omega[-1] < 0.92 * omega0
            assert record.omega[after_drop(record, 0.05)] < record.omega[record.drop_index]
        else:
            assert record.omega[-1] > 0.99 * omega0


def test_axial_load_adds_2000_N_once_settled(campaign):
    def settled(record: DropRecord) -> float:
        return float(record.F_z[-int(SETTLED / record.sample_period) :].mean())

    loaded = [settled(r) for r in campaign if r.condition.axial_load]
    unloaded = [settled(r) for r in campaign if not r.condition.axial_load]
    assert np.mean(unloaded) == pytest.approx(RIG.mass * RIG.gravity, rel=0.03)
    assert np.mean(loaded) - np.mean(unloaded) == pytest.approx(2000.0, rel=0.1)
    # The same drop with and without the loader.
    condition = CAMPAIGN[7]
    without = simulate_drop(CONFIG, replace(condition, axial_load=False), seed=8)
    assert settled(campaign[7]) - settled(without) == pytest.approx(2000.0, rel=0.1)


def test_steel_differs_from_ceramic(campaign):
    steel = campaign[20]
    ceramic = simulate_drop(CONFIG, replace(steel.condition, ball="ceramic"), seed=21)
    assert not np.array_equal(steel.position, ceramic.position)
    # Softer steel balls: lower first impact; heavier balls: the ring spins up later.
    assert drop_features(steel).impacts[0].peak < drop_features(ceramic).impacts[0].peak

    def spin_up(record: DropRecord) -> float:
        k = record.drop_index + int(np.argmax(record.omega_ring[record.drop_index :] > 0.9 * record.omega[0]))
        return float(record.t[k])

    assert spin_up(steel) > spin_up(ceramic)


# --- Sensor and seeding -----------------------------------------------------------------------


def test_sensor_noise_and_quantisation(campaign):
    for record in campaign[::7]:
        error = record.measured - record.position
        assert np.abs(error.mean(axis=0)).max() < 0.2 * CONFIG.noise_rms
        np.testing.assert_allclose(error.std(axis=0), CONFIG.noise_rms, rtol=0.06)
        steps = record.measured / CONFIG.quantisation
        assert np.abs(steps - np.round(steps)).max() < 1e-6


def test_seeded_determinism(campaign):
    again = simulate_drop(CONFIG, CAMPAIGN[0], seed=1)  # the campaign runs experiment N with seed + N
    for f in fields(DropRecord):
        value, reference = getattr(again, f.name), getattr(campaign[0], f.name)
        if isinstance(value, np.ndarray):
            assert np.array_equal(value, reference), f.name
        else:
            assert value == reference, f.name
    other = simulate_drop(CONFIG, CAMPAIGN[0], seed=2)
    noise, other_noise = again.measured - again.position, other.measured - other.position
    assert np.abs(noise - other_noise).mean() > CONFIG.noise_rms
    assert not np.array_equal(again.position, other.position)  # theta_0 and constants differ too


# --- Feature extraction on a hand-made record -------------------------------------------------


def test_features_of_a_synthetic_record():
    n, period = 200, 1e-4
    t = np.arange(n) * period
    zeros, flags = np.zeros(n), np.zeros(n, dtype=bool)
    axial, F_z = flags.copy(), zeros.copy()
    for start, stop, peak in [(30, 40, 9e3), (70, 78, 12e3), (110, 115, 5e3)]:
        axial[start:stop] = True
        F_z[start:stop] = peak * np.sin(np.linspace(0.1, np.pi - 0.1, stop - start))
    radial, F_n = flags.copy(), zeros.copy()
    radial[100:] = True
    F_n[100:] = 4e3
    angle = 200.0 * t  # anticlockwise orbit after the contact
    position = np.zeros((n, 3))
    position[:, 0], position[:, 1] = 2.6e-4 * np.cos(angle), 2.6e-4 * np.sin(angle)
    velocity = np.zeros((n, 3))
    velocity[:, 0], velocity[:, 1] = -0.052 * np.sin(angle), 0.052 * np.cos(angle)
    record = DropRecord(
        condition=DropCondition(1, 5000.0, False, False, "ceramic"),
        stamps_ns=(t * 1e9).astype(np.int64),
        t=t,
        drop_time=20 * period,
        measured=position,
        position=position,
        velocity=velocity,
        acceleration=np.zeros((n, 3)),
        contact_force=np.stack([zeros, zeros, F_z], axis=1),
        F_n=F_n,
        F_t=zeros,
        F_z=F_z,
        radial_contact=radial,
        axial_contact=axial,
        omega=np.full(n, 523.6),
        omega_ring=zeros,
    )
    f = drop_features(record)
    assert [round(i.peak) for i in f.impacts] == [
        round(F_z[30:40].max()),
        round(F_z[70:78].max()),
        round(F_z[110:115].max()),
    ]
    assert [i.start for i in f.impacts] == pytest.approx([t[30], t[70], t[110]])
    assert f.first_radial_contact == pytest.approx(t[100])
    assert f.bounces_before_radial == 2
    assert f.largest_impact == 1
    assert f.force_ratio == pytest.approx(4e3 / F_z.max())
    assert f.whirl_direction == 1.0 and f.radial_contact_share == 1.0


# --- Hidden effects (the workbench's truth) --------------------------------------------------


HIDDEN = {
    "radial_load_x": 300.0,
    "radial_load_y": -200.0,
    "magnetic_stiffness_radial": 1.0e6,
    "magnetic_stiffness_axial": 2.0e6,
    "rotor_drag_radial": 3000.0,
    "rotor_drag_axial": 4000.0,
    "cross_coupled_stiffness": 5.0e5,
    "twice_per_rev_force": 300.0,
}


def test_hidden_forces_by_hand():
    """physics.hidden_force written out: side load + k r outward + q (-y, x) - c v + A (cos 2t, sin 2t)."""
    from touchdown_ros.sim.physics import hidden_force

    truth = _truth()._replace(**HIDDEN)
    x, y, z, vx, vy, vz, theta = 1e-4, -2e-4, -3e-4, 0.05, -0.02, 0.1, 0.7
    s = np.array([x, y, z, vx, vy, vz, theta, 500.0, 0.0])
    expected = [
        300.0 + 1e6 * x - 5e5 * y - 3000.0 * vx + 300.0 * np.cos(2 * theta),
        -200.0 + 1e6 * y + 5e5 * x - 3000.0 * vy + 300.0 * np.sin(2 * theta),
        2e6 * z - 4000.0 * vz,
    ]
    np.testing.assert_allclose(np.asarray(hidden_force(truth, s)), expected, rtol=1e-12)
    assert np.all(np.asarray(hidden_force(_truth(), s)) == 0.0)  # the reference rig has none


def test_contact_angle_pushes_up_by_tan_beta_times_the_bore_force():
    from touchdown_ros.sim.physics import contact

    truth = _truth()
    s = np.array([truth.radial_clearance + 2e-6, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # bore only
    plain, tilted = contact(truth, s), contact(truth._replace(contact_angle_tan=0.2), s)
    assert float(plain.F_n) > 100.0 and float(plain.F_z) == 0.0
    assert float(tilted.F_z) == pytest.approx(0.2 * float(plain.F_n), rel=1e-12)


def test_levitated_orbit_is_periodic_with_the_hidden_effects():
    """levitated_state solves the AMB loop with the effects' stiffness, drag and 2x force: the state a
    small time later is the orbit rotated, and its acceleration is that of the two harmonics."""
    from touchdown_ros.sim.physics import derivative, levitated_state

    truth = _truth()._replace(drop_time=1.0, **HIDDEN)
    speed = 500.0
    s = levitated_state(truth, 0.3, speed)
    ds = np.asarray(derivative(truth, 0.0, s))
    # x'' of the harmonic orbit: sum over n of -(n omega)^2 times each harmonic; from the 1x and 2x parts
    one = levitated_state(truth._replace(twice_per_rev_force=0.0), 0.3, speed)
    two = s - one
    expected = -(speed**2) * one[:2] - (2 * speed) ** 2 * two[:2]
    np.testing.assert_allclose(ds[3:5], expected, rtol=1e-6, atol=1e-9)
    assert abs(two[0]) > 1e-9  # the 2x force moves the orbit
    assert ds[5] == pytest.approx(0.0, abs=1e-9)  # z stays at 0 (loads compensated)


def _truth():
    from touchdown_ros.sim.params import simulator_parameters, truth_constants

    rng = np.random.default_rng(0)
    params = simulator_parameters(load_config(overrides={"simulator.variation": 0.0}))
    return truth_constants(CONFIG, params, "ceramic", False, False, 0.0, rng)


# --- Parameter validation ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("simulator.substeps", 0, "simulator.substeps"),
        ("simulator.substeps", 2.5, "simulator.substeps"),
        ("simulator.ceramic.radial_stiffness", -1.0, "simulator.ceramic.radial_stiffness"),
        ("simulator.steel.axial_damping", "1.0e8", "simulator.steel.axial_damping"),
        ("simulator.amb_decay_time", "1e-5",
         "simulator.amb_decay_time' must be a finite number, got '1e-5' \\(YAML reads a number as text unless it has "
         "a decimal point and a signed exponent"),
        ("simulator.amb_unbalance_compensation", 1.5, "simulator.amb_unbalance_compensation"),
        ("simulator.steel.friction_kinetic", 0.5, "simulator.steel.friction_kinetic"),
        ("simulator.variation", 0.5, "simulator.variation"),
        ("simulator.start_time", "yesterday", "simulator.start_time"),
        ("simulator.drop_duration", 1e-4, "simulator.drop_duration"),
        ("simulator.brake", True, "simulator.brake"),
        ("simulator.ceramic.colour", "white", "simulator.ceramic.colour"),
        ("simulator.regularisation_velocity", 1e-4, "simulator.substeps"),
    ],
)
def test_bad_parameters_name_the_key(key, value, message):
    config = load_config(overrides={key: value})
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        simulate_drop(config, CAMPAIGN[0], seed=0)


def test_unknown_ball_is_refused():
    with pytest.raises(ValueError, match="glass"):
        simulate_drop(CONFIG, DropCondition(1, 5000.0, False, False, "glass"), seed=0)
