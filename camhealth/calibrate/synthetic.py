"""Calibration stacks of a known camera, made by camhealth's physics core (tests, benchmark, docs).

:func:`synthetic_sets` records what ``docs/calibration.md`` asks of a real camera — a bias set, dark sets at
several exposures and temperatures, flat sets at several light levels and two gains — from
:func:`camhealth.physics.form_image` (or any other simulator with the same signature), so that the
calibration's result can be compared with the metadata the frames were made with.

The stacks draw every photon and dark electron count exactly from Poisson(S) (``form_image``'s
``poisson_exact_below=inf``): a real sensor's shot noise is Poisson, skew included, and the calibration's
dark fit models that skew. ``form_image``'s default normal approximation N(S, S) above 1000 e⁻ is a
training-speed shortcut of the data generator, not a property of a camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch

from camhealth.calibrate.frames import FrameSet
from camhealth.physics.metadata import CameraMetadata

__all__ = ["Protocol", "synthetic_sets", "form_image_simulator"]

Simulator = Callable[[torch.Tensor, CameraMetadata, torch.Generator], torch.Tensor]


@dataclass(frozen=True)
class Protocol:
    """What is recorded: exposures [s], temperatures [°C], gains [dB] and flat levels (output intensity in
    [0, 1] at each gain: the light is set so that the flat sits at that fraction of full scale)."""

    bias_exposure_s: float = 0.001
    dark_exposures_s: tuple[float, ...] = (0.05, 0.1, 0.2)
    dark_temperatures_c: tuple[float, ...] = (25.0, 50.0, 75.0)
    dark_gain_db: float = 12.0
    flat_levels: tuple[float, ...] = (0.05, 0.1, 0.2, 0.35, 0.5, 0.7)
    flat_gains_db: tuple[float, ...] = (0.0, 12.0)
    flat_exposure_s: float = 0.01
    flat_temperature_c: float = 25.0


def form_image_simulator(clean: torch.Tensor, meta: CameraMetadata, generator: torch.Generator) -> torch.Tensor:
    """camhealth's Fig. 3.7 chain (:func:`camhealth.physics.form_image`), unquantised, with exact Poisson draws
    of every photon and dark electron count (``poisson_exact_below=inf``; see the module docstring)."""
    from camhealth.physics.image_formation import form_image

    return form_image(clean, meta, generator=generator, poisson_exact_below=math.inf).image


def synthetic_sets(
    sensor: CameraMetadata,
    protocol: Protocol = Protocol(),
    frames: int = 20,
    size: int = 64,
    seed: int = 0,
    simulate: Simulator | None = None,
) -> list[FrameSet]:
    """In-memory frame sets of ``sensor`` (batch 1; its gain, exposure and temperature are replaced by the
    protocol's) recorded by ``protocol``: ``frames`` frames of ``size``×``size`` px per set, float32 in [0, 1].

    ``simulate(clean B×1×H×W, meta (batch B), generator) -> noisy`` defaults to :func:`form_image_simulator`.
    Every set has a name of its own (a calibration refuses sets that share one): a set the protocol repeats (a flat
    level given twice) is named with a suffix ``_2``, ``_3`` ….
    """
    if sensor.batch_size != 1:
        raise ValueError(f"synthetic_sets needs one sensor (metadata batch 1), got batch {sensor.batch_size}")
    simulate = simulate or form_image_simulator
    gen = torch.Generator().manual_seed(int(seed))
    out: list[FrameSet] = []
    names: dict[str, int] = {}

    def record(kind: str, level: float, gain_db: float, exposure_s: float, temperature_c: float, name: str) -> None:
        names[name] = names.get(name, 0) + 1
        if names[name] > 1:
            name = f"{name}_{names[name]}"
        meta = sensor.replace(gain_db=gain_db, exposure_s=exposure_s, temperature_c=temperature_c).expand(frames)
        clean = torch.full((frames, 1, size, size), float(level))
        noisy = simulate(clean, meta, gen)
        out.append(FrameSet(kind, exposure_s, gain_db, temperature_c, frames=noisy[:, 0].float().numpy(), name=name))

    p = protocol
    for t_c in p.dark_temperatures_c:
        record("bias", 0.0, p.dark_gain_db, p.bias_exposure_s, t_c, f"bias_{p.bias_exposure_s * 1e3:g}ms_{p.dark_gain_db:g}dB_{t_c:g}C")
        for t in p.dark_exposures_s:
            record("dark", 0.0, p.dark_gain_db, t, t_c, f"dark_{t * 1e3:g}ms_{p.dark_gain_db:g}dB_{t_c:g}C")
    for g in p.flat_gains_db:
        for lvl in p.flat_levels:
            record("flat", lvl, g, p.flat_exposure_s, p.flat_temperature_c,
                   f"flat_{p.flat_exposure_s * 1e3:g}ms_{g:g}dB_{p.flat_temperature_c:g}C_L{lvl:g}")
    return out
