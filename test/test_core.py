"""Core model and filter against hand computations and independent implementations."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import band_added_and_by_hand, central_differences
from filterpy.kalman import ExtendedKalmanFilter

from touchdown_ros.core.dynamics import (
    contact_forces,
    contact_forces_and_jacobian,
    phi,
    rk4_step,
    step_with_jacobian,
    transition_jacobian,
)
from touchdown_ros.core.ekf import (
    Belief,
    NoiseAdaptation,
    adapted_log_scale,
    ekf,
    extended_kalman_filter,
    model_transition,
    position,
    predict,
    predict_with_rate,
    rts_smoother,
)
from touchdown_ros.core.estimate import DropDetector, GridError, force_model_variance, force_std, signals, to_grid
from touchdown_ros.core.pkbkr import axial_parameters, radial_parameters, rkhs_distance
from touchdown_ros.core.types import Coefficients, FilterNoise, Nominal, Rig
from touchdown_ros.io.config import load_config

#: The paper's friction and seven states, as `make_model`'s law and the hand-written references (filterpy, numpy).
CONFIG = load_config(overrides={"contact.friction": "paper"})
RIG = Rig(mass=200.0, eccentricity=1e-5, speed=500.0, radial_clearance=2e-4, axial_clearance=3e-4, gravity=9.81)
NOMINAL = Nominal(k_R=1e8, c_R=2e4, mu=0.12, k_Z=3e8, c_Z=5e4, k_ZR=0.07)


def make_model(coeffs=None, rig=RIG, nominal=NOMINAL):
    kernel = CONFIG.kernel
    return type(CONFIG.model())(rig, nominal, kernel, coeffs or Coefficients.zeros(kernel))


def random_coeffs(seed=0, scale=0.3):
    rng = np.random.default_rng(seed)
    zeros = Coefficients.zeros(CONFIG.kernel)
    return Coefficients(
        alpha_R=scale * rng.standard_normal(zeros.alpha_R.shape),
        alpha_Z=scale * rng.standard_normal(zeros.alpha_Z.shape),
    )


def hand_forces(xi, rig=RIG, p=NOMINAL):
    """Eq. 5-8 written out with plain math, constant parameters."""
    x, y, z, _, xd, yd, zd = (float(v) for v in xi)
    r = math.hypot(x, y)
    a = math.atan2(y, x)
    rdot = math.cos(a) * xd + math.sin(a) * yd
    F_nR = p.k_R * (r - rig.radial_clearance) + p.c_R * rdot if r > rig.radial_clearance else 0.0
    F_tR = p.mu * F_nR
    F_zR = -p.mu * math.copysign(1.0, zd) * F_nR if zd != 0 else 0.0
    F_zZ = -p.k_Z * (z + rig.axial_clearance) - p.c_Z * zd if z < -rig.axial_clearance else 0.0
    F_tZ = p.k_ZR * F_zZ
    F_n, F_t, F_z = F_nR, F_tR + F_tZ, F_zR + F_zZ
    F_x = -F_n * math.cos(a) + F_t * math.sin(a)
    F_y = -F_n * math.sin(a) - F_t * math.cos(a)
    return F_n, F_t, F_z, F_x, F_y


CASES = {
    "free": [1e-4, -0.5e-4, -1e-4, 0.3, 0.01, -0.02, -0.05],
    "radial": [1.5e-4, 1.6e-4, -1e-4, 1.1, 0.03, -0.01, 0.02],
    "axial": [0.5e-4, 0.2e-4, -3.2e-4, 2.0, 0.01, 0.02, -0.06],
    "both": [-2.0e-4, 0.9e-4, -3.1e-4, 4.0, -0.04, 0.03, 0.01],
}


@pytest.mark.parametrize("case", CASES)
def test_forces_equal_hand_computed_eq5_8(case):
    xi = jnp.array(CASES[case])
    forces = contact_forces(make_model(), xi)
    expected = hand_forces(CASES[case])
    got = (forces.F_n, forces.F_t, forces.F_z, forces.F_x, forces.F_y)
    np.testing.assert_allclose(np.array(got, dtype=float), expected, rtol=1e-12, atol=1e-9)
    assert bool(forces.radial_contact) == (case in ("radial", "both"))
    assert bool(forces.axial_contact) == (case in ("axial", "both"))
    if case == "free":
        assert np.all(np.array(got, dtype=float) == 0.0)


def test_phi_is_eq12():
    xi = np.array(CASES["both"])
    F_n, F_t, F_z, F_x, F_y = hand_forces(xi)
    unbalance = RIG.eccentricity * RIG.speed**2
    expected = [
        xi[4],
        xi[5],
        xi[6],
        RIG.speed,
        F_x / RIG.mass + unbalance * math.cos(xi[3]),
        F_y / RIG.mass + unbalance * math.sin(xi[3]),
        F_z / RIG.mass - RIG.gravity,
    ]
    np.testing.assert_allclose(np.asarray(phi(make_model(), jnp.asarray(xi))), expected, rtol=1e-12)


def test_pkbkr_with_zero_alpha_is_the_constant_model_and_alpha_changes_it():
    xi = jnp.array(CASES["both"])
    constant = contact_forces(make_model(), xi)
    zero = contact_forces(make_model(Coefficients.zeros(CONFIG.kernel)), xi)
    learned = contact_forces(make_model(random_coeffs()), xi)
    assert float(zero.F_z) == float(constant.F_z) and float(zero.F_n) == float(constant.F_n)
    assert abs(float(learned.F_z) - float(constant.F_z)) > 1.0
    assert abs(float(learned.F_n) - float(constant.F_n)) > 1.0
    assert float(rkhs_distance(CONFIG.kernel, Coefficients.zeros(CONFIG.kernel))) == 0.0
    assert float(rkhs_distance(CONFIG.kernel, random_coeffs())) > 0.0


def test_learned_parameters_at_one_state_match_a_hand_kernel():
    kernel = CONFIG.kernel
    coeffs = Coefficients.zeros(kernel)
    centre = 7  # one radial centre carries alpha_1 = 0.5
    coeffs = coeffs._replace(alpha_R=coeffs.alpha_R.at[0, centre].set(0.5))
    xi = np.array(CASES["radial"])
    r = math.hypot(xi[0], xi[1])
    rdot = (xi[0] * xi[3 + 1] + xi[1] * xi[5]) / r
    s = np.array([(r - RIG.radial_clearance) / kernel.scale_R[0], rdot / kernel.scale_R[1]])
    q = math.exp(-np.sum((s - np.asarray(kernel.T_R[centre])) ** 2) / (2 * kernel.width**2))
    k_R = NOMINAL.k_R * (1 + 0.5 * q)
    expected_F_n = k_R * (r - RIG.radial_clearance) + NOMINAL.c_R * rdot
    got = contact_forces(make_model(coeffs), jnp.asarray(xi)).F_n
    np.testing.assert_allclose(float(got), expected_F_n, rtol=1e-12)


def _hand_parameters(f0s, alpha, T, scale, width, deformation, velocity):
    """p = f0 * (1 + Q alpha) with Q_i = exp(-|s - t_i|^2 / (2 w^2)), s = (deformation, velocity) / scale,
    before and after the floor at 0; one row per parameter, one column per state."""
    s = np.stack([deformation / scale[0], velocity / scale[1]], axis=-1)
    Q = np.exp(-np.sum((s[:, None, :] - T[None]) ** 2, axis=-1) / (2.0 * width**2))
    raw = np.array([f0 * (1.0 + Q @ a) for f0, a in zip(f0s, alpha)])
    return raw, np.maximum(raw, 0.0)


@pytest.mark.parametrize("negative", [False, True], ids=["positive", "floored"])
def test_all_six_parameter_functions_match_a_hand_kernel_of_width_0_7(negative):
    """Each of k_R, c_R, mu, k_Z, c_Z, k_ZR with its own alpha, a kernel width other than 1, states on and
    between the centres; the negative case drives f0 * (1 + Q alpha) below 0 where the floor must give 0."""
    kernel = CONFIG.kernel._replace(width=0.7)
    T_R, T_Z = np.asarray(kernel.T_R), np.asarray(kernel.T_Z)
    scale_R, scale_Z = np.asarray(kernel.scale_R), np.asarray(kernel.scale_Z)
    rng = np.random.default_rng(18)
    alpha_R = 0.1 * rng.standard_normal((3, T_R.shape[0]))
    alpha_Z = 0.1 * rng.standard_normal((3, T_Z.shape[0]))
    if negative:  # strongly negative on the centres of large deformation only
        alpha_R[:, T_R[:, 0] > np.median(T_R[:, 0])] -= 2.0
        alpha_Z[:, T_Z[:, 0] > np.median(T_Z[:, 0])] -= 2.0
    coeffs = Coefficients(alpha_R=jnp.asarray(alpha_R), alpha_Z=jnp.asarray(alpha_Z))
    n = 40
    deformation_R = scale_R[0] * rng.uniform(T_R[:, 0].min(), T_R[:, 0].max(), n)
    velocity_R = scale_R[1] * rng.uniform(T_R[:, 1].min(), T_R[:, 1].max(), n)
    deformation_Z = scale_Z[0] * rng.uniform(T_Z[:, 0].min(), T_Z[:, 0].max(), n)
    velocity_Z = scale_Z[1] * rng.uniform(T_Z[:, 1].min(), T_Z[:, 1].max(), n)

    raw_R, want_R = _hand_parameters(
        (NOMINAL.k_R, NOMINAL.c_R, NOMINAL.mu), alpha_R, T_R, scale_R, 0.7, deformation_R, velocity_R
    )
    raw_Z, want_Z = _hand_parameters(
        (NOMINAL.k_Z, NOMINAL.c_Z, NOMINAL.k_ZR), alpha_Z, T_Z, scale_Z, 0.7, deformation_Z, velocity_Z
    )
    got_R = radial_parameters(kernel, NOMINAL, coeffs, jnp.asarray(deformation_R), jnp.asarray(velocity_R))
    got_Z = axial_parameters(kernel, NOMINAL, coeffs, jnp.asarray(deformation_Z), jnp.asarray(velocity_Z))
    f0s = (NOMINAL.k_R, NOMINAL.c_R, NOMINAL.mu, NOMINAL.k_Z, NOMINAL.c_Z, NOMINAL.k_ZR)
    for name, f0, got, raw, want in zip(
        ("k_R", "c_R", "mu", "k_Z", "c_Z", "k_ZR"), f0s, (*got_R, *got_Z), (*raw_R, *raw_Z), (*want_R, *want_Z)
    ):
        # each parameter is moved by its own alpha, well beyond the tolerance
        assert np.max(np.abs(raw / f0 - 1.0)) > 0.05, name
        if negative:
            assert np.sum(raw < 0) >= 5 and np.sum(raw > 0) >= 1, name  # the floor acts on some states only
            assert np.all(np.asarray(got)[raw < 0] == 0.0), name
        else:
            assert np.all(raw > 0), name
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-12, atol=1e-12 * f0, err_msg=name)


def test_axial_kernel_input_is_the_compression():
    """zeta's deformation is -(z + z0) >= 0 in contact, so a centre at +2 scales covers 2 scales of compression."""
    kernel = CONFIG.kernel
    centre = int(np.argmin(np.sum((np.asarray(kernel.T_Z) - np.array([2.0, 0.0])) ** 2, axis=1)))
    assert np.allclose(kernel.T_Z[centre], [2.0, 0.0])
    coeffs = Coefficients.zeros(kernel)
    coeffs = coeffs._replace(alpha_Z=coeffs.alpha_Z.at[0, centre].set(0.5))
    compression = 2.0 * kernel.scale_Z[0]
    xi = jnp.array([0.0, 0.0, -RIG.axial_clearance - compression, 0.0, 0.0, 0.0, 0.0])
    others = np.delete(np.asarray(kernel.T_Z), centre, axis=0)
    q_others = np.exp(-np.sum((others - np.array([2.0, 0.0])) ** 2, axis=1) / (2 * kernel.width**2))
    assert np.all(q_others < 0.61)  # the chosen centre dominates
    k_Z = NOMINAL.k_Z * (1 + 0.5 * 1.0)
    np.testing.assert_allclose(float(contact_forces(make_model(coeffs), xi).F_z), k_Z * compression, rtol=1e-12)


