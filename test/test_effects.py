"""Effects framework (core.effects): default Model unchanged, effects add force / m, jit/grad see params."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from touchdown_ros.core import effects as fx
from touchdown_ros.core.dynamics import phi
from touchdown_ros.core.types import THETA, X, Z
from touchdown_ros.io.config import load_config


def _user_force(xi, p, rig):
    """A user-written once-per-revolution axial thrust."""
    return jnp.stack([0.0 * xi[2], 0.0 * xi[2], p["F_a"] * jnp.cos(xi[3])])


_user_force.parameters = {"F_a": (500.0, "N", "axial thrust amplitude")}


def _contact_push(xi, p, rig):
    """A user-written force through the bearing's contact: F along x."""
    return jnp.stack([p["F"] + 0.0 * xi[0], 0.0 * xi[0], 0.0 * xi[0]])


_contact_push.parameters, _contact_push.contact = {"F": (100.0, "N", "push along x")}, True


@fx.effect("face_share", {"share": (0.1, "1", "share of the face's normal force pushed back up")}, contact=True,
           normal=True)
def _face_share(xi, p, rig, normal):
    """A user-written force through the contact that reads the model's normal forces: share x F_zZ along z."""
    return jnp.stack([0.0 * xi[0], 0.0 * xi[0], p["share"] * normal[1]])


def _user_ramp(xi, p, rig, t):
    """A user-written clocked force: an axial pull growing at `rate` N/s from the drop onset."""
    return jnp.stack([0.0 * xi[2], 0.0 * xi[2], -p["rate"] * t + 0.0 * xi[2]])


_user_ramp.parameters, _user_ramp.clocked = {"rate": (1.0e5, "N/s", "growth of the pull")}, True


def _user_drift(xi, p, rig, t):
    """A user-written clocked measurement effect: the z sensor's zero drifting at `rate` m/s from the onset."""
    return jnp.stack([0.0 * xi[2], 0.0 * xi[2], p["rate"] * t + 0.0 * xi[2]])


_user_drift.parameters, _user_drift.kind, _user_drift.clocked = {"rate": (0.01, "m/s", "drift")}, "measurement", True


def test_default_model_has_no_effects_and_axial_load_adds_force():
    model = load_config().model()
    assert len(model.effects) == 0
    xi = jnp.zeros(model.law.state_size).at[THETA].set(0.3)
    base = phi(model, xi)
    load = fx.resolve("axial_load")
    loaded = model._replace(effects=fx.Effects((load,), ({**load.defaults(), "force": 2000.0},)))
    out = phi(loaded, xi)
    np.testing.assert_allclose(out[6] - base[6], -2000.0 / model.rig.mass)
    np.testing.assert_allclose(out[:6], base[:6])


def test_a_force_through_the_contact_is_part_of_the_contact_force_and_counted_once_in_phi():
    """contact_angle_coupling (tan(beta) F_nR up, in radial contact) acts through the bearing's contact: the
    published contact force carries it (the simulator's does), phi counts it once; a force beside the contact
    (axial_load) stays out of the contact force. A user's effect says so by a `contact` attribute."""
    from touchdown_ros.core.dynamics import contact_forces

    model = load_config().model()
    rig = model.rig
    xi = jnp.zeros(model.law.state_size).at[THETA].set(0.3)
    xi = xi.at[X].set(rig.radial_clearance + 10e-6)  # 10 um into the bore
    angle, load = fx.resolve("contact_angle_coupling"), fx.resolve("axial_load")
    assert angle.contact and not load.contact
    assert angle.normal and set(angle.parameters) == {"tan_beta"}
    effects = fx.Effects((angle, load), ({"tan_beta": 0.2}, {"force": 2000.0}))
    with_both = model._replace(effects=effects)
    bare, moved = contact_forces(model, xi), contact_forces(with_both, xi)
    push = 0.2 * float(bare.F_n)  # tan(beta) times the model's own normal force in the bore; the load not in it
    assert float(bare.F_n) > 1000.0
    np.testing.assert_allclose(moved.F_z - bare.F_z, push, rtol=1e-9)
    np.testing.assert_allclose([moved.F_x, moved.F_y, moved.F_n, moved.F_t], [bare.F_x, bare.F_y, bare.F_n, bare.F_t])
    np.testing.assert_allclose(phi(with_both, xi)[6] - phi(model, xi)[6], (push - 2000.0) / rig.mass, rtol=1e-9)
    user = fx.resolve(f"{__name__}:_contact_push")
    assert user.contact
    pushed = contact_forces(model._replace(effects=fx.Effects((user,))), xi)
    np.testing.assert_allclose([pushed.F_x - bare.F_x, pushed.F_n - bare.F_n], [100.0, -100.0], atol=1e-9)
    with pytest.raises(ValueError, match="only a force acts through the contact"):
        fx.Effect("bad", _contact_push, _contact_push.parameters, kind=fx.MEASUREMENT, contact=True)


