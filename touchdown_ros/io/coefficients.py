"""PKBKR coefficient files: human-readable YAML, versioned, tied to one rig, written atomically."""
from __future__ import annotations

import datetime as _dt
import hashlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from touchdown_ros import __version__
from touchdown_ros.core.effects import Effects
from touchdown_ros.core.effects import resolve as resolve_effect
from touchdown_ros.core.types import AXIAL_PARAMETERS, RADIAL_PARAMETERS, Coefficients, Model
from touchdown_ros.io.config import Config

SCHEMA_VERSION = 1
KIND = "touchdown_ros/pkbkr_coefficients"


class CoefficientFileError(ValueError):
    """A coefficient file is unreadable, of another schema, or made for another rig."""


@dataclass(frozen=True)
class TrainingRecord:
    """How a coefficient set was obtained."""

    bags: Sequence[Mapping[str, str]] = ()  # [{"path": ..., "sha256": ...}]
    regularisation: float = 0.0  # lambda of eq. 18
    final_loss: float | None = None
    steps: int = 0
    extra: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class CoefficientFile:
    coeffs: Coefficients
    training: TrainingRecord
    document: Mapping[str, Any]
    effects: Effects = Effects()  # the add-on effects the coefficients were fitted with

    def model(self, config: Config) -> Model:
        """The estimator's model with these coefficients and effects."""
        return config.model(self.coeffs, self.effects)


def sha256_of(path: str | Path) -> str:
    """SHA-256 of a file, or of every file of a directory in name order (a rosbag2 bag)."""
    path = Path(path)
    digest = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for file in files:
        digest.update(file.relative_to(path).as_posix().encode() if path.is_dir() else b"")
        with open(file, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def save_coefficients(
    path: str | Path, coeffs: Coefficients, config: Config, training: TrainingRecord, effects: Effects | None = None
) -> Path:
    """Write the coefficient file atomically (temporary file, then rename); effects default to the rig's."""
    path = Path(path)
    effects = config.effects if effects is None else effects
    alpha_R, alpha_Z = np.asarray(coeffs.alpha_R), np.asarray(coeffs.alpha_Z)
    document = {
        "kind": KIND,
        "schema_version": SCHEMA_VERSION,
        "software_version": __version__,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "rig_fingerprint": config.fingerprint(),
        "model": config.model_identity(),
        "coefficients": {
            "units": "dimensionless, relative to each nominal value: p(s) = f0 * (1 + Q(s, T) alpha)",
            **{name: alpha_R[i].tolist() for i, name in enumerate(RADIAL_PARAMETERS)},
            **{name: alpha_Z[i].tolist() for i, name in enumerate(AXIAL_PARAMETERS)},
        },
        "effects": {
            effect.name: {"source": effect.source or effect.name, "when": effect.when, "parameters": values}
            for effect, values in zip(effects.effects, effects.values().values())
        },
        "training": {
            "regularisation": float(training.regularisation),
            "final_loss": None if training.final_loss is None else float(training.final_loss),
            "steps": int(training.steps),
            "bags": [dict(b) for b in training.bags],
            **dict(training.extra),
        },
    }
    text = "# touchdown_ros PKBKR coefficients (paper eq. 9, 18). Edit at your own risk.\n" + yaml.safe_dump(
        document, sort_keys=False, width=120
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(handle, "w") as stream:
            stream.write(text)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def load_coefficients(path: str | Path, config: Config) -> CoefficientFile:
    """Read a coefficient file and check it belongs to this rig; refuse with what differs."""
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise CoefficientFileError(f"{path}: coefficient file not found") from None
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise CoefficientFileError(f"{path}: not a readable YAML coefficient file: {error}") from None
    if not isinstance(document, dict) or document.get("kind") != KIND:
        raise CoefficientFileError(f"{path}: not a touchdown_ros coefficient file (kind must be {KIND!r})")
    if document.get("schema_version") != SCHEMA_VERSION:
        raise CoefficientFileError(
            f"{path}: schema version {document.get('schema_version')!r}, this software reads {SCHEMA_VERSION}"
        )
    if document.get("rig_fingerprint") != config.fingerprint():
        differences = _differences(document.get("model", {}), config.model_identity())
        raise CoefficientFileError(
            f"{path}: made for another rig than {config.source}; differs in: " + "; ".join(differences[:8])
        )
    table = document.get("coefficients")
    sizes = {**{name: len(config.kernel.T_R) for name in RADIAL_PARAMETERS}, **{name: len(config.kernel.T_Z) for name in AXIAL_PARAMETERS}}
    rows = {}
    for name, size in sizes.items():
        value = table.get(name) if isinstance(table, dict) else None
        try:
            row = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            row = np.empty(0)
        if row.shape != (size,) or not np.isfinite(row).all():
            raise CoefficientFileError(f"{path}: coefficients.{name} must be {size} finite numbers (one per kernel centre)")
        rows[name] = row
    alpha_R = np.stack([rows[name] for name in RADIAL_PARAMETERS])
    alpha_Z = np.stack([rows[name] for name in AXIAL_PARAMETERS])
    training = document.get("training") or {}
    record = TrainingRecord(
        bags=training.get("bags", ()),
        regularisation=training.get("regularisation", 0.0),
        final_loss=training.get("final_loss"),
        steps=training.get("steps", 0),
        extra={k: v for k, v in training.items() if k not in ("bags", "regularisation", "final_loss", "steps")},
    )
    return CoefficientFile(Coefficients(alpha_R, alpha_Z), record, document, _load_effects(path, document.get("effects")))


def _load_effects(path: Path, table: Any) -> Effects:
    """The `effects` section: {name: {source, parameters: {parameter: value}}}."""
    if not table:
        return Effects()
    if not isinstance(table, dict):
        raise CoefficientFileError(f"{path}: 'effects' must map effect names to their source and parameters")
    chosen, values = [], []
    for name, entry in table.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("parameters"), dict):
            raise CoefficientFileError(f"{path}: effects.{name} needs 'source' and 'parameters'")
        try:
            effect = resolve_effect(str(entry.get("source", name)), name=name, when=str(entry.get("when") or ""))
        except ValueError as error:
            raise CoefficientFileError(f"{path}: effects.{name}: {error}") from None
        given = entry["parameters"]
        if set(given) != set(effect.parameters):
            raise CoefficientFileError(
                f"{path}: effects.{name} has parameters {sorted(given)}, the effect expects {sorted(effect.parameters)}"
            )
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in given.values()):
            raise CoefficientFileError(f"{path}: effects.{name}: every parameter must be a finite number")
        chosen.append(effect)
        values.append({k: float(given[k]) for k in effect.parameters})
    return Effects(tuple(chosen), tuple(values))


def _differences(saved: Any, current: Any, prefix: str = "") -> list[str]:
    if isinstance(saved, dict) and isinstance(current, dict):
        found = []
        for key in sorted(set(saved) | set(current)):
            found += _differences(saved.get(key), current.get(key), f"{prefix}{key}.")
        return found
    if saved != current:
        shown = lambda v: f"{len(v)} values" if isinstance(v, list) and len(v) > 4 else repr(v)  # noqa: E731
        return [f"{prefix.rstrip('.')}: file {shown(saved)}, rig {shown(current)}"]
    return []
