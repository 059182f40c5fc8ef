"""PKBKR coefficient files: human-readable YAML, versioned, tied to one rig, written atomically."""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
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
from touchdown_ros.core.types import (
    AXIAL_PARAMETERS,
    EXACT_PAIR,
    RADIAL_PARAMETERS,
    Coefficients,
    ContactLaw,
    FilterNoise,
    Kernel,
    Model,
    Nominal,
)
from touchdown_ros.io.config import Config

SCHEMA_VERSION = 2  # 2: the file carries its calibrated contact law and constants, kernel and filter noise
KIND = "touchdown_ros/pkbkr_coefficients"
#: Sections whose content the file's results depend on; `content_sha256` covers them.
CONTENT_SECTIONS = ("contact", "kernel", "filter", "coefficients", "effects", "training")


def content_sha256(document: Mapping[str, Any]) -> str:
    """SHA-256 of the file's content sections (CONTENT_SECTIONS) as canonical JSON."""
    content = {name: document.get(name) for name in CONTENT_SECTIONS}
    return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()


def identity_sha256(identity: Any) -> str:
    """SHA-256 of a `model` section, as `Config.fingerprint` computes it from the rig."""
    return hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()


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

    calibrated: Config | None = None  # the rig with the file's contact law, f0, kernel and noise

    def config(self, config: Config) -> Config:
        """The rig as this file calibrated it (contact law and constants, kernel, filter noise)."""
        return self.calibrated if self.calibrated is not None else config

    def model(self, config: Config) -> Model:
        """The estimator's model with the file's calibration, coefficients and effects."""
        return self.config(config).model(self.coeffs, self.effects)

    @property
    def calibration_notes(self) -> list[str]:
        """What stage 1 said the training bags left open (`training.calibration.notes`; none in a file
        written before them)."""
        return list((self.training.extra.get("calibration") or {}).get("notes", []))


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
        "contact": {
            "law": config.law.name,
            "exponent": float(config.law.exponent),
            "support_preload": float(config.law.support_preload),  # N; .inf: a rigid axial support
            "support_span": float(config.law.support_span),  # N, it passes at most preload + span
            # covariance of (ln preload, ln span) from stage 1; the force band carries it above the knee
            "support_log_covariance": [[float(v) for v in row] for row in config.law.support_log_covariance],
            "friction": config.law.friction,
            "slip_velocity": float(config.law.slip_velocity),  # m/s
            "friction_drop": float(config.law.friction_drop),  # mu_s / mu_k - 1 of the ring friction; 0: none
            "stribeck_velocity": float(config.law.stribeck_velocity),  # m/s
            # covariance of (ln friction_drop, ln stribeck_velocity) where stage 1 fitted them, for the force band
            "stribeck_log_covariance": [[float(v) for v in row] for row in config.law.stribeck_log_covariance],
            "units": _contact_units(config),
            **{name: float(value) for name, value in config.nominal._asdict().items()},
            # m, r0 and z0 as stage 1 calibrated them (the rig YAML's rig.*_clearance moved); absent: the YAML's
            **({"radial_clearance": float(config.clearances[0]), "axial_clearance": float(config.clearances[1])}
               if config.clearances is not None else {}),
        },
        "kernel": {
            "width": float(config.kernel.width),
            "scale_R": np.asarray(config.kernel.scale_R, dtype=float).tolist(),
            "scale_Z": np.asarray(config.kernel.scale_Z, dtype=float).tolist(),
            "T_R": np.asarray(config.kernel.T_R, dtype=float).tolist(),
            "T_Z": np.asarray(config.kernel.T_Z, dtype=float).tolist(),
        },
        "filter": {
            "process_noise": np.asarray(config.noise.process, dtype=float).tolist(),
            "measurement_noise": np.sqrt(np.asarray(config.noise.measurement, dtype=float)).tolist(),
            "initial_covariance": np.asarray(config.noise.initial, dtype=float).tolist(),
            # factor on process_noise for the offline (smoothed) estimate; the live node filters with it as it is
            "smoothing_noise_scale": float(config.smoothing_noise_scale),
            # N^2 per axis, the model's own force error in contact on the training bags (the force band's);
            # absent: m^2 Q_v / h^2
            **({"force_model_variance": [float(v) for v in config.force_model_variance]}
               if config.force_model_variance is not None else {}),
        },
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
    # what yaml writes and reads back (tuples become lists): the checksum is of the loaded form
    document = yaml.safe_load(yaml.safe_dump(document, sort_keys=False))
    document["content_sha256"] = content_sha256(document)
    text = (
        "# touchdown_ros PKBKR coefficients (paper eq. 9, 18). rig_fingerprint ties the file to its rig (model);\n"
        "# content_sha256 covers contact, kernel, filter, coefficients, effects and training: "
        "an edited file is refused.\n"
    ) + yaml.safe_dump(document, sort_keys=False, width=120)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(handle, "w") as stream:
            stream.write(text)
            stream.flush()
            os.fsync(stream.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)  # as open() would create it (mkstemp makes it 0600)
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
    except IsADirectoryError:
        raise CoefficientFileError(f"{path}: is a directory, not a coefficient file") from None
    except OSError as error:
        raise CoefficientFileError(f"{path}: cannot read the coefficient file: {error.strerror or error}") from None
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise CoefficientFileError(f"{path}: not a readable YAML coefficient file: {error}") from None
    if not isinstance(document, dict) or document.get("kind") != KIND:
        raise CoefficientFileError(f"{path}: not a touchdown_ros coefficient file (kind must be {KIND!r})")
    if document.get("schema_version") != SCHEMA_VERSION:
        raise CoefficientFileError(
            f"{path}: schema version {document.get('schema_version')!r}, this software reads {SCHEMA_VERSION}"
        )
    if "rig_fingerprint" not in document:
        raise CoefficientFileError(
            f"{path}: no rig_fingerprint: the file cannot be tied to a rig (restore the line or retrain)"
        )
    if not isinstance(document.get("model"), dict) or identity_sha256(document["model"]) != document["rig_fingerprint"]:
        raise CoefficientFileError(
            f"{path}: the model section does not match the file's rig_fingerprint: it was edited after training "
            "(restore it or retrain)"
        )
    if document.get("rig_fingerprint") != config.fingerprint():
        differences = _differences(document.get("model", {}), config.model_identity())
        raise CoefficientFileError(
            f"{path}: made for another rig than {config.source}; differs in: " + "; ".join(differences[:8])
        )
    calibrated = _calibrated_config(path, document, config)
    table = document.get("coefficients")
    kernel = calibrated.kernel
    sizes = {
        **{name: len(kernel.T_R) for name in RADIAL_PARAMETERS},
        **{name: len(kernel.T_Z) for name in AXIAL_PARAMETERS},
    }
    rows = {}
    for name, size in sizes.items():
        value = table.get(name) if isinstance(table, dict) else None
        try:
            row = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            row = np.empty(0)
        if row.shape != (size,) or not np.isfinite(row).all():
            raise CoefficientFileError(
                f"{path}: coefficients.{name} must be {size} finite numbers (one per kernel centre)"
            )
        rows[name] = row
    alpha_R = np.stack([rows[name] for name in RADIAL_PARAMETERS])
    alpha_Z = np.stack([rows[name] for name in AXIAL_PARAMETERS])
    training = document.get("training") or {}
    if not isinstance(training, dict):
        raise CoefficientFileError(f"{path}: 'training' must be a mapping")
    regularisation = training.get("regularisation", 0.0)
    if (
        isinstance(regularisation, bool)
        or not isinstance(regularisation, (int, float))
        or not np.isfinite(regularisation)
        or regularisation < 0
    ):
        raise CoefficientFileError(
            f"{path}: training.regularisation must be a finite number >= 0, got {regularisation!r}"
        )
    effects = _load_effects(path, document.get("effects"))
    if "content_sha256" not in document:
        raise CoefficientFileError(
            f"{path}: no content_sha256: written by an earlier version or edited; "
            "its content cannot be checked (retrain)"
        )
    if document["content_sha256"] != content_sha256(document):
        raise CoefficientFileError(
            f"{path}: the content (sections {', '.join(CONTENT_SECTIONS)}) was edited after training: its "
            "content_sha256 does not match; restore the file or retrain"
        )
    record = TrainingRecord(
        bags=training.get("bags", ()),
        regularisation=training.get("regularisation", 0.0),
        final_loss=training.get("final_loss"),
        steps=training.get("steps", 0),
        extra={k: v for k, v in training.items() if k not in ("bags", "regularisation", "final_loss", "steps")},
    )
    return CoefficientFile(Coefficients(alpha_R, alpha_Z), record, document, effects, calibrated)


