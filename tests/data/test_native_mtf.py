"""Native-MTF measurement: the slanted edge recovers a known blur on a rendered edge; the spectral estimate's
contract (shape, range of its inputs, a blurred source reads softer than the same source sharp)."""

from __future__ import annotations

import pytest
import torch

from camhealth.data.native_mtf import edge_native_mtf, spectral_native_mtf
from camhealth.estimators.charts import slanted_edge_chart, slanted_edge_rois
from camhealth.physics import apply_psf, gaussian_psf, mtf_hv


@pytest.mark.parametrize("sigma", [0.6, 1.0, 1.6])
def test_edge_recovers_a_known_blur_on_a_rendered_edge(sigma):
    chart = slanted_edge_chart(256).double()
    k = gaussian_psf(torch.tensor([sigma], dtype=torch.float64), 15)
    blurred = apply_psf(chart, k)
    r0, r1, c0, c1 = slanted_edge_rois(256)["left"]
    got = edge_native_mtf(blurred[:, :, r0:r1, c0:c1], aperture=True)[0]
    want = mtf_hv(k)[0, :8]  # the applied kernel's exact DFT: what a label of that blur is
    assert torch.allclose(got, want, atol=0.02), (got, want)
    sharp = edge_native_mtf(chart[:, :, r0:r1, c0:c1], aperture=True)[0]
    assert torch.allclose(sharp, torch.ones_like(sharp), atol=0.03)  # the rendering itself adds no blur


def test_spectral_estimate_reads_a_blurred_source_as_softer():
    from camhealth.data.dead_leaves import dead_leaves

    xs = [torch.as_tensor(dead_leaves((256, 256), seed=i)).double().reshape(1, 256, 256) for i in range(3)]
    k = gaussian_psf(torch.tensor([1.0], dtype=torch.float64), 11)
    ys = [apply_psf(x[None], k)[0] for x in xs]
    fn = (0.1, 0.3, 0.6)
    sharp, soft = spectral_native_mtf(xs, fn), spectral_native_mtf(ys, fn)
    assert sharp.shape == (3,) and bool((soft[1:] < sharp[1:] - 0.1).all())  # above the fit band: softer
    assert abs(float(sharp[0]) - 1.0) < 0.05 and abs(float(soft[0]) - 1.0) < 0.05  # in the fit band: 1 by construction


@pytest.mark.parametrize("kwargs,match", [
    ({"tile": 16}, "tile"), ({"fit_band": (0.3, 0.2)}, "fit_band"), ({"frequencies": (0.0, 0.5)}, "frequencies"),
])
def test_spectral_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        spectral_native_mtf(torch.rand(1, 128, 128), **kwargs)


def test_spectral_image_too_small():
    with pytest.raises(ValueError, match="smaller than tile"):
        spectral_native_mtf(torch.rand(1, 64, 200))
