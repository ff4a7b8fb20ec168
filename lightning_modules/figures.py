"""Matplotlib figures the estimators log to TensorBoard (and the benchmark/model cards reuse).

- :func:`sigma_scatter_figure` — σ̂ against σ per noise source, with the identity line and RMS per panel.
- :func:`mtf_curves_figure` — estimated against true MTF (H and V) for a few patches.
- :func:`patch_grid_figure` — patches with a caption each (estimate vs truth).
"""

from __future__ import annotations

from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from camhealth.physics.mtf import NORMALIZED_FREQUENCIES  # noqa: E402

__all__ = ["sigma_scatter_figure", "mtf_curves_figure", "patch_grid_figure"]


def sigma_scatter_figure(estimate: torch.Tensor, truth: torch.Tensor, names: Sequence[str], unit: str = "DN"):
    """One panel per column of (N, k) ``estimate``/``truth``: scatter, identity line, RMS in the title."""
    k = len(names)
    fig, axes = plt.subplots(1, k, figsize=(3.0 * k, 3.0), squeeze=False)
    for i, (ax, name) in enumerate(zip(axes[0], names)):
        t, e = truth[:, i].float().numpy(), estimate[:, i].float().numpy()
        lo, hi = float(min(t.min(), e.min(), 0.0)), float(max(t.max(), e.max(), 1e-3))
        ax.plot([lo, hi], [lo, hi], color="0.6", lw=1)
        ax.scatter(t, e, s=4, alpha=0.5)
        rms = float(((estimate[:, i] - truth[:, i]).double().pow(2).mean().sqrt()))
        ax.set_title(f"{name}: RMS {rms:.2f} {unit}", fontsize=9)
        ax.set_xlabel(f"true σ [{unit}]", fontsize=8)
        ax.set_ylabel(f"estimated σ [{unit}]", fontsize=8)
    fig.tight_layout()
    return fig


def mtf_curves_figure(estimate: torch.Tensor, truth: torch.Tensor, captions: Sequence[str] | None = None, n: int = 6):
    """Estimated (dashed) vs true (solid) MTF, H and V, for the first ``n`` samples of (N, 16) tensors."""
    n = min(n, estimate.shape[0])
    f = list(NORMALIZED_FREQUENCIES)
    fig, axes = plt.subplots(1, max(n, 1), figsize=(2.6 * max(n, 1), 2.6), squeeze=False)
    for j in range(n):
        ax = axes[0][j]
        for o, (name, color) in enumerate((("H", "tab:blue"), ("V", "tab:orange"))):
            ax.plot(f, truth[j, 8 * o : 8 * o + 8].tolist(), color=color, label=f"{name} true")
            ax.plot(f, estimate[j, 8 * o : 8 * o + 8].tolist(), color=color, ls="--", label=f"{name} est.")
        ax.set_ylim(-0.05, 1.05)
        ax.set_xlabel("f / f_Nyquist", fontsize=8)
        if captions is not None:
            ax.set_title(captions[j], fontsize=8)
    axes[0][0].legend(fontsize=6)
    fig.tight_layout()
    return fig


def patch_grid_figure(images: torch.Tensor, captions: Sequence[str], n: int = 8):
    """The first ``n`` B×1×H×W patches in gray with a caption each."""
    n = min(n, images.shape[0])
    fig, axes = plt.subplots(1, max(n, 1), figsize=(2.2 * max(n, 1), 2.5), squeeze=False)
    for j in range(n):
        ax = axes[0][j]
        ax.imshow(images[j, 0].float().numpy(), cmap="gray", vmin=0, vmax=1)
        ax.set_title(captions[j], fontsize=7)
        ax.axis("off")
    fig.tight_layout()
    return fig
