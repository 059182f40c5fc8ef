"""The inner ring's speed as a state (contact.friction: spinning_ring): its friction, its stiff
implicit update, the step's Jacobian, the eighth state through configuration and coefficient
files, and the model against the simulator's truth along a drop it did not see."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from conftest import band_added_and_by_hand, central_differences

from touchdown_ros.core import dynamics
from touchdown_ros.core.dynamics import contact_forces, phi, ring_speed_after, rk4_step, step_with_jacobian
from touchdown_ros.core.effects import Effects, resolve
from touchdown_ros.core.types import OMEGA_RING, STATE_SIZE, Coefficients, ContactLaw, Nominal, Rig
from touchdown_ros.io.coefficients import CoefficientFileError, content_sha256, load_coefficients, save_coefficients
from touchdown_ros.io.coefficients import TrainingRecord
from touchdown_ros.io.config import RING_INITIAL_COVARIANCE, RING_PROCESS_NOISE, load_config

CONFIG = load_config()
RIG = Rig(mass=200.0, eccentricity=1e-5, speed=500.0, radial_clearance=2e-4, axial_clearance=3e-4, gravity=9.81)
NOMINAL = Nominal(k_R=1e8, c_R=2e4, mu=0.12, k_Z=3e8, c_Z=5e4, k_ZR=0.07)
#: States in contact with the bore, the face or both (x y z theta xdot ydot zdot), as test_core's.
CASES = {
    "radial": [1.5e-4, 1.6e-4, -1e-4, 1.1, 0.03, -0.01, 0.02],
    "axial": [0.5e-4, 0.2e-4, -3.2e-4, 2.0, 0.01, 0.02, -0.06],
    "both": [-2.0e-4, 0.9e-4, -3.1e-4, 4.0, -0.04, 0.03, 0.01],
}


def model_with(friction: str, slip_velocity: float = 0.02, effects: Effects = Effects()):
    kernel = CONFIG.kernel
    law = ContactLaw().with_friction(friction, slip_velocity)
    return type(CONFIG.model())(RIG, NOMINAL, kernel, Coefficients.zeros(kernel), effects, law=law)


@pytest.mark.parametrize("case", CASES)
def test_a_ring_turning_with_the_rotor_is_the_co_rotating_ring(case):
    """At omega_ring = omega the bore slips at whirl + R omega - (R + r) omega = whirl - omega r and the
    face does not spin: the forces are the co-rotating ring's. A ring at rest is not."""
    xi = jnp.asarray(CASES[case])
    co_rotating = contact_forces(model_with("co_rotating_ring"), xi)
    spinning = model_with("spinning_ring")
    turning = contact_forces(spinning, jnp.append(xi, RIG.speed))
    for name in ("F_n", "F_t", "F_z"):
        assert float(getattr(turning, name)) == pytest.approx(float(getattr(co_rotating, name)), rel=1e-9, abs=1e-9)
    at_rest = contact_forces(spinning, jnp.append(xi, 0.0))
    assert abs(float(at_rest.F_t) - float(co_rotating.F_t)) > 0.05 * abs(float(co_rotating.F_n))


@pytest.mark.parametrize("case", CASES)
def test_the_friction_torque_turns_the_ring_towards_the_rotor(case):
    """Slower than the rotor, the ring is sped up; faster, slowed; friction takes energy out of the
    rotor-ring slip (torque times (omega - omega_ring) >= 0 for the ring)."""
    model, xi = model_with("spinning_ring"), jnp.asarray(CASES[case])
    torque = {w: float(contact_forces(model, jnp.append(xi, w)).ring_torque) for w in (0.0, 250.0, 2 * RIG.speed)}
    assert torque[0.0] > 0.0 and torque[250.0] > 0.0 and torque[2 * RIG.speed] < 0.0
    assert torque[0.0] >= torque[250.0]  # the slip is larger at rest


