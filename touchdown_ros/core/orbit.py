"""The rotor's speed and the bearing's centre read from its orbit, and effects started there.

A rotor that has settled on the bore whirls forward about the bearing's centre at about its own
speed (the ring turns with it, the slip is a fraction of a per cent), so the angle of the measured
(x, y) advances at the rotor's speed: a braked rotor's decay can be read off the displacements
before any model is fitted. Stage 1's fit of a speed effect's parameters has many local minima
(the ring's friction changes sign with the slip the speed sets), and from the library's defaults
it stays in one: `speed_effects_from_orbits` gives it a start read from the data instead.

The same whirl goes round a circle about the bearing's centre: where the sensors read that centre
off their zero (a sensor offset, or a bearing mounted off the sensors' axis, which the model cannot
tell apart), the centre of the measured orbit is the offset (`orbit_centre`). From zero a sensor
offset's fit moves only with the contact constants, and can stop on the way (drawn_1_1, 30 um in x:
3.3 um, 2026-12-07): `sensor_offsets_from_orbits` starts it at the orbit's centre.
"""
from __future__ import annotations

from typing import Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares

from touchdown_ros.core.effects import SPEED, Effect, Effects
from touchdown_ros.core.types import STATE_SIZE, THETA

#: s, the window over which one orbit speed is read (about 40 revolutions' worth of angle at 5000 rpm).
WINDOW = 5.0e-3
#: A window counts when the rotor is on the bore: its radius at least this share of the record's
#: 95th percentile ...
ON_BORE = 0.8
#: ... and steady: its radius varies by at most this share of its mean within the window.
STEADY = 0.1
#: The whirl has spun up once a window's speed is within this share of the fastest window's.
SPUN_UP = 0.01
#: Orbit speeds a speed effect may be fitted to: at least this many windows ...
MIN_WINDOWS = 4
#: ... over at least this span (s) between the first and the last; and the orbits show the effect when
#: its fit leaves at most this share of the misfit of a constant speed (the scatter of a steady whirl).
MIN_SPAN = 0.02
SHOWN = 0.25
#: The on-bore samples go round the bore when each of this many equal sectors of angle about the orbit's
#: centre holds at least `SECTOR_SHARE` of its even share of them (a rotor resting on one side does not).
SECTORS = 12
SECTOR_SHARE = 0.2
#: A centre off the sensors' zero shows an offset on an axis when it lies this many standard errors of the
#: records' centres from zero, and further than the on-bore samples scatter about their circle (the
#: rotor's bouncing put one record's centre 0-9 um from zero on rigs without an offset, 2026-12-07).
CENTRE_SIGNIFICANCE = 3.0
#: The sensor offsets an orbit's centre starts: effect -> axis of the centre (x 0, y 1).
OFFSET_AXES = {"sensor_offset_x": 0, "sensor_offset_y": 1}


class OrbitSpeeds(NamedTuple):
    """The orbit's angular speed (rad/s) at `times` (s from the record's first sample)."""

    times: np.ndarray
    speeds: np.ndarray


def whirl_speeds(etas: np.ndarray, h: float, window: float = WINDOW) -> OrbitSpeeds:
    """The orbit's angular speed of a record (N, 3) m sampled every h s, over windows of `window` s
    where the rotor whirls steadily on the bore (`ON_BORE`, `STEADY`), from the first such window
    within `SPUN_UP` of the fastest on: before it the whirl is still spinning up to the rotor's speed.
    NaN rows break a window."""
    n = max(int(round(window / h)), 3)
    xy = np.asarray(etas, dtype=float)[:, :2]
    radius = np.hypot(xy[:, 0], xy[:, 1])
    finite = np.isfinite(radius)
    if finite.sum() < n:
        return OrbitSpeeds(np.empty(0), np.empty(0))
    top = np.percentile(radius[finite], 95)
    angle = np.full(len(xy), np.nan)
    angle[finite] = np.unwrap(np.arctan2(xy[finite, 1], xy[finite, 0]))
    offsets = np.arange(n) * h
    times, speeds = [], []
    for start in range(0, len(xy) - n + 1, n):
        r = radius[start : start + n]
        if not np.isfinite(r).all() or r.mean() < ON_BORE * top or r.max() - r.min() > STEADY * r.mean():
            continue
        times.append((start + (n - 1) / 2) * h)
        speeds.append(np.polyfit(offsets, angle[start : start + n], 1)[0])
    if not speeds:
        return OrbitSpeeds(np.empty(0), np.empty(0))
    speeds_ = np.asarray(speeds)
    first = int(np.argmax(speeds_ >= (1.0 - SPUN_UP) * speeds_.max()))
    return OrbitSpeeds(np.asarray(times[first:]), speeds_[first:])


