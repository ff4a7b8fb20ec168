"""Tiles overlapping objects, patch-wise estimation with injected estimators, Eq. 4.4 medians."""

import pytest
import torch

from camhealth.iopc import (
    PHYSICS,
    ImmerkaerNoiseEstimator,
    estimate_regions,
    extract_tiles,
    median_estimates,
    overlap_mask,
    resolve_estimator,
    tile_grid,
)
from camhealth.iopc.estimation import RegionEstimates
from camhealth.physics import CameraMetadata
from tests.iopc.fakes import FakeMTFEstimator, FakeNoiseEstimator, smooth_frames


def test_tile_grid_centred_and_extract_matches_slicing():
    tiles = tile_grid(100, 130, 32)  # 3 × 4 tiles, offsets (2, 1)
    assert tiles.shape == (12, 4) and tiles[0].tolist() == [1, 2, 33, 34] and tiles[-1].tolist() == [97, 66, 129, 98]
    img = torch.rand(2, 1, 100, 130)
    got = extract_tiles(img, 32, torch.tensor([1, 0]), torch.tensor([5, 11]))
    x0, y0, x1, y1 = tiles[5].tolist()
    assert torch.equal(got[0, 0], img[1, 0, y0:y1, x0:x1])
    x0, y0, x1, y1 = tiles[11].tolist()
    assert torch.equal(got[1, 0], img[0, 0, y0:y1, x0:x1])
    with pytest.raises(ValueError, match="does not fit"):
        tile_grid(20, 20, 32)


def test_overlap_needs_positive_area():
    tiles = tile_grid(64, 64, 32)  # 4 tiles
    touching = torch.tensor([[32.0, 0, 40, 10]])  # starts at the border of tile 0
    assert overlap_mask(tiles, touching).tolist() == [False, True, False, False]
    assert overlap_mask(tiles, torch.tensor([[30.0, 30, 34, 34]])).tolist() == [True] * 4
    assert overlap_mask(tiles, torch.zeros(0, 4)).tolist() == [False] * 4


@pytest.mark.parametrize("batch", [1, 3])
def test_only_object_tiles_are_estimated(batch):
    frames = smooth_frames(batch, 96, 128)
    noise, mtf = FakeNoiseEstimator(32), FakeMTFEstimator(0.8, 48)
    regions = [torch.tensor([[20.0, 10, 30, 20]])] + [torch.zeros(0, 4)] * (batch - 1)
    meta = CameraMetadata.preset("ICX285", gain_db=6.0)
    est = estimate_regions(frames, regions, noise, mtf, metadata=meta)
    assert est.n_noise_tiles == 1 and est.n_mtf_tiles == 1  # one tile overlaps the box; other images: none
    assert noise.calls == [(1, 1)] and mtf.calls == [1]
    med = median_estimates(est)
    assert med["mtf_tilde"] == pytest.approx(0.8) and med["sigma_sources_tilde"][0] == 0.0
    est_all = estimate_regions(frames, regions, noise, mtf, metadata=meta, fallback_all=True)
    assert est_all.n_noise_tiles == 1 + (batch - 1) * 12  # images without objects: every 32-px tile


def test_metadata_required_and_output_checked():
    frames = smooth_frames(1, 64, 64)
    with pytest.raises(ValueError, match="needs camera metadata"):
        estimate_regions(frames, [torch.tensor([[0.0, 0, 64, 64]])], FakeNoiseEstimator(32), None)

    class Bad(FakeMTFEstimator):
        def predict(self, patches, metadata=None):
            return {"wrong": torch.zeros(patches.shape[0])}

    with pytest.raises(ValueError, match="lacks 'mtf'"):
        estimate_regions(frames, [torch.tensor([[0.0, 0, 64, 64]])], None, Bad(patch_size=32))


def test_physics_labels_are_the_realised_noise():
    g = torch.Generator().manual_seed(0)
    blurred = smooth_frames(2, 256, 256)
    noisy = (blurred + 0.02 * torch.randn(blurred.shape, generator=g)).clamp(0, 1)
    mtf = torch.full((2, 16), 0.7)
    est = estimate_regions(noisy, [torch.tensor([[0.0, 0, 256, 256]])] * 2, PHYSICS, PHYSICS,
                           physics={"blurred": blurred, "mtf": mtf, "sigma_dn": torch.tensor([[1.0, 0.0, 2.0]] * 2)})
    assert est.sigma.shape == (8,) and float(est.sigma.mean()) == pytest.approx(0.02 * 255, rel=0.03)
    assert torch.allclose(est.mtf, torch.full((2,), 0.7))  # 192-px tiles: one per image
    # per-source split keeps the image's ratio: PN² : RN² = 1 : 4
    src = est.sigma_sources
    assert torch.allclose(src[:, 2] / src[:, 0], torch.full((8,), 2.0))
    with pytest.raises(ValueError, match="need physics"):
        estimate_regions(noisy, [torch.zeros(1, 4)] * 2, PHYSICS, None, fallback_all=True)