def test_a_user_force_through_the_contact_reads_the_models_normal_forces_and_diagnose_sees_the_same():
    """An effect with `normal` gets (F_nR, F_zZ) of the model at the state: in the filter's contact force and in the
    force diagnose's regressors use; only a force through the contact may read them."""
    from touchdown_ros.core.diagnostics.regressors import force_equivalent
    from touchdown_ros.core.dynamics import contact_forces, normal_forces

    model = load_config().model()
    rig = model.rig
    xi = jnp.zeros(model.law.state_size).at[Z].set(-rig.axial_clearance - 8e-6)  # 8 um into the face
    face = normal_forces(model, xi)
    assert float(face[0]) == 0.0 and float(face[1]) > 1000.0
    share = fx.resolve(f"{__name__}:_face_share")
    assert share.normal and share.contact
    bare = contact_forces(model, xi)
    moved = contact_forces(model._replace(effects=fx.Effects((share,), ({"share": 0.1},))), xi)
    np.testing.assert_allclose(moved.F_z - bare.F_z, 0.1 * face[1], rtol=1e-9)
    np.testing.assert_allclose(force_equivalent(share, xi, {"share": 0.1}, model, None), [0.0, 0.0, 0.1 * face[1]],
                               rtol=1e-9)
    with pytest.raises(ValueError, match="only a force through the contact reads its normal forces"):
        fx.Effect("bad", _face_share.function, _face_share.parameters, normal=True)


def test_dotted_path_effect_is_jittable_and_differentiable():
    model = load_config().model()
    e = fx.Effects((fx.resolve(f"{__name__}:_user_force"),))
    assert e.values() == {"_user_force": {"F_a": 500.0}}
    xi = jnp.zeros(model.law.state_size)

    def zdd(effects):
        return jax.jit(phi)(model._replace(effects=effects), xi)[6]

    g = jax.grad(zdd)(e)
    np.testing.assert_allclose(g.params[0]["F_a"], 1.0 / model.rig.mass)
    assert fx.regressors(fx.LIBRARY["axial_load"], xi, model.rig).shape == (3, 1)


# ---------------------------------------------------------------- rig YAML, coefficient files, trainer

import yaml  # noqa: E402

from touchdown_ros.core.dynamics import rk4_step  # noqa: E402
from touchdown_ros.io.coefficients import (  # noqa: E402
    CoefficientFileError,
    TrainingRecord,
    load_coefficients,
    save_coefficients,
)
from touchdown_ros.io.config import ConfigError  # noqa: E402
from touchdown_ros.workflows.train import Trainable, TrainingData, fit  # noqa: E402

LOADED = {"effects.active": ["axial_load"], "effects.axial_load.force": 1500.0}


