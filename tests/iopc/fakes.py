"""Small fakes shared by the IOPC, control and callback tests: an estimator pair with the
``camhealth.inference`` predict contract and a noise-sensitive detector with known boxes."""

from __future__ import annotations

import math

import torch

from camhealth.detection import Detection
from camhealth.iopc.estimation import ImmerkaerNoiseEstimator


class FakeNoiseEstimator:
    """kind noise_source, minimal metadata: σ_total from Immerkær's estimator, split 0/0/all to RN.
    Records every batch it sees (``calls``: number of patches, metadata batch size)."""

    kind = "noise_source"
    metadata_set = "minimal"
    name = "fake-noise"

    def __init__(self, patch_size: int = 32) -> None:
        self.patch_size = patch_size
        self.calls: list[tuple[int, int | None]] = []
        self._classical = ImmerkaerNoiseEstimator(patch_size)

    def predict(self, patches, metadata=None):
        if metadata is None:
            raise ValueError("metadata required")
        assert patches.shape[-1] == self.patch_size
        self.calls.append((patches.shape[0], metadata.batch_size))
        out = self._classical.predict(patches)
        s = out["sigma_total"]
        return {"sigma_total": s, "sigma": torch.stack([0 * s, 0 * s, s], 1), "xi": 0 * s,
                "assessable": out["assessable"], "reason": [""] * len(s)}


class FakeMTFEstimator:
    """kind mtf: returns a constant MTF (indicator ``value``)."""

    kind = "mtf"
    metadata_set = "none"
    name = "fake-mtf"

    def __init__(self, value: float = 0.8, patch_size: int = 48) -> None:
        self.value, self.patch_size = value, patch_size
        self.calls: list[int] = []

    def predict(self, patches, metadata=None):
        self.calls.append(patches.shape[0])
        b = patches.shape[0]
        return {"mtf": torch.full((b, 16), self.value), "assessable": torch.ones(b, dtype=torch.bool)}


class NoiseSensitiveDetector:
    """Returns fixed ``boxes`` on every image with score 0.95 − σ̂/10 (σ̂: Immerkær on the whole image,
    DN) — AP 1 on clean images, 0 once σ̂ > 4.5 DN. Counts calls."""

    name = "noise-sensitive-fake"

    def __init__(self, boxes: list[list[float]]) -> None:
        self.boxes = torch.tensor(boxes, dtype=torch.float32)
        self.n_calls = 0
        self.last_images: torch.Tensor | None = None

    def config(self):
        return {"name": self.name, "boxes": self.boxes.tolist()}

    def __call__(self, images):
        self.n_calls += 1
        self.last_images = images.detach().cpu()
        est = ImmerkaerNoiseEstimator().predict(images.float().cpu())["sigma_total"]  # whole images: any size >= 8 px
        out = []
        for s in est.tolist():
            score = min(max(0.95 - s / 10.0, 0.01), 1.0)
            n = len(self.boxes)
            out.append(Detection(boxes=self.boxes.clone(), scores=torch.full((n,), score),
                                 labels=torch.ones(n, dtype=torch.int64)))
        return out


def smooth_frames(n: int = 2, h: int = 96, w: int = 128, seed: int = 0) -> torch.Tensor:
    """Smooth textured frames in [0.2, 0.8] (sums of low-frequency sinusoids)."""
    g = torch.Generator().manual_seed(seed)
    y = torch.linspace(0, 1, h)[:, None]
    x = torch.linspace(0, 1, w)[None, :]
    frames = []
    for _ in range(n):
        a = torch.rand(4, generator=g) * 2 * math.pi
        img = 0.5 + 0.15 * torch.sin(6 * x + a[0]) * torch.cos(5 * y + a[1]) + 0.1 * torch.sin(11 * (x + y) + a[2])
        frames.append(img.clamp(0.2, 0.8))
    return torch.stack(frames)[:, None]
