"""Drop-test simulator: the truth for tests, demos and benchmarks (never imported by core)."""
from touchdown_ros.core import xla

xla.configure()

import jax  # noqa: E402  (after the XLA options, before any JAX computation)

jax.config.update("jax_enable_x64", True)
