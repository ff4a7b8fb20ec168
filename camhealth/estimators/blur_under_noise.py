"""Blur estimation in the presence of high noise: extra defocus pre-filter b₂ (thesis Sec. 5.5, Fig. 5.15).

Strong sensor noise that follows the blur (DCSN, readout noise, σ ≳ 10 DN) hides the missing high
frequencies and makes MTF estimators see a sharp image. Noise that *precedes* a defocus blur, on the other
hand, hardly disturbs the estimation of that defocus (Sec. 5.4). So the noisy image I* = b₁ ⊛ x + n is
filtered once more with a known defocus disk b₂ of diameter d₂ (default 7 px, the thesis's best
trade-off between suppressing noise and keeping detail):

    I** = b₂ ⊛ I* = (b₂ ⊛ b₁) ⊛ x + b₂ ⊛ n,

the overall MTF is estimated from I**, MTF^(b₁, b₂) = MTF^(b₁)·MTF(b₂) (convolution theorem), and the known
MTF of b₂ — the exact MTF of the sampled kernel, :func:`camhealth.physics.mtf_hv` — is divided out:

    MTF^(b₁) ≈ MTF^(b₁, b₂) / MTF(b₂).

The division is kept only at the sampled frequencies where three preconditions hold (ε = 0.05):
(i) MTF^(b₁, b₂) ≤ MTF(b₂), (ii) MTF(b₂) > ε, (iii) MTF^(b₁, b₂) > ε; the other frequencies are omitted
(NaN, with a ``valid`` mask) — the AMAE of :mod:`camhealth.metrics` skips them.

Works with any MTF estimator that maps ``B×1×H×W`` images to (B, 16) H/V MTFs (the learned MTF estimator,
or a chart-based measurement such as :func:`~camhealth.estimators.slanted_edge.slanted_edge_mtf_hv`).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from typing import Callable

import torch

from camhealth._validation import check_float, check_image, check_tensor
from camhealth.physics.defocus_psf import default_kernel_size, defocus_psf
from camhealth.physics.image_formation import apply_psf
from camhealth.physics.mtf import NORMALIZED_FREQUENCIES, mtf_hv

__all__ = ["PREFILTER_DIAMETER_PX", "EPSILON", "BlurUnderNoiseResult", "prefilter", "prefilter_mtf", "divide_out_prefilter", "estimate_blur_under_noise"]

#: Diameter d₂ of the defocus pre-filter b₂ recommended by the thesis (px).
PREFILTER_DIAMETER_PX: float = 7.0
#: Precondition threshold ε of Sec. 5.5.
EPSILON: float = 0.05


@dataclass
class BlurUnderNoiseResult:
    """MTF of the first blur b₁ after dividing out b₂.

    Attributes:
        mtf: (B, 16) estimate of MTF(b₁); NaN at omitted frequencies.
        valid: (B, 16) bool, True where the three preconditions held.
        overall: (B, 16) the estimate on the pre-filtered image, MTF^(b₁, b₂).
        prefilter_mtf: (16,) MTF of b₂.
    """

    mtf: torch.Tensor
    valid: torch.Tensor
    overall: torch.Tensor
    prefilter_mtf: torch.Tensor


def _check_diameter(d2: float) -> float:
    if isinstance(d2, bool) or not isinstance(d2, numbers.Real):  # NumPy floats and ints are Real; bool is not a number
        raise TypeError(f"prefilter diameter d2 must be a real number (px), got {d2!r} ({type(d2).__name__})")
    if not (0.0 <= float(d2) <= 63.0):
        raise ValueError(f"prefilter diameter d2 = {float(d2):g} px is out of the allowed range [0, 63] px")
    return float(d2)


def _check_epsilon(epsilon: float) -> float:
    if isinstance(epsilon, bool) or not isinstance(epsilon, numbers.Real):
        raise TypeError(f"epsilon must be a real number in [0, 1), got {epsilon!r} ({type(epsilon).__name__})")
    if not (0.0 <= float(epsilon) < 1.0):
        raise ValueError(f"epsilon = {float(epsilon):g} is out of the allowed range [0, 1)")
    return float(epsilon)


def _kernel(d2: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    d = torch.tensor([d2], dtype=torch.float64)
    return defocus_psf(d, default_kernel_size(d2)).to(device=device, dtype=dtype)


def prefilter_mtf(d2: float = PREFILTER_DIAMETER_PX) -> torch.Tensor:
    """(16,) H/V MTF of the defocus pre-filter b₂ of diameter ``d2`` px (exact, of the sampled kernel)."""
    d2 = _check_diameter(d2)
    return mtf_hv(_kernel(d2, torch.float64, torch.device("cpu")))[0]


def prefilter(images: torch.Tensor, d2: float = PREFILTER_DIAMETER_PX) -> torch.Tensor:
    """Apply the defocus disk b₂ (diameter ``d2`` px, reflect borders) to a batch ``B×1×H×W`` in [0, 1]; same dtype.

    Images outside [0, 1] (DN/255; e.g. 8-bit DN values not divided by 255) raise a ``ValueError`` naming their range.
    b₂ is non-negative and sums to 1, so the result stays in the input's range; the final clamp to [0, 1] only
    removes the last-bit rounding of the convolution at 0 and 1.
    """
    x = check_image(images, "images", channels=1, value_range=(0.0, 1.0))
    d2 = _check_diameter(d2)
    work = torch.float64 if x.dtype == torch.float64 else torch.float32
    return apply_psf(x.to(work), _kernel(d2, work, x.device)).clamp(0.0, 1.0).to(x.dtype)


def divide_out_prefilter(
    overall: torch.Tensor, b2_mtf: torch.Tensor, epsilon: float = EPSILON
) -> tuple[torch.Tensor, torch.Tensor]:
    """MTF^(b₁) = MTF^(b₁, b₂) / MTF(b₂) where the preconditions of Sec. 5.5 hold, NaN elsewhere.

    Args:
        overall: (…, 16) estimated overall MTF; b2_mtf: (16,) or another shape that broadcasts to ``overall``'s
            (``ValueError`` otherwise, naming both shapes).
        epsilon: threshold ε of preconditions (ii) and (iii), a real number in [0, 1) (``TypeError`` for another type).

    Returns:
        (mtf, valid): the quotient (NaN where omitted) and the bool mask of kept frequencies.
    """
    o = check_float(check_tensor(overall, "overall"), "overall")
    m2 = check_float(check_tensor(b2_mtf, "b2_mtf"), "b2_mtf").to(device=o.device, dtype=o.dtype)
    try:
        fits = torch.broadcast_shapes(o.shape, m2.shape) == o.shape
    except RuntimeError:
        fits = False
    if not fits:
        raise ValueError(f"b2_mtf {tuple(m2.shape)} must broadcast to the shape of overall {tuple(o.shape)} (one MTF "
                         f"value per frequency of overall's last dimension)")
    epsilon = _check_epsilon(epsilon)
    valid = (o <= m2) & (m2 > epsilon) & (o > epsilon) & torch.isfinite(o)
    q = o / torch.where(m2 > 0, m2, torch.ones_like(m2))
    return torch.where(valid, q, torch.full_like(q, float("nan"))), valid


def estimate_blur_under_noise(
    images: torch.Tensor,
    mtf_estimator: Callable[[torch.Tensor], torch.Tensor],
    d2: float = PREFILTER_DIAMETER_PX,
    epsilon: float = EPSILON,
) -> BlurUnderNoiseResult:
    """Pre-filter with b₂, estimate the overall MTF with ``mtf_estimator`` and divide out MTF(b₂).

    Args:
        images: noisy ``B×1×H×W`` batch in [0, 1] (DN/255; values outside raise a ``ValueError``).
        mtf_estimator: callable images → (B, 16) H/V MTF.
        d2: pre-filter diameter in px (thesis: 7 or 11; 7 worked best).
        epsilon: precondition threshold ε.
    """
    images = check_image(images, "images", channels=1, value_range=(0.0, 1.0))
    _check_epsilon(epsilon)  # before the estimator runs
    filtered = prefilter(images, d2)
    overall = mtf_estimator(filtered)
    overall = check_float(check_tensor(overall, "mtf_estimator output"), "mtf_estimator output")
    if overall.shape != (images.shape[0], 2 * len(NORMALIZED_FREQUENCIES)):
        raise ValueError(f"mtf_estimator must return (B, 16) H/V MTFs, got shape {tuple(overall.shape)}")
    m2 = prefilter_mtf(d2)
    mtf, valid = divide_out_prefilter(overall, m2, epsilon)
    return BlurUnderNoiseResult(mtf=mtf, valid=valid, overall=overall, prefilter_mtf=m2.to(overall.dtype))
