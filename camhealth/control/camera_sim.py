"""A simulated camera that renders clean frames through the physics core at any exposure and gain.

Radiometry (linear sensor, thesis Sec. 4.4.2 assumption (i)): a clean frame value c ∈ [0, 1] is the
scene radiance relative to the frame's white. With scene illumination E [1/s] — the reciprocal of the
exposure time that fills the full well at a radiance of 1 — the sensor collects

    electrons = c · E · t_exp · FW,     output intensity (noise-free) I = c · E · t_exp · g

with g = 10^(gain_dB/20) the digital gain of the conventions' gain model ("the scene delivers I·FW/g
electrons for an output intensity I"). Scene/camera motion of v [px/s] in direction Φ blurs the frame with the
sub-pixel linear-motion PSF of length L = v · t_exp (thesis Eq. 3.10 / Sec. 7.2), and the full Fig. 3.7 chain of
:func:`camhealth.physics.form_image` adds photon shot noise (before the motion blur), dark-current shot
noise and readout noise of the sensor preset at its temperature, then clips and quantises to 8 bit. The chain
renders I clipped at 1; where the frame is overexposed (I > 1: the ADC's 255 DN; the full well saturates later,
at I = g), the light beyond full scale, blurred alike (in float64), is added back before the clipping to [0, 1]
and the quantisation to whole DN (in that order), so such pixels read 255 DN as on a real sensor, not full scale
less the noise, and every rendered value stays in [0, 1] and, with ``quantize``, on the 8-bit grid. The
radiometry c·E·t·g is computed in float32 at least, whatever the frames' dtype (fp16 overflows at 65504).

Several captures (e.g. the same frame for three controllers) are requested together; radiometry, PSFs
and MTF labels are computed for the batch at once, and the noise of each request is drawn from its own
generator seeded by (seed, frame index, exposure, gain), so equal requests give equal images whatever
else is in the batch (common random numbers: controllers are compared on the same noise).
"""

from __future__ import annotations

import hashlib
import math
import numbers
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from camhealth._validation import check_choice, check_image
from camhealth.physics.image_formation import NOISE_SOURCES, apply_psf, form_image
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.motion_psf import linear_motion_psf
from camhealth.physics.mtf import mtf_hv

__all__ = ["Capture", "MAX_ILLUMINATION_PER_S", "MAX_MOTION_PX", "SimulatedCamera", "motion_kernel_for"]


@dataclass
class Capture:
    """Result of :meth:`SimulatedCamera.capture` for B requests.

    Attributes:
        image: B×1×H×W rendered frames in [0, 1].
        blurred: B×1×H×W noise-free signal after motion blur (for physics labels).
        mtf: (B, 16) MTF of the motion PSF (H then V at the 8 normalised frequencies).
        meta: camera metadata of each capture (physical units).
        exposure_s, gain_db: (B,) the parameters used.
        blur_length_px: (B,) motion length L = v·t_exp [px].
        sigma_dn: (B, 3) realised σ of PN/DCSN/RN [DN]; sigma_total_dn (B,) all together.
        mean_intensity: (B,) mean of the rendered frame in [0, 1].
        clipped_fraction: (B,) fraction of the rendered frame's pixels at 0 or 255 DN.
        frame_index: (B,) which clean frame.
    """

    image: torch.Tensor
    blurred: torch.Tensor
    mtf: torch.Tensor
    meta: CameraMetadata
    exposure_s: torch.Tensor
    gain_db: torch.Tensor
    blur_length_px: torch.Tensor
    sigma_dn: torch.Tensor
    sigma_total_dn: torch.Tensor
    mean_intensity: torch.Tensor
    clipped_fraction: torch.Tensor
    frame_index: torch.Tensor

    def __getitem__(self, i: int) -> "Capture":
        """Capture ``i`` (−B ≤ i < B, negative from the end) as a batch of one; ``i`` is an integer (Python, NumPy or a
        one-element integer tensor), not a bool."""
        b = int(self.image.shape[0])
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, numbers.Integral) and not (
                isinstance(i, torch.Tensor) and i.numel() == 1 and not i.is_floating_point() and not i.is_complex()
                and i.dtype != torch.bool):
            raise TypeError(f"a capture is indexed by an int, got {type(i).__name__} {i!r:.40}")
        i = int(i)
        if not -b <= i < b:
            raise IndexError(f"capture index {i} is out of the allowed range [{-b}, {b - 1}] for a batch of {b}")
        i %= b
        sl = slice(i, i + 1)
        return Capture(self.image[sl], self.blurred[sl], self.mtf[sl], self.meta[i], self.exposure_s[sl],
                       self.gain_db[sl], self.blur_length_px[sl], self.sigma_dn[sl], self.sigma_total_dn[sl],
                       self.mean_intensity[sl], self.clipped_fraction[sl], self.frame_index[sl])


