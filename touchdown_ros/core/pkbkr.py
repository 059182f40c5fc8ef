"""Prior Knowledge Based Kernel Regression of the contact parameters (paper eq. 1-3, 9-10).

Each parameter is p(s) = f0 * (1 + Q(s, T) alpha), floored at 0 so stiffness, damping
and friction stay physically admissible. alpha is dimensionless (relative to the
nominal value f0), so one regularisation weight lambda suits all six parameters and
all alpha = 0 gives exactly the constant model. The RKHS distance of eq. 18 between
p / f0 - 1 and 0 is alpha^T K alpha with K = Q(T, T).
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array
from jax.scipy.linalg import solve_triangular

from touchdown_ros.core.types import Coefficients, Kernel, Nominal


def gaussian_kernel(s: Array, T: Array, width: float) -> Array:
    """Q(s, T) of eq. 1: row of exp(-|s - t_i|^2 / (2 width^2)) over the centres T (m, 2)."""
    squared_distance = jnp.sum((s[..., None, :] - T) ** 2, axis=-1)
    return jnp.exp(-squared_distance / (2.0 * width**2))


def normalise(scale: Array, deformation: Array, velocity: Array) -> Array:
    """rho or zeta of eq. 10 in normalised units: (deformation, velocity) / scale (m, m/s)."""
    return jnp.stack([deformation / scale[0], velocity / scale[1]], axis=-1)


def _learned(f0: Array, Q: Array, alpha: Array) -> Array:
    return jnp.maximum(f0 * (1.0 + Q @ alpha), 0.0)


def _parameters(
    kernel: Kernel, T: Array, scale: Array, nominal: tuple, alpha: Array, deformation: Array, velocity: Array
):
    Q = gaussian_kernel(normalise(scale, deformation, velocity), T, kernel.width)
    return tuple(_learned(f0, Q, a) for f0, a in zip(nominal, alpha))


def radial_parameters(
    kernel: Kernel, nominal: Nominal, coeffs: Coefficients, deformation: Array, velocity: Array
) -> tuple[Array, Array, Array]:
    """k_R, c_R, mu at rho = (r - r0, rdot) (eq. 9a-c)."""
    f0 = (nominal.k_R, nominal.c_R, nominal.mu)
    return _parameters(kernel, kernel.T_R, kernel.scale_R, f0, coeffs.alpha_R, deformation, velocity)


def axial_parameters(
    kernel: Kernel, nominal: Nominal, coeffs: Coefficients, deformation: Array, velocity: Array
) -> tuple[Array, Array, Array]:
    """k_Z, c_Z, k_ZR at zeta (eq. 9d-f); deformation = -(z + z0), the compression, >= 0 in contact."""
    f0 = (nominal.k_Z, nominal.c_Z, nominal.k_ZR)
    return _parameters(kernel, kernel.T_Z, kernel.scale_Z, f0, coeffs.alpha_Z, deformation, velocity)


def gram(kernel: Kernel) -> tuple[Array, Array]:
    """K_R = Q(T_R, T_R) and K_Z = Q(T_Z, T_Z): the RKHS metrics of the coefficients."""
    K_R = gaussian_kernel(kernel.T_R, kernel.T_R, kernel.width)
    K_Z = gaussian_kernel(kernel.T_Z, kernel.T_Z, kernel.width)
    return K_R, K_Z


def rkhs_distance(kernel: Kernel, coeffs: Coefficients) -> Array:
    """Sum over the six parameters of ||Q alpha_k||_H^2 = alpha_k^T K alpha_k (eq. 18 penalty)."""
    K_R, K_Z = gram(kernel)
    radial = jnp.einsum("pi,ij,pj->", coeffs.alpha_R, K_R, coeffs.alpha_R)
    axial = jnp.einsum("pi,ij,pj->", coeffs.alpha_Z, K_Z, coeffs.alpha_Z)
    return radial + axial


#: Added to K's unit diagonal before its Cholesky factor, so that centres that coincide still factor.
GRAM_JITTER = 1.0e-9


class Whitening(NamedTuple):
    """Cholesky factors K = L L^T of the two centre sets. In the coordinates beta_k = L^T alpha_k
    the RKHS distance is |beta|^2 and the loss is far better conditioned for L-BFGS
    (docs/calibration.md, "Stage 2 in whitened coordinates")."""

    L_R: Array
    L_Z: Array


def whitening(kernel: Kernel) -> Whitening:
    def factor(K: Array) -> Array:
        return jnp.linalg.cholesky(K + GRAM_JITTER * jnp.eye(K.shape[0]))

    K_R, K_Z = gram(kernel)
    return Whitening(factor(K_R), factor(K_Z))


def whitened(w: Whitening, coeffs: Coefficients) -> Coefficients:
    """beta_k = L^T alpha_k of every row of the coefficients."""
    return Coefficients(coeffs.alpha_R @ w.L_R, coeffs.alpha_Z @ w.L_Z)


def coloured(w: Whitening, beta: Coefficients) -> Coefficients:
    """alpha_k = L^-T beta_k: the coefficients whose whitened coordinates are beta."""

    def solve(L: Array, rows: Array) -> Array:
        return solve_triangular(L, rows.T, lower=True, trans="T").T

    return Coefficients(solve(w.L_R, beta.alpha_R), solve(w.L_Z, beta.alpha_Z))
