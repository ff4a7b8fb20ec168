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


def test_spectral_list_element_with_a_batch_pools_all_its_images():
    """A B×1×H×W element of the list gives all its B images, as the same images stacked in one tensor or listed one by
    one (not only its first)."""
    from camhealth.data.dead_leaves import dead_leaves

    sharp = torch.as_tensor(dead_leaves((128, 128), seed=0)).double().reshape(1, 1, 128, 128)
    k = gaussian_psf(torch.tensor([1.5], dtype=torch.float64), 13)
    blurred = torch.cat([apply_psf(torch.as_tensor(dead_leaves((128, 128), seed=i)).double().reshape(1, 1, 128, 128), k)
                         for i in (1, 2, 3)])  # 3×1×H×W
    fn = (0.3, 0.6)
    stacked = spectral_native_mtf(torch.cat([sharp, blurred]), fn, tile=64)
    one_by_one = spectral_native_mtf([sharp[0], *blurred], fn, tile=64)
    assert torch.allclose(spectral_native_mtf([sharp, blurred], fn, tile=64), stacked)
    assert torch.allclose(one_by_one, stacked)
    assert bool((spectral_native_mtf([sharp, blurred[:1]], fn, tile=64) > stacked + 0.05).all())  # fewer soft images: sharper


@pytest.mark.parametrize("kwargs,match", [
    ({"tile": 16}, "tile"), ({"fit_band": (0.3, 0.2)}, "fit_band"), ({"frequencies": (0.0, 0.5)}, "frequencies"),
])
def test_spectral_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        spectral_native_mtf(torch.rand(1, 128, 128), **kwargs)


def test_spectral_image_too_small():
    with pytest.raises(ValueError, match="smaller than tile"):
        spectral_native_mtf(torch.rand(1, 64, 200))


@pytest.mark.parametrize("s", [1, 2, 4, 8])
def test_rendered_native_mtf_matches_the_closed_form_of_point_sample_averaging(s):
    """A pixel that is the mean of s×s point samples has, against the exact pixel area integral, the MTF
    sin(πf)/(s·sin(πf/s)) / sinc(f) (f = f_n/2 cycles/px): 1/sinc for s = 1 (no aperture), → 1 as s grows."""
    import math

    from camhealth.data.native_mtf import rendered_native_mtf

    fn = torch.tensor([0.1, 0.3, 0.6], dtype=torch.float64)
    f = fn / 2
    closed = torch.sin(math.pi * f) / (s * torch.sin(math.pi * f / s)) / torch.special.sinc(f)
    got = rendered_native_mtf(s, fn.tolist())
    assert torch.allclose(got.double(), closed, atol=0.025), (got, closed)


def test_rendered_native_mtf_rejects_bad_supersample():
    from camhealth.data.native_mtf import rendered_native_mtf

    with pytest.raises(ValueError, match=r"supersample = 9 is out of the allowed range \[1, 8\]"):
        rendered_native_mtf(9)


def test_street_edge_native_mtf_contract():
    from camhealth.data.native_mtf import STREET_EDGE_ROIS, street_edge_native_mtf

    m = street_edge_native_mtf((0.05, 0.3, 0.6))
    assert m.shape == (len(STREET_EDGE_ROIS), 3) and bool(torch.isfinite(m).all())
    assert bool((m[:, 0] > 0.85).all())  # near 1 at low frequency
    assert bool((m[:, 2] < 0.5).all())  # the clip is soft at f_n 0.6 (docs/data.md)


def test_native_mtf_cli(monkeypatch, capsys):
    from camhealth.data import native_mtf

    monkeypatch.setattr(native_mtf, "native_mtf_report", lambda f: [
        {"source": "a", "method": "m1", "mtf": 0.99, "passes": True},
        {"source": "b", "method": "m2", "mtf": (0.1, 0.2, 0.3), "passes": False},
        {"source": "c", "method": "m3", "mtf": 0.5, "passes": None}])
    assert native_mtf.main(["--frequency", "0.5"]) == 0
    out = capsys.readouterr().out
    assert "native MTF at f_n = 0.5" in out and "| a | 0.990 | yes | m1 |" in out
    assert "| b | 0.20 (0.10–0.30) | no | m2 |" in out and "| c | 0.500 | unknown | m3 |" in out
    with pytest.raises(SystemExit):
        native_mtf.main(["--frequency", "1.5"])
    assert "out of the allowed range (0, 1]" in capsys.readouterr().err