def _contact_units(config: Config) -> str:
    if config.law.name == "linear":
        return "F = k d + c d_dot: k_R, k_Z N/m; c_R, c_Z N s/m; mu, k_ZR 1"
    n = f"{config.law.exponent:.4g}"
    if config.law.name == "kelvin_voigt":
        return f"F = k d^{n} + c d_dot: k_R, k_Z N/m^{n}; c_R, c_Z N s/m; mu, k_ZR 1"
    return f"F = d^{n} (k + c d_dot): k_R, k_Z N/m^{n}; c_R, c_Z N s/m^({n}+1); mu, k_ZR 1"


def _array(
    path: Path, document: Mapping[str, Any], key: str, shape: tuple[int | None, ...], positive: bool = False
) -> np.ndarray:
    section, _, name = key.partition(".")
    value = (document.get(section) or {}).get(name) if isinstance(document.get(section), dict) else None
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        array = np.empty(0)
    fits = array.ndim == len(shape) and all(want is None or got == want for got, want in zip(array.shape, shape))
    if not fits or array.size == 0 or not np.isfinite(array).all() or (positive and (array <= 0).any()):
        what = "positive " if positive else ""
        raise CoefficientFileError(
            f"{path}: {key} must be {what}finite numbers of shape {tuple('n' if s is None else s for s in shape)}"
        )
    return array


