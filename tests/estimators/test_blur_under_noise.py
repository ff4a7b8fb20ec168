"""Sec. 5.5: defocus pre-filter b₂, division by MTF(b₂), the three preconditions with ε = 0.05."""

import pytest
import torch

from camhealth.estimators.blur_under_noise import (
    EPSILON,
    PREFILTER_DIAMETER_PX,
    divide_out_prefilter,
    estimate_blur_under_noise,
    prefilter,
    prefilter_mtf,
)
from camhealth.estimators.charts import slanted_edge_chart
from camhealth.estimators.slanted_edge import slanted_edge_mtf_hv
from camhealth.metrics import amae
from camhealth.physics import apply_psf, linear_motion_psf, mtf_from_psf, mtf_hv
from camhealth.physics.defocus_psf import defocus_psf


def test_defaults_of_the_thesis():
    assert PREFILTER_DIAMETER_PX == 7.0 and EPSILON == 0.05


def test_prefilter_mtf_is_the_exact_kernel_mtf():
    m = prefilter_mtf(7.0)
    assert m.shape == (16,)
    assert torch.allclose(m, mtf_hv(defocus_psf(torch.tensor([7.0], dtype=torch.float64), 9))[0])


def test_preconditions_by_hand():
    m2 = torch.tensor([1.0, 0.8, 0.5, 0.2, 0.04, 0.5, 0.5, 0.3] * 2)
    overall = torch.tensor([[0.9, 0.4, 0.6, 0.1, 0.03, 0.04, 0.25, 0.3] * 2])
    q, valid = divide_out_prefilter(overall, m2, epsilon=0.05)
    # kept: 0.9/1, 0.4/0.8, 0.1/0.2, 0.25/0.5, 0.3/0.3; omitted: 0.6 > 0.5 (i), MTF(b2) = 0.04 (ii), 0.04 (iii)
    assert valid[0, :8].tolist() == [True, True, False, True, False, False, True, True]
    assert q[0, :8][valid[0, :8]].tolist() == pytest.approx([0.9, 0.5, 0.5, 0.5, 1.0])
    assert torch.isnan(q[0, 2]) and torch.isnan(q[0, 4])
    # the AMAE skips the omitted frequencies
    assert float(amae(q, torch.full((1, 16), 0.5))) == pytest.approx(100 * (0.4 + 0 + 0 + 0 + 0.5) / 5)


def test_prefilter_keeps_shape_dtype_and_mean():
    x = torch.rand(2, 1, 40, 40, dtype=torch.float64)
    y = prefilter(x)
    assert y.shape == x.shape and y.dtype == torch.float64
    assert float((y.mean() - x.mean()).abs()) < 0.01


def test_recovers_motion_blur_under_strong_noise_on_a_chart():
    """Linear motion b₁ (11 px, 0°) + noise σ = 25 DN on a slanted-edge chart: with b₂ = 7 px the
    slanted-edge estimate of MTF(b₁) is closer to the truth than without the pre-filter."""
    chart = slanted_edge_chart(256).double()
    b1 = linear_motion_psf(torch.tensor([11.0], dtype=torch.float64), torch.tensor([0.0], dtype=torch.float64), 13)
    g = torch.Generator().manual_seed(3)
    noisy = (apply_psf(chart, b1) + torch.randn(chart.shape, generator=g, dtype=torch.float64) * 25 / 255).clamp(0, 1)
    truth = mtf_from_psf(b1, (5.0, 95.0)).reshape(1, 16)  # the slanted edge measures at 5° / 95°
    direct = slanted_edge_mtf_hv(noisy)
    res = estimate_blur_under_noise(noisy, slanted_edge_mtf_hv)
    assert res.mtf.shape == (1, 16) and res.valid.any()
    assert float(amae(res.mtf, truth)) < float(amae(direct, truth))
    assert float(amae(res.mtf, truth)) < 6.0


def test_bad_arguments():
    with pytest.raises(ValueError, match="d2"):
        prefilter(torch.rand(1, 1, 16, 16), d2=-1.0)
    with pytest.raises(ValueError, match="epsilon"):
        divide_out_prefilter(torch.rand(1, 16), prefilter_mtf(), epsilon=1.5)
    with pytest.raises(ValueError, match=r"\(B, 16\)"):
        estimate_blur_under_noise(torch.rand(2, 1, 32, 32), lambda x: torch.rand(2, 8))


@pytest.mark.parametrize("scale", [255.0, 1.4])
def test_images_outside_0_1_are_refused(scale):
    """A DN-scale chart went through ``prefilter``'s clamp as a uniform 1.0 (and then "no edge found"); a chart reaching
    1.12 was clamped silently and read MTF 0.818 where the truth is 0.062. Both are refused, naming the range."""
    chart = apply_psf(slanted_edge_chart(256).double(), defocus_psf(torch.tensor([5.0], dtype=torch.float64), 7)) * scale
    hi = 0.8 * scale
    with pytest.raises(ValueError, match=rf"images must lie in \[0, 1\] \(DN/255\), got values in \[[\d.]+, {hi:g}"):
        prefilter(chart)
    with pytest.raises(ValueError, match=r"images must lie in \[0, 1\] \(DN/255\)"):
        estimate_blur_under_noise(chart, slanted_edge_mtf_hv)


def test_prefilter_stays_in_the_input_range():
    """b₂ is non-negative and sums to 1: the filtered image never leaves [min, max] of the input, beyond rounding."""
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(3, 1, 48, 48, generator=g, dtype=torch.float64) > 0.5).double()
    y = prefilter(x)
    assert float(y.min()) >= 0.0 and float(y.max()) <= 1.0
    z = apply_psf(x, defocus_psf(torch.tensor([7.0], dtype=torch.float64), 9))  # the convolution alone
    assert float((y - z).abs().max()) < 1e-12


@pytest.mark.parametrize("value_range, x, ok", [
    (None, torch.full((1, 1, 4, 4), 204.0), True),
    ((0.0, 1.0), torch.full((1, 1, 4, 4), 1.0), True),
    ((0.0, 1.0), torch.full((1, 1, 4, 4), 204.0), False),
    ((0.0, 1.0), torch.full((1, 1, 4, 4), -0.01), False),
    ((-1.0, 2.0), torch.full((1, 1, 4, 4), 1.5), True),
])
def test_check_image_range_is_opt_in(value_range, x, ok):
    from camhealth._validation import check_image

    if ok:
        assert check_image(x, "img", value_range=value_range) is x
    else:
        with pytest.raises(ValueError, match=r"img must lie in \[-?[\d.]+, [\d.]+\].*, got values in \["):
            check_image(x, "img", value_range=value_range)