def test_the_stuck_ring_is_stable_where_an_explicit_step_is_not():
    """A ring on the face of a rotor held in contact (J = 3e-3 kg m^2, h = 0.1 ms) spins up at the
    Coulomb torque's rate and then sticks to the rotor, a stiff equation: within 0.02 rad/s of the
    rotor's speed an explicit Euler step overshoots it many times over; the implicit update reaches
    it without overshooting."""
    model = model_with("spinning_ring", 0.01)
    xi = jnp.asarray(CASES["axial"] + [0.0])
    h, J = 1e-4, model.rig.ring_inertia
    update = jax.jit(lambda w: ring_speed_after(model, xi.at[OMEGA_RING].set(w), h))
    speeds, w = [], 0.0
    for _ in range(400):
        w = float(update(w))
        speeds.append(w)
    speeds = np.array(speeds)
    assert np.all(np.diff(speeds) >= -1e-9) and speeds.max() <= RIG.speed * (1 + 1e-9)
    assert speeds[-1] == pytest.approx(RIG.speed, rel=1e-4)
    # backward Euler: each update solves w = w0 + h T(w) / J
    w0, w1 = speeds[100], speeds[101]
    T1 = float(contact_forces(model, xi.at[OMEGA_RING].set(w1)).ring_torque)
    assert w1 == pytest.approx(w0 + h * T1 / J, rel=1e-12)
    near = RIG.speed - 0.02
    explicit = near + h * float(contact_forces(model, xi.at[OMEGA_RING].set(near)).ring_torque) / J
    assert explicit - RIG.speed > 10 * (RIG.speed - near)
    implicit = float(update(near))
    assert near < implicit <= RIG.speed


@pytest.mark.parametrize("stiffness", [1.0, 10.0], ids=["the face's k_Z", "ten times"])
@pytest.mark.parametrize("case", CASES)
def test_the_rings_implicit_update_solves_its_equation_wherever_the_ring_meets_the_rotor(case, stiffness):
    """From every speed a step short of the rotor's, where the ring reaches the rotor's speed within the step (the
    torque flat on one side of the stick, steep on the other), the update solves backward Euler's w = w0 + h T(w) / J
    to rounding, and it moves continuously with w0 (no jump between neighbouring starts)."""
    model = model_with("spinning_ring", 0.01)
    model = model._replace(nominal=NOMINAL._replace(k_Z=NOMINAL.k_Z * stiffness))
    xi = jnp.asarray(CASES[case] + [0.0])
    h, J = 1e-4, model.rig.ring_inertia
    torque = jax.jit(jax.vmap(lambda w: contact_forces(model, xi.at[OMEGA_RING].set(w)).ring_torque))
    span = h * float(torque(jnp.zeros(1))[0]) / J  # the speed one step of the Coulomb torque gains
    starts = RIG.speed - jnp.linspace(1.5 * span, 0.0, 3001)
    update = jax.jit(jax.vmap(lambda w: ring_speed_after(model, xi.at[OMEGA_RING].set(w), h)))
    after = update(starts)
    residual = np.asarray(after - starts - h * torque(after) / J)
    assert np.max(np.abs(residual)) < 1e-9 * RIG.speed, (span, float(np.max(np.abs(residual))))
    assert np.all(np.diff(np.asarray(after)) >= -1e-9)  # monotone in the start, as the equation's root is


@pytest.mark.parametrize("drop", [0.0, 0.4], ids=["Coulomb", "Stribeck"])
@pytest.mark.parametrize("braked", [False, True], ids=["constant speed", "braked"])
@pytest.mark.parametrize("case", CASES)
def test_step_jacobian_with_a_spinning_ring_matches_central_differences(case, braked, drop):
    """Also with the ring carried along with a braked rotor's falling speed (brake_decay), and with a
    Stribeck drop of the friction over a slip comparable to the state's."""
    effects = Effects((resolve("brake_decay"),), ({"rate": 0.8},)) if braked else Effects()
    model, h = model_with("spinning_ring", 0.05, effects), 1e-4
    model = model._replace(law=model.law.with_stribeck(drop, 0.05))
    xi = np.array(CASES[case] + [RIG.speed - 0.3])  # nearly caught up: the slip, and its derivative, is small
    mean, Phi = step_with_jacobian(model, jnp.asarray(xi), h)
    np.testing.assert_allclose(np.asarray(mean), np.asarray(rk4_step(model, jnp.asarray(xi), h)), rtol=1e-12)
    scales = np.array([1e-9, 1e-9, 1e-9, 1e-6, 1e-6, 1e-6, 1e-6, 1e-5])
    Phi_fd = central_differences(lambda s: rk4_step(model, jnp.asarray(s), h), xi, scales)
    np.testing.assert_allclose(np.asarray(Phi), Phi_fd, rtol=1e-5, atol=1e-7)
    assert np.any(np.abs(np.asarray(Phi)[4:7, OMEGA_RING]) > 1e-6)  # the ring's speed moves the rotor