def hand_ring_forces(xi, v, rig=RIG, p=NOMINAL, speed=None):
    """F_n, F_t, F_z with Coulomb friction on the slip against a ring spinning at the rotor speed
    (`speed`, rad/s, default the rig's), written out: the slip of the rotor centre is its velocity
    minus the ring's (omega x position)."""
    omega = rig.speed if speed is None else speed
    x, y, z, _, xd, yd, zd = (float(v_) for v_ in xi)
    r = math.hypot(x, y)
    n = (x / r, y / r)
    t = (-n[1], n[0])  # anticlockwise, the rotor's sense of rotation
    u = (xd + omega * y, yd - omega * x)  # centre velocity minus the ring's velocity there
    u_n, u_t = u[0] * n[0] + u[1] * n[1], u[0] * t[0] + u[1] * t[1]
    F_nR = p.k_R * (r - rig.radial_clearance) + p.c_R * (xd * n[0] + yd * n[1]) if r > rig.radial_clearance else 0.0
    F_zZ = -p.k_Z * (z + rig.axial_clearance) - p.c_Z * zd if z < -rig.axial_clearance else 0.0
    bore = p.mu * F_nR / math.sqrt(u_t**2 + zd**2 + v**2)  # N per m/s of slip
    face = p.k_ZR * F_zZ / math.sqrt(u_t**2 + u_n**2 + v**2)
    force = [-F_nR * n[0] - bore * u_t * t[0] - face * u[0], -F_nR * n[1] - bore * u_t * t[1] - face * u[1]]
    # F_n along -n, F_t along -t (the paper's directions)
    F_n = -(force[0] * n[0] + force[1] * n[1])
    F_t = -(force[0] * t[0] + force[1] * t[1])
    return F_n, F_t, F_zZ - bore * zd