#: Longest motion path [px] a capture renders: the largest odd kernel (255 px) less the 1-px margin each side.
MAX_MOTION_PX = 253.0

#: Largest scene illumination E [1/s] a camera accepts: a radiance of 1 fills the well in 1 µs, i.e. up to 3.2·10⁶ times
#: full scale at the longest exposure and highest gain (0.2 s, 24 dB). Beyond it the light above full scale, which is
#: blurred in the Fourier domain, would carry rounding errors of whole DN into the dark pixels next to it (and, far
#: beyond, overflow to NaN).
MAX_ILLUMINATION_PER_S = 1e6


def motion_kernel_for(length_px: float) -> int:
    """Smallest odd kernel size that holds a linear motion path of ``length_px`` with a 1 px margin."""
    k = int(math.ceil(max(float(length_px), 1.0))) + 2
    return k + 1 - k % 2


def _saturate(image: torch.Tensor, blurred: torch.Tensor, sigma: torch.Tensor, sigma_total: torch.Tensor,
              excess: torch.Tensor, quantize: bool) -> tuple[torch.Tensor, ...]:
    """An overexposed frame's light beyond full scale, put back before the ADC's clipping and quantisation.

    :func:`form_image` takes signals in [0, 1], so the capture renders the frame clipped at full scale (and not yet
    quantised); ``excess`` (B×1×H×W, intensity) is what was cut off, blurred by the same PSF (values below 0, from
    the Fourier-domain convolution's rounding, are read as 0). The ADC clips signal plus noise to [0, 1] (Fig. 3.7),
    so the rendered value is min(image + excess, 1): a pixel far above full scale reads 255 DN, not 255 DN less the
    noise drawn at full scale; then, with ``quantize``, it is rounded to whole DN (clipping → quantisation). The
    noise-free signal becomes min(blurred + excess, 1), clipped to [0, 1] as well, and the realised σ of every
    source is scaled by the change of the realised total noise (image − noise-free signal, before quantisation, as
    :func:`form_image`'s labels) that the newly clipped pixels bring (their noise is cut to 0)."""
    # image and blurred lie in [0, 1] (blurred up to rounding): an excess of 2 clips any of them at 1 as a larger one
    # would, and keeps the sum finite in the frames' dtype
    excess = excess.clamp(0.0, 2.0).to(image.dtype)
    new_image = (image + excess).clamp_(0.0, 1.0)
    new_blurred = (blurred + excess).clamp_(0.0, 1.0)
    before = (image - blurred).flatten(1).double().std(1)
    after = (new_image - new_blurred).flatten(1).double().std(1)
    ratio = torch.where(before > 0, after / before.clamp_min(1e-300), torch.ones_like(before)).float().to(sigma.device)
    if quantize:  # whole DN, after the clipping
        new_image = (new_image.double() * 255.0).round_().div_(255.0).to(image.dtype)
    return new_image, new_blurred, sigma * ratio[:, None], sigma_total * ratio


def _check_numbers(value: object, name: str, what: str) -> None:
    """Refuse what is not a number, a (nested) sequence of numbers, a numeric array or a numeric tensor: text, bytes,
    None, booleans and complex numbers, naming ``name``, the value and ``what`` is allowed (``ValueError``)."""
    bad = f"{name} = {value!r:.80} must be {what}"
    if isinstance(value, torch.Tensor):
        if value.dtype == torch.bool or value.is_complex():
            raise ValueError(f"{bad} (got a tensor of {value.dtype})")
        return
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "iuf":
            raise ValueError(f"{bad} (got an array of {value.dtype})")
        return
    stack = [value]
    while stack:
        v = stack.pop()
        if isinstance(v, (list, tuple)):
            stack.extend(v)
        elif isinstance(v, torch.Tensor) or isinstance(v, np.ndarray):
            _check_numbers(v, name, what)
        elif isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
            raise ValueError(f"{bad} (got {type(v).__name__} {v!r:.40})")


