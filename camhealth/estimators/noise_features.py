"""Physics the noise estimators compute in closed form instead of learning it.

- :func:`metadata_from_matrix` — (B, 11) raw metadata (``FULL_FIELDS`` order, physical units) →
  validated :class:`~camhealth.physics.CameraMetadata` (out-of-range values raise, naming field and range).
- :func:`physics_prior_dn` — the noise model's σ per source for the metadata the network is given
  (conventions.md): σ_PN = 255·√(g·Ī/FW) from the patch mean Ī of the (noisy) input, σ_DCSN = √(DC·t_exp)·g·255/FW
  (Eq. 3.14–3.15) and σ_RN (Eq. 3.16–3.19), all in DN, before clipping; plus their root-sum-square total.
  Dark-current and readout σ are exact functions of the metadata; σ_PN is exact up to the noise in Ī.
  With ``clipping=True`` also the same σ after clipping to [0, 255] DN (:func:`clipped_prior_dn`).
- :func:`image_statistics` — cheap per-patch scalars: mean intensity, its square root (σ_PN ∝ √I), the
  fractions of clipped pixels at 0 and 255 DN, and Immerkær's (1996) fast noise estimate
  σ ≈ √(π/2) · Σ|I ∗ N| / (6 (W−2)(H−2)) with the Laplacian-difference mask
  N = [[1, −2, 1], [−2, 4, −2], [1, −2, 1]] (I in DN), which texture inflates and the network corrects;
  and Donoho's robust median-absolute-deviation estimate on the finest diagonal Haar detail,
  d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 over 2×2 blocks (var d = σ² for white noise), σ ≈ median|d| / 0.6745,
  which edges barely move. (The noise-source networks read them.)
- :func:`block_details`, :func:`clipped_prior_dn` — the 2×2-block quantities of the noise-level fits and the σ the
  metadata predict after clipping, used by :mod:`camhealth.estimators.physics_noise`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from camhealth._order import _traced, lower_median
from camhealth._validation import check_image, check_range
from camhealth.estimators._common import check_patches
from camhealth.physics.clipping import _NEAR_SIGMAS, clipped_sigma_dn, estimate_clean_dn
from camhealth.physics.dark_current import dark_current_shot_sigma_e
from camhealth.physics.metadata import FULL_FIELDS, CameraMetadata, SensorConstants
from camhealth.physics.readout_noise import readout_sigma_e

__all__ = [
    "metadata_from_matrix", "physics_prior_dn", "clipped_prior_dn", "image_statistics", "laplace_difference", "box_mean3",
    "IMAGE_STATISTICS", "CLIP_TOLERANCE", "block_details", "plane_free_details", "truncated_second_moment",
]

#: Names of the columns of :func:`image_statistics`.
IMAGE_STATISTICS: tuple[str, ...] = (
    "mean", "sqrt_mean", "clipped_low", "clipped_high", "immerkaer_sigma_dn", "haar_mad_sigma_dn",
)

#: A pixel counts as clipped within half a DN of 0 or 255.
CLIP_TOLERANCE = 0.5 / 255.0


def metadata_from_matrix(meta_raw: torch.Tensor, constants: SensorConstants | None = None) -> CameraMetadata:
    """(B, 11) raw metadata in ``FULL_FIELDS`` order → :class:`CameraMetadata` (validated).

    The rows carry the 11 fields only: the fixed :class:`~camhealth.physics.metadata.SensorConstants` of the camera
    are ``constants`` (None: the defaults, those of every preset)."""
    if not isinstance(meta_raw, torch.Tensor) or meta_raw.ndim != 2 or meta_raw.shape[1] != len(FULL_FIELDS):
        shape = tuple(meta_raw.shape) if isinstance(meta_raw, torch.Tensor) else type(meta_raw).__name__
        raise ValueError(f"raw metadata must be a (B, {len(FULL_FIELDS)}) tensor in FULL_FIELDS order, got {shape}")
    if constants is not None and not isinstance(constants, SensorConstants):
        raise TypeError(f"constants must be SensorConstants or None, got {type(constants).__name__} {constants!r:.60}")
    fields = {n: meta_raw[:, i] for i, n in enumerate(FULL_FIELDS)}
    return CameraMetadata(**fields) if constants is None else CameraMetadata(**fields, constants=constants)


def physics_prior_dn(image: torch.Tensor, meta: CameraMetadata, cache: dict | None = None, clipping: bool = False) -> torch.Tensor:
    """Closed-form σ [DN] of (PN, DCSN, RN, total) for the metadata ``meta``, shape (B, 4), float32 ((B, 8) with
    ``clipping``).

    Args:
        image: B×1×H×W noisy patches in [0, 1] (floating point; integer DN images: divide by 255 first); only their
            mean intensity is used (for σ_PN), and with ``clipping`` their 3×3 means. Anything else raises a
            ``TypeError`` (not a floating tensor) or ``ValueError`` (shape, NaN/inf, values outside [0, 1]) naming it.
        meta: :class:`~camhealth.physics.CameraMetadata` of batch 1 or B, physical units (another type raises a
            ``TypeError``).
        cache: optional dict that keeps (σ_DCSN, σ_RN) [DN] per distinct metadata row between calls (an
            inference loop that sees the same camera state on every frame integrates the readout noise
            once); at most 64 rows are kept. Another type raises a ``TypeError``.
        clipping: also return, as columns 4–7, the σ [DN] of (PN, DCSN, RN, total) that the metadata predict
            *after* clipping to [0, 255] DN (:func:`clipped_prior_dn`), shape (B, 8). True or False (a string such
            as ``"no"`` raises a ``TypeError``).
    """
    check_patches(image, "image")
    if not isinstance(meta, CameraMetadata):
        raise TypeError(f"meta must be CameraMetadata (e.g. CameraMetadata.preset('ICX285') or "
                        f"CameraMetadata.lookup(path)), got {type(meta).__name__} {meta!r:.60}")
    if cache is not None and not isinstance(cache, dict):
        raise TypeError(f"cache = {cache!r:.60} must be a dict or None, got {type(cache).__name__}")
    if not isinstance(clipping, (bool, np.bool_)):
        raise TypeError(f"clipping = {clipping!r:.60} must be True or False, got {type(clipping).__name__}")
    b = image.shape[0]
    if meta.batch_size not in (1, b):
        raise ValueError(f"metadata batch {meta.batch_size} does not match the {b} patches")
    mean_i = image.detach().float().clamp(0, 1).flatten(1).mean(1).double()
    # Dark-current and readout σ depend on the metadata only: evaluate them once per distinct metadata row
    # (a monitored frame's patches share one camera state; the readout integral is the costly part).
    rows = torch.stack([getattr(meta, n).to(device=image.device, dtype=torch.float64) for n in FULL_FIELDS], dim=1)
    if rows.shape[0] == 1:
        unique, inverse = rows, torch.zeros(1, dtype=torch.long, device=rows.device)
    else:
        unique, inverse = torch.unique(rows, dim=0, return_inverse=True)
    keys = [(tuple(r), meta.constants) for r in unique.tolist()]  # the fixed sensor constants are part of the key
    found = [cache.get(k) if cache is not None else None for k in keys]
    todo = [i for i, f in enumerate(found) if f is None]
    if todo:
        meta64 = meta.to(device=image.device, dtype=torch.float64)
        first = torch.full((unique.shape[0],), rows.shape[0], dtype=torch.long, device=rows.device)
        first = first.scatter_reduce(0, inverse, torch.arange(rows.shape[0], device=rows.device), reduce="amin")
        distinct = meta64[first[torch.tensor(todo, dtype=torch.long, device=rows.device)]]
        dn = distinct.dn_per_electron
        values = torch.stack([dark_current_shot_sigma_e(distinct) * dn, readout_sigma_e(distinct) * dn,
                              distinct.gain_factor / distinct.full_well_e], dim=1).tolist()
        for i, v in zip(todo, values):
            found[i] = tuple(v)
            if cache is not None:
                if len(cache) >= 64:
                    cache.pop(next(iter(cache)))
                cache[keys[i]] = found[i]
    dc_u, rn_u, g_fw_u = torch.tensor(found, dtype=torch.float64, device=rows.device).unbind(1)
    dc, rn, g_fw = dc_u[inverse], rn_u[inverse], g_fw_u[inverse]
    if meta.batch_size == 1:
        dc, rn, g_fw = dc.expand(b), rn.expand(b), g_fw.expand(b)
    pn = 255.0 * (mean_i * g_fw).sqrt()
    total = (pn.pow(2) + dc.pow(2) + rn.pow(2)).sqrt()
    prior = torch.stack([pn, dc, rn, total], dim=1)
    if clipping:
        prior = torch.cat([prior, _clipped_prior_dn(image, 255.0 * g_fw, dc, rn)], dim=1)
    return prior.float()


def truncated_second_moment(u: torch.Tensor) -> torch.Tensor:
    """h(u) = E[z² | |z| < u] for z ~ N(0, 1): 1 − 2u·φ(u)/(2Φ(u) − 1), → u²/3 as u → 0 and 1 as u → ∞ (h(1) = 0.291,
    h(2) = 0.774, h(3) = 0.973; h(∞) = 1, h(u < 0) = h(0) = 0, NaN stays NaN). Elementwise, float64 inside, the input's
    dtype out (float64 for an integer input)."""
    if not isinstance(u, torch.Tensor):
        raise TypeError(f"u must be a torch.Tensor of real numbers, got {type(u).__name__} {u!r:.60}")
    # beyond u = 40 the tail 2u·φ(u) is below 1e-340, 0 in float64: h = 1 exactly (and ∞·e^−∞ gives no NaN)
    t = u.double().clamp(0.0, 40.0)
    tail = 2.0 * t * torch.exp(-0.5 * t * t) / math.sqrt(2.0 * math.pi) / torch.erf(t / math.sqrt(2.0)).clamp_min(1e-300)
    return torch.where(t < 1e-2, t * t / 3.0, 1.0 - tail).to(u.dtype if u.is_floating_point() else torch.float64)


# Inliers of the fits: |d| < 3 σ; E[d² | inlier] = _TRUNCATED_CHI2 · σ² for Gaussian d.
_INLIER_Z = 3.0
_TRUNCATED_CHI2 = float(truncated_second_moment(torch.tensor(_INLIER_Z, dtype=torch.float64)))
# Coarse-gradient test of the texture mask: χ²₂ at 99 %.
_TEXTURE_CHI2 = 9.21
# Fewer inlier details than this: a patch carries no evidence about its noise-level function.
_MIN_FIT_BLOCKS = 32


def block_details(image: torch.Tensor, caller: str = "block_details") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The 2×2-block quantities the noise fits are made from, float32 (B×1×H×W patches in [0, 1], H, W ≥ 8):
    block means m [DN] (B, 1, h, w); squared Haar details d² [DN²] (diagonal, horizontal, vertical; (3, B, 1, h, w));
    the usable mask (no pixel within ½ DN of 0 or 255, not on the patch border); and g², the squared central
    differences of the block means (the next coarser scale's gradient; noise variance v/2 each).

    ``image`` must be a floating B×1×H×W tensor of finite intensities (DN/255; integer DN images: divide by 255 first)
    within [−1, 2] — [0, 1] for an image, wider for the unclamped fold of a static pair
    (:func:`~camhealth.estimators.static_pair.pair_fold`), which a DN-scaled image (up to 255) is not. Another type or
    dtype raises a ``TypeError``, another shape, NaN/inf or a value outside [−1, 2] a ``ValueError``, naming it."""
    check_image(image, "image", channels=1)
    lo, hi = torch.aminmax(image.detach())
    if lo < -1.0 or hi > 2.0:
        raise ValueError(f"image must hold intensities in [0, 1] (DN/255; a static pair's unclamped fold within [-1, 2]), "
                         f"got values in [{lo.item():g}, {hi.item():g}]; integer DN images: divide by 255 first")
    x = image.detach().float()
    if x.shape[-1] < 8 or x.shape[-2] < 8:
        raise ValueError(f"{caller} needs patches of at least 8×8 px, got {tuple(x.shape[-2:])}")
    p00, p01, p10, p11 = _block_pixels(x)
    m = (p00 + p01 + p10 + p11) / 4.0
    lo = torch.minimum(torch.minimum(p00, p01), torch.minimum(p10, p11))
    hi = torch.maximum(torch.maximum(p00, p01), torch.maximum(p10, p11))
    usable = (lo > 0.5) & (hi < 254.5)
    usable[..., 0, :] = False
    usable[..., -1, :] = False
    usable[..., :, 0] = False
    usable[..., :, -1] = False
    d2 = torch.stack([(p00 - p01 - p10 + p11) / 2.0, (p00 + p01 - p10 - p11) / 2.0, (p00 - p01 + p10 - p11) / 2.0]).square()
    g2 = torch.zeros_like(m)
    g2[..., 1:-1, :] += (m[..., 2:, :] - m[..., :-2, :]).square()
    g2[..., :, 1:-1] += (m[..., :, 2:] - m[..., :, :-2]).square()
    return m, d2, usable, g2


