"""Drop-test simulator: the truth for tests, demos and benchmarks (never imported by core)."""
import touchdown_ros.core  # noqa: F401  (sets the XLA options, core.xla, before JAX starts)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