def test_the_force_band_carries_the_stribeck_drops_uncertainty_where_the_bore_hardly_slips():
    """A fitted drop's covariance of (ln drop, ln v_s) adds J C J^T to the force's covariance, J the force's
    derivative by those logarithms (central differences here): where the ring has caught up with the rotor
    (the drop acts), not where it slides fast (the factor is 1 there), and nothing without a drop."""
    drop, v_s, log_covariance = 0.4, 0.05, ((0.09, -0.03), (-0.03, 0.04))  # sd 0.3 and 0.2, correlation -0.5
    xi = np.array(CASES["radial"])
    r = np.hypot(xi[0], xi[1])
    whirl = (xi[0] * xi[5] - xi[1] * xi[4]) / r
    caught_up = (whirl + RIG.journal_radius * RIG.speed) / (RIG.journal_radius + r)
    spinning = model_with("spinning_ring")
    exact = spinning._replace(law=spinning.law.with_stribeck(drop, v_s))
    uncertain = spinning._replace(law=spinning.law.with_stribeck(drop, v_s, log_covariance))
    assert uncertain.law.stribeck_uncertain and not exact.law.stribeck_uncertain
    assert not spinning.law.with_stribeck(0.0, v_s, log_covariance).stribeck_uncertain  # no drop, nothing uncertain
    P = np.diag(np.array([2e-6, 2e-6, 2e-6, 1e-2, 3e-3, 3e-3, 3e-3, 1.0]) ** 2)
    for ring_speed in (caught_up, 0.0):
        state = np.append(xi, ring_speed)
        added, by_hand = band_added_and_by_hand(
            exact, uncertain, state, P,
            lambda log_scale: exact.law.with_stribeck(drop * np.exp(log_scale[0]), v_s * np.exp(log_scale[1])),
            log_covariance,
        )
        if ring_speed == 0.0:  # sliding at about R omega: the drop has faded, the band is as before
            np.testing.assert_allclose(added, 0.0, atol=1e-12)
        else:
            friction = abs(float(contact_forces(exact, jnp.asarray(state)).F_t))
            assert np.trace(by_hand) > (0.05 * friction) ** 2  # the friction's sd grows by more than 5 %
            np.testing.assert_allclose(added, by_hand, rtol=1e-6, atol=1e-9 * np.trace(by_hand))


