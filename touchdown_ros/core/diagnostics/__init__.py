"""Model diagnostics (issue #5): where the model fails and which physical effect it lacks.

Pure functions over arrays (no ROS, no files), one job per module:

- `breakdown`: contact phases (`PHASES`), the deformations along states, errors by label, by
  window and over the (deformation, velocity) planes (impact numbers: `core.impacts`).
- `prediction`: the model's own prediction quality (one-step and k-step, fit %), per axis, phase
  and impact, and the after / before ratios of two models.
- `residuals`: whiteness and cross-correlation tests of the innovations (99 % band).
- `missing_force`: the disturbance smoother, an EKF + RTS smoother of the state augmented with a
  force on the rotor: the force the model lacks, with its standard deviation.
- `regressors`: d force / d parameters of the model's coefficients and of each candidate effect.
- `frols`: the candidates ranked by how much of the missing force they explain (FROLS).
- `signature`: the missing force's spectrum, harmonics and correlations, when nothing explains it.

Candidates fitted and judged on held-out data: `core.selection`.
"""
