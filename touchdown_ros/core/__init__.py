"""ROS-free numerical core: pure JAX functions over arrays (float64)."""
from touchdown_ros.core import xla

xla.configure()

import jax  # noqa: E402  (after the XLA options, before any JAX computation)

jax.config.update("jax_enable_x64", True)
