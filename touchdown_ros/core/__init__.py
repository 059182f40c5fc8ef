"""ROS-free numerical core: pure JAX functions over arrays (float64)."""
import jax

jax.config.update("jax_enable_x64", True)