class OrbitCentre(NamedTuple):
    """The centre of the circle the rotor goes round on the bore, as the sensors read it."""

    centre: np.ndarray  # (2,) m, x and y: the mean of the records'
    sd: np.ndarray  # (2,) m, standard error of the mean from the records' scatter (NaN with one record)
    scatter: float  # m, rms distance of the on-bore samples from their circle, over the records

    def shows(self, axis: int) -> bool:
        """Whether the centre is off the sensors' zero on `axis` (`CENTRE_SIGNIFICANCE`)."""
        offset = abs(float(self.centre[axis]))
        significant = not np.isfinite(self.sd[axis]) or offset > CENTRE_SIGNIFICANCE * float(self.sd[axis])
        return significant and offset > self.scatter


def _circle(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (2,) m of the circle through points (N, 2) by algebraic least squares, and the points'
    distances from it minus its radius (N,) m."""
    design = np.column_stack([2.0 * xy, np.ones(len(xy))])
    solution = np.linalg.lstsq(design, np.sum(xy**2, axis=1), rcond=None)[0]
    centre = solution[:2]
    distance = np.hypot(*(xy - centre).T)
    return centre, distance - np.sqrt(max(solution[2] + centre @ centre, 0.0))


def record_orbit_centre(etas: np.ndarray, iterations: int = 4) -> tuple[np.ndarray, float] | None:
    """The centre (2,) m of the samples of a record (N, 3) m on the bore (their radius about the centre at
    least `ON_BORE` of its 95th percentile), found from the sensors' zero by refitting the circle
    `iterations` times, and their rms distance from the circle (m); None where they do not go round the
    bore (`SECTORS`)."""
    xy = np.asarray(etas, dtype=float)[:, :2]
    xy = xy[np.isfinite(xy).all(axis=1)]
    centre = np.zeros(2)
    if len(xy) < 3 * SECTORS:
        return None
    for _ in range(iterations):
        radius = np.hypot(*(xy - centre).T)
        on_bore = xy[radius >= ON_BORE * np.percentile(radius, 95)]
        centre, misfit = _circle(on_bore)
    angles = np.arctan2(on_bore[:, 1] - centre[1], on_bore[:, 0] - centre[0])
    counts = np.histogram(angles, bins=SECTORS, range=(-np.pi, np.pi))[0]
    if counts.min() < SECTOR_SHARE * len(on_bore) / SECTORS or not np.isfinite(centre).all():
        return None
    return centre, float(np.sqrt(np.mean(misfit**2)))


def orbit_centre(records: Sequence[np.ndarray]) -> OrbitCentre | None:
    """The mean of the records' orbit centres (`record_orbit_centre`, each (N, 3) m) and its standard
    error from their scatter; None where no record goes round the bore."""
    found = [c for c in map(record_orbit_centre, records) if c is not None]
    if not found:
        return None
    centres = np.asarray([c for c, _ in found])
    sd = centres.std(axis=0, ddof=1) / np.sqrt(len(centres)) if len(centres) > 1 else np.full(2, np.nan)
    return OrbitCentre(centres.mean(axis=0), sd, float(np.sqrt(np.mean([s**2 for _, s in found]))))


def sensor_offsets_from_orbits(names: Sequence[str], records: Sequence[np.ndarray]) -> dict[str, dict[str, float]]:
    """{offset: {"offset": m}} of the sensor offsets among `names` (`OFFSET_AXES`) on whose axis the
    records' orbit centre shows an offset (`OrbitCentre.shows`): where each starts."""
    wanted = {name: axis for name, axis in OFFSET_AXES.items() if name in names}
    centre = orbit_centre(records) if wanted else None
    if centre is None:
        return {}
    return {name: {"offset": float(centre.centre[axis])} for name, axis in wanted.items() if centre.shows(axis)}


def _speed_of(effect: Effect, params: dict[str, jax.Array], times: np.ndarray, rig) -> jax.Array:
    """The effect's rotor speed (rad/s) at `times` (s from the drop onset), theta = the rig's speed x t."""
    times = jnp.asarray(times)
    states = jnp.zeros((len(times), STATE_SIZE)).at[:, THETA].set(rig.speed * times)
    return jax.vmap(lambda xi, t: effect(xi, params, rig, t)[0])(states, times)


def fit_speed_effect(effect: Effect, start: dict[str, float], rig, orbits: OrbitSpeeds) -> dict[str, float] | None:
    """The effect's parameters that fit its speed, times a free factor (the whirl turns a little
    faster or slower than the rotor), to the orbit speeds by least squares from `start`, within the
    effect's bounds; None when the orbits are too few or too short (`MIN_WINDOWS`, `MIN_SPAN`), when
    they do not show the effect (its fit leaves more than `SHOWN` of the misfit of a constant speed)
    or the fit does not lower the misfit of `start`."""
    times, speeds = np.asarray(orbits.times), np.asarray(orbits.speeds)
    if len(times) < MIN_WINDOWS or np.ptp(times) < MIN_SPAN:
        return None
    names = list(start)

    def residuals(x: np.ndarray) -> np.ndarray:
        params = {k: jnp.asarray(v) for k, v in zip(names, x[1:])}
        return np.asarray(x[0] * _speed_of(effect, params, times, rig)) - speeds

    def factor_at(params: np.ndarray) -> float:
        modelled = np.asarray(_speed_of(effect, {k: jnp.asarray(v) for k, v in zip(names, params)}, times, rig))
        return float(modelled @ speeds / (modelled @ modelled)) if modelled @ modelled > 0 else 1.0

    x0 = np.asarray([start[k] for k in names], dtype=float)
    first = np.concatenate([[factor_at(x0)], x0])
    bounds = [(-np.inf, np.inf)] + [effect.bounds.get(k, (-np.inf, np.inf)) for k in names]
    result = least_squares(residuals, first, bounds=tuple(np.asarray(b, dtype=float) for b in zip(*bounds)),
                           x_scale="jac")
    constant = float(np.sum((speeds - speeds.mean()) ** 2))  # a constant speed times the best factor
    if not np.isfinite(result.x).all() or result.cost >= 0.5 * min(float(np.sum(residuals(first) ** 2)),
                                                                   SHOWN * constant):
        return None
    return {k: float(v) for k, v in zip(names, result.x[1:])}


def speed_effects_from_orbits(
    effects: Effects, rig, records: Sequence[np.ndarray], gates: Sequence[Sequence[float]], h: float
) -> tuple[Effects, dict[str, dict[str, float]]]:
    """`effects` with each speed effect started where its speed fits the orbit speeds of the records
    (each (N, 3) m from the drop onset) it acts in (gates: one row per record, one factor per effect),
    and {effect: fitted parameters} of those it moved; the others keep their values."""
    if not effects.acts_on(SPEED):
        return effects, {}
    read = [whirl_speeds(etas, h) for etas in records]
    values, moved = effects.values(), {}
    for i, effect in enumerate(effects.effects):
        if effect.kind != SPEED:
            continue
        acting = [o for o, g in zip(read, gates) if g[i] > 0.5]
        if not acting:
            continue
        pooled = OrbitSpeeds(np.concatenate([o.times for o in acting]), np.concatenate([o.speeds for o in acting]))
        fitted = fit_speed_effect(effect, values[effect.name], rig, pooled)
        if fitted is not None:
            moved[effect.name] = fitted
    return effects.with_values(moved), moved


def effects_from_orbits(
    effects: Effects, rig, records: Sequence[np.ndarray], gates: Sequence[Sequence[float]], h: float
) -> tuple[Effects, dict[str, dict[str, float]]]:
    """`speed_effects_from_orbits`, and the sensor offsets started at the orbit's centre of the records
    they act in (`sensor_offsets_from_orbits`): the effects and {effect: parameters} of those moved."""
    started, moved = speed_effects_from_orbits(effects, rig, records, gates, h)
    by_records: dict[tuple[bool, ...], list[str]] = {}  # the offsets acting in the same records share one centre
    for i, name in enumerate(effects.names):
        if name in OFFSET_AXES:
            by_records.setdefault(tuple(g[i] > 0.5 for g in gates), []).append(name)
    for acts, names in by_records.items():
        moved.update(sensor_offsets_from_orbits(names, [etas for etas, on in zip(records, acts) if on]))
    return started.with_values(moved), moved


def candidate_starts(
    candidates: Sequence[Effect], rig, records: Sequence[np.ndarray], h: float
) -> dict[str, dict[str, float]]:
    """{candidate: parameters} of the candidates (acting in every record) that the records' orbits
    start (`effects_from_orbits`): speed effects whose speed fits them, sensor offsets their centre
    shows; candidates the orbits do not move are left out."""
    shown = Effects(tuple(c for c in candidates if c.kind == SPEED or c.name in OFFSET_AXES))
    return effects_from_orbits(shown, rig, records, [shown.gates] * len(records), h)[1]


def describe_starts(
    moved: Mapping[str, Mapping[str, float]], before: Mapping[str, Mapping[str, float]]
) -> list[str]:
    """One line per effect `effects_from_orbits` moved: its new start and the value it had."""
    return [
        f"{name} starts "
        + ("at the orbit's centre (the bearing's centre as the sensors read it)" if name in OFFSET_AXES
           else "where its speed fits the orbit's (the rotor whirling on the bore)")
        + ": " + ", ".join(f"{k} {v:.4g} (was {before[name][k]:.4g})" for k, v in values.items())
        for name, values in moved.items()
    ]


__all__ = [
    "OrbitCentre",
    "OrbitSpeeds",
    "candidate_starts",
    "describe_starts",
    "effects_from_orbits",
    "fit_speed_effect",
    "orbit_centre",
    "record_orbit_centre",
    "sensor_offsets_from_orbits",
    "speed_effects_from_orbits",
    "whirl_speeds",
]
