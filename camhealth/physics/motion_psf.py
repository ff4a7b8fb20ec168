"""Motion-blur point spread functions: linear (thesis Eq. 3.10) and non-linear camera shake (Sec. 3.2.1.2).

Conventions (shared by both PSFs and by :mod:`camhealth.physics.mtf`):

* **Angle** Φ in degrees, 0° = horizontal, counter-clockwise positive **as seen on screen** with the image
  y axis (rows) pointing down: the unit direction in (x = column, y = row) coordinates is
  ``(cos Φ, −sin Φ)``. So 90° is vertical, 45° runs from bottom-left to top-right, and rotating the
  kernel counter-clockwise by 90° (``torch.rot90(psf, 1, (-2, -1))``) gives the kernel of Φ + 90°.
  Reflecting across the main diagonal (transpose) maps Φ to 90° − Φ (so 0° ↔ 90°).
* **Centring**: the linear segment is centred on the kernel centre ``c = (k − 1)/2``; the non-linear path
  is centred by its **bounding box** (centre of its x and y extents on the kernel centre).
* **Rasterisation** (sub-pixel exact): the path is a uniform-in-time polyline; the kernel value of a pixel
  is the exposure time the path spends inside that pixel's square ``[j ± 0.5] × [i ± 0.5]`` (exact
  line/square intersection lengths; the line-measure analogue of the disk's pixel-area coverage in
  :mod:`camhealth.physics.defocus_psf`). Kernels sum to 1. L = 0 (or L <= 1 px along an axis) gives the
  delta kernel.
* **Size policy**: a path of arc length L can never reach farther than L/2 from its bounding-box centre
  in x or y, so ``L <= kernel_size`` guarantees the whole path lies inside the kernel and **no mass is
  ever clipped**; ``L > kernel_size`` raises ``ValueError`` (choose a larger kernel).
* **Randomness** lives only in :func:`sample_shake_noise` (Kornia style: the parameter generator draws,
  the PSF function is deterministic given the noise tensor).

Non-linear model: the path has ``N = n_steps`` segments of equal duration. The heading of step n is
``Φ + intensity · κ · W_n`` where W is a random walk over smoothed ``shake_noise[..., 0]`` (zero-mean over
the path, end-to-end spread ≈ κ = HEADING_SPREAD_RAD at intensity 1); the speed of step n is
``exp(intensity · SPEED_LOG_STD · ñ_n)`` with ñ the smoothed ``shake_noise[..., 1]``, so slow steps are
short and, having the same duration, brighter (inhomogeneous intensities, Fig. 3.8). The step lengths are
rescaled so the arc length is exactly L. Intensity 0 gives exactly the straight line of
:func:`linear_motion_psf`.
"""

from __future__ import annotations


import torch

from camhealth._validation import check_finite, check_float, check_odd_kernel_size, check_tensor
from camhealth.physics._format import check_range, show_outside
from camhealth.physics.defocus_psf import _batch_vector, _out_dtype, _work_dtype

__all__ = [
    "HEADING_SPREAD_RAD",
    "SPEED_LOG_STD",
    "MAX_SHAKE_NOISE",
    "linear_motion_psf",
    "sample_shake_noise",
    "nonlinear_motion_psf",
]

#: End-to-end standard deviation (rad) of the heading random walk at intensity 1.
HEADING_SPREAD_RAD = 2.5
#: Standard deviation of the log-speed at intensity 1 (speed factor e^{±1} at one sigma).
SPEED_LOG_STD = 1.0
#: Largest |shake_noise| entry :func:`nonlinear_motion_psf` takes: standard-normal draws beyond 8 have probability
#: 1e-15; far beyond, exp of the smoothed speed noise overflows into NaN steps (float32 beyond ≈ 88 / Σ|weights|).
MAX_SHAKE_NOISE = 8.0
#: Width (std) of the Gaussian smoothing of the shake noise, as a fraction of the number of steps.
_SMOOTH_FRACTION = 1.0 / 32.0


