from __future__ import annotations

import pytest
import torch

from lightning_modules import MTFEstimator, MTFPreprocess


@pytest.mark.parametrize("batch,stack", [(1, 1), (3, 1), (2, 3)])
def test_preprocess_shape(batch, stack):
    x = torch.rand(batch, stack, 64, 64)
    y = MTFPreprocess(4)(x)
    assert y.shape == (2 * batch * stack, 48, 16, 16)
    assert torch.isfinite(y).all()


def test_preprocess_v_branch_is_the_rotated_patch():
    x = torch.rand(1, 1, 32, 32)
    pre = MTFPreprocess(1)
    y = pre(x)
    rotated = pre(torch.rot90(x, 1, dims=(2, 3)))
    assert torch.allclose(y[1], rotated[0], atol=1e-6)


@pytest.mark.parametrize("fill", [0.0, 0.5, 1.0])
def test_flat_black_and_saturated_patches_are_finite(fill):
    m = MTFEstimator(patch_size=64).eval()
    with torch.no_grad():
        mtf = m(torch.full((2, 1, 64, 64), fill))["mtf"]
    assert mtf.shape == (2, 16) and torch.isfinite(mtf).all()
    assert ((mtf >= 0) & (mtf <= 1)).all()


def test_temporal_stack_of_identical_patches_equals_single_patch():
    torch.manual_seed(0)
    m = MTFEstimator(patch_size=64).eval()
    x = torch.rand(2, 1, 64, 64)
    with torch.no_grad():
        single = m(x)["mtf"]
        stacked = m(x.expand(2, 4, 64, 64).contiguous())["mtf"]
    assert torch.allclose(single, stacked, atol=1e-5)


def test_training_step_learns_on_blurred_batch():
    from datamodules import BlurDataModule

    torch.manual_seed(0)
    dm = BlurDataModule(source="deadleaves", source_kwargs={"n_images": 2, "size": (64, 64)}, patch_size=64, size_range=(1.0, 9.0))
    g = torch.Generator().manual_seed(0)
    batch = dm.corrupt(torch.rand(6, 1, 64, 64, generator=g), g)
    m = MTFEstimator(patch_size=64)
    opt = torch.optim.Adam(m.parameters(), lr=2e-3)
    losses = []
    for _ in range(25):
        loss = torch.nn.functional.l1_loss(m(batch["image"])["mtf"], batch["mtf"])
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert min(losses[-5:]) < 0.5 * losses[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(1, 1, 5, 7), (3, 2, 32, 24)])
def test_sobel_equals_kornia_spatial_gradient(dtype, shape):
    import kornia

    from lightning_modules.mtf import sobel

    x = torch.rand(*shape, generator=torch.Generator().manual_seed(0), dtype=dtype)
    ref = kornia.filters.spatial_gradient(x, mode="sobel", order=1, normalized=True)
    gx, gy = sobel(x)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert torch.allclose(gx, ref[:, :, 0], atol=tol) and torch.allclose(gy, ref[:, :, 1], atol=tol)
    xg = x[:1, :1, :5, :5].double().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: sobel(t)[0] + sobel(t)[1], (xg,))


def test_h_estimate_reads_the_v_features():
    """Through the network's own forward: pooled features are injected, and only the V pass's are changed."""

    class Given(torch.nn.Module):
        def __init__(self, f):
            super().__init__()
            self.f = f

        def forward(self, _x):
            return self.f

    torch.manual_seed(1)
    x = torch.rand(3, 1, 64, 64)
    net = MTFEstimator(patch_size=64).net.eval()
    feats = torch.randn(2 * 3, 3 * 96)  # (2·B·T, F): the H passes of the 3 patches, then their V passes
    other = feats.clone()
    other[3:] += 1.0
    with torch.no_grad():
        net.pool = Given(feats)
        h, v = net(x).split(8, dim=1)
        net.pool = Given(other)
        h_other, v_other = net(x).split(8, dim=1)
        net.pool = Given(feats.roll(3, dims=0))  # H and V features swapped: H and V estimates swap
        swapped = net(x)
    assert not torch.allclose(h, h_other) and not torch.allclose(v, v_other)
    assert torch.allclose(swapped, torch.cat([v, h], dim=1))