@pytest.mark.parametrize("case", ["radial", "axial", "both"])
def test_co_rotating_ring_friction_opposes_the_slip_against_the_spinning_ring(case):
    xi = np.array(CASES[case])
    paper = make_model()
    ring = paper._replace(law=paper.law.with_friction("co_rotating_ring", 0.02))
    forces = contact_forces(ring, jnp.asarray(xi))
    got = np.array([forces.F_n, forces.F_t, forces.F_z], dtype=float)
    np.testing.assert_allclose(got, hand_ring_forces(xi, 0.02), rtol=1e-10)
    assert got[1] < 0.0  # a rotor whirling slower than omega r is driven forward (F_t along +t)
    assert ring.law.friction == "co_rotating_ring" and paper.law.friction == "paper"
    # a rotor rolling in forward synchronous whirl (centre velocity omega x position) does not slide
    x, y = xi[0], xi[1]
    rolling = xi.copy()
    rolling[4:6] = (-RIG.speed * y, RIG.speed * x)
    rolling[6] = 0.0
    assert float(contact_forces(ring, jnp.asarray(rolling)).F_t) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("case", ["radial", "both"])
def test_a_braked_rotor_slips_against_the_ring_at_its_own_speed(case):
    """A speed effect (brake_decay) sets the speed of the ring the rotor slips on, omega (1 - rate t)
    with t = theta / omega, and the unbalance: m e omega_t^2 at the lagging angle in phi."""
    from touchdown_ros.core.dynamics import phi
    from touchdown_ros.core.effects import LIBRARY, Effects

    xi = np.array(CASES[case])
    xi[3] = 0.1 * RIG.speed  # 0.1 s after the onset: the rotor at 0.92 of its speed
    rate, t = 0.8, xi[3] / RIG.speed
    ring = make_model()._replace(law=make_model().law.with_friction("co_rotating_ring", 0.02))
    braked = ring._replace(effects=Effects((LIBRARY["brake_decay"],), ({"rate": rate},)))
    forces = contact_forces(braked, jnp.asarray(xi))
    got = np.array([forces.F_n, forces.F_t, forces.F_z], dtype=float)
    omega_t = RIG.speed * (1.0 - rate * t)
    np.testing.assert_allclose(got, hand_ring_forces(xi, 0.02, speed=omega_t), rtol=1e-10)
    assert not np.allclose(got, hand_ring_forces(xi, 0.02), rtol=1e-3)  # not the constant speed's
    angle = xi[3] - 0.5 * rate * RIG.speed * t * t
    unbalance = RIG.eccentricity * omega_t**2 * np.array([np.cos(angle), np.sin(angle)])
    c = contact_forces(braked, jnp.asarray(xi))
    expected = np.array([c.F_x, c.F_y]) / RIG.mass + unbalance
    np.testing.assert_allclose(np.asarray(phi(braked, jnp.asarray(xi)))[4:6], expected, rtol=1e-12)
    assert float(phi(braked, jnp.asarray(xi))[3]) == RIG.speed  # theta stays the clock


