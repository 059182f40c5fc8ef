"""Typed reading of flat, dotted ROS parameters (`rig.mass`): each value checked, a refusal names the key."""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np


class ConfigError(ValueError):
    """The rig YAML is missing, malformed or holds an invalid value."""


def flatten_parameters(tree: Mapping[str, Any], prefix: str = ""):
    """(dotted name, value) of every leaf of a nested parameter tree (`rig: {mass: ...}` -> `rig.mass`)."""
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            yield from flatten_parameters(value, name + ".")
        else:
            yield name, value


class ParameterReader:
    """Takes typed values out of the flat parameter dict and remembers what it used."""

    def __init__(self, flat: Mapping[str, Any], source: str):
        self.flat, self.source, self.used = flat, source, set()

    def _get(self, key: str, default: Any = ...) -> Any:
        if key not in self.flat:
            if default is ...:
                raise ConfigError(f"{self.source}: missing parameter '{key}'")
            return default
        self.used.add(key)
        return self.flat[key]

    def number(self, key: str, default: Any = ..., positive: bool = False, non_negative: bool = False) -> float:
        value = self._get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(
                f"{self.source}: parameter '{key}' must be a finite number, got {value!r}{number_text_hint(value)}"
            )
        if positive and value <= 0:
            raise ConfigError(f"{self.source}: parameter '{key}' must be > 0, got {value!r}")
        if non_negative and value < 0:
            raise ConfigError(f"{self.source}: parameter '{key}' must be >= 0, got {value!r}")
        return float(value)

    def numbers(self, key: str, length: int | None = None, non_negative: bool = False) -> np.ndarray:
        value = self._get(key)
        if not isinstance(value, list) or not value or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value
        ):
            why = ""
            for i, entry in enumerate(value if isinstance(value, list) else [], 1):
                if hint := number_text_hint(entry):  # the first entry YAML read as text
                    why = f"; entry {i} is {entry!r}{hint}"
                    break
            raise ConfigError(f"{self.source}: parameter '{key}' must be a non-empty list of finite numbers{why}")
        if length is not None and len(value) != length:
            raise ConfigError(f"{self.source}: parameter '{key}' must have {length} values, got {len(value)}")
        array = np.asarray(value, dtype=float)
        if non_negative and (array < 0).any():
            raise ConfigError(f"{self.source}: parameter '{key}' must not be negative")
        return array

    def text(self, key: str, default: str, allow_empty: bool = False) -> str:
        value = self._get(key, default)
        if not isinstance(value, str) or not (value or allow_empty):
            raise ConfigError(f"{self.source}: parameter '{key}' must be a non-empty string")
        return value

    def flag(self, key: str, default: bool) -> bool:
        value = self._get(key, default)
        if not isinstance(value, bool):
            raise ConfigError(f"{self.source}: parameter '{key}' must be true or false, got {value!r}")
        return value

    def choice(self, key: str, default: str, allowed: tuple[str, ...]) -> str:
        value = self.text(key, default)
        if value not in allowed:
            raise ConfigError(f"{self.source}: parameter '{key}' must be one of {', '.join(allowed)}, got {value!r}")
        return value

    def integer(self, key: str, default: Any = ..., minimum: int = 1, maximum: int | None = None) -> int:
        value = self._get(key, default)
        if (isinstance(value, bool) or not isinstance(value, int) or value < minimum
                or maximum is not None and value > maximum):
            bounds = f">= {minimum}" if maximum is None else f"in {minimum}..{maximum}"
            raise ConfigError(f"{self.source}: parameter '{key}' must be an integer {bounds}, got {value!r}")
        return value

    def integers(self, key: str, default: tuple[int, ...], minimum: int = 1) -> tuple[int, ...]:
        value = self._get(key, list(default))
        if not isinstance(value, (list, tuple)) or not value or not all(
            isinstance(v, int) and not isinstance(v, bool) and v >= minimum for v in value
        ):
            raise ConfigError(f"{self.source}: parameter '{key}' must be a non-empty list of integers >= {minimum}")
        return tuple(value)


def number_text_hint(value: Any) -> str:
    """Why YAML read a number as text, for an error message: its float needs a decimal point and a signed exponent
    (YAML 1.1); empty for anything else."""
    if not (isinstance(value, str) and _looks_numeric(value)):
        return ""
    return (" (YAML reads a number as text unless it has a decimal point and a signed exponent: write 1.0e+8 or "
            "1.0e-5, not 1.0e8, 1e+8 or 1e-5)")


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
