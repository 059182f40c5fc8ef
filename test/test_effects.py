"""Effects framework (core.effects): default Model unchanged, effects add force / m, jit/grad see params."""
import jax
import jax.numpy as jnp
import numpy as np

from touchdown_ros.core import effects as fx
from touchdown_ros.core.dynamics import phi
from touchdown_ros.io.config import load_config


def _user_force(xi, p, rig):
    """A user-written once-per-revolution axial thrust."""
    return jnp.stack([0.0 * xi[2], 0.0 * xi[2], p["F_a"] * jnp.cos(xi[3])])


_user_force.parameters = {"F_a": (500.0, "N", "axial thrust amplitude")}


def test_default_model_has_no_effects_and_axial_load_adds_force():
    model = load_config().model()
    assert len(model.effects) == 0
    xi = jnp.array([0.0, 0.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    base = phi(model, xi)
    loaded = model._replace(effects=fx.build(["axial_load"], {"axial_load": {"force": 2000.0}}))
    out = phi(loaded, xi)
    np.testing.assert_allclose(out[6] - base[6], -2000.0 / model.rig.mass)
    np.testing.assert_allclose(out[:6], base[:6])


def test_dotted_path_effect_is_jittable_and_differentiable():
    model = load_config().model()
    e = fx.build([f"{__name__}:_user_force"])
    assert e.values() == {"_user_force": {"F_a": 500.0}}
    xi = jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])

    def zdd(effects):
        return jax.jit(phi)(model._replace(effects=effects), xi)[6]

    g = jax.grad(zdd)(e)
    np.testing.assert_allclose(g.params[0]["F_a"], 1.0 / model.rig.mass)
    assert fx.regressors(fx.LIBRARY["axial_load"], xi, model.rig).shape == (3, 1)