def test_friction_model_is_static_in_a_compiled_program():
    """The friction model is pytree aux data: a jitted function of the model sees it as a Python value
    (one model traced, not both selected per sample) and compiles once per model; the law's numbers
    stay traced (one program for every exponent and slip velocity)."""
    paper = make_model()
    ring = paper._replace(law=paper.law.with_friction("co_rotating_ring", 0.02))
    seen = []

    @jax.jit
    def force(model, xi):
        seen.append((model.law.friction, isinstance(model.law.slip_velocity, jax.core.Tracer)))
        return contact_forces(model, xi).F_t

    xi = jnp.asarray(CASES["radial"])
    for model in (paper, ring, ring._replace(law=ring.law.with_friction("co_rotating_ring", 0.03))):
        expected = contact_forces(model, xi).F_t
        assert float(force(model, xi)) == pytest.approx(float(expected), rel=1e-12)
    assert seen == [("paper", True), ("co_rotating_ring", True)]  # the second ring reused the program
    numbers = [getattr(ring.law, f) for f in type(ring.law)._fields if f != "friction_model"]
    assert jax.tree.leaves(ring.law) == jax.tree.leaves(numbers)  # all but the friction model are leaves


@pytest.mark.parametrize("case", CASES)
def test_ad_jacobian_matches_central_differences(case):
    model = make_model(random_coeffs(1))
    xi = np.array(CASES[case])
    h = 1e-4
    J = np.asarray(transition_jacobian(model, jnp.asarray(xi), h))
    scales = np.array([1e-9, 1e-9, 1e-9, 1e-6, 1e-6, 1e-6, 1e-6])
    J_fd = central_differences(lambda s: rk4_step(model, jnp.asarray(s), h), xi, scales)
    np.testing.assert_allclose(J, J_fd, rtol=1e-5, atol=1e-7)
    assert not np.allclose(J, np.eye(7))


def force_xyz_jax(model, xi):
    forces = contact_forces(model, xi)
    return jnp.stack([forces.F_x, forces.F_y, forces.F_z])


def known_covariance(seed: int) -> np.ndarray:
    """A full state covariance (7, 7): standard deviations of the filter's order, random correlations."""
    rng = np.random.default_rng(seed)
    sd = np.array([2e-6, 2e-6, 2e-6, 1e-2, 3e-3, 3e-3, 3e-3])  # m, rad, m/s
    A = rng.standard_normal((7, 7))
    correlation = A @ A.T + 7 * np.eye(7)
    d = 1 / np.sqrt(np.diag(correlation))
    return sd[:, None] * (d[:, None] * correlation * d[None, :]) * sd[None, :]


@pytest.mark.parametrize("case", CASES)
def test_force_std_is_finite_difference_jacobian_through_a_known_covariance(case):
    """sigma_F = sqrt(diag(J P J^T)) with J from central differences of contact_forces (F_x, F_y, F_z)."""
    model = make_model(random_coeffs(2))
    xi, P = np.array(CASES[case]), known_covariance(3)
    scales = np.array([1e-10, 1e-10, 1e-10, 1e-6, 1e-7, 1e-7, 1e-7])

    def force_xyz(state):
        forces = contact_forces(model, jnp.asarray(state))
        return np.array([forces.F_x, forces.F_y, forces.F_z], dtype=float)

    J_fd = np.empty((3, 7))
    for j in range(7):
        step = np.zeros(7)
        step[j] = scales[j]
        J_fd[:, j] = (force_xyz(xi + step) - force_xyz(xi - step)) / (2 * scales[j])
    by_hand = J_fd @ P @ J_fd.T

    _, J = contact_forces_and_jacobian(model, jnp.asarray(xi))
    J_forward = jax.jacfwd(lambda s: jnp.asarray(force_xyz_jax(model, s)))(jnp.asarray(xi))
    np.testing.assert_allclose(np.asarray(J), np.asarray(J_forward), rtol=1e-12, atol=1e-12 * np.max(np.abs(J_fd)))
    out = signals(model, Belief(jnp.asarray(xi)[None], jnp.asarray(P)[None]))
    std = force_std(np.asarray(out.force_cov))[0]
    np.testing.assert_allclose(np.asarray(out.force_xyz)[0], force_xyz(xi), rtol=1e-14, atol=0)
    if case == "free":  # out of contact the force does not depend on the state: no uncertainty
        assert np.all(np.asarray(out.force_cov) == 0.0) and np.all(std == 0.0)
        return
    np.testing.assert_allclose(np.asarray(out.force_cov)[0], by_hand, rtol=1e-6, atol=1e-9 * np.max(np.abs(by_hand)))
    np.testing.assert_allclose(std, np.sqrt(np.diag(by_hand)), rtol=1e-6)
    assert np.all(std > 1.0)  # N: a contact force is uncertain on every axis (friction couples z to the radial contact)
    # linear in the state's standard deviation: a quarter of the covariance halves sigma_F
    half = signals(model, Belief(jnp.asarray(xi)[None], 0.25 * jnp.asarray(P)[None]))
    np.testing.assert_allclose(force_std(np.asarray(half.force_cov))[0], 0.5 * std, rtol=1e-12)


