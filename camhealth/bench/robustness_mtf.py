"""Blur (MTF) estimation on PSFs and scenes camhealth's training never saw: ``python -m camhealth.bench robustness --task mtf``.

Every MTF estimator is scored on a matrix of

- **generators** — held out of training entirely (:mod:`camhealth.physics`): defocus as a Gaussian
  (:func:`~camhealth.physics.gaussian_psf`, size = 4σ, random sub-pixel shift), a 5–8-blade polygonal iris
  (:func:`~camhealth.physics.polygon_psf`, random rotation and shift), a donut (:func:`~camhealth.physics.ring_psf`,
  ε 0.3–0.7) and defocus with spherical aberration (:func:`~camhealth.physics.spherical_psf`, s ∈ [−1, 1]);
  linear motion rendered by point sampling with a sub-pixel shift and with an accelerating speed (another
  rasteriser than training's exact line coverage); non-linear motion as a random walk with inertia and jerks
  (:func:`~camhealth.physics.sample_random_walk`); and tiny random kernels on 2–5 px supports
  (:func:`~camhealth.physics.sample_tiny_psf`, size = support);
- **in-distribution** — training's own generators (disk, line, camera shake of intensity 0.5–1) on dead leaves rendered
  as the training scenes are (``configs/mtf_full.yaml``'s dead-leaves arguments, other seeds), and on the scene groups below, to separate the shift of the scenes from that of the PSFs;
- **sizes** — blur size (disk diameter, 4σ, path length, support) from ``--mtf-sizes`` (default 3 5 9 15 21 px);
- **scenes**, in three groups (each patch carries its group; the crops of a cell cycle :data:`GROUP_CYCLE`, so half
  of them are rendered); 192-px patches, one random crop each:

  - ``rendered`` — held-out scene classes rendered with an exact pixel aperture
    (:mod:`camhealth.bench.rendered_scenes`: line art, gradient-filled polygons and ellipses, 1/f^β texture; the
    mean of 8×8 point samples per pixel): their native MTF is 1 (closed form 1.002 at f_n 0.6), so the truth below
    is exact. The headline numbers are on this group;
  - ``photos`` — photographs without an exact truth, none in the MTF model's training (``configs/mtf*.yaml`` set
    ``include_skimage: false``): scikit-image's retina, immunohistochemistry and Hubble deep field (in no training
    source) and the photos of :data:`camhealth.data.skimage_photos.SKIMAGE_PHOTOS` (a noise-training source only),
    area-downsampled (:data:`SCENE_DOWNSAMPLE`);
  - ``street`` — the street frames area-downsampled 2× (native MTF ≈ 0.32 at f_n 0.6, ``docs/data.md``; not in the
    MTF model's training either: ``include_street: false``).

  On ``photos`` and ``street`` the truth ignores the scene's own blur (the photos' native MTF is unknown — no
  straight edges — and the street clip's is far below 1): a network that sees that blur is scored as wrong there.
  The ``native`` rows print the spectral estimate of each source (:func:`camhealth.data.native_mtf.spectral_native_mtf`),
  and for the rendered scenes their exact closed form beside the spectral estimate on them (its error where the truth is 1);
- **conditions** — clean (8-bit rounded); JPEG quality 75–95 (OpenCV) after the blur; white Gaussian noise
  σ 1–10 DN after the blur; 5 DN noise (the target: ≤ 1.5× the clean AMAE).

Truth is the exact DFT of each kernel (:func:`camhealth.physics.mtf_hv`). Printed: AMAE (Eq. 5.1, mean |Ĥ − H|
over the 16 values × 100, the training metric) on held-out generators × rendered scenes per family and condition,
per generator, per blur size (also on the assessable patches alone, with the signed error per rendered class) and
per rendered class, the ratio to the in-distribution value on dead leaves and, on clean patches, to the training
generators on the same rendered scenes (what the held-out PSFs alone cost, the scene shift taken out); per scene group (rendered, photos,
street) per family, for held-out and training generators;
the fraction of patches called assessable and the AMAE on those alone (a patch without edges — Gaussian-like texture,
whose steep spectrum and blur look alike — is not assessable, :func:`camhealth._inputs.has_edges`), ms per patch, and the uncertainty ``mtf_std`` (views 1 and 4; the
error table of ``python -m camhealth.bench mtf_error``, which is measured on training's generators only) against the
error on the assessable patches: the share of values within u and 2u, beside the views' spread alone; the clean
held-out patches again with white noise of 0–20 DN or JPEG q 95–75 after the blur (paired: the same patches in every
row, so the ratio to the untouched ones is the perturbation's alone), with row noise and with defective pixels. The classical reference is the ISO 12233 slanted
edge (:func:`~camhealth.estimators.slanted_edge.slanted_edge_mtf_hv`) on an area-rendered slanted-edge chart blurred
with the same held-out kernels — a scene that has an edge — beside the network on the same chart patches; its ROIs
sit on the rendered square's edges (:func:`chart_rois`) and it is scored against the exact MTF in the directions its
edges measure (5°/95°, :data:`CHART_ANGLE_DEG`; as ``bench classical``), and against the 0°/90° truth beside it.
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import json
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

import numpy as np
import torch
import torch.nn.functional as F

from camhealth.bench import BenchResult, Row

PATCH = 192
#: Area-downsampling of each photographed source (factor): photographs 2×, the 1411-px retina 4×, Hubble 3×, street 2×.
SCENE_DOWNSAMPLE = {"photo": 2, "retina": 4, "immunohistochemistry": 2, "hubble_deep_field": 3, "street": 2}
HELD_OUT_IMAGES = ("retina", "immunohistochemistry", "hubble_deep_field")
CONDITIONS = ("clean", "jpeg", "noise", "noise5")
FAMILIES = {
    "defocus": ("gaussian", "polygon", "ring", "spherical"),
    "linear": ("line_sampled", "line_accelerating"),
    "nonlinear": ("random_walk",),
    "tiny": ("tiny",),
}
IN_DIST = {"defocus": "disk", "linear": "line", "nonlinear": "shake"}
KERNEL = 31
#: Scene groups (module docstring): ``rendered`` has an exact truth; on ``photos`` and ``street`` the truth (the
#: kernel's MTF alone) ignores the scene's own blur.
GROUPS = ("rendered", "photos", "street")
#: The crops of one cell (generator × size × condition) cycle through these groups: half on rendered scenes.
GROUP_CYCLE = ("rendered", "photos", "rendered", "street")
#: Rendered scenes per class (:data:`camhealth.bench.rendered_scenes.CLASSES`) and their side (px).
RENDERED_PER_CLASS = 4
RENDERED_SIZE = 320
TRUTH_NOTE = "truth ignores the scene's own blur"
#: The slanted-edge chart of the reference: rendered at :data:`CHART_SIZE` px (the patch and the kernel's margin on
#: each side, which :func:`blur_patches` crops off), its square ``CHART_SQUARE_FRAC·CHART_SIZE`` px a side, rotated by
#: :data:`CHART_ANGLE_DEG`: its edges measure the MTF at 5° and 95°.
CHART_SIZE = PATCH + 2 * (KERNEL // 2 + 1)
CHART_SQUARE_FRAC = 0.5
CHART_ANGLE_DEG = 5.0


def chart_rois() -> dict[str, tuple[int, int, int, int]]:
    """The slanted-edge ROIs on the :data:`PATCH`-px chart patches: the chart of :data:`CHART_SIZE` px cropped to its
    centre keeps its square (``CHART_SQUARE_FRAC·CHART_SIZE`` px a side), which is ``CHART_SQUARE_FRAC·CHART_SIZE/PATCH``
    of the patch — not the default ROIs of a :data:`PATCH`-px chart, whose square is smaller."""
    from camhealth.estimators.charts import slanted_edge_rois

    return slanted_edge_rois(PATCH, CHART_ANGLE_DEG, square_frac=CHART_SQUARE_FRAC * CHART_SIZE / PATCH)


def _gray(arr: np.ndarray) -> torch.Tensor:
    from camhealth.data import to_gray

    a = arr.astype(np.float64) / 255.0
    if a.ndim == 3:
        a = to_gray(a[..., :3])
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).clamp(0, 1)[None]


def _area(x: torch.Tensor, factor: int) -> torch.Tensor:
    return F.avg_pool2d(x[None], factor)[0] if factor > 1 else x


def scene_sources(seed: int = 0) -> dict[str, list[tuple[str, torch.Tensor]]]:
    """The scenes by group, each ``(label, 1×H×W in [0, 1])`` at least 192 + 32 px on each side:

    - ``rendered``: :data:`RENDERED_PER_CLASS` scenes of :data:`RENDERED_SIZE` px of each class of
      :mod:`camhealth.bench.rendered_scenes` (label = class), rendered with seed ``seed`` + 2000;
    - ``photos``: scikit-image's photographs in no training source (``held_out_photo``) and those of
      :data:`~camhealth.data.skimage_photos.SKIMAGE_PHOTOS` (``skimage_photo``; a source of the noise training, not of
      the MTF model's), area-downsampled (:data:`SCENE_DOWNSAMPLE`);
    - ``street``: every 10th street frame, area-downsampled 2× (``street``)."""
    import skimage.data

    from camhealth.bench.rendered_scenes import CLASSES, render_scenes
    from camhealth.data.skimage_photos import SKIMAGE_PHOTOS, load_skimage_photo
    from camhealth.data.street_sample import StreetSampleSource

    rendered = [(cls, x) for cls in CLASSES for x in render_scenes(cls, RENDERED_PER_CLASS, RENDERED_SIZE, seed=seed + 2000)]
    held = [("held_out_photo", _area(_gray(np.asarray(getattr(skimage.data, n)())), SCENE_DOWNSAMPLE[n])) for n in HELD_OUT_IMAGES]
    photos = [("skimage_photo", _area(load_skimage_photo(n), SCENE_DOWNSAMPLE["photo"])) for n in SKIMAGE_PHOTOS]
    street = StreetSampleSource(stride=10)
    frames = [("street", _area(street[i][0].float(), SCENE_DOWNSAMPLE["street"])) for i in range(len(street))]
    keep = lambda xs: [x for x in xs if min(x[1].shape[-2:]) >= PATCH + KERNEL + 1]  # noqa: E731
    return {"rendered": keep(rendered), "photos": keep(held + photos), "street": keep(frames)}


def _dead_leaves(n: int, seed: int) -> list[torch.Tensor]:
    """``n`` dead-leaves scenes rendered as the shipped MTF schedule renders its training scenes (the dead-leaves
    arguments of ``configs/mtf_full.yaml``'s ``source_kwargs``: aperture, edge density, contrast, shading, coverage, thin
    leaves), another seed."""
    from camhealth.bench.estimators import mtf_training_source
    from camhealth.data.dead_leaves import DeadLeavesSource

    _, kwargs = mtf_training_source()
    keys = ("r_min", "r_max", "contrast", "supersample", "shading", "thin", "coverage")
    src = DeadLeavesSource(n, size=(256, 256), seed=seed, **{k: kwargs[k] for k in keys if k in kwargs})
    return [src[i][0].float().reshape(1, 256, 256) for i in range(n)]


def _point_line(length: torch.Tensor, angle: torch.Tensor, shift: torch.Tensor, speed_ramp: torch.Tensor) -> torch.Tensor:
    """Linear motion by dense point sampling (another rasteriser than training's exact coverage): 4096 equal-time
    samples along a segment of length L, position s(t) = L·(t + r t(t − 1))/… with r the speed ramp (0: uniform
    speed; r > 0: accelerating), moved by a sub-pixel shift; each sample counted in its pixel."""
    from camhealth.physics._psf_common import bin_points, normalise

    t = (torch.arange(4096, dtype=torch.float64) + 0.5) / 4096
    r = speed_ramp[:, None].double()
    s = (t[None] + r * t[None] * (t[None] - 1.0)) - 0.5  # in [−0.5, 0.5], monotone for r ≤ 1
    phi = torch.deg2rad(angle.double())[:, None]
    pos = length.double()[:, None] * s
    xy = torch.stack([pos * torch.cos(phi), -pos * torch.sin(phi)], -1) + shift.double()[:, None, :]
    return normalise(bin_points(xy, torch.ones(4096, dtype=torch.float64), KERNEL))


def make_kernels(gen_name: str, size: float, n: int, g: torch.Generator) -> torch.Tensor:
    """``n`` (KERNEL×KERNEL) float64 kernels of generator ``gen_name`` at blur size ``size`` px."""
    from camhealth import physics as ph

    u = torch.rand(n, 4, generator=g, dtype=torch.float64)
    d = torch.full((n,), float(size), dtype=torch.float64)
    shift = u[:, :2] - 0.5
    angle = 360.0 * u[:, 2]
    if gen_name == "gaussian":
        return ph.gaussian_psf(d / 4.0, KERNEL, shift)
    if gen_name == "polygon":
        blades = int(torch.randint(5, 9, (1,), generator=g))
        return ph.polygon_psf(d, blades, KERNEL, rotation_deg=angle, shift_px=shift)
    if gen_name == "ring":
        return ph.ring_psf(d, 0.3 + 0.4 * u[:, 3], KERNEL)
    if gen_name == "spherical":
        return ph.spherical_psf(d, 2.0 * u[:, 3] - 1.0, KERNEL, n_rings=48)
    if gen_name == "line_sampled":
        return _point_line(d, angle, shift, torch.zeros(n))
    if gen_name == "line_accelerating":
        return _point_line(d, angle, shift, 0.5 + 0.5 * u[:, 3])
    if gen_name == "random_walk":
        return ph.trajectory_psf(ph.sample_random_walk(n, 64, generator=g), d, KERNEL)
    if gen_name == "tiny":
        return ph.sample_tiny_psf(n, int(min(max(round(size), 2), 5)), KERNEL, generator=g, dtype=torch.float64)
    if gen_name == "disk":
        return ph.defocus_psf(d, KERNEL)
    if gen_name == "line":
        return ph.linear_motion_psf(d, angle, KERNEL)
    if gen_name == "shake":
        noise = ph.sample_shake_noise(n, generator=g, dtype=torch.float64)
        return ph.nonlinear_motion_psf(d, angle, 0.5 + 0.5 * u[:, 3], noise, KERNEL)
    raise ValueError(f"unknown generator {gen_name!r}")


def _jpeg(x: torch.Tensor, quality: int) -> torch.Tensor:
    import cv2

    u8 = (x[0].numpy() * 255.0).round().astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("OpenCV could not encode a JPEG")
    return torch.from_numpy(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0)[None]


def blur_patches(pools: list[list[tuple[str, torch.Tensor]]], kernels: torch.Tensor, g: torch.Generator) -> tuple[torch.Tensor, list[str]]:
    """One random crop per kernel from a random scene of that patch's pool (``pools[i]``: ``(label, 1×H×W)``
    scenes), blurred by true convolution over a margin → ((n, 1, 192, 192), the n scene labels)."""
    from camhealth.physics import apply_psf

    m = KERNEL // 2 + 1
    crops, labels = [], []
    for i in range(kernels.shape[0]):
        label, s = pools[i][int(torch.randint(0, len(pools[i]), (1,), generator=g))]
        h, w = s.shape[-2:]
        y = int(torch.randint(0, h - PATCH - 2 * m + 1, (1,), generator=g))
        x = int(torch.randint(0, w - PATCH - 2 * m + 1, (1,), generator=g))
        crops.append(s[:, y:y + PATCH + 2 * m, x:x + PATCH + 2 * m])
        labels.append(label)
    big = apply_psf(torch.stack(crops).double(), kernels.double())
    return big[..., m:m + PATCH, m:m + PATCH].float().clamp(0, 1), labels


def degrade(x: torch.Tensor, cond: str, g: torch.Generator) -> torch.Tensor:
    """Apply a condition after the blur; everything is 8-bit rounded at the end (a camera's output)."""
    if cond in ("noise", "noise5"):
        n = x.shape[0]
        sigma = torch.full((n,), 5.0) if cond == "noise5" else 1.0 + 9.0 * torch.rand(n, generator=g)
        x = x + sigma[:, None, None, None] / 255.0 * torch.randn(x.shape, generator=g)
    x = ((x.clamp(0, 1) * 255.0).round() / 255.0).float()
    if cond == "jpeg":
        q = torch.randint(75, 96, (x.shape[0],), generator=g).tolist()
        x = torch.stack([_jpeg(p, qi) for p, qi in zip(x, q)])
    return x


@dataclass
class Cell:
    """One batch: a generator × size × condition on one scene set (``mixed``: the crops cycle
    :data:`GROUP_CYCLE`; ``dead_leaves``; ``chart``), with each patch's scene group and scene label."""

    family: str
    generator: str
    scene: str
    condition: str
    size: float
    image: torch.Tensor
    truth: torch.Tensor
    groups: tuple[str, ...] = ()
    labels: tuple[str, ...] = ()
    #: chart cells: the exact MTF in the directions the chart's edges measure (:data:`CHART_ANGLE_DEG`, + 90°).
    edge_truth: torch.Tensor | None = None
    out: dict[str, Any] = field(default_factory=dict)


def make_cells(per_cell: int, sizes: tuple[float, ...], seed: int) -> tuple[list[Cell], list[Cell]]:
    """The cells (held-out and training generators on the ``mixed`` scene groups; training generators on dead
    leaves) and the edge-chart cells (the same held-out kernels on a slanted-edge chart).

    Args:
        per_cell: patches per generator × size × condition × scene set, 1 … 256; in a ``mixed`` cell the i-th crop
            comes from group ``GROUP_CYCLE[i % 4]``.
        sizes: blur sizes in px, each in [0, 29] (kernels are 31 px).
        seed: seed of the kernels, crops, conditions and rendered scenes.
    """
    from camhealth.estimators.charts import slanted_edge_chart
    from camhealth.physics import mtf_from_psf, mtf_hv

    if not 1 <= int(per_cell) <= 256:
        raise ValueError(f"per_cell = {per_cell} is out of the allowed range [1, 256]")
    if not sizes or any(not 0.0 <= float(z) <= KERNEL - 2 for z in sizes):
        raise ValueError(f"sizes = {list(sizes)} must be non-empty with every size in the allowed range [0, {KERNEL - 2}] px")
    g = torch.Generator().manual_seed(seed)
    scenes = scene_sources(seed)
    groups = tuple(GROUP_CYCLE[i % len(GROUP_CYCLE)] for i in range(per_cell))
    mixed = [scenes[gr] for gr in groups]
    chart = [("chart", slanted_edge_chart(CHART_SIZE, CHART_ANGLE_DEG, CHART_SQUARE_FRAC)[0])]
    leaves = [("dead_leaves", x) for x in _dead_leaves(6, seed + 1000)]
    cells, charts = [], []
    jobs = [(fam, gen, "mixed") for fam, gens in FAMILIES.items() for gen in gens]
    jobs += [(fam, gen, "mixed") for fam, gen in IN_DIST.items()] + [(fam, gen, "dead_leaves") for fam, gen in IN_DIST.items()]
    for fam, gen, scene in jobs:
        for size in sizes:
            if gen == "tiny" and size > 5:
                continue
            for cond in CONDITIONS:
                k = make_kernels(gen, size, per_cell, g)
                truth = mtf_hv(k).float()
                pools, grs = (mixed, groups) if scene == "mixed" else ([leaves] * per_cell, ("dead_leaves",) * per_cell)
                img, labels = blur_patches(pools, k, g)
                cells.append(Cell(fam, gen, scene, cond, size, degrade(img, cond, g), truth, grs, tuple(labels)))
                if scene == "mixed" and cond in ("clean", "noise5") and gen not in IN_DIST.values():
                    kc = k[: max(1, per_cell // 4)]
                    img, labels = blur_patches([chart] * kc.shape[0], kc, g)
                    edge = mtf_from_psf(kc, (CHART_ANGLE_DEG, CHART_ANGLE_DEG + 90.0)).reshape(kc.shape[0], -1).float()
                    charts.append(Cell(fam, gen, "chart", cond, size, degrade(img, cond, g), mtf_hv(kc).float(),
                                       ("chart",) * kc.shape[0], tuple(labels), edge_truth=edge))
    return cells, charts


#: Offset of the rendered scenes' seed in :func:`calibration_cells` (the benchmark's own use ``seed + 2000``).
CALIBRATION_SCENE_SEED = 5000
#: Rendered scenes per class in :func:`calibration_cells` (3× the benchmark's: a few scenes dominate a class's error).
CALIBRATION_PER_CLASS = 12


def calibration_cells(per_cell: int, sizes: tuple[float, ...], seed: int) -> list[Cell]:
    """The MTF error-table calibration set (``python -m camhealth.bench mtf_error``): training's own generators
    (:data:`IN_DIST`) on rendered scenes only — their own set of :data:`CALIBRATION_PER_CLASS` per class, rendered with
    seed ``seed`` + :data:`CALIBRATION_SCENE_SEED` — every condition; none of the benchmark's held-out generators.

    Args:
        per_cell: patches per generator × size × condition, 1 … 256.
        sizes: blur sizes in px, each in [0, 29].
        seed: seed of the kernels, crops, conditions and scenes.
    """
    from camhealth.bench.rendered_scenes import CLASSES, render_scenes
    from camhealth.physics import mtf_hv

    if not 1 <= int(per_cell) <= 256:
        raise ValueError(f"per_cell = {per_cell} is out of the allowed range [1, 256]")
    if not sizes or any(not 0.0 <= float(z) <= KERNEL - 2 for z in sizes):
        raise ValueError(f"sizes = {list(sizes)} must be non-empty with every size in the allowed range [0, {KERNEL - 2}] px")
    g = torch.Generator().manual_seed(seed)
    scenes = [(cls, x) for cls in CLASSES
              for x in render_scenes(cls, CALIBRATION_PER_CLASS, RENDERED_SIZE, seed=seed + CALIBRATION_SCENE_SEED)]
    cells = []
    for fam, gen in IN_DIST.items():
        for size in sizes:
            for cond in CONDITIONS:
                k = make_kernels(gen, size, per_cell, g)
                img, labels = blur_patches([scenes] * per_cell, k, g)
                cells.append(Cell(fam, gen, "rendered", cond, size, degrade(img, cond, g), mtf_hv(k).float(),
                                  ("rendered",) * per_cell, tuple(labels)))
    return cells


#: Rendered scenes per class behind :func:`calibration_frames` (at :data:`FRAME_SCENE_SIZE` px).
CALIBRATION_FRAME_SCENES = 4


def calibration_frames(per_cell: int, sizes: tuple[float, ...], seed: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Frames of the MTF error-table calibration (``python -m camhealth.bench mtf_error``), for the share of the error
    that the patches of one scene have in common: training's own generators (:data:`IN_DIST`) × ``sizes``,
    ``per_cell`` frames each, every frame cut from one calibration scene (:data:`CALIBRATION_FRAME_SCENES` per class at
    :data:`FRAME_SCENE_SIZE` px, seed ``seed`` + :data:`CALIBRATION_SCENE_SEED` + 1) by :func:`scene_frames` →
    [((n, 1, 576, 576) frames, (n, 16) their kernels' MTF)], one entry per generator × size."""
    from camhealth.bench.rendered_scenes import CLASSES, render_scenes
    from camhealth.physics import mtf_hv

    if not 1 <= int(per_cell) <= 256:
        raise ValueError(f"per_cell = {per_cell} is out of the allowed range [1, 256]")
    if not sizes or any(not 0.0 <= float(z) <= KERNEL - 2 for z in sizes):
        raise ValueError(f"sizes = {list(sizes)} must be non-empty with every size in the allowed range [0, {KERNEL - 2}] px")
    g = torch.Generator().manual_seed(seed + CALIBRATION_SCENE_SEED + 1)
    scenes = [(cls, x) for cls in CLASSES for x in render_scenes(cls, CALIBRATION_FRAME_SCENES, FRAME_SCENE_SIZE,
                                                                 seed=seed + CALIBRATION_SCENE_SEED + 1,
                                                                 supersample=FRAME_SUPERSAMPLE)]
    out = []
    for gen in IN_DIST.values():
        for size in sizes:
            k = make_kernels(gen, size, per_cell, g)
            out.append((scene_frames(scenes, k, g)[0], mtf_hv(k).float()))
    return out


def _amae(est: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Per-patch AMAE (%) — Eq. 5.1, as in training and ``bench estimators``: the mean of the H and V mean absolute
    errors |Ĥ − H| over the 8 frequencies, × 100."""
    return 100.0 * (est.double() - truth.double()).abs().view(-1, 2, 8).mean(2).mean(1)


def run_estimator(est: Any, cells: list[Cell], views: int) -> float:
    """Fill ``cell.out[views]``; returns ms per patch (median over the cells)."""
    times = []
    for c in cells:
        t = time.perf_counter()
        o = est.predict(c.image, views=views)
        times.append((time.perf_counter() - t) * 1e3 / c.image.shape[0])
        c.out[views] = o
    return float(np.median(times))


def slanted_edge_reference(charts: list[Cell]) -> float:
    """Fill ``cell.out["edge"]`` with the ISO 12233 slanted edge on the chart cells (ROIs :func:`chart_rois`); returns
    ms per patch (median over the cells)."""
    from camhealth.estimators.slanted_edge import slanted_edge_mtf_hv

    rois = chart_rois()
    times = []
    for c in charts:
        t = time.perf_counter()
        c.out["edge"] = {"mtf": slanted_edge_mtf_hv(c.image, rois=rois).clamp(0, 1)}
        times.append((time.perf_counter() - t) * 1e3 / c.image.shape[0])
    return float(np.median(times))


def _mask(c: Cell, where: str | None) -> torch.Tensor:
    """Patches of cell ``c`` whose scene group or scene label is ``where`` (every patch for None)."""
    return torch.tensor([where is None or where in (gr, lab) for gr, lab in zip(c.groups, c.labels)], dtype=torch.bool)


def _agg(cells: list[Cell], key: Any, pred: Callable[[Cell], bool], where: str | None = None,
         assessable_only: bool = False, truth: str = "truth") -> tuple[float, int, float]:
    """(mean AMAE %, patches, fraction assessable) over the patches of the cells ``pred`` keeps, in ``where``
    (``assessable_only``: the AMAE over the patches the estimator calls assessable; the fraction stays that of all),
    against the cells' attribute ``truth`` (``"edge_truth"``: a chart's exact MTF in its edges' directions)."""
    a, ok = [], []
    for c in cells:
        if not (pred(c) and key in c.out):
            continue
        m = _mask(c, where)
        good = torch.as_tensor(c.out[key].get("assessable", torch.ones(c.truth.shape[0], dtype=torch.bool)))
        a.append(_amae(c.out[key]["mtf"], getattr(c, truth))[m & good if assessable_only else m])
        ok.append(good[m])
    if not a or sum(x.numel() for x in a) == 0:
        return float("nan"), 0, float("nan")
    av = torch.cat(a)
    return float(av.mean()), int(av.numel()), float(torch.cat(ok).float().mean())


def _bias(cells: list[Cell], pred: Callable[[Cell], bool], where: str | None = None) -> float:
    """Mean signed error (Ĥ − H) × 100 over the 16 values (views 1): < 0 reads the blur as stronger than it is."""
    d = [(c.out[1]["mtf"].double() - c.truth.double())[_mask(c, where)].flatten() for c in cells if pred(c) and 1 in c.out]
    d = [x for x in d if x.numel()]
    return float(100.0 * torch.cat(d).mean()) if d else float("nan")


def _uncertainty_values(cells: list[Cell], views: int, where: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """|Ĥ − H|, ``mtf_std`` and ``mtf_spread`` of every value of the assessable patches in ``where`` (views ``views``)."""
    e, u, s = [], [], []
    for c in cells:
        if views not in c.out:
            continue
        o = c.out[views]
        m = _mask(c, where) & torch.as_tensor(o["assessable"])
        e.append((o["mtf"][m] - c.truth[m]).abs().flatten())
        u.append(o["mtf_std"][m].flatten())
        s.append(o.get("mtf_spread", torch.full_like(o["mtf"], float("nan")))[m].flatten())
    if not e:
        return torch.zeros(0), torch.zeros(0), torch.zeros(0)
    return torch.cat(e), torch.cat(u), torch.cat(s)


def _f(v: float, fmt: str = ".1f") -> str:
    return "–" if v != v else format(v, fmt)


def _closed_form_native(s: int, fn: float) -> float:
    """MTF of the mean of s×s point samples against the exact pixel-area integral at f_n (f = f_n/2 cycles/px)."""
    f = fn / 2.0
    return float(math.sin(math.pi * f) / (s * math.sin(math.pi * f / s)) / (math.sin(math.pi * f) / (math.pi * f)))


#: Row noise [DN] added after the blur in :func:`banding_lines` (0: the patches as they are).
BANDING_DN = (0.0, 1.0, 3.0, 6.0)


def banding_lines(est: Any, held: list[Cell], seed: int, r: dict[str, Any]) -> list[str]:
    """The table of row noise after the blur: the clean held-out cells' rendered-scene patches with an offset N(0, σ²)
    per pixel row added (8-bit rounded; its own generator, seed + 3000, so no other number moves), on the patches the
    estimator calls assessable: AMAE % across the rows (V) and along them (H), the signed error across, the share
    assessable. Fills ``r["banding"]``."""
    g = torch.Generator().manual_seed(seed + 3000)
    clean = [c for c in held if c.condition == "clean"]
    x = torch.cat([c.image[_mask(c, "rendered")] for c in clean])
    truth = torch.cat([c.truth[_mask(c, "rendered")] for c in clean])
    lines = ["", f"Row noise after the blur ({x.shape[0]} clean patches of the held-out generators on rendered scenes, an offset "
             "per pixel row; the monitor refuses a frame's MTF from 2 DN of it, `MTF_BANDING_LIMIT_DN`), on the patches "
             "the estimator calls assessable:", "",
             "| row noise [DN] | AMAE across the rows (V) % | AMAE along them (H) % | signed error across × 100 | assessable |",
             "|---:|---:|---:|---:|---:|"]
    r["banding"] = {}
    for band in BANDING_DN:
        xb = ((x + band / 255.0 * torch.randn(x.shape[0], 1, x.shape[-2], 1, generator=g)).clamp(0, 1) * 255.0).round() / 255.0
        o = est.predict(xb)
        ok = torch.as_tensor(o.get("assessable", torch.ones(x.shape[0], dtype=torch.bool))).bool()
        err = (o["mtf"].double() - truth.double())[ok]
        row = {"across": float(100 * err[:, 8:].abs().mean()), "along": float(100 * err[:, :8].abs().mean()),
               "signed_across": float(100 * err[:, 8:].mean()), "assessable": float(ok.float().mean())}
        r["banding"][str(band)] = row
        lines.append(f"| {band:g} | {_f(row['across'])} | {_f(row['along'])} | {row['signed_across']:+.1f} | "
                     f"{_f(100 * row['assessable'], '.0f')} % |")
    return lines


#: Frames of :func:`frame_lines`: per held-out generator × size this many frames, each a :data:`FRAME_GRID` ×
#: :data:`FRAME_GRID` grid of MTF patches cut from one rendered scene of :data:`FRAME_SCENE_SIZE` px (rendered with
#: :data:`FRAME_SUPERSAMPLE` × :data:`FRAME_SUPERSAMPLE` samples per pixel: native MTF 1.009 at f_n 0.6).
FRAMES_PER_CELL = 4
FRAME_GRID = 3
FRAME_SCENE_SIZE = 704
FRAME_SUPERSAMPLE = 4


def scene_frames(scenes: list[tuple[str, torch.Tensor]], kernels: torch.Tensor, g: torch.Generator) -> tuple[torch.Tensor, list[str]]:
    """((n, 1, 576, 576) frames, their scene classes): per kernel a random crop of a random scene of ``scenes``
    (``(class, 1 × S × S)``, S ≥ 608), blurred by true convolution with that kernel, the inner :data:`FRAME_GRID` ×
    :data:`PATCH` px kept (no border of the convolution enters), 8-bit rounded."""
    from camhealth.physics import apply_psf

    side, m = FRAME_GRID * PATCH, KERNEL // 2 + 1
    small = [(label, tuple(x.shape[-2:])) for label, x in scenes if min(x.shape[-2:]) < side + 2 * m]
    if not scenes or small:
        raise ValueError(f"scene_frames needs scenes of at least {side + 2 * m} px a side (the frame and the kernel's "
                         f"margin), got {small[0][1] if small else 'none'}{f' ({small[0][0]})' if small else ''}")
    crops, labels = [], []
    for _ in range(kernels.shape[0]):
        label, x = scenes[int(torch.randint(0, len(scenes), (1,), generator=g))]
        y0 = int(torch.randint(0, x.shape[-2] - side - 2 * m + 1, (1,), generator=g))
        x0 = int(torch.randint(0, x.shape[-1] - side - 2 * m + 1, (1,), generator=g))
        crops.append(x[..., y0:y0 + side + 2 * m, x0:x0 + side + 2 * m])
        labels.append(label)
    big = apply_psf(torch.stack(crops).double(), kernels.double())
    return ((big[..., m:m + side, m:m + side].clamp(0, 1) * 255.0).round() / 255.0).float(), labels


def frame_lines(est: Any, seed: int, sizes: tuple[float, ...], r: dict[str, Any]) -> list[str]:
    """What the monitor reports for a whole frame against the patches it reads: per held-out generator × size,
    :data:`FRAMES_PER_CELL` frames of one rendered scene each (:func:`scene_frames`; the benchmark's scene classes at
    :data:`FRAME_SCENE_SIZE` px, 4 per class, and its kernels' generators, their own seed + 4000), each read by a
    map-mode monitor (``Monitor(mode="map", adaptive=False)``: the frame's answer is the median over its assessable
    patches). AMAE % per family and per scene class of the frame answers and of the assessable patches behind them,
    the share of frames with an answer, and the share of the answers' values within two of the report's
    ``uncertainty``. Fills ``r["frames"]``."""
    from camhealth.bench.rendered_scenes import CLASSES, render_scenes
    from camhealth.monitor import Monitor
    from camhealth.monitor.tiling import ESTIMATED
    from camhealth.physics import mtf_hv

    g = torch.Generator().manual_seed(seed + 4000)
    scenes = [(cls, x) for cls in CLASSES for x in render_scenes(cls, RENDERED_PER_CLASS, FRAME_SCENE_SIZE, seed=seed + 4000,
                                                                 supersample=FRAME_SUPERSAMPLE)]
    keys = list(FAMILIES) + list(CLASSES)
    per: dict[str, dict[str, list]] = {k: {"frame": [], "patch_ok": [], "answered": [], "within": []} for k in keys}
    n_frames = 0
    for fam, gens in FAMILIES.items():
        for gen in gens:
            for size in sizes:
                if gen == "tiny" and size > 5:
                    continue
                k = make_kernels(gen, size, FRAMES_PER_CELL, g)
                truth = mtf_hv(k).float()
                frames, labels = scene_frames(scenes, k, g)
                for i in range(frames.shape[0]):
                    rep = Monitor(None, est, mode="map", adaptive=False, warmup=False).process(frames[i, 0])
                    ok = rep.mtf.code == ESTIMATED  # the patches the frame's answer is the median of
                    patch_err = _amae(rep.mtf.values[ok], truth[i : i + 1].expand(int(ok.sum()), -1))
                    for key in (fam, labels[i]):
                        per[key]["patch_ok"].append(patch_err)
                        per[key]["answered"].append(rep.mtf.assessable)
                        if rep.mtf.assessable:
                            med = torch.as_tensor(rep.mtf.median).float()
                            per[key]["frame"].append(float(_amae(med[None], truth[i : i + 1])))
                            err = (med - truth[i]).abs()
                            per[key]["within"].append(err <= 2.0 * torch.as_tensor(rep.mtf.uncertainty).float())
                    n_frames += 1
    lines = ["", f"Per frame, what the monitor reports ({n_frames} frames of 576 × 576 px, {FRAMES_PER_CELL} per held-out "
                 f"generator × size, each cut from one rendered scene of {FRAME_SCENE_SIZE} px and read as a 3 × 3 grid of MTF "
                 "patches by a map-mode monitor, whose frame MTF is the median over the assessable patches): AMAE % of the "
                 "frame answers and of the assessable patches behind them, the share of frames with an answer, and the "
                 "share of the frame answers' values within two of their stated uncertainties (the report's "
                 "`uncertainty`, a standard error of the median), by family and by scene class:", "",
             "| family or scene class | frames | frame answer | its assessable patches | frames with an answer | "
             "within 2 × uncertainty |",
             "|---|---:|---:|---:|---:|---:|"]
    r["frames"] = {}
    for key in keys:
        v = per[key]
        fr = torch.tensor(v["frame"], dtype=torch.float64)
        po = torch.cat(v["patch_ok"]) if v["patch_ok"] else torch.zeros(0)
        row = {"frames": len(v["answered"]), "frame": float(fr.mean()) if fr.numel() else float("nan"),
               "patches_assessable": float(po.mean()) if po.numel() else float("nan"),
               "answered": sum(v["answered"]) / max(len(v["answered"]), 1),
               "within_2u": float(torch.cat(v["within"]).float().mean()) if v["within"] else float("nan")}
        r["frames"][key] = row
        lines.append(f"| {key} | {row['frames']} | **{_f(row['frame'])}** | {_f(row['patches_assessable'])} | "
                     f"{_f(100 * row['answered'], '.0f')} % | {_f(100 * row['within_2u'], '.0f')} % |")
    return lines


#: What :func:`paired_lines` does to the clean patches after the blur: ("noise", σ [DN]) white noise, ("jpeg", quality)
#: OpenCV's libjpeg; ("none", 0) the patches as they are.
PAIRED = (("none", 0), ("noise", 1), ("noise", 2), ("noise", 5), ("noise", 10), ("noise", 20),
          ("jpeg", 95), ("jpeg", 85), ("jpeg", 75))


def paired_lines(est: Any, held: list[Cell], seed: int, r: dict[str, Any]) -> list[str]:
    """The paired table of white noise and JPEG after the blur: the clean held-out cells' rendered-scene patches
    themselves with N(0, σ²) per pixel added (8-bit rounded; its own generator, seed + 5000, so no other number moves)
    or JPEG-compressed — the same scenes and kernels in every row, so the ratio to the untouched patches is the
    perturbation's alone (the condition columns above draw other kernels and crops per condition). AMAE % per family
    over all patches and over those the estimator calls assessable, the ratio to the untouched patches, the share
    assessable. Fills ``r["paired"]`` (keys ``"none"``, ``"noise_5"``, ``"jpeg_85"`` …)."""
    g = torch.Generator().manual_seed(seed + 5000)
    clean = [c for c in held if c.condition == "clean"]
    x = torch.cat([c.image[_mask(c, "rendered")] for c in clean])
    truth = torch.cat([c.truth[_mask(c, "rendered")] for c in clean])
    fam = [c.family for c in clean for keep in _mask(c, "rendered").tolist() if keep]
    lines = ["", f"White noise and JPEG after the blur, paired ({x.shape[0]} clean patches of the held-out generators on "
             "rendered scenes, the same patches in every row, 8-bit): AMAE % over all patches / on the patches the "
             "estimator calls assessable, per family and in all, its ratio to the untouched patches, and the share "
             "assessable:", "",
             "| after the blur | " + " | ".join(FAMILIES) + " | all families | ratio to none | share assessable |",
             "|---|" + "---|" * (len(FAMILIES) + 2) + "---:|"]
    r["paired"] = {}
    base: dict[str, float] = {}
    for kind, level in PAIRED:
        if kind == "noise":
            xp = ((x + level / 255.0 * torch.randn(x.shape, generator=g)).clamp(0, 1) * 255.0).round() / 255.0
        elif kind == "jpeg":
            xp = torch.stack([_jpeg(p, level) for p in x])
        else:
            xp = x
        o = est.predict(xp)
        ok = torch.as_tensor(o.get("assessable", torch.ones(x.shape[0], dtype=torch.bool))).bool()
        amae = _amae(o["mtf"], truth)
        row: dict[str, Any] = {}
        for f in (*FAMILIES, "all"):
            m = torch.tensor([f in ("all", k) for k in fam], dtype=torch.bool)
            row[f] = {"all": float(amae[m].mean()),
                      "assessable": float(amae[m & ok].mean()) if bool((m & ok).any()) else float("nan")}
        row["share_assessable"] = float(ok.float().mean())
        if kind == "none":
            base = {"all": row["all"]["all"], "assessable": row["all"]["assessable"]}
        row["ratio"] = {k: row["all"][k] / base[k] for k in ("all", "assessable")}
        key = "none" if kind == "none" else f"{kind}_{level}"
        r["paired"][key] = row
        label = {"none": "none", "noise": f"white noise {level} DN", "jpeg": f"JPEG q {level}"}[kind]
        lines.append(f"| {label} | " + " | ".join(f"{_f(row[f]['all'])} / {_f(row[f]['assessable'])}" for f in FAMILIES)
                     + f" | {_f(row['all']['all'])} / {_f(row['all']['assessable'])} | {_f(row['ratio']['all'], '.2f')}× / "
                     f"{_f(row['ratio']['assessable'], '.2f')}× | {_f(100 * row['share_assessable'], '.0f')} % |")
    return lines


#: Shares of defective pixels added after the blur in :func:`defects_lines` (0: the patches as they are).
DEFECT_SHARES = (0.0, 1e-4, 1e-3, 1e-2)


@contextlib.contextmanager
def swapped_global(method: Any, name: str, value: Any) -> Iterator[None]:
    """Within the block, the global ``name`` that ``method`` (decorators unwrapped) reads is ``value``: the module the
    function was defined in, even where that module has been imported afresh since."""
    scope = inspect.unwrap(method).__globals__
    missing = object()
    old = scope.get(name, missing)
    scope[name] = value
    try:
        yield
    finally:
        if old is missing:
            del scope[name]
        else:
            scope[name] = old


def _without_repair(p: torch.Tensor, noise_dn: torch.Tensor | None = None) -> tuple[torch.Tensor, Any]:
    from camhealth.estimators.defective_pixels import defective_pixels

    return p, defective_pixels(p, noise_dn)


def defects_lines(est: Any, held: list[Cell], seed: int, r: dict[str, Any]) -> list[str]:
    """The table of defective pixels after the blur: the clean held-out cells' rendered-scene patches with a share of
    their pixels moved by 10–200 DN up or down (:func:`camhealth.bench.robustness.add_defects`, its own seed,
    seed + 4000, so no other number moves): AMAE % over all patches and over those the estimator calls assessable, and
    the share assessable — as the estimator ships (MTF models replace the defective pixels they find by their
    neighbours' mean before reading a patch) and with that repair switched off. Fills ``r["defects"]``."""
    from camhealth.bench.robustness import add_defects

    clean = [c for c in held if c.condition == "clean"]
    x = torch.cat([c.image[_mask(c, "rendered")] for c in clean])
    truth = torch.cat([c.truth[_mask(c, "rendered")] for c in clean])
    lines = ["", f"Defective pixels after the blur ({x.shape[0]} clean patches of the held-out generators on rendered "
             "scenes; a share of the pixels moved by 10–200 DN up or down): AMAE % over all patches / on the patches "
             "the estimator calls assessable, and the share assessable — as shipped (the defective pixels it finds "
             "replaced by their neighbours' mean) and without that repair:", "",
             "| defective pixels | as shipped: all / assessable | assessable | without the repair: all / assessable | assessable |",
             "|---:|---|---:|---|---:|"]
    r["defects"] = {}
    for share in DEFECT_SHARES:
        xd = add_defects(x, share, seed + 4000)[0] if share else x
        row = {}
        for key, ctx in (("shipped", contextlib.nullcontext()),
                         ("unrepaired", swapped_global(type(est).predict, "repair_defective_pixels", _without_repair))):
            with ctx:
                o = est.predict(xd)
            ok = torch.as_tensor(o.get("assessable", torch.ones(x.shape[0], dtype=torch.bool))).bool()
            amae = _amae(o["mtf"], truth)
            row[key] = {"all": float(amae.mean()), "assessable_amae": float(amae[ok].mean()) if bool(ok.any()) else float("nan"),
                        "assessable": float(ok.float().mean())}
        r["defects"][str(share)] = row
        a, b = row["shipped"], row["unrepaired"]
        lines.append(f"| {100 * share:g} % | {_f(a['all'])} / {_f(a['assessable_amae'])} | {_f(100 * a['assessable'], '.0f')} % | "
                     f"{_f(b['all'])} / {_f(b['assessable_amae'])} | {_f(100 * b['assessable'], '.0f')} % |")
    return lines


def run(args: argparse.Namespace) -> BenchResult:
    from camhealth.bench.rendered_scenes import CLASSES, SUPERSAMPLE, render_scenes
    from camhealth.data.native_mtf import native_mtf_table, spectral_native_mtf
    from camhealth.inference import load_estimator

    t0 = time.perf_counter()
    sizes = tuple(args.mtf_sizes)
    cells, charts = make_cells(args.per_cell, sizes, args.seed)
    names = args.models or ["mtf"]
    n_group = {gr: sum(c.groups.count(gr) for c in cells if c.scene == "mixed") for gr in GROUPS}
    header = [f"{sum(c.image.shape[0] for c in cells)} patches of {PATCH} px ({args.per_cell} per generator × size × condition × "
              f"scene set; the crops of a cell cycle {' → '.join(GROUP_CYCLE)}: "
              + ", ".join(f"{v} {k}" for k, v in n_group.items())
              + f", {sum(c.image.shape[0] for c in cells if c.scene == 'dead_leaves')} dead leaves) + "
              f"{sum(c.image.shape[0] for c in charts)} slanted-edge chart patches, seed {args.seed}; "
              f"data made in {time.perf_counter() - t0:.0f} s", f"command: {args.command_line}"]
    summary: list[str] = []
    results: dict[str, Any] = {"patches_per_group": n_group}
    rows = []
    edge_ms = slanted_edge_reference(charts)
    held_p = lambda c: c.scene == "mixed" and c.generator not in IN_DIST.values()  # noqa: E731
    ind_p = lambda c, f: c.scene == "mixed" and c.generator == IN_DIST.get(f)  # noqa: E731
    dl_p = lambda c, f: c.family == f and c.scene == "dead_leaves" and c.condition == "clean"  # noqa: E731
    for name in names:
        est = load_estimator(name)
        ms1 = run_estimator(est, cells + charts, 1)
        ms4 = run_estimator(est, cells, 4)
        rows.append(Row(f"{est.name} (views 1)", [ms1], note="ms per patch"))
        rows.append(Row(f"{est.name} (views 4)", [ms4], note="ms per patch"))
        held = [c for c in cells if held_p(c)]
        r: dict[str, Any] = {"ms_views1": ms1, "ms_views4": ms4, "families": {}, "sizes": {}, "generators": {},
                             "rendered_classes": {}}
        summary += ["", f"**{est.name}** — AMAE % (views 1) on held-out generators × rendered scenes (exact truth: the "
                        "scenes' native MTF is 1), by condition; in-distribution: training generators on dead leaves "
                        "(clean) and on rendered scenes (clean):", "",
                    "| family | " + " | ".join(CONDITIONS) + " | all | in-dist. dead leaves | in-dist. gen. × rendered | "
                    "clean / in-dist. dead leaves | clean / in-dist. gen. × rendered | assessable | all, assessable patches only |",
                    "|---|" + "---:|" * (len(CONDITIONS) + 7)]
        for fam in FAMILIES:
            per = {cond: _agg(held, 1, lambda c, f=fam, k=cond: c.family == f and c.condition == k, "rendered")[0] for cond in CONDITIONS}
            allv, n, ok = _agg(held, 1, lambda c, f=fam: c.family == f, "rendered")
            only = _agg(held, 1, lambda c, f=fam: c.family == f, "rendered", assessable_only=True)[0]
            ind = _agg(cells, 1, lambda c, f=fam: dl_p(c, f))[0]
            ind_r = _agg(cells, 1, lambda c, f=fam: ind_p(c, f) and c.condition == "clean", "rendered")[0]
            r["families"][fam] = {**per, "all": allv, "n": n, "assessable": ok, "in_dist_dead_leaves": ind,
                                  "in_dist_rendered": ind_r, "assessable_only": only,
                                  "clean_over_in_dist_rendered": per["clean"] / ind_r if ind_r > 0 else float("nan"),
                                  "clean_over_in_dist_dead_leaves": per["clean"] / ind if ind > 0 else float("nan"),
                                  "groups": {}}
            summary.append(f"| {fam} | " + " | ".join(_f(per[c]) for c in CONDITIONS)
                           + f" | **{_f(allv)}** | {_f(ind)} | {_f(ind_r)} | {_f(r['families'][fam]['clean_over_in_dist_dead_leaves'], '.2f')}× "
                           f"| {_f(r['families'][fam]['clean_over_in_dist_rendered'], '.2f')}× | {_f(100 * ok, '.0f')} % | {_f(only)} |")
        summary += ["", f"AMAE % (views 1) by scene group, every condition. **photos** (photographs) and **street** (street frames 2×, "
                        f"native MTF ≈ 0.32 at f_n 0.6), both held out of the MTF training and without an exact truth: {TRUTH_NOTE} (the kernel's MTF "
                        "alone), so a network that sees that blur is counted wrong there; **rendered**: exact truth:", "",
                    "| family | held-out gen. × rendered | held-out gen. × photos (" + TRUTH_NOTE + ") | held-out gen. × street ("
                    + TRUTH_NOTE + ") | in-dist. gen. × rendered | in-dist. gen. × photos (" + TRUTH_NOTE
                    + ") | in-dist. gen. × street (" + TRUTH_NOTE + ") |", "|---|" + "---:|" * 6]
        for fam in FAMILIES:
            vals = []
            for gr in GROUPS:
                h, nh, _ = _agg(held, 1, lambda c, f=fam: c.family == f, gr)
                i, ni, _ = _agg(cells, 1, lambda c, f=fam: ind_p(c, f), gr)
                r["families"][fam]["groups"][gr] = {"held_out": h, "n_held_out": nh, "in_dist": i, "n_in_dist": ni}
                vals.append((h, i))
            summary.append(f"| {fam} | " + " | ".join(_f(v[0]) for v in vals) + " | " + " | ".join(_f(v[1]) for v in vals) + " |")
        summary += ["", "Mean signed error (Ĥ − H) × 100, clean, views 1 (< 0: the blur read as stronger than it is):", "",
                    "| family | held-out gen. × rendered | held-out gen. × photos (" + TRUTH_NOTE + ") | held-out gen. × street ("
                    + TRUTH_NOTE + ") | in-dist. gen. × rendered | in-dist. dead leaves |", "|---|---:|---:|---:|---:|---:|"]
        r["bias"] = {}
        for fam in FAMILIES:
            b = {gr: _bias(held, lambda c, f=fam: c.family == f and c.condition == "clean", gr) for gr in GROUPS}
            b["in_dist_rendered"] = _bias(cells, lambda c, f=fam: ind_p(c, f) and c.condition == "clean", "rendered")
            b["in_dist_dead_leaves"] = _bias(cells, lambda c, f=fam: dl_p(c, f))
            r["bias"][fam] = b
            summary.append(f"| {fam} | " + " | ".join(_f(v, "+.1f") for v in b.values()) + " |")
        summary += ["", "AMAE % by generator (held-out generators × rendered scenes, views 1; clean / 5 DN noise / ratio, over "
                        "all patches and over the patches the estimator calls assessable; the two conditions draw their own "
                        "kernels and crops, so the ratio mixes the noise with the scenes: the paired table below holds the "
                        "patches fixed):", "",
                    "| generator | family | clean | noise 5 DN | noise 5 / clean | clean, assessable | noise 5 DN, assessable "
                    "| noise 5 / clean, assessable |", "|---|---|---:|---:|---:|---:|---:|---:|"]
        for fam, gens in FAMILIES.items():
            for gen in gens:
                vals = [_agg(held, 1, lambda c, g_=gen, k=cond: c.generator == g_ and c.condition == k, "rendered",
                             assessable_only=only)[0] for only in (False, True) for cond in ("clean", "noise5")]
                cl, n5, cl_a, n5_a = vals
                r["generators"][gen] = {"clean": cl, "noise5": n5, "clean_assessable": cl_a, "noise5_assessable": n5_a}
                summary.append(f"| {gen} | {fam} | {_f(cl)} | {_f(n5)} | {_f(n5 / cl, '.2f')}× | {_f(cl_a)} | {_f(n5_a)} "
                               f"| {_f(n5_a / cl_a, '.2f')}× |")
        summary += ["", "AMAE % by blur size (held-out generators × rendered scenes, every condition; views 1), over all patches "
                        "and over the patches the estimator calls assessable, and the mean signed error (Ĥ − H) × 100 per "
                        "rendered class on the clean ones:", "",
                    "| size px | " + " | ".join(FAMILIES) + " | all | " + " | ".join(f"{f}, assessable" for f in FAMILIES)
                    + " | all, assessable | " + " | ".join(f"signed, {k}" for k in CLASSES) + " |",
                    "|---:|" + "---:|" * (2 * len(FAMILIES) + 2 + len(CLASSES))]
        for size in sizes:
            vals = [_agg(held, 1, lambda c, f=fam, s=size: c.family == f and c.size == s, "rendered")[0] for fam in FAMILIES]
            allv = _agg(held, 1, lambda c, s=size: c.size == s, "rendered")[0]
            vals_a = [_agg(held, 1, lambda c, f=fam, s=size: c.family == f and c.size == s, "rendered", True)[0]
                      for fam in FAMILIES]
            allv_a = _agg(held, 1, lambda c, s=size: c.size == s, "rendered", True)[0]
            bias = [_bias(held, lambda c, s=size: c.size == s and c.condition == "clean", cls) for cls in CLASSES]
            r["sizes"][str(size)] = {**dict(zip(FAMILIES, vals)), "all": allv,
                                     "assessable": {**dict(zip(FAMILIES, vals_a)), "all": allv_a},
                                     "bias_clean": dict(zip(CLASSES, bias))}
            summary.append(f"| {size:g} | " + " | ".join(_f(v) for v in vals) + f" | **{_f(allv)}** | "
                           + " | ".join(_f(v) for v in vals_a) + f" | **{_f(allv_a)}** | "
                           + " | ".join(_f(b, "+.1f") for b in bias) + " |")
        summary += ["", "AMAE % by rendered scene class (held-out generators, every condition; views 1), the share of patches "
                        "called assessable, and the mean signed error (Ĥ − H) × 100 on the clean ones:", "",
                    "| family | " + " | ".join(CLASSES) + " | " + " | ".join(f"assessable, {k}" for k in CLASSES) + " | "
                    + " | ".join(f"signed, {k}" for k in CLASSES) + " |",
                    "|---|" + "---:|" * (3 * len(CLASSES))]
        for fam in FAMILIES:
            aggs = [_agg(held, 1, lambda c, f=fam: c.family == f, cls) for cls in CLASSES]
            vals, oks = [a[0] for a in aggs], [a[2] for a in aggs]
            bias = [_bias(held, lambda c, f=fam: c.family == f and c.condition == "clean", cls) for cls in CLASSES]
            r["rendered_classes"][fam] = {**dict(zip(CLASSES, vals)), "bias_clean": dict(zip(CLASSES, bias)),
                                          "assessable": dict(zip(CLASSES, oks))}
            summary.append(f"| {fam} | " + " | ".join(_f(v) for v in vals) + " | "
                           + " | ".join(f"{_f(100 * o, '.0f')} %" for o in oks) + " | " + " | ".join(_f(b, "+.1f") for b in bias) + " |")
        # uncertainty: mtf_std (the error table in quadrature with the views' spread) against the error, on the
        # assessable patches of held-out generators per scene group; the views' spread alone beside it
        r["uncertainty"] = {"amae_views4": _agg(held, 4, lambda c: True, "rendered")[0],
                            "amae_views1": _agg(held, 1, lambda c: True, "rendered")[0]}
        summary += ["", "Uncertainty `mtf_std` against the error |Ĥ − H| on the assessable patches of held-out generators "
                        "(share of values with |Ĥ − H| ≤ u and ≤ 2u; Gaussian errors would give 68 % and 95 %); on photos and "
                        "street frames the truth ignores the scene's own blur:", "",
                    "| scene group | views | mean abs. error | mean u | ≤ u | ≤ 2u | views' spread alone: ≤ 2·spread |",
                    "|---|---:|---:|---:|---:|---:|---:|"]
        for gr in GROUPS:
            for views in (1, 4):
                e, u, s4 = _uncertainty_values(held, views, gr)
                if e.numel() == 0:
                    continue
                has_u = bool(torch.isfinite(u).all())  # a file without an error table gives none at views 1
                nan = float("nan")
                row = {"mean_abs_error": float(e.mean()), "mean_std": float(u.mean()) if has_u else nan,
                       "within_1std": float((e <= u).float().mean()) if has_u else nan,
                       "within_2std": float((e <= 2 * u).float().mean()) if has_u else nan}
                if views == 4:
                    row["within_2spread"] = float((e <= 2 * s4).float().mean())
                r["uncertainty"][f"{gr}/views{views}"] = row
                summary.append(f"| {gr} | {views} | {row['mean_abs_error']:.3f} | {_f(row['mean_std'], '.3f')} | "
                               f"{_f(100 * row['within_1std'], '.0f')} % | {_f(100 * row['within_2std'], '.0f')} % | "
                               + (f"{100 * row['within_2spread']:.0f} % |" if views == 4 else "– |"))
        # classical reference on the edge chart
        summary += ["", "Slanted-edge chart blurred with the held-out kernels (a scene with an edge): AMAE % network (against "
                        "the 0°/90° truth, what it estimates) vs ISO 12233 slanted edge (ROIs on the square's edges) against "
                        "the exact MTF in the directions its edges measure (5°/95°) and against the 0°/90° truth:", "",
                    "| family | condition | network | slanted edge (truth at 5°/95°) | slanted edge against 0°/90° |",
                    "|---|---|---:|---:|---:|"]
        r["chart"] = {}
        for fam in FAMILIES:
            for cond in ("clean", "noise5"):
                pred = lambda c, f=fam, k=cond: c.family == f and c.condition == k  # noqa: E731
                nv = _agg(charts, 1, pred)[0]
                ev = _agg(charts, "edge", pred, truth="edge_truth")[0]
                ev0 = _agg(charts, "edge", pred)[0]
                r["chart"][f"{fam}/{cond}"] = {"network": nv, "edge": ev, "edge_vs_0_90": ev0}
                summary.append(f"| {fam} | {cond} | {_f(nv)} | {_f(ev)} | {_f(ev0)} |")
        summary += frame_lines(est, args.seed, sizes, r)
        summary += paired_lines(est, held, args.seed, r)
        summary += banding_lines(est, held, args.seed, r)
        summary += defects_lines(est, held, args.seed, r)
        summary.append(f"\nms per patch (fp32, threads {torch.get_num_threads()}): network views 1 {ms1:.1f}, views 4 {ms4:.1f}; "
                       f"slanted edge {edge_ms:.1f} (per chart patch, 4 edges)")
        results[est.name] = r
    table = native_mtf_table()
    exact = {fn: _closed_form_native(SUPERSAMPLE, fn) for fn in (0.3, 0.6)}
    summary += ["", "Native MTF of the scene sources (spectral estimate, camhealth.data.native_mtf; H = V assumed; "
                    "median over images, f_n = 0.3 / 0.6; `closed form`: the rendered scenes' exact native MTF; "
                    "`rendered … (spectral estimate)`: the spectral estimate on those scenes, whose native MTF is 1):", "",
                "| source | images | MTF(0.3) | MTF(0.6) |", "|---|---:|---:|---:|",
                f"| rendered (s = {SUPERSAMPLE}, closed form) | {len(CLASSES) * RENDERED_PER_CLASS} | {exact[0.3]:.3f} | {exact[0.6]:.3f} |"]
    for src, v in table.items():
        summary.append(f"| {src} | {v['n']} | {v['mtf_0.3']:.2f} | {v['mtf_0.6']:.2f} |")
    for cls in CLASSES:  # the spectral estimate on scenes whose native MTF is exactly 1: how far it is to be trusted
        xs = render_scenes(cls, RENDERED_PER_CLASS, RENDERED_SIZE, seed=args.seed + 2000)
        m = torch.stack([spectral_native_mtf(x, (0.3, 0.6)) for x in xs]).median(0).values
        table[f"rendered_{cls}"] = {"n": int(xs.shape[0]), "mtf_0.3": float(m[0]), "mtf_0.6": float(m[1])}
        summary.append(f"| rendered {cls} (true 1; spectral estimate) | {xs.shape[0]} | {float(m[0]):.2f} | {float(m[1]):.2f} |")
    results["native_mtf"] = {**table, "rendered_closed_form": {"n": len(CLASSES) * RENDERED_PER_CLASS,
                                                                "mtf_0.3": exact[0.3], "mtf_0.6": exact[0.6]}}
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1))
    rows.append(Row("slanted edge (chart)", [edge_ms], note="ms per patch"))
    return BenchResult(title="robustness of the MTF estimators", rows=rows, baseline=rows[0].name, header=header, summary=summary)
