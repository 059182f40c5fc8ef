"""The touchdown model and EKF the conventional way: numpy model, filterpy's EKF,
central finite-difference Jacobian. The baseline of `ekf_cost.py` and `train_cost.py`."""
from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

# central-difference steps: m for x, y, z; rad for theta; m/s for the velocities
FD_STEPS = np.array([1e-9, 1e-9, 1e-9, 1e-6, 1e-6, 1e-6, 1e-6])
H = np.eye(3, 7)


def numpy_model(model):
    """The same eq. 5-12 model (no add-on effects) written with numpy: xi -> dxi/dt."""
    rig, p, kernel, coeffs = model[:4]
    T_R, T_Z = np.asarray(kernel.T_R), np.asarray(kernel.T_Z)
    a_R, a_Z = np.asarray(coeffs.alpha_R), np.asarray(coeffs.alpha_Z)

    def q(deformation, velocity, T, scale):
        s = np.array([deformation / scale[0], velocity / scale[1]])
        return np.exp(-np.sum((s - T) ** 2, axis=1) / (2 * kernel.width**2))

    def phi(xi):
        x, y, z, theta, xd, yd, zd = xi
        r = math.hypot(x, y)
        c, s = (x / r, y / r) if r > 0 else (1.0, 0.0)
        rdot = c * xd + s * yd
        F_n = F_t = F_z = 0.0
        if r > rig.radial_clearance:
            Q = q(r - rig.radial_clearance, rdot, T_R, np.asarray(kernel.scale_R))
            k_R, c_R, mu = (max(f0 * (1 + Q @ a), 0.0) for f0, a in zip((p.k_R, p.c_R, p.mu), a_R))
            F_n = k_R * (r - rig.radial_clearance) + c_R * rdot
            F_t = mu * F_n
            F_z = -mu * np.sign(zd) * F_n
        if z < -rig.axial_clearance:
            Q = q(-(z + rig.axial_clearance), zd, T_Z, np.asarray(kernel.scale_Z))
            k_Z, c_Z, k_ZR = (max(f0 * (1 + Q @ a), 0.0) for f0, a in zip((p.k_Z, p.c_Z, p.k_ZR), a_Z))
            F_zZ = -k_Z * (z + rig.axial_clearance) - c_Z * zd
            F_t += k_ZR * F_zZ
            F_z += F_zZ
        u = rig.eccentricity * rig.speed**2
        return np.array(
            [xd, yd, zd, rig.speed,
             (-F_n * c + F_t * s) / rig.mass + u * math.cos(theta),
             (-F_n * s - F_t * c) / rig.mass + u * math.sin(theta),
             F_z / rig.mass - rig.gravity]
        )

    return phi


def numpy_rk4(phi, xi, h):
    """Eq. 15: one RK4 step of length h, s."""
    k1 = h * phi(xi)
    k2 = h * phi(xi + 0.5 * k1)
    k3 = h * phi(xi + 0.5 * k2)
    k4 = h * phi(xi + k3)
    return xi + (k1 + 2 * k2 + 2 * k3 + k4) / 6


def fd_jacobian(f, xi, steps=FD_STEPS):
    """Central finite-difference Jacobian of f at xi (7x7)."""
    J = np.empty((7, 7))
    for j in range(7):
        d = np.zeros(7)
        d[j] = steps[j]
        J[:, j] = (f(xi + d) - f(xi - d)) / (2 * steps[j])
    return J


def filterpy_innovations(model, noise, h, etas, initial_mean, initial_cov) -> np.ndarray:
    """(N, 3) one-step prediction errors eta_k - H xi_{k,-} of filterpy's EKF, m."""
    phi = numpy_model(model)

    def f(xi):
        return numpy_rk4(phi, xi, h)

    class Filter(ExtendedKalmanFilter):
        def predict_x(self, u=0):
            self.x = f(self.x[:, 0])[:, None]

    kf = Filter(dim_x=7, dim_z=3)
    kf.x = np.asarray(initial_mean, float)[:, None].copy()
    kf.P = np.asarray(initial_cov, float).copy()
    kf.Q, kf.R = np.diag(noise.process), np.diag(noise.measurement)
    innovations = np.empty((len(etas), 3))
    for k, eta in enumerate(np.asarray(etas)):
        kf.update(eta[:, None], lambda x: H, lambda x: H @ x)
        innovations[k] = kf.y[:, 0]
        kf.F = fd_jacobian(f, kf.x[:, 0])
        kf.predict()
    return innovations