@pytest.mark.parametrize("case", ["axial", "both"])
def test_a_yielding_support_passes_the_face_force_up_to_its_preload_then_creeps_to_preload_plus_span(case):
    xi = np.array(CASES[case])
    F_n, F_t, F_z, _, _ = hand_forces(xi)
    F_zZ = -NOMINAL.k_Z * (xi[2] + RIG.axial_clearance) - NOMINAL.c_Z * xi[6]
    rigid = make_model()
    for preload, span in ((0.5 * F_zZ, 0.2 * F_zZ), (0.9 * F_zZ, 1e-9), (2.0 * F_zZ, 0.2 * F_zZ)):
        model = rigid._replace(law=rigid.law.with_support(preload, span))
        x = F_zZ - preload
        passed = F_zZ if x <= 0 else preload + span * x / (span + x)
        forces = contact_forces(model, jnp.asarray(xi))
        assert float(forces.F_z) == pytest.approx(F_z - F_zZ + passed, rel=1e-12)
        assert float(forces.F_t) == pytest.approx(
            F_t + NOMINAL.k_ZR * (passed - F_zZ), rel=1e-12
        )  # face friction on what passes
        assert float(forces.F_n) == F_n
    # rigid (preload inf) is the paper's force bit for bit
    assert contact_forces(rigid, jnp.asarray(xi)) == contact_forces(
        rigid._replace(law=rigid.law.with_support()), jnp.asarray(xi)
    )


@pytest.mark.parametrize("case", ["axial", "both"])
def test_the_force_band_carries_the_supports_uncertainty_above_its_knee_only(case):
    xi, P = np.array(CASES[case]), known_covariance(3)
    F_zZ = -NOMINAL.k_Z * (xi[2] + RIG.axial_clearance) - NOMINAL.c_Z * xi[6]
    log_covariance = ((0.04, -0.05), (-0.05, 0.09))  # ln preload, ln span: sd 0.2 and 0.3, correlation -0.83
    rigid = make_model()
    for preload in (0.5 * F_zZ, 2.0 * F_zZ):  # the face force above the knee, and below it
        span = 0.3 * F_zZ
        exact = rigid._replace(law=rigid.law.with_support(preload, span))
        uncertain = rigid._replace(law=rigid.law.with_support(preload, span, log_covariance))
        assert uncertain.law.support_uncertain and not exact.law.support_uncertain

        added, by_hand = band_added_and_by_hand(
            exact, uncertain, xi, P,
            lambda log_scale: exact.law.with_support(preload * math.exp(log_scale[0]), span * math.exp(log_scale[1])),
            log_covariance,
        )
        if preload > F_zZ:  # below the knee the support passes the force as it is: nothing to add
            assert np.all(added == 0.0)
        else:
            assert by_hand[2, 2] > (0.01 * F_zZ) ** 2  # the axial sd grows by more than 1 % of the face force
            np.testing.assert_allclose(added, by_hand, rtol=1e-6, atol=1e-9 * by_hand[2, 2])
    # a rigid support carries none, whatever covariance the law holds
    assert not rigid.law._replace(support_log_covariance=log_covariance).support_uncertain


@pytest.mark.parametrize("case", CASES)
def test_the_force_band_adds_the_models_own_error_in_contact_only(case):
    model = make_model(random_coeffs(2))
    xi, P = jnp.asarray(CASES[case])[None], jnp.asarray(known_covariance(3))[None]
    noise = CONFIG.noise._replace(process=np.array([1e-14, 1e-14, 1e-14, 1e-8, 2e-7, 3e-7, 5e-8]))
    variance = np.asarray(force_model_variance(model, noise, 1e-4))
    np.testing.assert_allclose(variance, RIG.mass**2 * np.array([2e-7, 3e-7, 5e-8]) / 1e-8, rtol=1e-12)  # m^2 Q_v / h^2
    added = np.asarray(signals(model, Belief(xi, P), variance).force_cov - signals(model, Belief(xi, P)).force_cov)[0]
    expected = np.zeros((3, 3)) if case == "free" else np.diag(variance)
    np.testing.assert_allclose(added, expected, rtol=1e-9, atol=1e-9 * variance.max())