def test_rig_yaml_switches_effects_on_with_values_and_user_functions():
    config = load_config(overrides=LOADED)
    assert config.effects.values() == {"axial_load": {"force": 1500.0}}
    assert config.model().effects.names == ("axial_load",)
    user = load_config(overrides={"effects.active": ["thrust"], "effects.user.thrust": f"{__name__}:_user_force"})
    assert user.effects.values() == {"thrust": {"F_a": 500.0}}  # the function's default


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"effects.active": ["warp_drive"]}, "unknown effect 'warp_drive'"),
        ({"effects.active": ["axial_load"], "effects.axial_load.mass": 1.0}, "effects.axial_load.mass"),
        ({"effects.axial_load.force": 1.0}, "belong to no active effect"),
        ({"effects.active": ["t"], "effects.user.t": "no_such_module:f"}, "cannot be imported"),
        ({"effects.active": ["axial_load"], "effects.axial_load.force": "2kN"}, "effects.axial_load.force"),
    ],
)
def test_bad_effect_settings_are_named(overrides, message):
    with pytest.raises(ConfigError, match=message):
        load_config(overrides=overrides)


def test_coefficient_file_keeps_effects_and_refuses_bad_ones(tmp_path):
    config = load_config(overrides=LOADED)
    effects = config.effects.with_values({"axial_load": {"force": 1987.5}})
    coeffs = config.model().coeffs
    path = save_coefficients(tmp_path / "c.yaml", coeffs, config, TrainingRecord(), effects)
    loaded = load_coefficients(path, load_config())  # effects come from the file, not the rig
    assert loaded.effects.values() == {"axial_load": {"force": 1987.5}}
    assert loaded.effects.effects[0].when == ""
    assert loaded.model(load_config()).effects.names == ("axial_load",)

    document = yaml.safe_load(path.read_text())
    document["effects"]["axial_load"]["parameters"] = {"newtons": 1.0}
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(document))
    with pytest.raises(CoefficientFileError, match="expects"):
        load_coefficients(tmp_path / "bad.yaml", config)
    document["effects"] = {"thing": {"source": "nowhere:f", "parameters": {}}}
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(document))
    with pytest.raises(CoefficientFileError, match="effects.thing"):
        load_coefficients(tmp_path / "bad.yaml", config)


def test_trainer_fits_an_effect_parameter_only_where_the_bag_condition_switches_it_on():
    """Two records from the model with a 2000 N axial load, one without (its bag's condition
    axial_load is false); training starts at 1500 N and must find 2000 N from the loaded ones."""
    config = load_config(overrides={**LOADED, "effects.when.axial_load": "axial_load"})
    h = config.sample_period
    rng = np.random.default_rng(1)
    records, conditions = [], []
    for b, loaded in enumerate((True, True, False)):
        force = 2000.0 if loaded else 0.0
        truth = config.model(effects=config.effects.with_values({"axial_load": {"force": force}}))
        step = jax.jit(lambda s, truth=truth: rk4_step(truth, s, h / 10))
        xi, states = jnp.zeros(truth.law.state_size).at[:2].set([2e-6 * b, -1e-6]), []
        for _ in range(400):
            for _ in range(10):
                xi = step(xi)
            states.append(np.asarray(xi[:3]))
        records.append(np.array(states) + config.noise_rms * rng.standard_normal((400, 3)))
        conditions.append({"axial_load": str(loaded).lower(), "brake": "true"})
    start = Trainable(config.model().coeffs, config.effects)
    result = fit(config, TrainingData((), tuple(records), tuple(conditions)), 1e-3, start, max_steps=15)
    force = result.effects.values()["axial_load"]["force"]
    assert abs(force - 2000.0) < 0.03 * 2000.0, force
    assert result.final_loss < result.initial_loss


def test_gates_follow_the_recorded_conditions():
    config = load_config(
        overrides={"effects.active": ["axial_load", "brake_decay"], "effects.when.axial_load": "axial_load"}
    )
    effects = config.effects
    assert fx.gates_for(effects, {"axial_load": "true"}) == (1.0, 1.0)
    assert fx.gates_for(effects, {"axial_load": "false"}) == (0.0, 1.0)
    assert fx.gates_for(effects, {}) == (0.0, 1.0)  # not recorded: the conditional effect is off
    with pytest.raises(ConfigError, match="not in effects.active"):
        load_config(overrides={"effects.when.axial_load": "axial_load"})