@pytest.mark.parametrize("sigma_dn", [3.0, 10.0])
def test_immerkaer_recovers_white_noise(sigma_dn):
    g = torch.Generator().manual_seed(1)
    clean = smooth_frames(4, 128, 128)
    noisy = clean + sigma_dn / 255 * torch.randn(clean.shape, generator=g)
    out = ImmerkaerNoiseEstimator().predict(noisy.clamp(0, 1))
    assert out["sigma_total"].shape == (4,) and bool(out["assessable"].all())
    assert float(out["sigma_total"].mean()) == pytest.approx(sigma_dn, rel=0.08)
    assert not bool(ImmerkaerNoiseEstimator().predict(torch.zeros(1, 1, 128, 128))["assessable"][0])


def test_median_is_midpoint_for_even_counts_and_nan_when_empty():
    e = RegionEstimates(torch.tensor([1.0, 2.0, 4.0, 10.0]), None, torch.zeros(4, dtype=torch.long),
                        torch.zeros(0), torch.zeros(0, dtype=torch.long), 4, 0)
    med = median_estimates(e)
    assert med["sigma_tilde"] == 3.0 and med["mtf_tilde"] != med["mtf_tilde"]


def test_resolve_estimator():
    assert resolve_estimator("physics", "mtf") == PHYSICS
    assert isinstance(resolve_estimator("immerkaer", "noise"), ImmerkaerNoiseEstimator)
    fake = FakeMTFEstimator()
    assert resolve_estimator(fake, "mtf") is fake
    with pytest.raises(ValueError, match="expected one of \\['mtf'\\]"):
        resolve_estimator(FakeNoiseEstimator(), "mtf")
    with pytest.raises(ValueError, match="cannot estimate the MTF"):
        resolve_estimator("immerkaer", "mtf")
    with pytest.raises(TypeError, match="lacks 'kind'"):
        resolve_estimator(object(), "noise")
    with pytest.raises(ValueError, match="role"):
        resolve_estimator(fake, "blur")


def test_estimator_fingerprint_changes_with_the_weights_not_the_name(tmp_path):
    """Retrained weights under the same file name must not reuse an IOPC sweep's cached cells."""
    import shutil
    from pathlib import Path

    import camhealth
    from camhealth import load_estimator
    from camhealth.export import export_weights
    from camhealth.iopc.estimation import estimator_fingerprint, estimator_name
    from lightning_modules import MTFEstimator

    a, b = tmp_path / "a" / "mtf.pt", tmp_path / "b" / "mtf.pt"
    a.parent.mkdir()
    b.parent.mkdir()
    shutil.copy(Path(camhealth.__file__).parent / "weights" / "mtf.pt", a)
    ea = load_estimator(str(a))
    torch.manual_seed(0)
    export_weights(MTFEstimator(**ea.description["init_args"]), b)  # same architecture, untrained weights
    eb = load_estimator(str(b))
    assert estimator_fingerprint(ea) == estimator_fingerprint(load_estimator(str(a)))  # stable
    assert estimator_name(ea) == estimator_name(eb) and estimator_fingerprint(ea) != estimator_fingerprint(eb)
    assert estimator_fingerprint("physics") == "physics" and estimator_fingerprint(None) == "none"


def test_estimator_fingerprint_of_a_network_in_memory_follows_its_weights():
    """An estimator without a file (a training's module, as the IOPC callback sweeps it every few epochs): its
    current weights, so a later epoch never reuses an earlier epoch's cells."""
    from camhealth.iopc.estimation import estimator_fingerprint

    class InMemory(torch.nn.Module):
        kind, patch_size, metadata_set = "mtf", 48, "none"

        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(3))

    a = InMemory()
    before = estimator_fingerprint(a)
    assert estimator_fingerprint(a) == before  # stable
    with torch.no_grad():
        a.w.add_(1.0)
    assert estimator_fingerprint(a) != before


def test_immerkaer_refuses_dn_scaled_floats_and_patches_too_small_to_read():
    """A float patch in DN (0…255) read 255× too noisy (σ̂ 2544 DN for 10); a 2×2 patch crashed inside torch and a
    3×3 one was read from one coefficient: refused, named."""
    from camhealth.iopc.estimation import ImmerkaerNoiseEstimator

    est = ImmerkaerNoiseEstimator()
    g = torch.Generator().manual_seed(0)
    x = (128.0 + 10.0 * torch.randn(2, 1, 64, 64, generator=g)).clamp(0, 255)
    with pytest.raises(ValueError, match=r"patches must lie in \[0, 1\] \(DN/255\)"):
        est.predict(x)
    for side in (2, 3, 7):
        with pytest.raises(ValueError, match=rf"patches must be at least 8×8 px, got {side}×{side}"):
            est.predict(x[..., :side, :side] / 255.0)
    assert est.predict(x / 255.0)["sigma_total"] == pytest.approx([10.0, 10.0], rel=0.1)