def plane_free_details(image: torch.Tensor, d2: torch.Tensor, usable: torch.Tensor) -> torch.Tensor:
    """The squared details of :func:`block_details` with each patch's plane taken out of the horizontal and vertical
    ones.

    A scene that is a plane I = a + s_y·r + s_x·c [DN] puts −s_y into every horizontal Haar detail
    h = (I₀₀ + I₀₁ − I₁₀ − I₁₁)/2 and −s_x into every vertical one v = (I₀₀ − I₀₁ + I₁₀ − I₁₁)/2; the diagonal one never
    sees it. The patch's slopes are read as the medians of its usable blocks' signed h and v (robust to the edges and
    texture a few blocks carry; texture has slopes of both signs, which the median leaves at about 0) and subtracted,
    so a smooth ramp, vignetting or a sky gradient leaves white noise's σ² in them (the medians of n blocks add
    about πσ²/(2n), 4·10⁻⁴ σ² on a 128-px patch).

    Args:
        image: B×1×H×W patches in [0, 1] (H, W ≥ 8).
        d2: squared details [DN²] (3, B, 1, h, w) and ``usable`` the mask (B, 1, h, w), both of :func:`block_details`.

    Returns d² (3, B, 1, h, w) [DN²] float32, the diagonal as given; a patch without a usable block keeps its raw
    details.
    """
    p00, p01, p10, p11 = _block_pixels(image.detach().float())
    signed = torch.stack([(p00 + p01 - p10 - p11) / 2.0, (p00 - p01 + p10 - p11) / 2.0])  # (2, B, 1, h, w)
    b = signed.shape[1]
    # the median of the usable blocks by one order statistic of whole rows: the unusable ones go to −∞ and +∞ in
    # turn, so as many lie below as above the usable ones (where an odd number of blocks is unusable, the order
    # statistic next to their median)
    off = (~usable).reshape(b, -1)
    side = torch.where(off.cumsum(1) % 2 == 1, float("-inf"), float("inf"))
    rows = torch.where(off.unsqueeze(0), side.unsqueeze(0), signed.reshape(2, b, -1))
    slope = torch.where(off.all(1), 0.0, lower_median(rows)).view(2, b, 1, 1, 1)
    return torch.cat([d2[:1].float(), (signed - slope).square()])