@pytest.mark.parametrize("case", CASES)
def test_eq16_chain_rule_equals_jacfwd_of_f(case):
    model = make_model(random_coeffs(6))
    xi = jnp.array(CASES[case])
    value, Phi = step_with_jacobian(model, xi, 1e-4)
    np.testing.assert_array_equal(np.asarray(value), np.asarray(rk4_step(model, xi, 1e-4)))
    np.testing.assert_allclose(
        np.asarray(Phi), np.asarray(transition_jacobian(model, xi, 1e-4)), rtol=1e-12, atol=1e-15
    )


@pytest.mark.parametrize("case", CASES)
def test_predict_with_rate_is_predict_plus_phi_and_its_jacobian(case):
    model = make_model(random_coeffs(7))
    belief = Belief(jnp.array(CASES[case]), jnp.diag(jnp.array([1e-10, 2e-10, 3e-10, 1.0, 1e-4, 2e-4, 3e-4])))
    Q = jnp.diag(jnp.array([1e-14, 1e-14, 1e-14, 1e-8, 1e-8, 1e-8, 1e-8]))
    expected, expected_Phi = predict(belief, Q, model_transition(model, 1e-4))
    got, Phi, rate, rate_jacobian = predict_with_rate(model, belief, Q, 1e-4)
    np.testing.assert_array_equal(np.asarray(got.mean), np.asarray(expected.mean))
    np.testing.assert_allclose(np.asarray(got.cov), np.asarray(expected.cov), rtol=1e-12, atol=0)
    np.testing.assert_allclose(np.asarray(Phi), np.asarray(expected_Phi), rtol=1e-12, atol=1e-15)
    # phi evaluated inside the compiled stage loop: equal to a direct call to round-off (XLA fuses differently)
    np.testing.assert_allclose(np.asarray(rate), np.asarray(phi(model, belief.mean)), rtol=1e-14, atol=0)
    J = jax.jacfwd(lambda s: phi(model, s))(belief.mean)
    np.testing.assert_allclose(
        np.asarray(rate_jacobian), np.asarray(J), rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(J)))
    )


def test_rk4_converges_with_fourth_order():
    model = make_model(random_coeffs(2, scale=0.1))
    xi0 = jnp.array([0.3e-4, 0.1e-4, -3.08e-4, 0.0, 0.0, 0.0, -0.005])  # stays in axial contact, no switching
    T = 2e-3

    def integrate(n):
        step = jax.jit(lambda s: rk4_step(model, s, T / n))
        s = xi0
        for _ in range(n):
            s = step(s)
        return np.asarray(s)

    reference = integrate(4096)
    assert reference[2] < -RIG.axial_clearance
    errors = [np.abs(integrate(n) - reference)[6] for n in (32, 64, 128)]
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((orders > 3.7) & (orders < 4.3)), orders


def _always_in_axial_contact_model():
    """A linear special case: resting on the axial bearing, no radial contact, no unbalance, no friction."""
    rig = RIG._replace(eccentricity=0.0)
    nominal = NOMINAL._replace(k_ZR=0.0, mu=0.0, k_Z=3e7)  # soft: 65 um static deflection
    return make_model(rig=rig, nominal=nominal)


def test_ekf_equals_independent_linear_kalman_filter():
    model = _always_in_axial_contact_model()
    h, m = 1e-4, RIG.mass
    # Continuous linear dynamics: zddot = -(k_Z (z + z0) + c_Z zdot) / m - g; x, y free.
    A = np.zeros((7, 7))
    A[0, 4] = A[1, 5] = A[2, 6] = 1.0
    k_Z, c_Z = model.nominal.k_Z, model.nominal.c_Z
    A[6, 2], A[6, 6] = -k_Z / m, -c_Z / m
    b = np.zeros(7)
    b[3] = RIG.speed
    b[6] = -k_Z * RIG.axial_clearance / m - RIG.gravity
    hA = h * A
    Ad = np.eye(7) + hA + hA @ hA / 2 + hA @ hA @ hA / 6 + hA @ hA @ hA @ hA / 24  # RK4 of a linear system
    bd = (h * np.eye(7) + h * hA / 2 + h * hA @ hA / 6 + h * hA @ hA @ hA / 24) @ b
    Hm = np.eye(3, 7)
    Q = np.diag([1e-14, 1e-14, 1e-14, 1e-8, 1e-8, 1e-8, 1e-8])
    R = np.eye(3) * 4e-12
    rng = np.random.default_rng(3)
    n = 300
    truth = np.zeros((n, 7))
    truth[0] = [1e-5, -2e-5, -3.5e-4, 0, 0.001, 0, -0.01]
    for k in range(1, n):
        truth[k] = Ad @ truth[k - 1] + bd
    etas = truth[:, :3] + 2e-6 * rng.standard_normal((n, 3))
    assert truth[:, 2].max() < -RIG.axial_clearance - 20e-6, "the linear case must stay in axial contact"
    x, P = np.array([0, 0, -3.5e-4, 0, 0, 0, 0.0]), np.diag([1e-10, 1e-10, 1e-10, 1.0, 1e-4, 1e-4, 1e-4])
    means = []
    for eta in etas:
        S = Hm @ P @ Hm.T + R
        K = P @ Hm.T @ np.linalg.inv(S)
        x = x + K @ (eta - Hm @ x)
        P = (np.eye(7) - K @ Hm) @ P
        means.append(x)
        x, P = Ad @ x + bd, Ad @ P @ Ad.T + Q
    noise = FilterNoise(np.diag(Q), np.diag(R), np.array([1e-10, 1e-10, 1e-10, 1.0, 1e-4, 1e-4, 1e-4]))
    out = ekf(
        model, noise, h, Belief(jnp.array([0, 0, -3.5e-4, 0, 0, 0, 0.0]), jnp.diag(noise.initial)), jnp.asarray(etas)
    )
    means = np.array(means)
    np.testing.assert_allclose(np.asarray(out.filtered.mean)[:, :3], means[:, :3], rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(out.filtered.mean)[:, 4:], means[:, 4:], rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.filtered.cov)[-1], _last_filtered_cov(etas, Ad, bd, Q, R), rtol=1e-8)


