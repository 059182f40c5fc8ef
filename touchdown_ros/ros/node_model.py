"""The live node's model: its coefficient file, or the constant model when there is none or it is
refused, with the effects that `node.conditions` switches on; and what the health diagnostics say of it."""
from __future__ import annotations

from typing import Callable, NamedTuple

from touchdown_ros.core.effects import gates_for
from touchdown_ros.core.types import Model
from touchdown_ros.io.coefficients import CoefficientFileError, load_coefficients, sha256_of
from touchdown_ros.io.config import Config
from touchdown_ros.ros.health import ERROR, OK, WARN, ModelInfo


class NodeModel(NamedTuple):
    config: Config  # the rig with the coefficient file's calibrated law, constants, kernel and noise
    model: Model  # effects gated by node.conditions
    info: ModelInfo  # the "model" diagnostic


def load_node_model(config: Config, log_error: Callable[[str], None], log_warning: Callable[[str], None]) -> NodeModel:
    """The model of `node.coefficients`; a bad coefficient file falls back to the constant model (the
    rig's effects) and an ERROR diagnostic, a conditional effect left off by node.conditions to a WARN."""
    config, model, info = _coefficients(config, config.node.coefficients, log_error)
    # the node has no bag metadata: node.conditions says which conditional effects act now
    gates = gates_for(model.effects, {name: "true" for name in config.node.conditions})
    model = model._replace(effects=model.effects.with_gates(gates))
    off = [f"{e.name} (when {e.when})" for e, gate in zip(model.effects.effects, gates) if gate == 0.0]
    if off and info.level == OK:
        why = (f"conditional effect(s) off: {', '.join(off)}; node.conditions {list(config.node.conditions)} "
               "does not name their condition (set node.conditions:=[...] when it is on in this run)")
        log_warning(why)
        info = ModelInfo(WARN, f"{info.message}; {why}", {**info.values, "effects_off": ", ".join(off)})
    return NodeModel(config, model, info)


def _coefficients(config: Config, path: str, log_error: Callable[[str], None]) -> NodeModel:
    identity = {"rig_fingerprint": config.fingerprint()[:16]}
    if not path:
        return NodeModel(config, config.model(), ModelInfo(OK, "constant model (node.coefficients is empty)",
                                                           {"model": "constant", "coefficients": "", **identity}))
    try:
        loaded = load_coefficients(path, config)
    except (CoefficientFileError, OSError, ValueError) as error:  # missing, unreadable, another rig
        log_error(f"{error}; running the constant model instead")
        return NodeModel(config, config.model(), ModelInfo(
            ERROR, f"coefficient file refused, running the constant model: {error}",
            {"model": "constant (fallback)", "coefficients": path, "error": str(error), **identity}))
    config = loaded.config(config)
    # what the training bags left open (a support's cap, the friction): alarm and logging nodes see it here
    notes = {"calibration_notes": " | ".join(loaded.calibration_notes)} if loaded.calibration_notes else {}
    info = ModelInfo(
        OK,
        f"PKBKR coefficients from {path}",
        {"model": "pkbkr", "coefficients": path, "coefficients_sha256": sha256_of(path)[:16],
         "trained_on_bags": len(loaded.training.bags), "contact_law": config.law.label, **notes, **identity},
    )
    return NodeModel(config, loaded.model(config), info)