def clipped_prior_dn(image: torch.Tensor, pn_slope: torch.Tensor, dcsn_dn: torch.Tensor, rn_dn: torch.Tensor) -> torch.Tensor:
    """σ [DN] of (PN, DCSN, RN, total) after clipping to [0, 255] DN, as the noise model predicts them for the
    scene of each noisy patch.

    The clean scene is recovered near the bounds from the noisy patch
    (:func:`~camhealth.physics.clipping.estimate_clean_dn`: the 3×3 mean inverted through the censored mean)
    and the per-pixel source variances σ_PN² = slope·x, σ_DCSN², σ_RN² are carried through the clipping in
    closed form (:func:`~camhealth.physics.clipping.clipped_sigma_dn`; the labels' attribution rule). Far from
    0 and 255 DN nothing is clipped and the result is the unclipped model; on a patch that is half black it is
    about 1/√2 of it. Given the metadata the image was made with, it is within 0.01 / 0.00 / 0.02 / 0.02 DN (RMS)
    of the σ an independent implementation of the sensor model realised, on photographs and street frames of every
    simulator variant (``python -m camhealth.bench robustness``, row ``closed_form``, matched).

    At a bound it reads high. The clean level recovered from a 3×3 mean is a point estimate clamped to [0, 255] DN,
    so the noise of the means pushes a level at a bound off it, and less clipping is predicted than happens.
    Measured on flat 128-px patches with their own metadata (ICX285 at 12 and 24 dB, EV76C661 at 18 dB, against the
    σ ``form_image`` realised), σ_Total reads:

    - 8.5–9.3 % high at 0 or 255 DN, which the estimators refuse as black or saturated;
    - 2.0–5.6 % high at 254 DN;
    - 2.5–3.3 % high on a patch half at 255 DN.

    A patch whose every pixel lies more than 6 σ(x) from both bounds (σ² = slope·x + σ_DCSN² + σ_RN², the test
    of :func:`~camhealth.physics.clipping.estimate_clean_dn`; its 3×3 means, which lie between the patch's extremes,
    then pass it too) has nothing clipped: its σ are the unclipped model's at the patch's mean intensity (the 3×3
    means with replicate borders sum to the patch's sum), read without the per-pixel moments (the values agree
    within 1e-6 DN, tested). Only the patches of a batch that come nearer a bound take the per-pixel path.

    Args:
        image: B×1×H×W noisy patches in [0, 1] (floating point; integer DN images: divide by 255 first). Anything
            else raises a ``TypeError`` (not a floating tensor) or ``ValueError`` (shape, NaN/inf, values outside
            [0, 1]) naming it.
        pn_slope: (B,) photon-noise variance per DN of signal, 255·g/FW [DN²/DN].
        dcsn_dn, rn_dn: (B,) dark-current and readout σ [DN] before clipping.
        Each of the three holds 1 value (for every patch) or B, finite and ≥ 0; another count, NaN, ±inf or a negative
        value raises a ``ValueError`` naming it.

    Returns (B, 4) float64.
    """
    check_patches(image, "image")
    b = image.shape[0]
    for name, value in (("pn_slope", pn_slope), ("dcsn_dn", dcsn_dn), ("rn_dn", rn_dn)):
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor of 1 or {b} values (one per patch), got {type(value).__name__}")
        if value.numel() not in (1, b):
            raise ValueError(f"{name} must hold 1 or {b} values (one per patch), got shape {tuple(value.shape)}")
        if value.dtype == torch.bool or value.is_complex():
            raise TypeError(f"{name} must hold real numbers, got dtype {value.dtype}")
        check_range(value.detach(), name, 0.0, math.inf, "DN²/DN" if name == "pn_slope" else "DN")
    return _clipped_prior_dn(image, pn_slope, dcsn_dn, rn_dn)