def _rasterise_polyline(vertices: torch.Tensor, weights: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """Exact pixel-coverage rasterisation of piecewise-linear paths. Returns **unnormalised** kernels.

    Args:
        vertices: (B, M+1, 2) path vertices (x right, y down) in px relative to the kernel centre.
        weights: (B, M) mass of each segment (its share of the exposure time), spread uniformly along it.
        kernel_size: odd k.

    Returns:
        (B, k, k): the mass of each segment lying in each pixel square. Mass outside the kernel is dropped
        (not clamped), so the sum equals ``weights.sum(-1)`` exactly iff the path fits in the kernel.
    """
    k = kernel_size
    b, m = weights.shape
    a = vertices[:, :-1]  # (B, M, 2) segment starts
    d = vertices[:, 1:] - a  # (B, M, 2) segment vectors
    grid = torch.arange(k + 1, device=vertices.device, dtype=vertices.dtype) - 0.5 * k  # pixel borders

    def crossings(a_c: torch.Tensor, d_c: torch.Tensor) -> torch.Tensor:
        # Segment parameters t in [0, 1] where the segment crosses each grid line (dummy 0 if parallel).
        ok = d_c.abs() > 1e-12
        t = (grid - a_c[..., None]) / torch.where(ok, d_c, torch.ones_like(d_c))[..., None]
        return torch.where(ok[..., None], t, torch.zeros_like(t)).clamp(0.0, 1.0)

    ends = torch.stack([torch.zeros_like(weights), torch.ones_like(weights)], dim=-1)
    t = torch.cat([ends, crossings(a[..., 0], d[..., 0]), crossings(a[..., 1], d[..., 1])], dim=-1)
    t = torch.sort(t, dim=-1).values  # (B, M, 2k+4) breakpoints; each sub-interval lies in one pixel
    dt = t[..., 1:] - t[..., :-1]
    dt = torch.where(dt > 1e-12, dt, torch.zeros_like(dt))  # drop rounding dust at pixel corners
    mid = 0.5 * (t[..., 1:] + t[..., :-1])
    px = a[..., 0:1] + mid * d[..., 0:1] + 0.5 * k  # column coordinate + 0.5
    py = a[..., 1:2] + mid * d[..., 1:2] + 0.5 * k
    ix = torch.floor(px)
    iy = torch.floor(py)
    inside = (ix >= 0) & (ix <= k - 1) & (iy >= 0) & (iy <= k - 1)
    mass = torch.where(inside, weights[..., None] * dt, torch.zeros_like(dt))
    idx = (iy.clamp(0, k - 1) * k + ix.clamp(0, k - 1)).long()
    out = torch.zeros(b, k * k, device=vertices.device, dtype=vertices.dtype)
    out.scatter_add_(1, idx.reshape(b, -1), mass.reshape(b, -1))
    return out.reshape(b, k, k)


def _broadcast_batch(*vectors: torch.Tensor) -> int:
    sizes = {v.shape[0] for v in vectors} - {1}
    if len(sizes) > 1:
        raise ValueError(f"per-sample arguments have incompatible batch sizes {sorted(sizes)} (each must be 1 or B)")
    return sizes.pop() if sizes else 1


def _check_length(length: torch.Tensor, k: int) -> None:
    check_finite(length, "length_px")
    bad = length > k
    if bool(bad.any()):
        raise ValueError(
            f"length_px = {show_outside(length[bad].flatten()[0].item(), 0.0, k, length.dtype)} px is out of the allowed "
            f"range [0, {k}] px for "
            f"kernel_size = {k}: a longer path could leave the kernel; use a larger kernel_size"
        )
    check_range(length, "length_px", 0.0, float(k), "px")


def linear_motion_psf(length_px: torch.Tensor, angle_deg: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """Linear motion-blur kernels (Eq. 3.10): a uniform line segment of length L at angle Φ.

    Args:
        length_px: (B,) blur lengths L = v_rel·t_exp in px, in ``[0, kernel_size]``.
        angle_deg: (B,) motion angle Φ in degrees (0° horizontal, counter-clockwise positive with y down,
            90° vertical); any finite value.
        kernel_size: odd kernel side k in px.

    Returns:
        (B, k, k) kernels summing to 1, the segment centred on the kernel centre, each pixel weighted by
        the segment length inside it. float64 if any input is float64, else float32; on ``length_px``'s
        device. (B = broadcast of the per-sample arguments, each of size 1 or B.)
    """
    k = check_odd_kernel_size(kernel_size)
    length = _batch_vector(length_px, "length_px")
    angle = _batch_vector(angle_deg, "angle_deg").to(length.device)
    b = _broadcast_batch(length, angle)
    _check_length(length, k)
    check_finite(angle, "angle_deg")
    out_dtype = _out_dtype(length, angle)
    work = _work_dtype(length.device)
    length = length.to(work).expand(b)
    phi = torch.deg2rad(angle.to(work)).expand(b)
    u = torch.stack([torch.cos(phi), -torch.sin(phi)], dim=-1)  # (B, 2)
    half = (0.5 * length)[:, None] * u
    vertices = torch.stack([-half, half], dim=1)  # (B, 2, 2)
    weights = torch.ones(b, 1, device=length.device, dtype=work)
    psf = _rasterise_polyline(vertices, weights, k)
    return (psf / psf.sum(dim=(-2, -1), keepdim=True)).to(out_dtype)


def sample_shake_noise(
    batch_size: int,
    n_steps: int = 64,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Draw the camera-shake noise of :func:`nonlinear_motion_psf`: standard normals (B, n_steps, 2).

    Channel 0 drives the heading, channel 1 the speed. This is the only random function of the module.

    Args:
        batch_size: B >= 1.
        n_steps: number of path steps (time samples) >= 2.
        generator: optional ``torch.Generator`` for reproducibility (must live on ``device``).
        device, dtype: of the result (floating dtype).
    """
    for name, v, low in (("batch_size", batch_size, 1), ("n_steps", n_steps, 2)):
        if isinstance(v, bool) or not isinstance(v, int):
            raise TypeError(f"{name} must be an int, got {type(v).__name__}")
        if v < low:
            raise ValueError(f"{name} = {v} is out of the allowed range [{low}, inf)")
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype}")
    return torch.randn(batch_size, n_steps, 2, generator=generator, device=device, dtype=dtype)


def _smoothing_matrix(n: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """(n, n) Gaussian smoothing whose rows have unit L2 norm (smoothed white noise keeps unit variance)."""
    sigma = max(n * _SMOOTH_FRACTION, 0.5)
    idx = torch.arange(n, device=device, dtype=dtype)
    s = torch.exp(-0.5 * ((idx[:, None] - idx[None, :]) / sigma) ** 2)
    return s / s.square().sum(dim=1, keepdim=True).sqrt()


def nonlinear_motion_psf(
    length_px: torch.Tensor,
    angle_deg: torch.Tensor,
    intensity: torch.Tensor,
    shake_noise: torch.Tensor,
    kernel_size: int,
) -> torch.Tensor:
    """Non-linear (camera-shake) motion-blur kernels: a coherent random path of arc length L.

    Deterministic given ``shake_noise`` (draw it with :func:`sample_shake_noise`). See the module
    docstring for the trajectory model and conventions.

    Args:
        length_px: (B,) arc length L of the path in px, in ``[0, kernel_size]``.
        angle_deg: (B,) mean motion direction Φ in degrees (0° horizontal, counter-clockwise positive
            with y down).
        intensity: (B,) shake intensity in [0, 1]: 0 → exactly :func:`linear_motion_psf` (straight line,
            uniform speed), 1 → strongly curved path with strongly varying speed.
        shake_noise: (B, N, 2) standard-normal noise, N >= 2 steps (channel 0: heading, 1: speed); entries beyond
            ±:data:`MAX_SHAKE_NOISE` are refused.
        kernel_size: odd kernel side k in px.

    Returns:
        (B, k, k) kernels summing to 1, the path's bounding box centred on the kernel centre. float64 if
        any input is float64, else float32; on ``length_px``'s device.
    """
    k = check_odd_kernel_size(kernel_size)
    length = _batch_vector(length_px, "length_px")
    dev = length.device
    angle = _batch_vector(angle_deg, "angle_deg").to(dev)
    inten = _batch_vector(intensity, "intensity").to(dev)
    noise = check_float(check_tensor(shake_noise, "shake_noise"), "shake_noise").to(dev)
    if noise.ndim != 3 or noise.shape[-1] != 2 or noise.shape[1] < 2 or noise.shape[0] < 1:
        raise ValueError(f"shake_noise must have shape (B, N >= 2, 2), got {tuple(noise.shape)}")
    check_finite(noise, "shake_noise")
    if noise.numel() and float(noise.abs().max()) > MAX_SHAKE_NOISE:  # exp(speed) would overflow into NaN steps
        raise ValueError(f"shake_noise must hold standard-normal draws, |value| ≤ {MAX_SHAKE_NOISE:g}; got "
                         f"{float(noise.abs().max()):g} (draw it with sample_shake_noise)")
    b = _broadcast_batch(length, angle, inten, noise)
    _check_length(length, k)
    check_finite(angle, "angle_deg")
    check_range(inten, "intensity", 0.0, 1.0)
    out_dtype = _out_dtype(length, angle, inten, noise)
    work = _work_dtype(dev)
    n = noise.shape[1]
    length, phi, inten = (v.to(work).expand(b)[:, None] for v in (length, torch.deg2rad(angle.to(work)), inten))
    noise = noise.to(work).expand(b, n, 2)

    smooth = _smoothing_matrix(n, dev, work)
    sm = torch.einsum("ij,bjc->bic", smooth, noise)  # (B, N, 2), unit variance, correlated over ~N/32 steps
    # A sum of N correlated unit-variance terms has variance N·g; scale so the walk's end spread is κ.
    g = smooth.sum(dim=1).square().mean()
    walk = torch.cumsum(sm[..., 0], dim=1) * (HEADING_SPREAD_RAD / torch.sqrt(n * g))
    walk = walk - walk.mean(dim=1, keepdim=True)
    heading = phi + inten * walk  # (B, N) rad; == Φ exactly at intensity 0
    speed = torch.exp(inten * SPEED_LOG_STD * sm[..., 1])  # (B, N) > 0; == 1 at intensity 0
    step = length * speed / speed.sum(dim=1, keepdim=True)  # arc length of each step, sums to L
    steps = step[..., None] * torch.stack([torch.cos(heading), -torch.sin(heading)], dim=-1)
    vertices = torch.cat([torch.zeros(b, 1, 2, device=dev, dtype=work), torch.cumsum(steps, dim=1)], dim=1)
    centre = 0.5 * (vertices.amax(dim=1, keepdim=True) + vertices.amin(dim=1, keepdim=True))
    vertices = vertices - centre
    weights = torch.full((b, n), 1.0 / n, device=dev, dtype=work)  # equal duration per step (dwell time)
    psf = _rasterise_polyline(vertices, weights, k)
    return (psf / psf.sum(dim=(-2, -1), keepdim=True)).to(out_dtype)