@pytest.mark.parametrize("friction", ["spinning_ring", "co_rotating_ring"])
def test_a_stribeck_drop_raises_the_friction_at_a_small_slip_and_fades_at_a_large_one(friction):
    """In bore contact alone the friction force is mu (1 + drop exp(-(s / v_s)^2)) F_n s / sqrt(s^2 + v^2)
    at the slip s: (1 + drop) times Coulomb's where the rotor hardly slips on the ring, Coulomb's where it
    slides fast; the normal force does not change."""
    drop, v_s = 0.4, 0.05
    xi = np.array(CASES["radial"])
    r = np.hypot(xi[0], xi[1])
    whirl = (xi[0] * xi[5] - xi[1] * xi[4]) / r
    caught_up = (whirl + RIG.journal_radius * RIG.speed) / (RIG.journal_radius + r)  # the bore does not slip
    for ring_speed in (caught_up, 0.0):
        state = jnp.asarray(np.append(xi, ring_speed)) if friction == "spinning_ring" else jnp.asarray(xi)
        coulomb = model_with(friction)
        stribeck = coulomb._replace(law=coulomb.law.with_stribeck(drop, v_s))
        without, with_drop = contact_forces(coulomb, state), contact_forces(stribeck, state)
        if friction == "spinning_ring":
            R = RIG.journal_radius
            slip = whirl + R * RIG.speed - (R + r) * ring_speed
        else:
            slip = whirl - RIG.speed * r
        factor = 1.0 + drop * np.exp(-(slip**2 + xi[6] ** 2) / v_s**2)
        assert float(with_drop.F_t) == pytest.approx(factor * float(without.F_t), rel=1e-10)
        assert float(with_drop.F_n) == pytest.approx(float(without.F_n), rel=1e-12)
        if friction == "spinning_ring":  # at rest it slides at ~R omega: Coulomb's; caught up, near the static
            assert factor == pytest.approx(1.0, abs=1e-9) if ring_speed == 0.0 else factor > 1.0 + 0.5 * drop
    with pytest.raises(ValueError, match="friction_drop must be >= 0"):
        ContactLaw().with_stribeck(-0.1, v_s)
    with pytest.raises(ValueError, match="stribeck_velocity must be > 0"):
        ContactLaw().with_stribeck(0.1, 0.0)


def test_the_ring_state_comes_from_the_friction_model_in_configuration_and_coefficient_files(tmp_path):
    paper = load_config(overrides={"contact.friction": "paper"})
    ring = load_config(overrides={"contact.friction": "spinning_ring", "filter.ring_process_noise": 4.0})
    assert (len(paper.noise.process), len(paper.noise.initial)) == (STATE_SIZE, STATE_SIZE)
    assert ring.law.state_size == 8
    np.testing.assert_array_equal(ring.noise.process, np.append(paper.noise.process, 4.0))
    np.testing.assert_array_equal(ring.noise.initial, np.append(paper.noise.initial, RING_INITIAL_COVARIANCE))
    assert RING_PROCESS_NOISE != 4.0
    assert ring.model().rig.ring_inertia == Rig._field_defaults["ring_inertia"]
    assert load_config(overrides={"rig.ring_inertia": 5e-3}).rig.ring_inertia == 5e-3
    with pytest.raises(ValueError, match="spinning_ring has a state of 8, the filter noise 7"):
        paper.calibrated(paper.nominal, ring.law, paper.kernel, paper.noise)

    path = tmp_path / "c.yaml"
    save_coefficients(path, ring.model().coeffs, ring, TrainingRecord())
    back = load_coefficients(path, paper).config(paper)
    assert back.law.friction == "spinning_ring"
    np.testing.assert_array_equal(back.noise.process, ring.noise.process)
    document = yaml.safe_load(path.read_text())
    document["filter"]["process_noise"] = document["filter"]["process_noise"][:STATE_SIZE]
    del document["content_sha256"]
    path.write_text(yaml.safe_dump({**document, "content_sha256": content_sha256(document)}))
    mismatch = "process_noise has 7 values; contact.friction spinning_ring has a state of 8"
    with pytest.raises(CoefficientFileError, match=mismatch):
        load_coefficients(path, paper).config(paper)


def test_a_state_without_the_rings_speed_is_refused_by_name():
    """A seven-entry state handed to a spinning ring's model is refused: JAX would read the missing ring speed as
    the state's last entry (zdot) and return numbers."""
    ring = load_config(overrides={"contact.friction": "spinning_ring"}).model()
    paper = load_config(overrides={"contact.friction": "paper"}).model()
    with pytest.raises(ValueError, match="a state of 7 entries for contact.friction spinning_ring, whose state has 8"):
        phi(ring, jnp.zeros(STATE_SIZE))
    with pytest.raises(ValueError, match="a state of 8 entries for contact.friction paper, whose state has 7"):
        contact_forces(paper, jnp.zeros(STATE_SIZE + 1))
    assert phi(ring, jnp.zeros(STATE_SIZE + 1)).shape == (STATE_SIZE + 1,)