def _clipped_prior_dn(image: torch.Tensor, pn_slope: torch.Tensor, dcsn_dn: torch.Tensor, rn_dn: torch.Tensor) -> torch.Tensor:
    """:func:`clipped_prior_dn` of arguments the caller has checked."""
    with torch.autocast(device_type=image.device.type, enabled=False):
        f32, f64 = torch.float32, torch.float64  # per-pixel arithmetic in float32 (sums in float64): within 1e-5 DN of float64, 2× faster
        flat = image.detach().flatten(1)
        a64, dc64, rn64 = (t.to(f64).reshape(-1).expand(flat.shape[0]) for t in (pn_slope, dcsn_dn, rn_dn))
        c64 = dc64.square() + rn64.square()
        k = _NEAR_SIGMAS
        low_band = 0.5 * k * k * a64 + (0.25 * k**4 * a64.square() + k * k * c64).sqrt()  # x < k·σ(x) below it
        high_band = 255.0 - k * (a64 * 255.0 + c64).sqrt()  # x > 255 − k·σ(x) only above it
        lo, hi = flat.amin(1), flat.amax(1)  # (6× faster than aminmax along a dimension); where the test below passes,
        # they lie in [0, 1] and the clamp to [0, 1] changes nothing
        # (metadata that are not finite or a negative slope go to the per-pixel path, whose checks name them)
        far = (lo.double() * 255.0 >= low_band) & (hi.double() * 255.0 <= high_band) & (a64 >= 0) & torch.isfinite(a64 + c64)
        mean_dn = flat.sum(1, dtype=f64) * (255.0 / flat.shape[1])
        pn2 = (a64 * mean_dn).clamp_min(0)
        out = torch.stack([pn2.sqrt(), dc64.abs(), rn64.abs(), (pn2 + c64).sqrt()], 1)
        if bool(far.all()):
            return out
        near = (~far).nonzero(as_tuple=True)[0]
        a, dc2, rn2 = a64[near].to(f32), dc64[near].to(f32).pow(2), rn64[near].to(f32).pow(2)
        img = image.detach()[near].to(f32).clamp(0, 1) * 255.0
        x = estimate_clean_dn(img, a, dc2 + rn2, dtype=f32)
        return out.index_copy(0, near, clipped_sigma_dn(x, [a.view(-1, 1, 1, 1) * x, dc2, rn2], dtype=f32))