def _last_filtered_cov(etas, Ad, bd, Q, R):
    P = np.diag([1e-10, 1e-10, 1e-10, 1.0, 1e-4, 1e-4, 1e-4])
    Hm = np.eye(3, 7)
    for _ in etas[:-1]:
        K = P @ Hm.T @ np.linalg.inv(Hm @ P @ Hm.T + R)
        P = Ad @ ((np.eye(7) - K @ Hm) @ P) @ Ad.T + Q
    K = P @ Hm.T @ np.linalg.inv(Hm @ P @ Hm.T + R)
    return (np.eye(7) - K @ Hm) @ P


def _touchdown_data(model, n=600, seed=4):
    """A trajectory of the model itself with contact switching, plus sensor noise."""
    step = jax.jit(lambda s: rk4_step(model, s, 1e-5))
    xi = jnp.array([2e-6, -1e-6, 0.0, 0.0, 0.0, 0.0, 0.0])
    states = []
    for _ in range(n):
        for _ in range(10):
            xi = step(xi)
        states.append(np.asarray(xi))
    states = np.array(states)
    etas = states[:, :3] + 2e-6 * np.random.default_rng(seed).standard_normal((n, 3))
    return states, etas


def test_ekf_agrees_with_filterpy_on_touchdown_model():
    model = make_model(random_coeffs(5, scale=0.2))
    noise = FilterNoise(CONFIG.noise.process, CONFIG.noise.measurement, CONFIG.noise.initial)
    h = 1e-4
    states, etas = _touchdown_data(model)
    assert (states[:, 2] < -RIG.axial_clearance).any(), "data must include axial contact"
    x0 = np.concatenate([etas[0], np.zeros(4)])
    out = ekf(model, noise, h, Belief(jnp.asarray(x0), jnp.diag(noise.initial)), jnp.asarray(etas))

    f = jax.jit(lambda s: rk4_step(model, s, h))
    F = jax.jit(lambda s: transition_jacobian(model, s, h))

    class TouchdownEKF(ExtendedKalmanFilter):
        def predict_x(self, u=0):
            self.x = np.asarray(f(jnp.asarray(self.x[:, 0])))[:, None]

    peer = TouchdownEKF(dim_x=7, dim_z=3)
    peer.x = x0[:, None].copy()
    peer.P = np.diag(np.asarray(noise.initial))
    peer.Q = np.diag(np.asarray(noise.process))
    peer.R = np.diag(np.asarray(noise.measurement))
    Hm = np.eye(3, 7)
    means = []
    for eta in etas:
        peer.update(eta[:, None], lambda x: Hm, lambda x: Hm @ x)
        means.append(peer.x[:, 0].copy())
        peer.F = np.asarray(F(jnp.asarray(peer.x[:, 0])))
        peer.predict()
    means = np.array(means)
    ours = np.asarray(out.filtered.mean)
    scale = np.abs(means).max(axis=0) + 1e-12
    assert np.max(np.abs(ours - means) / scale) < 1e-9


def test_nan_sample_is_predicted_through_not_used():
    model = make_model()
    states, etas = _touchdown_data(model, n=100)
    etas_gap = etas.copy()
    etas_gap[40] = np.nan
    noise = CONFIG.noise
    init = Belief(jnp.asarray(np.concatenate([etas[0], np.zeros(4)])), jnp.diag(noise.initial))
    out = ekf(model, noise, 1e-4, init, jnp.asarray(etas_gap))
    assert not bool(out.used[40]) and bool(out.used[39])
    np.testing.assert_array_equal(np.asarray(out.filtered.mean[40]), np.asarray(out.prior.mean[40]))
    assert np.all(np.isfinite(np.asarray(out.filtered.mean)))


def test_smoother_beats_filter_on_velocity():
    model = make_model()
    states, etas = _touchdown_data(model, n=600)
    noise = CONFIG.noise
    init = Belief(jnp.asarray(np.concatenate([etas[0], np.zeros(4)])), jnp.diag(noise.initial))
    out = ekf(model, noise, 1e-4, init, jnp.asarray(etas))
    smoothed = rts_smoother(out)
    radial = slice(4, 6)
    err_f = np.sqrt(np.mean((np.asarray(out.filtered.mean)[:, radial] - states[:, radial]) ** 2))
    err_s = np.sqrt(np.mean((np.asarray(smoothed.mean)[:, radial] - states[:, radial]) ** 2))
    assert err_s < err_f
    np.testing.assert_array_equal(np.asarray(smoothed.mean[-1]), np.asarray(out.filtered.mean[-1]))


def _random_covariance(rng, n, scale):
    A = rng.standard_normal((n, n))
    return scale * (A @ A.T + n * np.eye(n))