def test_brake_decay_gives_the_braked_rotors_unbalance_with_its_lagging_angle():
    """brake_decay is a speed effect: with the model's angle theta = omega t it gives the speed
    omega_t = omega (1 - rate t) and the angle phi, its integral; phi's unbalance is then
    m e omega_t^2 (cos, sin) phi, and at rate 0 the constant speed's, exactly."""
    config = load_config()
    rig = config.rig
    effect, e, omega = fx.LIBRARY["brake_decay"], rig.eccentricity, rig.speed
    assert effect.kind == fx.SPEED
    braked = config.model(effects=fx.Effects((effect,), ({"rate": 0.8},)))
    still = config.model(effects=fx.Effects((effect,), ({"rate": 0.0},)))
    for t in (0.0, 0.02, 0.15):
        theta = omega * t
        xi = jnp.zeros(config.law.state_size).at[THETA].set(theta)  # centred, free: the unbalance alone acts
        w, angle = omega * (1.0 - 0.8 * t), omega * (t - 0.4 * t * t)
        np.testing.assert_allclose(np.asarray(effect.function(xi, {"rate": 0.8}, rig)), [w, angle], rtol=1e-12)
        np.testing.assert_allclose(
            np.asarray(phi(braked, xi))[4:6], e * w * w * np.array([np.cos(angle), np.sin(angle)]),
            rtol=1e-9, atol=1e-12 * e * omega**2,
        )
        np.testing.assert_array_equal(np.asarray(phi(still, xi)), np.asarray(phi(config.model(), xi)))


def _nested_force_equivalent(effect, model, xi, params):
    """The force a measurement effect stands for, by nested forward derivatives of phi (the
    definition: m (d^2 D / dt^2 - A (D, 0, dD/dt)) with the time derivatives along phi)."""
    def rate(s):
        return phi(model, s)

    def change_rate(s):
        return jax.jvp(lambda q: effect.function(q, params, model.rig), (s,), (rate(s),))[1]

    change = effect.function(xi, params, model.rig)
    change_velocity, change_acceleration = jax.jvp(change_rate, (xi,), (rate(xi),))
    shift = jnp.concatenate([change, jnp.zeros(1), change_velocity, jnp.zeros(len(xi) - 7)])  # the ring: unshifted
    return model.rig.mass * (change_acceleration - jax.jvp(lambda s: rate(s)[4:7], (xi,), (shift,))[1])


def _speed_force(effect, model, xi, params):
    """A speed effect's force with the paper's friction, written out: the change of the unbalance force
    m e (omega^2 (cos, sin) angle - Omega^2 (cos, sin) theta), omega and angle from the effect."""
    rig = model.rig
    omega, angle = effect.function(xi, params, rig)
    me = rig.mass * rig.eccentricity
    return jnp.stack([me * (omega**2 * jnp.cos(angle) - rig.speed**2 * jnp.cos(xi[3])),
                      me * (omega**2 * jnp.sin(angle) - rig.speed**2 * jnp.sin(xi[3])), 0.0 * xi[3]])


def _defined_force(effect, model, xi, params):
    """The force each kind of effect stands for, by its definition."""
    if effect.kind == fx.MEASUREMENT:
        return _nested_force_equivalent(effect, model, xi, params)
    if effect.kind == fx.SPEED:
        return _speed_force(effect, model, xi, params)
    return effect.function(xi, params, model.rig)


@fx.effect("z_curvature", {"a": (3.0e3, "1/m", "sensor reads z + a x^2")}, kind=fx.MEASUREMENT)
def _z_curvature(xi, p, rig):
    return jnp.stack([0.0 * xi[0], 0.0 * xi[0], p["a"] * xi[0] ** 2])