_LAPLACE_DIFF = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])


def laplace_difference(x: torch.Tensor) -> torch.Tensor:
    """Immerkær's mask N = [[1, −2, 1], [−2, 4, −2], [1, −2, 1]] over B×C×H×W without padding → (H−2)×(W−2).

    N is the outer product of [1, −2, 1] with itself, so it is applied as two second differences of shifted
    slices (exactly the 3×3 correlation, ~5× faster on CPU than a one-channel ``conv2d``)."""
    r = x[..., :, :-2] - 2.0 * x[..., :, 1:-1] + x[..., :, 2:]
    return r[..., :-2, :] - 2.0 * r[..., 1:-1, :] + r[..., 2:, :]


def box_mean3(x: torch.Tensor) -> torch.Tensor:
    """3×3 mean of B×C×H×W with replicate borders (= ``avg_pool2d(pad(x, 1, "replicate"), 3, stride=1)``),
    separably from shifted slices (~5× faster on CPU than ``avg_pool2d``).

    ``x`` must be a floating tensor of 4 dimensions (else a ``TypeError`` or ``ValueError`` naming it; only its type and
    shape are checked, so a network's forward that calls it stays traceable and exportable)."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"x must be a torch.Tensor (B×C×H×W), got {type(x).__name__}")
    if not x.dtype.is_floating_point:
        raise TypeError(f"x must be a floating tensor (B×C×H×W intensities), got dtype {x.dtype}"
                        + ("; convert integer DN images with x.float() / 255" if not x.dtype.is_complex else ""))
    if x.ndim != 4:
        raise ValueError(f"x must have shape B×C×H×W (4 dims), got {tuple(x.shape)}")
    p = F.pad(x, (1, 1, 1, 1), mode="replicate")
    r = p[..., :, :-2] + p[..., :, 1:-1] + p[..., :, 2:]
    return (r[..., :-2, :] + r[..., 1:-1, :] + r[..., 2:, :]) / 9.0


def image_statistics(image: torch.Tensor) -> torch.Tensor:
    """Per-patch scalars (B, 6) = (B, len(IMAGE_STATISTICS)) in the order of :data:`IMAGE_STATISTICS` (float32; see module docstring).

    ``image``: B×1×H×W patches in [0, 1] (floating point; integer DN images: divide by 255 first), H, W ≥ 3 (Immerkær's
    3×3 mask needs one full window). Anything else raises a ``TypeError`` (not a floating tensor) or ``ValueError``
    (shape, size, NaN/inf, values outside [0, 1]) naming it — except while the caller is traced or exported
    (a network's forward), where the graph cannot hold the data-dependent check.

    Always computed in float32, also under bf16 autocast (bf16 cannot resolve 1 DN at 255 DN)."""
    if not _traced():
        check_patches(image, "image", min_size=(3, 3))
    if torch.is_autocast_enabled(image.device.type):
        with torch.autocast(device_type=image.device.type, enabled=False):
            return _image_statistics(image.float())
    return _image_statistics(image.float())


def _block_pixels(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The four pixels I₀₀, I₀₁, I₁₀, I₁₁ [DN] of every 2×2 block of B×1×H×W patches in [0, 1], each
    B×1×⌊H/2⌋×⌊W/2⌋ (an odd last row or column is dropped)."""
    h, w = (x.shape[-2] // 2) * 2, (x.shape[-1] // 2) * 2
    q = x[..., :h, :w] * 255.0
    return q[..., 0::2, 0::2], q[..., 0::2, 1::2], q[..., 1::2, 0::2], q[..., 1::2, 1::2]


def _haar_blocks(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """|d| and the mean [DN] of every 2×2 block of B×1×H×W patches in [0, 1], each (B, ⌊H/2⌋·⌊W/2⌋), with
    d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 the finest diagonal Haar detail (var d = σ² for white noise)."""
    a, b, c, e = _block_pixels(x)
    return ((a - b - c + e) / 2.0).abs().flatten(1), ((a + b + c + e) / 4.0).flatten(1)


def _image_statistics(x: torch.Tensor) -> torch.Tensor:
    mean = x.flatten(1).mean(1)
    low = (x <= CLIP_TOLERANCE).float().flatten(1).mean(1)
    high = (x >= 1.0 - CLIP_TOLERANCE).float().flatten(1).mean(1)
    resp = laplace_difference(x * 255.0).abs().flatten(1).mean(1)
    immerkaer = math.sqrt(math.pi / 2.0) * resp / 6.0
    mad = lower_median(_haar_blocks(x)[0]) / 0.6745
    return torch.stack([mean, mean.clamp_min(0).sqrt(), low, high, immerkaer, mad], dim=1)
