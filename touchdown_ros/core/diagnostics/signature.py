"""The missing force's signature, for when no candidate explains it: spectrum peak and share once and
twice per revolution per axis, its correlation with deformation and velocity and its mean per
contact phase, summarised in words."""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from touchdown_ros.core.diagnostics.breakdown import AXES, PHASES, deformations
from touchdown_ros.core.types import Rig


def spectrum_peak(signal: np.ndarray, h: float, min_frequency: float = 20.0) -> tuple[float, float]:
    """Frequency (Hz) of the largest peak of the Hann-windowed power spectrum above
    min_frequency (and above 3 frequency bins), and the share of the spectrum's energy in
    that band lying within +-2 bins of the peak."""
    x = np.asarray(signal, float)
    x = x[np.isfinite(x)]
    if len(x) < 16:
        return float("nan"), float("nan")
    x = x - np.polyval(np.polyfit(np.arange(len(x)), x, 1), np.arange(len(x)))
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x)))) ** 2
    freqs = np.fft.rfftfreq(len(x), h)
    band = freqs >= max(min_frequency, 3.0 * freqs[1])
    if not band.any() or spectrum[band].sum() == 0:
        return float("nan"), float("nan")
    peak = int(np.flatnonzero(band)[np.argmax(spectrum[band])])
    near = band & (np.abs(np.arange(len(freqs)) - peak) <= 2)
    share = spectrum[near].sum() / spectrum[band].sum()
    return float(freqs[peak]), float(share)


def harmonic_share(signal: np.ndarray, angle: np.ndarray, harmonic: int = 1) -> float:
    """Share of the variance of signal explained by cos(harmonic angle), sin(harmonic angle)
    (least squares with a constant): how much of it is `harmonic` times per revolution when
    angle is the rotor angle (robust on records too short for a fine spectrum)."""
    x, a = np.asarray(signal, float), np.asarray(angle, float)
    ok = np.isfinite(x) & np.isfinite(a)
    x, a = x[ok], a[ok]
    if len(x) < 4 or np.std(x) == 0:
        return float("nan")
    A = np.stack([np.ones_like(a), np.cos(harmonic * a), np.sin(harmonic * a)], axis=1)
    coef, *_ = np.linalg.lstsq(A, x, rcond=None)
    residual = x - A @ coef
    return float(1.0 - np.var(residual) / np.var(x))


def signature(
    rig: Rig, h: float, forces: Sequence[np.ndarray], states: Sequence[np.ndarray], phases: Sequence[np.ndarray]
) -> dict[str, Any]:
    """What the missing force looks like, from each record's missing force (N, 3), the state it was
    estimated with (N, n) and the contact phase (N,): spectrum peak per axis vs rotor speed, and its
    dependence on contact phase, deformation and velocity (correlation coefficients)."""
    rotor_hz = rig.speed / (2.0 * np.pi)
    out: dict[str, Any] = {"rotor_frequency_Hz": rotor_hz, "axes": {}}
    force, state, phase = (np.concatenate(list(v)) for v in (forces, states, phases))
    d_r, v_r, d_z, v_z = deformations(rig, state)
    for i, axis in enumerate(AXES):
        peaks = [spectrum_peak(f[:, i], h) for f in forces]
        freq = float(np.median([p[0] for p in peaks]))
        share = float(np.mean([p[1] for p in peaks]))
        # rotor angle of the model (omega t from the onset; each bag's phase fitted separately)
        harmonics = {
            n: float(np.nanmean([harmonic_share(f[:, i], s[:, 3], n) for f, s in zip(forces, states)]))
            for n in (1, 2)
        }
        corr = {}
        for label, u in (
            ("axial deformation", d_z),
            ("axial velocity", v_z),
            ("radial deformation", d_r),
            ("radial velocity", v_r),
        ):
            ok = np.isfinite(u) & np.isfinite(force[:, i])
            corr[label] = float(np.corrcoef(force[ok, i], u[ok])[0, 1]) if np.std(u[ok]) > 0 else 0.0
        means = {PHASES[p]: float(force[phase == p, i].mean()) for p in range(4) if (phase == p).any()}
        out["axes"][axis] = {
            "peak_Hz": freq,
            "peak_per_revolution": freq / rotor_hz,
            "peak_energy_share": share,
            "once_per_revolution_share": harmonics[1],
            "twice_per_revolution_share": harmonics[2],
            "correlation": corr,
            "mean_by_phase_N": means,
            "rms_N": float(np.sqrt(np.mean(force[:, i] ** 2))),
        }
    strongest = max(out["axes"], key=lambda a: out["axes"][a]["rms_N"])
    s = out["axes"][strongest]
    words = [f"largest on {strongest} ({s['rms_N']:.0f} N rms)"]
    words.append(
        f"{100 * s['once_per_revolution_share']:.0f} % of its variance once per revolution, "
        f"{100 * s['twice_per_revolution_share']:.0f} % twice"
    )
    if s["peak_energy_share"] > 0.2:
        words.append(f"spectrum peak at {s['peak_Hz']:.1f} Hz ({s['peak_per_revolution']:.2f} x rotor speed)")
    top = max(s["correlation"], key=lambda k: abs(s["correlation"][k]))
    words.append(f"most correlated with {top} (r = {s['correlation'][top]:+.2f})")
    words.append("mean by phase " + ", ".join(f"{k} {v:.0f} N" for k, v in s["mean_by_phase_N"].items()))
    out["summary"] = "; ".join(words)
    return out