@pytest.fixture(scope="module")
def stiff_quiet_drop():
    return simulated_drop_and_truth_config("stiff_quiet")


def simulated_drop_and_truth_config(name: str, brake: bool = False):
    """One drop of the family's rig `name` (its rotor braked from the drop on if `brake`) and the
    estimator's configuration with the truth's constants transcribed (Hertz law, Hunt-Crossley damping,
    the support, mu for both friction coefficients)."""
    from touchdown_ros.sim.family import variant, variant_config
    from touchdown_ros.sim.params import simulator_parameters
    from touchdown_ros.sim.simulator import simulate_drop

    v = dataclasses.replace(variant(name), brake=brake)
    config = variant_config(v)
    params = simulator_parameters(config)
    record = simulate_drop(config, v.condition(1), seed=1, params=params)
    values = {**params.scalars, **params.balls["ceramic"]}
    mu = values["friction_kinetic"]
    nominal = Nominal(
        values["radial_stiffness"], values["radial_stiffness"] * values["radial_damping"], mu,
        values["axial_stiffness"], values["axial_stiffness"] * values["axial_damping"], mu,
    )
    law = ContactLaw.of("hertz", values["contact_exponent"]).with_support(
        values["axial_mount_preload"], values["axial_mount_span"]
    )
    rig = config.rig._replace(
        journal_radius=values["journal_radius"], face_radius=values["face_radius"], ring_inertia=values["ring_inertia"]
    )
    return record, dataclasses.replace(config, nominal=nominal, law=law, rig=rig)


def test_along_the_true_path_the_spinning_ring_carries_the_truths_contact_force(stiff_quiet_drop):
    """The estimator's contact force along the simulator's true path of a stiff_quiet drop, the
    ring's speed integrated by the implicit update from rest: its speed follows the truth's, and the
    force error is a fraction of the paper's friction's (2026-11-26: 3.6x less on this drop)."""
    record, config = stiff_quiet_drop
    onset = int(round(record.drop_time / config.sample_period))
    states = np.column_stack([
        record.position[onset:], np.zeros(len(record.t) - onset), record.velocity[onset:],
    ])
    truth = record.contact_force[onset:]
    spinning = config.model()._replace(law=config.law.with_friction("spinning_ring", 0.01))
    update = jax.jit(lambda s: ring_speed_after(spinning, s, config.sample_period))
    ring, w = [], 0.0
    for s in states:
        ring.append(w)
        w = float(update(jnp.append(jnp.asarray(s), w)))
    ring = np.array(ring)
    moving = record.omega_ring[onset:] > 50.0
    assert moving[-1] and abs(ring[-1] - record.omega_ring[-1]) < 0.05 * record.omega_ring[-1]
    np.testing.assert_allclose(ring[moving], record.omega_ring[onset:][moving], rtol=0.15, atol=10.0)

    def rmse(model, path):
        force = jax.jit(jax.vmap(lambda s: dynamics.contact_force_xyz(contact_forces(model, s))))(jnp.asarray(path))
        return float(np.sqrt(np.mean(np.sum((np.asarray(force) - truth) ** 2, axis=1))))

    paper = rmse(config.model()._replace(law=config.law.with_friction("paper")), states)
    ring_error = rmse(spinning, np.column_stack([states, ring]))
    assert ring_error < 0.5 * paper, (ring_error, paper)