@pytest.mark.parametrize("friction", ["paper", "spinning_ring"])
def test_library_regressors_share_phi_and_equal_the_nested_definition(friction):
    """`library_regressors` computes phi and its Jacobian once per state for every measurement effect;
    each force equivalent (and its parameter Jacobian) equals the nested-derivative definition, for the
    sensor errors and for a nonlinear user effect (its second derivative enters), free and in contact;
    with the ring's speed as an eighth state too (the brake's force is written out for the paper's friction)."""
    from touchdown_ros.core.diagnostics.regressors import effect_regressors, library_regressors

    model = load_config(overrides={"contact.friction": friction}).model()
    states = jnp.array([
        [1e-4, -0.5e-4, -1e-4, 0.3, 0.01, -0.02, -0.05, 100.0],  # free
        [1.5e-4, 1.6e-4, -1e-4, 1.1, 0.03, -0.01, 0.02, 300.0],  # radial contact
        [-2.0e-4, 0.9e-4, -3.1e-4, 4.0, -0.04, 0.03, 0.01, 500.0],  # both contacts
    ])[:, : model.law.state_size]
    names = ("sensor_gain_x", "sensor_offset_z", "axial_load") + (("brake_decay",) if friction == "paper" else ())
    effects = {name: fx.LIBRARY[name] for name in names}
    effects["z_curvature"] = _z_curvature
    together = library_regressors(effects, states, model)
    for name, effect in effects.items():
        params = {k: jnp.asarray(v) for k, v in effect.defaults().items()}
        J, f0 = together[name]
        alone = effect_regressors(effect, states, model)
        np.testing.assert_allclose(np.asarray(J), np.asarray(alone[0]), rtol=1e-12, atol=0)
        for i, xi in enumerate(states):
            expected = _defined_force(effect, model, xi, params)
            np.testing.assert_allclose(np.asarray(f0[i]), np.asarray(expected), rtol=1e-9, atol=1e-9)
            jac = jax.jacfwd(lambda p: _defined_force(effect, model, xi, p))(params)
            expected_J = np.stack([np.asarray(jac[k]) for k in params], axis=-1)
            np.testing.assert_allclose(np.asarray(J[i]), expected_J, rtol=1e-9, atol=1e-9)
    assert np.abs(np.asarray(together["z_curvature"][1])).max() > 0.0


def test_amb_release_decays_from_the_onset_and_each_rk4_stage_reads_its_own_time():
    """The AMB's support of the weight letting go, share exp(-t / tau): the rotor at rest at the centre
    accelerates at -g (1 - exp(-t / tau)), and one RK4 step (plain and with its Jacobian) from t0 gains the
    exact integral of it to round-off (stages held at the step's start would miss it by ~g h^2 / (2 tau))."""
    from touchdown_ros.core.dynamics import at_time, rk4_step, step_with_jacobian

    base = load_config().model()
    amb = fx.resolve("amb_release")
    tau, h, t0 = 1.0e-3, 1.0e-4, 3.0e-4
    model = base._replace(effects=fx.Effects((amb,), ({"share": 1.0, "decay_time": tau, "release": 0.0},)))
    g, xi = base.rig.gravity, jnp.zeros(base.law.state_size)
    for t in (0.0, tau, 5 * tau):
        np.testing.assert_allclose(phi(at_time(model, t), xi)[6], -g * (1.0 - np.exp(-t / tau)), atol=1e-12)
    held = base._replace(effects=fx.Effects((amb,), ({"share": 1.0, "decay_time": tau, "release": 2 * tau},)))
    for t in (0.0, 2 * tau, 3 * tau):  # levitated until the release, then letting go as from the onset
        np.testing.assert_allclose(phi(at_time(held, t), xi)[6], -g * (1.0 - np.exp(-max(t - 2 * tau, 0.0) / tau)),
                                   atol=1e-12)
    exact = -g * h + g * tau * np.exp(-t0 / tau) * (1.0 - np.exp(-h / tau))
    np.testing.assert_allclose(rk4_step(at_time(model, t0), xi, h)[6], exact, rtol=1e-6)
    np.testing.assert_allclose(step_with_jacobian(at_time(model, t0), xi, h)[0][6], exact, rtol=1e-6)
    assert "amb_release" not in fx.LIBRARY  # a term the user switches on, not a candidate of the workbench's
    ramp = base._replace(effects=fx.Effects((fx.resolve(f"{__name__}:_user_ramp"),)))  # a clocked one by dotted path
    np.testing.assert_allclose(phi(at_time(ramp, 2.0e-3), xi)[6] - phi(at_time(ramp, 0.0), xi)[6],
                               -1.0e5 * 2.0e-3 / base.rig.mass)


