"""Drop-test simulator: the truth for tests, demos and benchmarks (never imported by core)."""
import jax

jax.config.update("jax_enable_x64", True)