def test_a_braked_rotors_ring_keeps_the_truths_slip_and_rolling_force():
    """A braked rotor (roller_noisy, the simulator's 400 rad/s^2 from the drop on) rolls on the bore, its
    whirl held back by the friction against the unbalance's forward push. Along the simulator's true
    path, with brake_decay at the truth's rate and the ring's speed from the implicit update, the
    model's tangential force in the rolling phase is the truth's: the ring is carried along with the
    rotor's falling speed within each step. Held at its updated speed instead, it lagged the rotor by
    h d omega / dt, 4 mm/s of bore slip, and its friction pushed the rotor forward (2026-12-02:
    -910 N for the truth's +540 N)."""
    from touchdown_ros.sim.params import simulator_parameters

    record, config = simulated_drop_and_truth_config("roller_noisy", brake=True)
    h = config.sample_period
    onset = int(round(record.drop_time / h))
    clock = config.rig.speed * (record.t[onset:] - record.t[onset])  # theta: brake_decay's clock from the drop
    states = np.column_stack([record.position[onset:], clock, record.velocity[onset:]])
    rate = simulator_parameters(config).scalars["brake_deceleration"] / config.rig.speed
    brake = Effects((resolve("brake_decay"),), ({"rate": rate},))
    # rolling slips (1-5 mm/s) lie far below the Stribeck velocity: the truth's friction is its static one there
    mu_s = simulator_parameters(config).balls["ceramic"]["friction_static"]
    model = config.model(effects=brake)._replace(
        law=config.law.with_friction("spinning_ring", 0.01), nominal=config.nominal._replace(mu=mu_s, k_ZR=mu_s)
    )
    # the implicit update, then the ring carried along with the rotor's falling speed, as `rk4_step` does
    update = jax.jit(lambda s: ring_speed_after(model, s, h) + h * dynamics.spin_acceleration(model, s))
    ring, w = [], 0.0
    for s in states:
        ring.append(w)
        w = float(update(jnp.append(jnp.asarray(s), w)))
    path = jnp.asarray(np.column_stack([states, ring]))
    F_t = np.asarray(jax.jit(jax.vmap(lambda s: contact_forces(model, s).F_t))(path))
    rolling = record.t[onset:] - record.t[onset] > 0.1  # on the bore throughout, the ring turning with the rotor
    assert record.radial_contact[onset:][rolling].all()
    truth = record.F_t[onset:][rolling].mean()
    assert truth > 300.0  # the friction holds the whirl back
    assert F_t[rolling].mean() == pytest.approx(truth, rel=0.1), (F_t[rolling].mean(), truth)


def test_the_live_chunk_filter_equals_the_offline_filter_with_a_spinning_ring():
    """The node's chunk filter with the eighth state gives the offline filter's estimates (the rotor's
    seven states and the ring's speed, published apart), on the model's own drop."""
    from test_streaming import CONFIG as STREAM_CONFIG
    from test_streaming import SIGNALS, batches, model_drop_record, offline

    from touchdown_ros.core.streaming import StreamingEstimator, estimate_stream, make_chunk_filter
    from touchdown_ros.io.config import load_config

    overrides = {f"contact.{name}": value for name, value in STREAM_CONFIG.nominal._asdict().items()}
    config = load_config(overrides={**overrides, "contact.friction": "spinning_ring"})
    record = model_drop_record(config)
    whole = offline(*record, config=config)
    reference = whole.filtered
    chunk = make_chunk_filter(config.model(), config.noise, config.sample_period)
    settings = config.stream_settings(chunk_sizes=(8, 32, 128))
    estimator = StreamingEstimator(config.model(), config.noise, settings, chunk)
    out, _ = estimate_stream(estimator, *record, batches("random_batches", len(record[0])))
    np.testing.assert_array_equal(out.stamps_ns, whole.stamps_ns)
    ring = np.asarray(reference.state)[:, OMEGA_RING]
    expected = {
        "state": np.asarray(reference.state)[:, :STATE_SIZE],
        "state_cov": np.asarray(reference.state_cov)[:, :STATE_SIZE, :STATE_SIZE],
        "ring_speed": ring,
        "ring_speed_std": np.sqrt(np.asarray(reference.state_cov)[:, OMEGA_RING, OMEGA_RING]),
        **{name: np.asarray(getattr(reference, name)) for name in SIGNALS[2:]},
    }
    for name, b in expected.items():
        np.testing.assert_allclose(getattr(out, name), b, rtol=1e-9, atol=1e-9 * np.max(np.abs(b)), err_msg=name)
    assert ring.max() > 50.0  # the contact spun the ring up