class SimulatedCamera:
    """Renders clean frames at requested exposure/gain through the physics core.

    Args:
        frames: clean frames N×1×H×W in [0, 1] (e.g. the embedded street clip).
        sensor: sensor preset, ``"ICX285"`` or ``"EV76C661"``.
        illumination_per_s: scene illumination E [1/s] (see the module docstring) in (0, ``MAX_ILLUMINATION_PER_S``
            = 1e6]; e.g. 40/s means a radiance of 1 fills the well in 25 ms at 0 dB.
        motion_px_per_s: relative speed of scene and camera v [px/s] (>= 0).
        motion_angle_deg: its direction Φ [deg] (0 = horizontal), any finite number (read modulo 360°).
        temperature_c: sensor temperature [°C].
        sources: noise sources to render.
        quantize: round the output to whole DN (8-bit camera).
        seed: noise seed.
    """

    def __init__(
        self,
        frames: torch.Tensor,
        sensor: str = "ICX285",
        illumination_per_s: float = 40.0,
        motion_px_per_s: float = 800.0,
        motion_angle_deg: float = 0.0,
        temperature_c: float = 25.0,
        sources: Sequence[str] = NOISE_SOURCES,
        quantize: bool = True,
        seed: int = 0,
    ) -> None:
        check_image(frames, "frames")
        lo, hi = torch.aminmax(frames)
        if lo < 0 or hi > 1:
            raise ValueError(f"frames must lie in [0, 1] (DN/255), got values in [{lo.item():g}, {hi.item():g}]")
        for nm, v, low in (("illumination_per_s", illumination_per_s, 0.0), ("motion_px_per_s", motion_px_per_s, 0.0),
                           ("motion_angle_deg", motion_angle_deg, -math.inf), ("temperature_c", temperature_c, -math.inf)):
            if isinstance(v, torch.Tensor) and v.numel() == 1 and not v.dtype == torch.bool:
                v = v.item()
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not (math.isfinite(v) and v >= low):
                raise ValueError(f"{nm} = {v!r} must be a finite number" + (f" >= {low:g}" if math.isfinite(low) else ""))
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
            raise ValueError(f"seed = {seed!r} must be an integer")
        if not isinstance(quantize, bool):
            raise ValueError(f"quantize = {quantize!r} must be True or False")
        if not 0 < float(illumination_per_s) <= MAX_ILLUMINATION_PER_S:
            raise ValueError(f"illumination_per_s = {illumination_per_s!r} is out of the allowed range "
                             f"(0, {MAX_ILLUMINATION_PER_S:g}] /s")
        for s in sources:
            check_choice(s, "noise source", NOISE_SOURCES)
        self.frames = frames.detach()
        self.sensor = sensor
        self.base = CameraMetadata.preset(sensor, temperature_c=temperature_c)  # validates preset/temperature
        self.illumination = float(illumination_per_s)
        self.speed = float(motion_px_per_s)
        # a direction: beyond one turn it is read modulo 360° (fmod is exact), so that any finite angle renders
        angle = float(motion_angle_deg)
        self.angle = math.fmod(angle, 360.0) if abs(angle) > 360.0 else angle
        self.temperature_c = float(temperature_c)
        self.sources = tuple(sources)
        self.quantize = bool(quantize)
        self.seed = int(seed)

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    def _seed(self, index: Sequence[int], t: Sequence[float], g: Sequence[float]) -> int:
        key = f"{self.seed}|" + ";".join(f"{i},{a:.9g},{b:.9g}" for i, a, b in zip(index, t, g))
        return int.from_bytes(hashlib.blake2b(key.encode(), digest_size=8).digest(), "big") >> 2

    def capture(
        self,
        frame_index: int | Sequence[int],
        exposure_s: float | Sequence[float] | torch.Tensor,
        gain_db: float | Sequence[float] | torch.Tensor,
    ) -> Capture:
        """Render frames ``frame_index`` at ``exposure_s`` [s] and ``gain_db`` [dB] (scalars broadcast).

        Exposure and gain must lie in the metadata ranges (Table 4.1: 0.001–0.2 s, 0–24 dB); a value
        outside raises ``ValueError`` naming it, and so does a value that is not a number (text, a bool, None,
        a complex number), alone or inside a sequence.
        """
        _check_numbers(frame_index, "frame_index", "whole frame numbers (an int, or a sequence/tensor of them)")
        raw = torch.as_tensor(frame_index).reshape(-1)
        if raw.is_floating_point() and not bool((raw == raw.round()).all()):
            raise ValueError(f"frame_index = {frame_index!r} must be whole frame numbers")
        idx = raw.to(torch.long)
        for nm, v in (("exposure_s", exposure_s), ("gain_db", gain_db)):
            _check_numbers(v, nm, "a number or a sequence/tensor of numbers")
        t = torch.as_tensor(exposure_s, dtype=torch.float64).reshape(-1)
        g = torch.as_tensor(gain_db, dtype=torch.float64).reshape(-1)
        b = max(idx.numel(), t.numel(), g.numel())
        for nm, v in (("frame_index", idx), ("exposure_s", t), ("gain_db", g)):
            if v.numel() not in (1, b):
                raise ValueError(f"{nm} has {v.numel()} values for a batch of {b}")
        idx, t, g = idx.expand(b), t.expand(b), g.expand(b)
        if bool(((idx < 0) | (idx >= len(self))).any()):
            raise IndexError(f"frame_index {idx.tolist()} out of range for {len(self)} frames")
        meta = CameraMetadata.preset(self.sensor, batch_size=b, temperature_c=self.temperature_c,
                                     exposure_s=t.float(), gain_db=g.float())  # validates the ranges
        dev = self.frames.device
        clean = self.frames[idx.to(dev)]
        # radiometry in float32 at least: c·E·t·g overflows fp16 (65504) for a bright scene that fp32 renders
        wd = torch.promote_types(clean.dtype, torch.float32)
        scale = (self.illumination * t * torch.pow(10.0, g / 20.0)).to(device=dev, dtype=wd)
        raw = clean.to(wd) * scale.view(-1, 1, 1, 1)  # [full scale]; above 1 where the frame is overexposed
        signal = raw.clamp(0.0, 1.0).to(clean.dtype)
        over = (raw > 1.0).flatten(1).any(1).tolist()  # per request: overexposed somewhere
        length = self.speed * t
        if float(length.max()) > MAX_MOTION_PX:
            j = int(length.argmax())
            raise ValueError(f"motion_px_per_s · exposure_s = {self.speed:g} px/s · {float(t[j]):g} s = {float(length[j]):g} px "
                             f"of motion blur is out of the allowed range [0, {MAX_MOTION_PX:g}] px (the largest motion "
                             f"kernel, 255 px); use a shorter exposure or a slower motion")
        k = motion_kernel_for(float(length.max()))
        psf = linear_motion_psf(length.float(), torch.full((b,), self.angle), k).to(dev)
        mtf = mtf_hv(psf.double()).float()
        meta_dev = meta.to(device=dev)
        parts = []
        with torch.no_grad():
            # one generator per request (common random numbers): a request's noise never depends on the
            # other requests in the batch — torch generators have no per-sample streams, and the exact
            # Poisson sampler consumes a data-dependent number of draws, so this loop is what makes it so
            for i in range(b):
                gen = torch.Generator(device=dev).manual_seed(self._seed([int(idx[i])], [float(t[i])], [float(g[i])]))
                # an overexposed request is quantised after its light beyond full scale is added and clipped
                parts.append(form_image(signal[i : i + 1], meta_dev[i], motion_psf=psf[i : i + 1], sources=self.sources,
                                        generator=gen, quantize=self.quantize and not over[i]))
        image = torch.cat([f.image for f in parts])
        blurred = torch.cat([f.blurred for f in parts]).to(image.dtype)
        sigma = torch.cat([f.sigma_dn for f in parts]).float()
        sigma_total = torch.cat([f.sigma_total_dn for f in parts]).float()
        if any(over):
            k_over = torch.tensor([i for i in range(b) if over[i]], device=dev)
            # in float64: the excess can be 10⁶ × full scale, and the Fourier-domain blur's rounding scales with it
            cut = raw.index_select(0, k_over).double()
            excess = apply_psf(cut - cut.clamp(0.0, 1.0), psf.index_select(0, k_over).double())
            sat = _saturate(image.index_select(0, k_over), blurred.index_select(0, k_over),
                            sigma.index_select(0, k_over.to(sigma.device)),
                            sigma_total.index_select(0, k_over.to(sigma.device)), excess, self.quantize)
            image, blurred = image.index_copy(0, k_over, sat[0]), blurred.index_copy(0, k_over, sat[1])
            k_cpu = k_over.to(sigma.device)
            sigma, sigma_total = sigma.index_copy(0, k_cpu, sat[2]), sigma_total.index_copy(0, k_cpu, sat[3])
        return Capture(
            image=image, blurred=blurred, mtf=mtf.cpu(), meta=meta,
            exposure_s=t.float(), gain_db=g.float(), blur_length_px=length.float(),
            sigma_dn=sigma.cpu(), sigma_total_dn=sigma_total.cpu(),
            mean_intensity=image.mean(dim=(1, 2, 3)).float().cpu(),
            clipped_fraction=((image <= 0) | (image >= 1)).flatten(1).float().mean(1).cpu(),
            frame_index=idx.clone(),
        )

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(n={len(self)}, sensor={self.sensor}, E={self.illumination:g}/s, "
                f"v={self.speed:g} px/s @ {self.angle:g}°, T={self.temperature_c:g} °C)")