def test_amb_release_is_the_rigs_pd_law_and_unbalance_compensation_and_the_filter_runs_it_in_time():
    """With the rig's AMB constants the force is -gain (k x + c xdot + comp m e omega^2 (cos, sin) theta) plus
    gain m g on z; the filter's scan gives step k the time k h: its priors follow the timed RK4 steps."""
    from touchdown_ros.core.dynamics import at_time, rk4_step
    from touchdown_ros.core.ekf import Belief, ekf

    config = load_config(overrides={
        "effects.active": ["amb_release"], "effects.amb_release.decay_time": 2.0e-3, "effects.amb_release.share": 0.8,
        "rig.amb_stiffness": 2.0e6, "rig.amb_damping": 2.0e4, "rig.amb_unbalance_compensation": 0.7,
    })
    model, rig = config.model(), config.rig
    rotor = [1e-5, -2e-5, 3e-5, 0.4, 0.01, 0.02, -0.03]
    xi = jnp.asarray(rotor + [rig.speed] * (model.law.state_size - len(rotor)))  # a spinning ring with the rotor
    t = 1.0e-3
    gain = 0.8 * np.exp(-t / 2.0e-3)
    comp = 0.7 * rig.mass * rig.eccentricity * rig.speed**2
    expected = gain * np.array([
        -2e6 * 1e-5 - 2e4 * 0.01 - comp * np.cos(0.4),
        -2e6 * -2e-5 - 2e4 * 0.02 - comp * np.sin(0.4),
        -2e6 * 3e-5 - 2e4 * -0.03 + rig.mass * rig.gravity,
    ])
    np.testing.assert_allclose(model._replace(effects=model.effects.at_time(t)).effects.force(xi, rig), expected,
                               rtol=1e-12)
    h, n = config.sample_period, 12
    etas = jnp.full((n, 3), jnp.nan)  # predict only: the priors are the model's own steps
    out = ekf(model, config.noise, h, Belief(xi, jnp.diag(config.noise.initial)), etas)
    state = xi
    for k in range(n - 1):
        state = rk4_step(at_time(model, k * h), state, h)
        np.testing.assert_allclose(out.prior.mean[k + 1], state, rtol=1e-10, atol=1e-16)


def test_amb_release_holds_the_static_loads_until_it_lets_go_and_not_a_once_per_revolution_force():
    """The AMB's integral action carried the loads in levitation: with an axial and a side load switched on, the
    rotor at rest at the centre feels nothing more than without them until the release, and the loads' whole
    force once the AMB has let go; a once-per-revolution thrust averages out of what it holds (it acts in both)."""
    from touchdown_ros.core.dynamics import at_time

    base = load_config().model()
    amb = ({"share": 1.0, "decay_time": 1.0e-3, "release": 2.0e-3},)
    loads = ({"force": 2000.0}, {"force_x": 300.0, "force_y": -150.0}, {"F_a": 500.0})
    alone = base._replace(effects=fx.Effects((fx.resolve("amb_release"),), amb))
    loaded = base._replace(effects=fx.Effects(
        (fx.resolve("amb_release"), fx.resolve("axial_load"), fx.resolve("radial_load"),
         fx.resolve(f"{__name__}:_user_force")), amb + loads))
    xi = jnp.zeros(base.law.state_size).at[3].set(0.7)
    thrust = np.array([0.0, 0.0, 500.0 * np.cos(0.7)])
    for t, kept in ((0.0, 1.0), (2.0e-3, 1.0), (3.0e-3, np.exp(-1.0)), (40.0e-3, 0.0)):
        extra = (phi(at_time(loaded, t), xi) - phi(at_time(alone, t), xi))[4:7] * base.rig.mass
        np.testing.assert_allclose(extra, (1.0 - kept) * np.array([300.0, -150.0, -2000.0]) + thrust, atol=1e-6)
    assert fx.resolve("amb_release").holds and not fx.resolve("axial_load").holds
    with pytest.raises(ValueError, match="only a clocked force off the contact"):
        dataclasses.replace(fx.resolve("axial_load"), holds=True)