def _log_covariance(path: Path, contact: Mapping[str, Any], key: str, of: str) -> tuple[tuple[float, float], ...]:
    """contact.`key`: a symmetric positive semi-definite (2, 2) covariance of the logarithms `of` (named in the
    message); absent (files before it): EXACT_PAIR, the pair taken as exact."""
    if key not in contact:
        return EXACT_PAIR
    covariance = _array(path, {"contact": contact}, f"contact.{key}", (2, 2))
    symmetric = np.allclose(covariance, covariance.T)
    if not symmetric or np.linalg.eigvalsh(covariance).min() < -1e-9 * np.abs(covariance).max():
        raise CoefficientFileError(
            f"{path}: contact.{key} must be a symmetric positive semi-definite 2 x 2 matrix (the covariance of {of})"
        )
    return tuple(tuple(float(v) for v in row) for row in covariance)


def _calibrated_config(path: Path, document: Mapping[str, Any], config: Config) -> Config:
    """The rig with the file's contact law and constants, kernel and filter noise."""
    contact = document.get("contact")
    if not isinstance(contact, dict):
        raise CoefficientFileError(f"{path}: no 'contact' section (law and calibrated constants)")
    try:
        law = ContactLaw.of(str(contact.get("law")), float(contact.get("exponent", 1.0)))
    except (TypeError, ValueError) as error:
        raise CoefficientFileError(f"{path}: contact.law / contact.exponent: {error}") from None
    preload, span = contact.get("support_preload", np.inf), contact.get("support_span", np.inf)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in (preload, span)):
        raise CoefficientFileError(
            f"{path}: contact.support_preload and contact.support_span must be numbers > 0 N (.inf: rigid)"
        )
    law = law.with_support(
        float(preload), float(span), _log_covariance(path, contact, "support_log_covariance", "ln preload, ln span")
    )
    slip_velocity = contact.get("slip_velocity", 0.01)  # files before friction models: the paper's friction
    if isinstance(slip_velocity, bool) or not isinstance(slip_velocity, (int, float)):
        raise CoefficientFileError(f"{path}: contact.slip_velocity must be a number > 0 m/s")
    try:
        law = law.with_friction(str(contact.get("friction", "paper")), float(slip_velocity))
    except ValueError as error:
        raise CoefficientFileError(f"{path}: contact.friction / contact.slip_velocity: {error}") from None
    drop, stribeck_velocity = contact.get("friction_drop", 0.0), contact.get("stribeck_velocity", 0.02)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (drop, stribeck_velocity)):
        raise CoefficientFileError(f"{path}: contact.friction_drop and contact.stribeck_velocity must be numbers")
    try:
        law = law.with_stribeck(
            float(drop), float(stribeck_velocity),
            _log_covariance(path, contact, "stribeck_log_covariance", "ln friction_drop, ln stribeck_velocity"),
        )
    except ValueError as error:
        raise CoefficientFileError(f"{path}: contact.friction_drop / contact.stribeck_velocity: {error}") from None
    values = []
    for name in Nominal._fields:
        value = contact.get(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
            raise CoefficientFileError(f"{path}: contact.{name} must be a finite number >= 0")
        values.append(float(value))
    width = (document.get("kernel") or {}).get("width") if isinstance(document.get("kernel"), dict) else None
    if isinstance(width, bool) or not isinstance(width, (int, float)) or not width > 0:
        raise CoefficientFileError(f"{path}: kernel.width must be a number > 0")
    kernel = Kernel(
        T_R=_array(path, document, "kernel.T_R", (None, 2)),
        T_Z=_array(path, document, "kernel.T_Z", (None, 2)),
        width=float(width),
        scale_R=_array(path, document, "kernel.scale_R", (2,), positive=True),
        scale_Z=_array(path, document, "kernel.scale_Z", (2,), positive=True),
    )
    size = law.state_size
    filter_section = document.get("filter") if isinstance(document.get("filter"), dict) else {}
    for key in ("filter.process_noise", "filter.initial_covariance"):
        diagonal = filter_section.get(key.partition(".")[2])
        if isinstance(diagonal, list) and len(diagonal) != size:
            raise CoefficientFileError(
                f"{path}: {key} has {len(diagonal)} values; contact.friction {law.friction} has a state of {size}"
            )
    noise = FilterNoise(
        process=_array(path, document, "filter.process_noise", (size,)),
        measurement=_array(path, document, "filter.measurement_noise", (3,), positive=True) ** 2,
        initial=_array(path, document, "filter.initial_covariance", (size,)),
    )
    scale = document["filter"].get("smoothing_noise_scale", 1.0)  # files before it: Q as it is
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not np.isfinite(scale) or scale <= 0:
        raise CoefficientFileError(f"{path}: filter.smoothing_noise_scale must be a number > 0, got {scale!r}")
    variance = None
    if "force_model_variance" in document["filter"]:  # files before it: m^2 Q_v / h^2
        array = _array(path, document, "filter.force_model_variance", (3,))
        if (array < 0.0).any():
            raise CoefficientFileError(f"{path}: filter.force_model_variance must be 3 numbers >= 0 (N^2 per axis)")
        variance = tuple(float(v) for v in array)
    return config.calibrated(Nominal(*values), law, kernel, noise, float(scale), variance, _clearances(path, contact))


def _clearances(path: Path, contact: Mapping[str, Any]) -> tuple[float, float] | None:
    """contact.radial_clearance and contact.axial_clearance (m), both or neither (files before 2026-11-29, or
    trained with training.clearance_tolerance 0: the rig YAML's)."""
    names = ("radial_clearance", "axial_clearance")
    present = [n for n in names if n in contact]
    if not present:
        return None
    values = [contact.get(n) for n in names]
    if len(present) < 2 or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0 for v in values
    ):
        raise CoefficientFileError(
            f"{path}: contact.radial_clearance and contact.axial_clearance must both be numbers > 0 m (or both absent)"
        )
    return float(values[0]), float(values[1])


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