def test_filter_and_smoother_equal_a_hand_written_linear_rts():
    """A 6-state constant-velocity model, 3 positions measured: the library's filter and RTS smoother
    against the textbook Kalman filter and Rauch-Tung-Striebel recursion written out in numpy."""
    rng = np.random.default_rng(7)
    n, m, N, h = 6, 3, 50, 0.1
    F = np.block([[np.eye(3), h * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
    H = np.eye(m, n)
    Q, R, P0 = _random_covariance(rng, n, 1e-3), _random_covariance(rng, m, 1e-2), _random_covariance(rng, n, 1.0)
    m0 = rng.standard_normal(n)
    x = m0 + np.linalg.cholesky(P0) @ rng.standard_normal(n)
    etas = np.empty((N, m))
    for k in range(N):
        etas[k] = H @ x + np.linalg.cholesky(R) @ rng.standard_normal(m)
        x = F @ x + np.linalg.cholesky(Q) @ rng.standard_normal(n)
    etas[23] = np.nan  # a missing sample: predicted through, not used

    # the reference: prior -> update with eta_k -> predict, as the library's convention
    m_f, P_f = np.empty((N, n)), np.empty((N, n, n))
    mean, cov = m0, P0
    for k in range(N):
        if np.all(np.isfinite(etas[k])):
            S = H @ cov @ H.T + R
            K = cov @ H.T @ np.linalg.inv(S)
            mean = mean + K @ (etas[k] - H @ mean)
            cov = (np.eye(n) - K @ H) @ cov
        m_f[k], P_f[k] = mean, cov
        mean, cov = F @ mean, F @ cov @ F.T + Q
    m_s, P_s = m_f.copy(), P_f.copy()
    for k in range(N - 2, -1, -1):
        m_pred, P_pred = F @ m_f[k], F @ P_f[k] @ F.T + Q
        G = P_f[k] @ F.T @ np.linalg.inv(P_pred)
        m_s[k] = m_f[k] + G @ (m_s[k + 1] - m_pred)
        P_s[k] = P_f[k] + G @ (P_s[k + 1] - P_pred) @ G.T

    transition = lambda xi: (jnp.asarray(F) @ xi, jnp.asarray(F))  # noqa: E731
    initial = Belief(jnp.asarray(m0), jnp.asarray(P0))
    out = extended_kalman_filter(transition, position, jnp.asarray(Q), jnp.asarray(R), initial, jnp.asarray(etas))
    smoothed = rts_smoother(out)
    assert not bool(out.used[23]) and bool(np.all(np.delete(np.asarray(out.used), 23)))

    def relative(ours, reference):
        return np.max(np.abs(np.asarray(ours) - reference)) / np.max(np.abs(reference))

    assert relative(out.filtered.mean, m_f) < 1e-9
    assert relative(out.filtered.cov, P_f) < 1e-9
    assert relative(smoothed.mean, m_s) < 1e-9
    assert relative(smoothed.cov, P_s) < 1e-9
    assert relative(smoothed.mean[:-1], m_f[:-1]) > 1e-3  # the smoother does change the estimates


def test_grid_fills_gaps_and_refuses_off_grid_stamps():
    stamps = np.array([0, 100_000, 200_000, 500_000], dtype=np.int64)
    grid = to_grid(stamps, np.full((4, 3), 1e-5), 1e-4)  # metres inside the sensor range
    assert grid.missing == 2 and grid.etas.shape == (6, 3)
    assert np.isnan(grid.etas[3]).all() and np.isfinite(grid.etas[5]).all()
    with pytest.raises(GridError, match="off the"):
        to_grid(np.array([0, 150_000], dtype=np.int64), np.ones((2, 3)), 1e-4)
    with pytest.raises(GridError, match="not after"):
        to_grid(np.array([0, 100_000, 100_000], dtype=np.int64), np.ones((3, 3)), 1e-4)


def test_drop_detection_finds_onset():
    h, g = 1e-4, 9.81
    t = np.arange(2000) * h
    onset = 500
    z = np.where(np.arange(2000) < onset, 0.0, -0.5 * g * (t - t[onset]) ** 2)
    z = z + 1e-6 * np.random.default_rng(0).standard_normal(2000)
    drop = DropDetector(h, threshold=20e-6, levitated_window=0.005, gravity=g)
    assert abs(drop.onset(z) - onset) <= 3
    assert drop.onset(np.zeros(100)) is None
    assert drop._replace(lead=3.0e-3).onset(z) == drop.onset(z) - 30  # a lead starts the record in levitation


def test_the_adaptive_q_factor_rises_with_the_nis_leaks_back_and_stays_in_its_range():
    """ln(factor): + gain (NIS / 3 - 1), times (1 - leak); held in [0, ln max_scale]; unchanged on an unused sample."""
    adaptation = NoiseAdaptation(gain=0.1, leak=0.01, max_scale=64.0)
    step = lambda log_scale, nis, used=True: float(adapted_log_scale(adaptation, log_scale, nis, used))  # noqa: E731
    assert step(0.0, 27.0) == pytest.approx(0.8)
    assert step(1.0, 3.0) == pytest.approx(0.99)  # a consistent sample: the leak alone
    assert step(0.0, 0.0) == 0.0  # never below Q as fitted
    assert step(4.0, 300.0) == pytest.approx(math.log(64.0))
    assert step(2.0, math.nan, used=False) == 2.0