def test_regressors_give_clocked_effects_each_states_time():
    """Along states timed from the onset, a clocked force is its value at each state's time, and a clocked sensor
    drift stands for the same force as the library's z offset of the drift's size at that time."""
    from touchdown_ros.core.diagnostics.regressors import library_regressors

    model = load_config().model()
    times = jnp.asarray([0.0, 1.0e-3, 2.0e-3])
    states = jnp.zeros((3, model.law.state_size)).at[:, 2].set(-(model.rig.axial_clearance + 2.0e-5))  # on the face
    ramp, drift = fx.resolve(f"{__name__}:_user_ramp"), fx.resolve(f"{__name__}:_user_drift")
    out = library_regressors({"ramp": ramp, "drift": drift}, states, model, times=times)
    np.testing.assert_allclose(out["ramp"][1][:, 2], -1.0e5 * np.asarray(times), atol=1e-9)
    offset = fx.LIBRARY["sensor_offset_z"]
    for j, t in enumerate(np.asarray(times)):
        same = library_regressors({"offset": offset}, states[j:j + 1], model, {"offset": {"offset": 0.01 * t}})
        np.testing.assert_allclose(out["drift"][1][j], same["offset"][1][0], rtol=1e-9, atol=1e-9)
    assert np.abs(np.asarray(out["drift"][1][2, 2])) > 1.0  # in contact the drift moves a force


def test_an_effects_further_starts_are_checked_and_put_where_the_fit_starts():
    """A braked rotor's rate: fitted from 0.1 or 0.3 on drawn_1_1's braked drops it ended at -0.06 (the loss of no
    brake), from 1 or 3 at 0.783 for 0.766 (2026-12-07): its fits start from `Effect.starts` too."""
    from touchdown_ros.core.calibration import (
        effect_coordinates, effect_scales, fit_starts, further_starts, stage1_start,
    )

    assert fx.LIBRARY["brake_decay"].starts == {"rate": (1.0, 3.0)}
    with pytest.raises(ValueError, match="starts rate"):
        fx.Effect("braked", fx.LIBRARY["brake_decay"].function, {"rate": (0.1, "1/s", "")}, bounds={"rate": (0.0, 5.0)},
                  starts={"rate": (-1.0,)})
    with pytest.raises(ValueError, match="name no parameter"):
        fx.Effect("braked", fx.LIBRARY["brake_decay"].function, {"rate": (0.1, "1/s", "")}, starts={"speed": (1.0,)})
    load, brake = fx.LIBRARY["axial_load"], fx.LIBRARY["brake_decay"]
    effects = fx.Effects((load, brake), (load.defaults(), brake.defaults()))
    scales = effect_scales(effects)
    theta = stage1_start(jnp.zeros(6), effects, scales)
    starts = further_starts(theta, scales, ["axial_load", "brake_decay"])
    assert [label for label, _ in starts] == [", from brake_decay.rate 1", ", from brake_decay.rate 3"]
    for (_, moved), rate in zip(starts, (1.0, 3.0)):
        index = moved.effects.names.index("brake_decay")
        assert float(moved.effects.params[index]["rate"]) * scales.params[index]["rate"] == pytest.approx(rate)
        load = moved.effects.names.index("axial_load")
        assert moved.effects.params[load] == theta.effects.params[load]
    # as a fit's free coordinates: its own start first, then the two further ones (the brake's rate alone free)
    coordinates = effect_coordinates(theta, ["brake_decay"])
    points = fit_starts(coordinates, scales, ["brake_decay"])
    assert [label for label, _ in points] == ["", ", from brake_decay.rate 1", ", from brake_decay.rate 3"]
    np.testing.assert_allclose([x[0] * scales.params[1]["rate"] for _, x in points], [0.1, 1.0, 3.0])
