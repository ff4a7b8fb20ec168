"""``python -m camhealth.evaluate``: classical and learned estimators on one fixed, seeded benchmark — the
thesis's tables with speed beside error, in one command.

The benchmark is built from any image source (:func:`camhealth.data.build_source`; default: the embedded
scikit-image photographs and street clip) plus procedural dead leaves as the texture-rich "Sim-like" set,
with seeded patch positions and noise, so every run of the same configuration sees the same data:

* **noise, isolated sources** (Sec. 5.1.1, Fig. 5.11): photon shot noise (PN), dark-current shot noise
  (DCSN) and readout noise (RN), each alone at σ ∈ {5, 10, 15, 20, 25} DN. As in the thesis the raw noise of
  the sensor model (EV76C661 CMOS at 57 °C = 330 K, 0.1 s, 0 dB) is generated with its physical
  statistics and amplified to the target σ; the label is the realised σ after clipping.
* **noise, combined, random sensors** (Sec. 6.1, Tab. 6.1): all sources through
  :func:`~camhealth.physics.form_image` with metadata sampled from Table 4.1, on the natural patches and on
  dead leaves; labels per source and total.
* **blur** (Tab. 5.1): defocus, linear and non-linear motion (camera shake, intensity 1) of size
  d ∈ {3, 7, 11, 15, 21} px in the directions 0/45/90/135° (defocus is isotropic: one direction), labels
  :func:`~camhealth.physics.mtf_hv` of the kernel. Learned MTF estimators see 192-px natural patches; the
  standard measurements see the synthetic charts (slanted edge, Siemens star) blurred by the same kernels —
  which also cross-checks the labels of the data pipeline.
* **blur under noise** (Tab. 5.2, Sec. 5.5): Defocus + DCSN and Photon + linear motion (0°), d as above,
  σ ∈ {0, 5, …, 25} DN; every blur method with and without the b₂ pre-filter (d₂ = 7 px, ε = 0.05), and the
  noise methods on the same patches.
* **aggregation** (Tab. 5.3): a frame sequence of the source (default: the street clip) with a static
  combined noise process of σ_Total ≈ 25 DN and fresh noise every frame; patch-wise estimates are
  median-aggregated over n consecutive frames (Eq. 5.4) and the dispersion σ_σ̃n is reported as Δ_{1→n}
  (Eq. 5.5).

Methods: PCA, B+F and wavelet MAD (noise), the slanted edge and the Siemens star (charts), and the learned
estimators of :func:`camhealth.inference.load_estimator` — every shipped model that loads and every
``--checkpoint`` (row ``checkpoint STEM``; files of the same name, the ``last.ckpt`` of two runs, with as many
parent folders as tell them apart: :func:`checkpoint_labels`). If ``camhealth.inference`` cannot be imported the learned rows are left out with a
printed note. Every method is timed in the same run (ms per 128/192-px patch, or per chart).

Outputs in ``--out``: ``results.md`` (Markdown tables), ``results.json`` (all numbers, configuration,
machine), ``plots/*.png`` (error vs time; MTF curves with min/median/max bands; noise estimates vs σ;
uncertainty vs window) and ``cache/`` (data and estimates per case and method: ``--resume`` reuses them).
``--quick`` runs a reduced benchmark (≈ 15 s with the classical methods on a 2-core CPU; the budget with
learned models is 2 minutes), the default one ≈ 40 s classical-only (budget ≈ 15 min with learned models).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import hashlib
import json
import math
import numbers
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import torch

from camhealth._cli import BitDepthOption, IntAtLeast, add_debug_flag, config_parser, run_cli

__all__ = [
    "NOISE_LEVELS_DN",
    "BLUR_SIZES_PX",
    "DIRECTIONS_DEG",
    "FAMILIES",
    "EvalConfig",
    "DEFAULT",
    "QUICK",
    "Method",
    "classical_methods",
    "learned_methods",
    "build_cases",
    "run_evaluation",
    "main",
]

NOISE_LEVELS_DN: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 25.0)
BLUR_SIZES_PX: tuple[float, ...] = (3.0, 7.0, 11.0, 15.0, 21.0)
DIRECTIONS_DEG: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0)
FAMILIES: tuple[str, ...] = ("defocus", "linear", "nonlinear")
SOURCES: tuple[str, ...] = ("photon", "dark", "readout")
SOURCE_LABELS = {"photon": "PN", "dark": "DCSN", "readout": "RN"}
BUN_CASES: tuple[str, ...] = ("defocus_dcsn", "photon_linmb")
BUN_LABELS = {"defocus_dcsn": "Defocus + DCSN", "photon_linmb": "Photon + linear motion"}
KERNEL_SIZE = 23
NOISE_PATCH = 128
BLUR_PATCH = 192
SLE_CHART = 256
STAR_CHART = 512
AGG_SIGMA_DN = 25.0
SHIPPED = ("mtf", "drne", "noise_source_none", "noise_source_min", "noise_source_full")
#: The first line of the results page (``results.md``, and the file ``--docs`` writes).
RESULTS_TITLE = "# camhealth evaluation: classical and learned estimators on one benchmark"


@dataclass(frozen=True)
class EvalConfig:
    """Size of the benchmark. Patches per cell: ``noise_patches`` per (source, σ); ``combined_patches``
    per data set; ``blur_patches`` per kernel (family, size, direction); ``bun_patches`` per (case, d, σ);
    ``agg_frames`` × ``agg_patches`` for the aggregation sequence. ``charts``: build the blurred test
    charts (needed by the slanted-edge and Siemens-star methods). ``blur_scenes``: where the learned estimator's
    blur patches come from — ``"rendered"`` (default): line art, shaded shapes and 1/f textures rendered with an
    exact pixel aperture (:mod:`camhealth.bench.rendered_scenes`, in no training source), whose own MTF is 1, so
    the label (the kernel's MTF) is the patch's whole MTF; ``"source"``: crops of ``source`` (a label that ignores
    the source's own blur: the street clip's native MTF is ≈ 0.08 at f_n 0.6). ``bit_depth``: significant bits of the
    image files of a folder ``source`` (:func:`camhealth.data.build_source`; ``"auto"``: each file's own)."""

    source: str = "default"
    seed: int = 0
    noise_patches: int = 40
    combined_patches: int = 192
    blur_patches: int = 12
    bun_patches: int = 6
    bun_sizes: tuple[float, ...] = BLUR_SIZES_PX
    bun_levels: tuple[float, ...] = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0)
    agg_frames: int = 50
    agg_patches: int = 24
    agg_windows: tuple[int, ...] = (1, 2, 4, 10, 20, 40)
    deadleaves: bool = True
    charts: bool = True
    batch: int = 32
    blur_scenes: str = "rendered"
    bit_depth: int | str = "auto"

    def __post_init__(self) -> None:
        if self.blur_scenes not in ("rendered", "source"):
            raise ValueError(f"blur_scenes = {self.blur_scenes!r} must be 'rendered' or 'source'")
        from camhealth.data.io import _check_bit_depth

        _check_bit_depth(self.bit_depth)

        def integer(name: str, low: int, note: str = "") -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < low:
                raise ValueError(f"{name} = {v!r} must be an integer >= {low}{note}")

        integer("seed", 0)
        for name in ("noise_patches", "combined_patches", "agg_patches", "batch"):
            integer(name, 1)
        for name in ("blur_patches", "bun_patches"):
            integer(name, 0, " (0: no patches)")
        integer("agg_frames", 2, " (the aggregation compares windows of consecutive frames)")
        for name in ("deadleaves", "charts"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} = {getattr(self, name)!r} must be True or False")

        def values(name: str, ok: Callable[[Any], bool], what: str) -> None:
            v = getattr(self, name)
            if isinstance(v, (str, bytes)) or not isinstance(v, Sequence) or not v or not all(ok(x) for x in v):
                raise ValueError(f"{name} = {v!r} must be a non-empty list of {what}")

        def real(x: Any) -> bool:
            return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x)

        values("agg_windows", lambda x: isinstance(x, numbers.Integral) and not isinstance(x, bool) and x >= 1,
               "window sizes: integers >= 1 [frames]")
        values("bun_levels", lambda x: real(x) and x >= 0, "noise levels σ >= 0 [DN] (0: blur alone)")
        values("bun_sizes", lambda x: real(x) and 0 <= x <= KERNEL_SIZE,
               f"blur sizes in [0, {KERNEL_SIZE}] px (the {KERNEL_SIZE}-px kernels hold no larger defocus or motion)")

    def key(self) -> str:
        """Hash of the configuration (cache entries are only reused for the same key; ``bit_depth`` enters it only when
        it is not ``"auto"``)."""
        fields = dataclasses.asdict(self)
        if fields["bit_depth"] == "auto":
            del fields["bit_depth"]
        return hashlib.sha1(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


DEFAULT = EvalConfig()
QUICK = EvalConfig(
    noise_patches=6, combined_patches=16, blur_patches=2, bun_patches=2, bun_sizes=(3.0, 11.0, 21.0),
    bun_levels=(0.0, 10.0, 25.0), agg_frames=12, agg_patches=8, agg_windows=(1, 2, 4, 10),
)  # fmt: skip


# ============================================================================================== data
def _generator(seed: int, *tags: object) -> torch.Generator:
    digest = hashlib.sha1(repr((seed,) + tags).encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:7], "little"))


def _nominal_meta(batch: int = 1):
    from camhealth.physics import CameraMetadata

    return CameraMetadata.preset("EV76C661", batch_size=batch, temperature_c=56.85, exposure_s=0.1, gain_db=0.0)


class _ImageCache:
    """Source images loaded once (gray float32 1×H×W)."""

    def __init__(self, source: Any) -> None:
        self.source = source
        self._imgs: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, i: int) -> torch.Tensor:
        if i not in self._imgs:
            self._imgs[i] = self.source[i][0].float()
        return self._imgs[i]


def _sample_patches(images: _ImageCache, n: int, size: int, gen: torch.Generator, min_std_dn: float = 0.0) -> torch.Tensor:
    """n seeded ``size``-px crops from the source; crops with > 5 % clipped pixels (or too flat) are redrawn."""
    usable = [i for i in range(len(images)) if min(images[i].shape[-2:]) >= size]
    if not usable:
        raise ValueError(f"no image of the source is at least {size}×{size} px (needed for {size}-px patches)")
    out = []
    tol = 0.5 / 255.0
    for _ in range(n):  # data preparation: a few hundred crops, each drawn until it qualifies
        for attempt in range(50):
            img = images[usable[int(torch.randint(len(usable), (1,), generator=gen))]]
            h, w = img.shape[-2:]
            y = int(torch.randint(h - size + 1, (1,), generator=gen))
            x = int(torch.randint(w - size + 1, (1,), generator=gen))
            crop = img[:, y : y + size, x : x + size]
            clipped = float(((crop <= tol) | (crop >= 1 - tol)).float().mean())
            if (clipped <= 0.05 and float(crop.std()) * 255.0 >= min_std_dn) or attempt == 49:
                out.append(crop)
                break
    return torch.stack(out)


def _raw_noise(x: torch.Tensor, source: str, meta, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Raw noise of one source in intensity units (same shape as x) and its expected σ per sample [DN]."""
    from camhealth.physics import dark_signal_e, readout_sigma_e
    from camhealth.physics.image_formation import sample_poisson
    from camhealth.physics.photon_shot_noise import photon_shot_sigma_patch_dn

    b = x.shape[0]
    meta = meta.expand(b)
    to_int = (meta.gain_factor / meta.full_well_e).view(-1, 1, 1, 1).to(x.dtype)
    dn_per_e = meta.dn_per_electron
    if source == "photon":
        e = x.clamp_min(0) / to_int
        n = (sample_poisson(e, gen) - e) * to_int
        expected = photon_shot_sigma_patch_dn(x, meta)
    elif source == "dark":
        s = dark_signal_e(meta).view(-1, 1, 1, 1).to(x.dtype).expand(x.shape).contiguous()
        n = (sample_poisson(s, gen) - s) * to_int
        expected = dark_signal_e(meta).sqrt() * dn_per_e
    else:
        rn = readout_sigma_e(meta)
        n = torch.randn(x.shape, generator=gen, dtype=x.dtype) * (rn.view(-1, 1, 1, 1).to(x.dtype) * to_int)
        expected = rn * dn_per_e
    return n, expected.to(x.dtype)


def _scaled(x: torch.Tensor, source: str, sigma_dn: float, gen: torch.Generator) -> torch.Tensor:
    """Raw noise of ``source`` amplified so its expected σ is ``sigma_dn`` (the thesis's "amplify the raw noise")."""
    n, expected = _raw_noise(x, source, _nominal_meta(), gen)
    return n * (sigma_dn / expected.clamp_min(1e-3)).view(-1, 1, 1, 1)


def _realised_dn(noisy: torch.Tensor, clean: torch.Tensor) -> torch.Tensor:
    return (noisy - clean).flatten(1).std(dim=1) * 255.0


def _kernels(family: str, size: float, angles: Sequence[float], seed: int) -> torch.Tensor:
    from camhealth.physics import defocus_psf, linear_motion_psf, nonlinear_motion_psf

    n = len(angles)
    d = torch.full((n,), float(size))
    ang = torch.tensor([float(a) for a in angles])
    if family == "defocus":
        return defocus_psf(d, KERNEL_SIZE)
    if family == "linear":
        return linear_motion_psf(d, ang, KERNEL_SIZE)
    g = _generator(seed, "shake", size)
    noise = torch.randn(1, 64, 2, generator=g).expand(n, 64, 2)  # the same path, rotated (Fig. 5.1b)
    return nonlinear_motion_psf(d, ang, torch.ones(n), noise, KERNEL_SIZE)


def _blur(x: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    from camhealth.physics import apply_psf

    return apply_psf(x, psf).clamp(0.0, 1.0)


def _case_noise_isolated(cfg: EvalConfig, images: _ImageCache) -> dict:
    gen = _generator(cfg.seed, "noise_isolated")
    clean = _sample_patches(images, cfg.noise_patches * len(SOURCES) * len(NOISE_LEVELS_DN), NOISE_PATCH, gen)
    noisy, src_idx, level = [], [], []
    k = 0
    for si, src in enumerate(SOURCES):
        for lv in NOISE_LEVELS_DN:
            x = clean[k : k + cfg.noise_patches]
            noisy.append((x + _scaled(x, src, lv, gen)).clamp(0, 1))
            src_idx += [si] * len(x)
            level += [lv] * len(x)
            k += cfg.noise_patches
    noisy_t = torch.cat(noisy)
    total = _realised_dn(noisy_t, clean)
    sigma = torch.zeros(len(total), 3)
    sigma[torch.arange(len(total)), torch.tensor(src_idx)] = total
    return {"patches": noisy_t, "total": total, "sigma": sigma, "source": torch.tensor(src_idx), "level": torch.tensor(level),
            "meta": _nominal_meta().to_dict()}  # fmt: skip


def _deadleaves(cfg: EvalConfig, n: int) -> torch.Tensor:
    from camhealth.data import DeadLeavesSource

    src = DeadLeavesSource(n, size=NOISE_PATCH, seed=cfg.seed, r_min=2.0, supersample=2)
    return torch.stack([src[i][0] for i in range(n)])


def _case_noise_combined(cfg: EvalConfig, images: _ImageCache, dataset: str) -> dict:
    from camhealth.physics import CameraMetadata, form_image

    gen = _generator(cfg.seed, "noise_combined", dataset)
    if dataset == "natural":
        clean = _sample_patches(images, cfg.combined_patches, NOISE_PATCH, gen)
    else:
        clean = _deadleaves(cfg, cfg.combined_patches)
    meta = CameraMetadata.sample(len(clean), generator=gen)
    res = form_image(clean, meta, generator=gen)
    return {"patches": res.image, "total": res.sigma_total_dn, "sigma": res.sigma_dn, "meta": meta.to_dict()}


def _rendered_blur_scenes(seed: int) -> _ImageCache:
    """Four scenes of each rendered class (exact pixel aperture, native MTF 1), 320 px."""
    from camhealth.bench.rendered_scenes import CLASSES, render_scenes

    scenes = [(x, f"rendered-{c}-{i}") for c in CLASSES for i, x in enumerate(render_scenes(c, 4, 320, seed=seed + 500))]
    return _ImageCache(scenes)


def _case_blur(cfg: EvalConfig, images: _ImageCache) -> dict:
    from camhealth.estimators.charts import siemens_star_chart, slanted_edge_chart
    from camhealth.physics import mtf_from_psf, mtf_hv

    gen = _generator(cfg.seed, "blur")
    if cfg.blur_patches and cfg.blur_scenes == "rendered":
        images = _rendered_blur_scenes(cfg.seed)
    rows, patches, p_rows, sle, star, labels, exact = [], [], [], [], [], [], []
    sle_chart = slanted_edge_chart(SLE_CHART) if cfg.charts else None
    star_chart = siemens_star_chart(STAR_CHART) if cfg.charts else None
    for fam in FAMILIES:
        for d in BLUR_SIZES_PX:
            angles = (0.0,) if fam == "defocus" else DIRECTIONS_DEG
            psf = _kernels(fam, d, angles, cfg.seed)
            for j, a in enumerate(angles):
                k = psf[j : j + 1]
                rows.append((FAMILIES.index(fam), d, a))
                labels.append(mtf_hv(k)[0])
                exact.append(mtf_from_psf(k, (5.0, 95.0)).reshape(-1))
                if cfg.charts:
                    sle.append(_blur(sle_chart, k)[0])
                    star.append(_blur(star_chart, k)[0])
                if cfg.blur_patches:
                    x = _sample_patches(images, cfg.blur_patches, BLUR_PATCH, gen, min_std_dn=2.0)
                    patches.append(_blur(x, k.expand(len(x), -1, -1)))
                    p_rows += [len(rows) - 1] * len(x)
    return {
        "rows": torch.tensor(rows), "labels": torch.stack(labels), "exact_5_95": torch.stack(exact),
        "sle": torch.stack(sle) if sle else torch.zeros(0, 1, SLE_CHART, SLE_CHART),
        "star": torch.stack(star) if star else torch.zeros(0, 1, STAR_CHART, STAR_CHART),
        "patches": torch.cat(patches) if patches else torch.zeros(0, 1, BLUR_PATCH, BLUR_PATCH),
        "patch_row": torch.tensor(p_rows, dtype=torch.long),
    }  # fmt: skip


def _bun_corrupt(x: torch.Tensor, case: str, d: float, sigma: float, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(noisy, realised σ DN, kernel) for Defocus + DCSN (blur, then noise) or Photon + LinMB (noise, then blur)."""
    if case == "defocus_dcsn":
        k = _kernels("defocus", d, (0.0,), 0)
        blurred = _blur(x, k.expand(len(x), -1, -1))
        noisy = (blurred + _scaled(blurred, "dark", sigma, gen)).clamp(0, 1) if sigma > 0 else blurred
    else:
        k = _kernels("linear", d, (0.0,), 0)
        blurred = _blur(x, k.expand(len(x), -1, -1))
        noisy = _blur((x + _scaled(x, "photon", sigma, gen)).clamp(0, 1), k.expand(len(x), -1, -1)) if sigma > 0 else blurred
    return noisy, _realised_dn(noisy, blurred), k


def _case_bun(cfg: EvalConfig, images: _ImageCache) -> dict:
    from camhealth.estimators.charts import siemens_star_chart, slanted_edge_chart
    from camhealth.physics import mtf_from_psf, mtf_hv

    gen = _generator(cfg.seed, "blur_under_noise")
    sle_chart = slanted_edge_chart(SLE_CHART) if cfg.charts else None
    star_chart = siemens_star_chart(STAR_CHART) if cfg.charts else None
    rows, patches, p_rows, sigma, sle, star, c_sigma, labels, exact = [], [], [], [], [], [], [], [], []
    for ci, case in enumerate(BUN_CASES):
        for d in cfg.bun_sizes:
            for lv in cfg.bun_levels:
                rows.append((ci, d, lv))
                r = len(rows) - 1
                if cfg.bun_patches:
                    x = _sample_patches(images, cfg.bun_patches, BLUR_PATCH, gen, min_std_dn=2.0)
                    noisy, s, k = _bun_corrupt(x, case, d, lv, gen)
                    patches.append(noisy)
                    sigma.append(s)
                    p_rows += [r] * len(x)
                k = _kernels("defocus" if case == "defocus_dcsn" else "linear", d, (0.0,), 0)
                if cfg.charts:
                    sn, ss, _ = _bun_corrupt(sle_chart, case, d, lv, gen)
                    tn, _, _ = _bun_corrupt(star_chart, case, d, lv, gen)
                    sle.append(sn[0])
                    star.append(tn[0])
                    c_sigma.append(ss[0])
                labels.append(mtf_hv(k)[0])
                exact.append(mtf_from_psf(k, (5.0, 95.0)).reshape(-1))
    return {
        "rows": torch.tensor(rows), "labels": torch.stack(labels), "exact_5_95": torch.stack(exact),
        "patches": torch.cat(patches) if patches else torch.zeros(0, 1, BLUR_PATCH, BLUR_PATCH),
        "patch_row": torch.tensor(p_rows, dtype=torch.long), "sigma": torch.cat(sigma) if sigma else torch.zeros(0),
        "sle": torch.stack(sle) if sle else torch.zeros(0, 1, SLE_CHART, SLE_CHART),
        "star": torch.stack(star) if star else torch.zeros(0, 1, STAR_CHART, STAR_CHART),
        "chart_sigma": torch.stack(c_sigma) if c_sigma else torch.zeros(0),
        "meta": _nominal_meta().to_dict(),
    }  # fmt: skip


def _sequence(cfg: EvalConfig, source: Any) -> list[torch.Tensor]:
    """Frames of the aggregation sequence: the street clip for the default source, else the source in order."""
    from camhealth.data import StreetSampleSource

    seq = StreetSampleSource() if isinstance(cfg.source, str) and cfg.source.strip().lower() in ("default", "street") else source
    n = min(cfg.agg_frames, len(seq))
    if n < 2:
        raise ValueError(f"the aggregation needs a sequence of >= 2 frames; the source has {len(seq)}")
    return [seq[i][0].float() for i in range(n)]


def _case_aggregation(cfg: EvalConfig, source: Any) -> dict:
    frames = _sequence(cfg, source)
    h = min(f.shape[-2] for f in frames) // NOISE_PATCH * NOISE_PATCH
    w = min(f.shape[-1] for f in frames) // NOISE_PATCH * NOISE_PATCH
    if h == 0 or w == 0:
        raise ValueError(f"aggregation frames must be at least {NOISE_PATCH} px, got {tuple(frames[0].shape[-2:])}")
    grid = [(y, x) for y in range(0, h, NOISE_PATCH) for x in range(0, w, NOISE_PATCH)]
    gen = _generator(cfg.seed, "aggregation")
    pick = torch.randperm(len(grid), generator=gen)[: cfg.agg_patches].sort().values.tolist()
    grid = [grid[i] for i in pick]
    clean = torch.stack([f[:, y : y + NOISE_PATCH, x : x + NOISE_PATCH] for f in frames for (y, x) in grid])
    raw = [_raw_noise(clean, s, _nominal_meta(), gen) for s in SOURCES]
    exp_total = torch.sqrt(sum(e.square().mean() for _, e in raw))  # one gain for the whole (static) sequence
    scale = AGG_SIGMA_DN / float(exp_total)
    noisy = (clean + scale * sum(n for n, _ in raw)).clamp(0, 1)
    return {"patches": noisy, "total": _realised_dn(noisy, clean), "frames": len(frames), "per_frame": len(grid),
            "meta": _nominal_meta().to_dict()}  # fmt: skip


def build_cases(cfg: EvalConfig, cache: Path | None = None, resume: bool = False, log: Callable[[str], None] = print) -> dict[str, dict]:
    """Build (or, with ``resume``, load) the benchmark data of every case for ``cfg``."""
    from camhealth.data import build_source

    source = build_source(cfg.source, bit_depth=cfg.bit_depth)
    images = _ImageCache(source)
    builders: dict[str, Callable[[], dict]] = {
        "noise_isolated": lambda: _case_noise_isolated(cfg, images),
        "noise_combined_natural": lambda: _case_noise_combined(cfg, images, "natural"),
        "blur": lambda: _case_blur(cfg, images),
        "blur_under_noise": lambda: _case_bun(cfg, images),
        "aggregation": lambda: _case_aggregation(cfg, source),
    }
    if cfg.deadleaves:
        builders["noise_combined_deadleaves"] = lambda: _case_noise_combined(cfg, images, "deadleaves")
    cases = {}
    for name, build in builders.items():
        path = None if cache is None else cache / name / "data.pt"
        blob = _read_cache(path, log) if resume else None
        if blob is not None and blob.get("config_key") == cfg.key():
            cases[name] = blob["data"]
            continue
        t0 = time.perf_counter()
        cases[name] = build()
        log(f"built case {name} in {time.perf_counter() - t0:.1f} s")
        if path is not None:
            _write_cache({"config_key": cfg.key(), "data": cases[name]}, path)
    return cases


def _write_cache(obj: Any, path: Path) -> None:
    """``torch.save`` to a temporary file next to ``path``, then rename it there: an interrupted run leaves the old
    entry or none, never a truncated one."""
    import os
    import tempfile

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _read_cache(path: Path | None, log: Callable[[str], None]) -> dict | None:
    """A cache entry (tensors and plain data only), or ``None`` where there is none or it cannot be read (a truncated
    or foreign file is reported and rebuilt)."""
    if path is None or not path.exists():
        return None
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - truncated by an interrupted run, another torch version, not a cache
        log(f"cache entry {path} cannot be read ({type(exc).__name__}); computing it again")
        return None
    if not isinstance(blob, dict):
        log(f"cache entry {path} is not a camhealth cache entry; computing it again")
        return None
    return blob


# ============================================================================================ methods
@dataclass
class Method:
    """One estimator as the benchmark runs it.

    ``kind``: ``"noise"`` (patches, metadata → dict with ``total`` (B,) DN and optionally ``sigma`` (B, 3)),
    ``"mtf"`` (patches → (B, 16)) or ``"chart_sle"`` / ``"chart_star"`` (charts → (B, 16)). ``patch_size``:
    the patch side the method reads (larger patches are centre-cropped). ``learned``: a learned estimator.
    """

    name: str
    kind: str
    fn: Callable[..., Any]
    patch_size: int | None = None
    learned: bool = False
    per_source: bool = False
    identity: str = ""  # what the cache of ``--resume`` checks besides the name (a learned file's SHA-256)


def classical_methods() -> list[Method]:
    """PCA, B+F, wavelet MAD (noise); slanted edge and Siemens star (charts)."""
    from camhealth.estimators import block_filter_noise_sigma, pca_noise_sigma, siemens_star_mtf, slanted_edge_mtf_hv, wavelet_noise_sigma

    def noise(fn: Callable[[torch.Tensor], torch.Tensor]) -> Callable[..., dict]:
        return lambda x, meta=None: {"total": fn(x)}

    return [
        Method("PCA", "noise", noise(pca_noise_sigma)),
        Method("B+F", "noise", noise(block_filter_noise_sigma)),
        Method("wavelet", "noise", noise(wavelet_noise_sigma)),
        Method("slanted edge", "chart_sle", slanted_edge_mtf_hv),
        Method("Siemens star", "chart_star", lambda x: siemens_star_mtf(x).mtf),
    ]


def _file_identity(est: Any) -> str:
    """SHA-256 of the file a learned estimator was loaded from ("" where it has none: the physics-first estimator)."""
    import hashlib

    path = Path(str(getattr(est, "source", "")))
    if not path.is_file():
        return ""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _wrap_learned(label: str, est: Any) -> Method:
    kind, p = getattr(est, "kind"), int(getattr(est, "patch_size"))
    needs_meta = getattr(est, "metadata_set", "none") != "none"
    identity = _file_identity(est)

    if kind == "mtf":
        return Method(label, "mtf", lambda x: est.predict(x)["mtf"].float(), patch_size=p, learned=True, identity=identity)

    def noise(x: torch.Tensor, meta: Any = None) -> dict:
        out = est.predict(x, meta if needs_meta else None)
        res = {"total": out["sigma_total"].float()}
        if "sigma" in out:
            res["sigma"] = out["sigma"].float()
        return res

    return Method(label, "noise", noise, patch_size=p, learned=True, per_source=kind == "noise_source", identity=identity)


def learned_methods(names: Sequence[str] = SHIPPED, checkpoints: Sequence[str | Path] = (), log: Callable[[str], None] = print) -> list[Method]:
    """Learned estimators through :func:`camhealth.inference.load_estimator`: the shipped ``names`` that load
    (others are skipped with a note) and every checkpoint (which must load)."""
    try:
        from camhealth.inference import load_estimator
    except ImportError as err:
        log(f"note: camhealth.inference is not importable ({err}); the learned rows are left out")
        return []
    out = []
    for name in names:
        try:
            est = load_estimator(name)
            kind = "learned" if est.description.get("params", 1) else "physics-first"  # noise_source_full has no network
            out.append(_wrap_learned(f"{kind} {name}", est))
        except Exception as err:  # a shipped model that is not there (yet) is skipped, with the reason
            log(f"note: learned estimator {name!r} not available ({type(err).__name__}: {err}); its rows are left out")
    for path, label in zip(checkpoints, checkpoint_labels(checkpoints)):
        method = _wrap_learned(label, load_estimator(str(path)))
        _check_patch_fits(method, f"--checkpoint {path}")
        out.append(method)
    return out


def _check_patch_fits(m: Method, what: str | None = None) -> None:
    """``ValueError`` naming the method (``what``: its file) and both sizes when a learned method reads larger patches
    than the benchmark has for it: :data:`NOISE_PATCH` px for a noise estimator, :data:`BLUR_PATCH` px for an MTF
    estimator (larger patches are centre-cropped to its size, smaller ones cannot be)."""
    if not m.learned or m.patch_size is None:
        return
    limit = BLUR_PATCH if m.kind == "mtf" else NOISE_PATCH
    if m.patch_size > limit:
        kind = "MTF" if m.kind == "mtf" else "noise"
        who, article = what if what else f"method {m.name!r}", "an" if kind == "MTF" else "a"
        raise ValueError(f"{who}: {article} {kind} estimator of patch_size = {m.patch_size} px; the benchmark's {kind} "
                         f"patches are {limit} px, so it can evaluate {kind} estimators of at most {limit} px")


def checkpoint_labels(paths: Sequence[str | Path]) -> list[str]:
    """The row names of ``--checkpoint`` files: ``checkpoint STEM``; files whose stems repeat (the ``last.ckpt`` of
    two runs) get as many of their parent folders as tell them apart (``checkpoint version_1/checkpoints/last``),
    and their whole path where only the suffix differs. The same file given twice is a ``ValueError``."""
    full = [Path(p).resolve() for p in paths]
    for i, p in enumerate(full):
        if p in full[:i]:
            raise ValueError(f"--checkpoint {paths[i]} is given twice (the file {p})")

    def label(p: Path, k: int) -> str:  # the stem and (up to) k parent folders, the root "/" left out
        folders = p.parent.parts[1:] if p.parent.anchor else p.parent.parts
        return "/".join([*folders[len(folders) - min(k, len(folders)):], p.stem])

    labels = []
    for p in full:
        group = [q for q in full if q.stem == p.stem]
        depth = max(len(q.parts) for q in group)
        k = next((k for k in range(depth) if len({label(q, k) for q in group}) == len(group)), None)
        labels.append(f"checkpoint {label(p, k) if k is not None else p}")
    return labels


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_").lower()


def _crop(x: torch.Tensor, p: int | None) -> torch.Tensor:
    if p is None or x.shape[-1] == p:
        return x
    if x.shape[-1] < p:
        raise ValueError(f"patches of {x.shape[-1]} px are smaller than the {p} px the estimator reads")
    o = (x.shape[-1] - p) // 2
    return x[..., o : o + p, o : o + p]


# ============================================================================================ running
class _Runner:
    """Runs (case, method, variant) units with caching, timing and a progress bar."""

    def __init__(self, cfg: EvalConfig, cache: Path | None, resume: bool, log: Callable[[str], None], progress: bool) -> None:
        self.cfg, self.cache, self.resume, self.log = cfg, cache, resume, log
        self.timing: dict[str, dict[str, float]] = {}
        self.reused = 0
        self.progress = progress

    def _time(self, method: Method, seconds: float, items: int, unit: str) -> None:
        t = self.timing.setdefault(method.name, {"seconds": 0.0, "items": 0, "unit": unit, "learned": method.learned})
        t["seconds"] += seconds
        t["items"] += items

    def run(self, case: str, method: Method, variant: str, inputs: torch.Tensor, call: Callable[[torch.Tensor, slice], Any], unit: str) -> dict:
        path = None if self.cache is None else self.cache / case / f"{_slug(method.name)}{variant}.pt"
        blob = _read_cache(path, self.log) if self.resume else None
        if (blob is not None and blob.get("config_key") == self.cfg.key() and blob.get("identity", "") == method.identity
                and {"seconds", "items", "out"} <= set(blob)):  # the same method: the same file, not only its name
            self._time(method, blob["seconds"], blob["items"], unit)
            self.reused += 1
            return blob["out"]
        chunk = self.cfg.batch if unit == "patch" else 8
        parts: list[Any] = []
        seconds = 0.0
        for s in range(0, len(inputs), chunk):
            sl = slice(s, min(len(inputs), s + chunk))
            batch = inputs[sl]
            t0 = time.perf_counter()
            with torch.inference_mode():
                parts.append(call(batch, sl))
            seconds += time.perf_counter() - t0
        out = _cat(parts)
        self._time(method, seconds, len(inputs), unit)
        if path is not None:
            _write_cache({"config_key": self.cfg.key(), "identity": method.identity, "out": out, "seconds": seconds,
                          "items": len(inputs)}, path)
        return out


def _cat(parts: list[Any]) -> Any:
    if not parts:
        return torch.zeros(0)
    if isinstance(parts[0], dict):
        return {k: torch.cat([p[k] for p in parts]) for k in parts[0] if isinstance(parts[0][k], torch.Tensor)}
    return torch.cat(parts)


def _meta_slice(meta_dict: dict, n_total: int):
    from camhealth.physics import CameraMetadata

    meta = CameraMetadata.from_dict(meta_dict)
    return meta.expand(n_total) if meta.batch_size == 1 else meta


def _units(cases: dict, methods: list[Method]) -> list[tuple[str, Method, str]]:
    units = []
    for m in methods:
        if m.kind == "noise":
            units += [(c, m, "") for c in cases if c.startswith("noise") or c == "aggregation"]
            units.append(("blur_under_noise", m, "_noise"))
        elif m.kind == "mtf":
            units += [("blur", m, ""), ("blur_under_noise", m, ""), ("blur_under_noise", m, "_b2")]
        else:
            units += [("blur", m, ""), ("blur_under_noise", m, ""), ("blur_under_noise", m, "_b2")]
    return units


def _run_unit(runner: _Runner, cases: dict, case: str, m: Method, variant: str) -> dict:
    from camhealth.estimators.blur_under_noise import estimate_blur_under_noise

    data = cases[case]
    if m.kind == "noise":
        patches = data["patches"]
        n = len(patches)
        meta = _meta_slice(data["meta"], n) if "meta" in data else None

        def call(x: torch.Tensor, sl: slice) -> dict:
            return m.fn(_crop(x, m.patch_size) if m.learned else _crop(x, NOISE_PATCH), None if meta is None else meta[sl])

        return runner.run(case, m, variant, patches, call, "patch")
    b2 = variant == "_b2"
    if m.kind == "mtf":
        def call(x: torch.Tensor, sl: slice) -> Any:
            x = _crop(x, m.patch_size)
            return estimate_blur_under_noise(x, m.fn).mtf if b2 else m.fn(x)

        return {"mtf": runner.run(case, m, variant, data["patches"], call, "patch")}
    charts = data["sle"] if m.kind == "chart_sle" else data["star"]

    def call_chart(x: torch.Tensor, sl: slice) -> Any:
        return estimate_blur_under_noise(x, m.fn).mtf if b2 else m.fn(x)

    return {"mtf": runner.run(case, m, variant, charts, call_chart, "chart")}


# ============================================================================================ metrics
def _amae_median(est: torch.Tensor, rows: torch.Tensor, n_rows: int, labels: torch.Tensor) -> torch.Tensor:
    """Per row: AMAE (%) of the median estimate over the patches of that row (Sec. 5.2)."""
    from camhealth.metrics import amae

    out = torch.full((n_rows,), float("nan"))
    for r in range(n_rows):  # one median per kernel (a few dozen rows)
        sel = est[rows == r]
        if len(sel):
            out[r] = amae(torch.nanmedian(sel.double(), dim=0).values, labels[r].double())
    return out


def _blur_table(cases: dict, results: dict, methods: list[Method]) -> dict:
    from camhealth.metrics import amae

    data = cases["blur"]
    rows = data["rows"]
    table: dict[str, dict[str, float]] = {}
    curves: dict[str, Any] = {}
    for m in methods:
        if m.kind not in ("mtf", "chart_sle", "chart_star"):
            continue
        est = results[("blur", m.name, "")]["mtf"].double()
        if m.kind == "mtf":
            per_row = _amae_median(est, data["patch_row"], len(rows), data["labels"])
        else:
            per_row = amae(est, data["labels"].double())
        table[m.name] = _by_family_size(rows, per_row)
        curves[m.name] = est
        if m.kind == "chart_sle":
            table["slanted edge vs. exact MTF at 5°/95°"] = _by_family_size(rows, amae(est, data["exact_5_95"].double()))
    return {"amae": table, "curves": curves}


def _by_family_size(rows: torch.Tensor, per_row: torch.Tensor) -> dict[str, float]:
    out = {}
    for fi, fam in enumerate(FAMILIES):
        for d in BLUR_SIZES_PX:
            sel = (rows[:, 0] == fi) & (rows[:, 1] == d)
            out[f"{fam} {d:g}"] = float(torch.nanmean(per_row[sel])) if bool(sel.any()) else float("nan")
    return out


def _finite_errors(est: torch.Tensor, truth: torch.Tensor, what: str,
                   excluded_by: dict[str, list[int]] | None) -> dict[str, float]:
    """:func:`camhealth.metrics.noise_errors` of the finite estimates: a method that cannot assess a patch (PCA on a flat
    black one) answers NaN/inf there. Those samples are left out, counted in the result's ``excluded`` and in
    ``excluded_by[what]`` ([left out, estimates]; ``what``: the method and the case, for the report's notes); with no
    finite estimate Bias/Std/RMS are NaN (no data). With every estimate finite the result is ``noise_errors``'s alone."""
    from camhealth.metrics import noise_errors

    est, truth = est.reshape(-1), truth.reshape(-1)
    finite = torch.isfinite(est)
    excluded = int((~finite).sum())
    if excluded_by is not None:
        count = excluded_by.setdefault(what, [0, 0])
        count[0] += excluded
        count[1] += est.numel()
    if not excluded:
        return noise_errors(est, truth)
    if not bool(finite.any()):
        nan = float("nan")
        return {"bias": nan, "std": nan, "rms": nan, "n": 0, "excluded": excluded}
    return {**noise_errors(est[finite], truth[finite]), "excluded": excluded}


def _noise_tables(cases: dict, results: dict, methods: list[Method], excluded: dict[str, list[int]] | None = None) -> dict:
    out: dict[str, Any] = {"combined": {}, "isolated": {}, "isolated_median": {}}
    for ds in ("natural", "deadleaves"):
        case = f"noise_combined_{ds}"
        if case not in cases:
            continue
        data = cases[case]
        for m in methods:
            if m.kind != "noise":
                continue
            r = results[(case, m.name, "")]
            row = {"Total": _finite_errors(r["total"], data["total"], f"{m.name} on {case} (total)", excluded)}
            if m.per_source and "sigma" in r:
                for i, s in enumerate(SOURCES):
                    row[SOURCE_LABELS[s]] = _finite_errors(r["sigma"][:, i], data["sigma"][:, i],
                                                           f"{m.name} on {case} ({SOURCE_LABELS[s]})", excluded)
            out["combined"].setdefault(ds, {})[m.name] = row
    data = cases["noise_isolated"]
    for m in methods:
        if m.kind != "noise":
            continue
        r = results[("noise_isolated", m.name, "")]
        rms, med = {}, {}
        for si, s in enumerate(SOURCES):
            for lv in NOISE_LEVELS_DN:
                sel = (data["source"] == si) & (data["level"] == lv)
                key = f"{SOURCE_LABELS[s]} {lv:g}"
                est = r["total"][sel]
                rms[key] = _finite_errors(est, data["total"][sel], f"{m.name} on noise_isolated", excluded)["rms"]
                est = est[torch.isfinite(est)]
                q = (torch.quantile(est.double(), torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)) if est.numel()
                     else torch.full((3,), float("nan"), dtype=torch.float64))
                med[key] = {"min": float(q[0]), "median": float(q[1]), "max": float(q[2]), "truth": float(data["total"][sel].median())}
        out["isolated"][m.name] = rms
        out["isolated_median"][m.name] = med
    return out


def _bun_tables(cases: dict, results: dict, methods: list[Method], excluded: dict[str, list[int]] | None = None) -> dict:
    from camhealth.metrics import amae

    data = cases["blur_under_noise"]
    rows = data["rows"]
    blur: dict[str, dict[str, dict[str, float]]] = {}
    for m in methods:
        if m.kind == "noise":
            continue
        for variant, suffix in (("", ""), ("_b2", " + b₂ (7 px)")):
            est = results[("blur_under_noise", m.name, variant)]["mtf"].double()
            if m.kind == "mtf":
                per_row = _amae_median(est, data["patch_row"], len(rows), data["labels"])
            else:
                truth = data["exact_5_95"] if m.kind == "chart_sle" else data["labels"]
                per_row = amae(est, truth.double())
            cells = {}
            for r, (ci, d, lv) in enumerate(rows.tolist()):
                cells[f"{BUN_CASES[int(ci)]}|{lv:g}|{d:g}"] = float(per_row[r])
            blur[m.name + suffix] = cells
    noise: dict[str, dict[str, dict[str, float]]] = {}
    if len(data["sigma"]):
        lv_of_patch = rows[data["patch_row"], 2]
        case_of_patch = rows[data["patch_row"], 0]
        for m in methods:
            if m.kind != "noise":
                continue
            est = results[("blur_under_noise", m.name, "_noise")]["total"]
            noise[m.name] = {}
            for ci, case in enumerate(BUN_CASES):
                sel = (case_of_patch == ci) & (lv_of_patch > 0)
                if bool(sel.any()):
                    noise[m.name][case] = _finite_errors(est[sel], data["sigma"][sel], f"{m.name} on blur_under_noise "
                                                         f"({BUN_LABELS[case]})", excluded)
    return {"blur": blur, "noise": noise}


def _window_errors(est: torch.Tensor, truth: torch.Tensor, windows: Sequence[int]) -> dict[int, dict[str, float]]:
    """The error of the aggregated estimate, σ̃_n − σ_n, per window size n (frames along dim 0, (T, P)): σ̃_n the
    median of the estimates over each sliding window of n frames (Eq. 5.4), σ_n the median of the realised σ over
    the same window. Per n: ``std`` (population, over the finite values of every window position and patch),
    ``median`` and ``delta`` = std at n = 1 − std at n, as :func:`~camhealth.estimators.aggregation.uncertainty_by_window`
    gives them for the estimates."""
    from camhealth.estimators.aggregation import temporal_median

    out: dict[int, dict[str, float]] = {}
    for n in sorted({int(n) for n in windows} | {1}):
        err = temporal_median(est, n, stride=1).median - temporal_median(truth, n, stride=1).median
        vals = err[torch.isfinite(err)].double()
        out[n] = {"std": float(vals.std(unbiased=False)) if vals.numel() else float("nan"),
                  "median": float(vals.median()) if vals.numel() else float("nan")}
    for n in out:
        out[n]["delta"] = out[1]["std"] - out[n]["std"]
    return out


def _agg_table(cases: dict, results: dict, methods: list[Method], windows: Sequence[int]) -> dict:
    from camhealth.estimators.aggregation import uncertainty_by_window

    data = cases["aggregation"]
    t, p = data["frames"], data["per_frame"]
    out = {}
    for m in methods:
        if m.kind != "noise":
            continue
        est = results[("aggregation", m.name, "")]["total"].reshape(t, p).double()
        truth = data["total"].reshape(t, p).double()
        out[m.name] = {str(k): v for k, v in uncertainty_by_window(est, windows).items()}
        # the same for the error σ̃_n − σ_n: removes the true patch-to-patch differences (photon noise ∝ √I)
        for k, v in _window_errors(est, truth, [int(n) for n in out[m.name]]).items():
            out[m.name][str(k)].update(err_std=v["std"], err_delta=v["delta"], err_median=v["median"])
    out["_truth_median_dn"] = float(data["total"].median())
    return out


# ============================================================================================ report
def _f(x: float, spec: str = ".2f") -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def _md_table(header: list[str], body: list[list[str]], align: str | None = None) -> list[str]:
    al = align or ("---|" + "---:|" * (len(header) - 1))
    return ["| " + " | ".join(header) + " |", "|" + al] + ["| " + " | ".join(r) + " |" for r in body] + [""]


def _speed_rows(timing: dict) -> list[dict]:
    rows = []
    for name, t in timing.items():
        ms = 1e3 * t["seconds"] / max(t["items"], 1)
        rows.append({"method": name, "ms_per_item": ms, "unit": t["unit"], "items": int(t["items"]), "learned": bool(t["learned"])})
    return rows


def _depth_note(cfg: dict) -> str:
    depth = cfg.get("bit_depth", "auto")
    return "" if depth == "auto" else f" read as {depth}-bit data"


def _markdown(report: dict) -> str:
    cfg = report["config"]
    lines = [
        RESULTS_TITLE,
        "",
        f"command: `{report['command']}`  ",
        f"machine: {report['machine']}  ",
        f"date: {report['date']}; wall time {report['wall_s']:.0f} s; configuration key `{report['config_key']}`"
        + (" (--quick)" if report.get("quick") else ""),
        "",
        f"Data: source `{cfg['source']}`{_depth_note(cfg)} (+ dead leaves as the texture-rich set), seed {cfg['seed']}; learned-MTF blur patches from "
        f"{'rendered scenes with an exact pixel aperture (native MTF 1: the label is exact)' if cfg.get('blur_scenes', 'rendered') == 'rendered' else 'the source (labels ignore its own blur)'}; noise patches 128 px, "
        f"blur patches 192 px, charts {SLE_CHART} px (slanted edge) and {STAR_CHART} px (Siemens star).",
        "",
    ]
    for note in report["notes"]:
        lines.append(f"> {note}")
    if not any(m["learned"] for m in report["methods"]):
        lines.append("> No learned estimator was evaluated in this run: the learned rows are added when their weights "
                     "exist (shipped in `camhealth/weights/` or given with `--checkpoint`) — re-run the command above.")  # fmt: skip
    if report["notes"] or not any(m["learned"] for m in report["methods"]):
        lines.append("")
    # --- Tab 5.1
    blur = report["blur"]["amae"]
    cols = [f"{fam[0].upper()}{d:g}" for fam in FAMILIES for d in BLUR_SIZES_PX]
    keys = [f"{fam} {d:g}" for fam in FAMILIES for d in BLUR_SIZES_PX]
    lines += ["## Blur: AMAE per kernel family and size [%] (like Tab. 5.1)", "",
              "D = defocus, L = linear motion, N = non-linear motion (camera shake); d in px. Learned rows: AMAE of the "
              "median estimate over the patches of a kernel, averaged over the 4 directions; chart rows: one chart per kernel "
              "(pixel aperture of the area-rendered chart divided out). The last row compares the slanted edge with the exact "
              "MTF of the kernel in the direction it measures (5°/95°): it cross-checks the labels of the data pipeline.", ""]  # fmt: skip
    lines += _md_table(["method"] + cols, [[name] + [_f(v.get(k), ".1f") for k in keys] for name, v in blur.items()])
    # --- Tab 6.1
    nt = report["noise"]
    lines += ["## Noise: Bias / Std / RMS per source and method [DN] (like Tab. 6.1)", "",
              "All sources together, random sensors from Table 4.1 (`form_image`); natural patches and dead leaves "
              "(texture-rich, Sim-like). Classical methods estimate the total only.", ""]  # fmt: skip
    hdr = ["data", "method"] + [f"{s} {q}" for s in ("PN", "DCSN", "RN", "Total") for q in ("Bias", "Std", "RMS")]
    body = []
    for ds, per_m in nt["combined"].items():
        for name, row in per_m.items():
            cells = []
            for s in ("PN", "DCSN", "RN", "Total"):
                e = row.get(s)
                cells += [_f(e["bias"]), _f(e["std"]), _f(e["rms"])] if e else ["–", "–", "–"]
            body.append([ds, name] + cells)
    lines += _md_table(hdr, body, "---|---|" + "---:|" * (len(hdr) - 2))
    lines += ["## Noise, isolated sources: RMS [DN] per source and σ (like Fig. 5.11)", "",
              "Raw noise of the sensor model amplified to σ (EV76C661, 57 °C, 0.1 s); label = realised σ after clipping.", ""]  # fmt: skip
    iso_cols = [f"{SOURCE_LABELS[s]} {lv:g}" for s in SOURCES for lv in NOISE_LEVELS_DN]
    lines += _md_table(["method"] + iso_cols, [[n] + [_f(v[c]) for c in iso_cols] for n, v in nt["isolated"].items()])
    # --- Tab 5.2
    bun = report["blur_under_noise"]
    cfgs, lvs = cfg["bun_sizes"], cfg["bun_levels"]
    lines += ["## Blur under noise: AMAE [%] (like Tab. 5.2, Sec. 5.5)", "",
              "Rows σ [DN], columns d [px]. `+ b₂ (7 px)`: extra defocus pre-filter, MTF(b₂) divided out where the "
              "preconditions hold (ε = 0.05). Slanted-edge rows are scored against the exact MTF in the measured direction. "
              "– : the method called the chart not assessable (a Siemens star whose corner noise exceeds "
              "`MAX_NOISE_CONTRAST` of its contrast I_w − I_b).", ""]  # fmt: skip
    for ci, case in enumerate(BUN_CASES):
        for name, cells in bun["blur"].items():
            lines += [f"**{BUN_LABELS[case]} — {name}**", ""]
            body = [[f"σ = {lv:g}"] + [_f(cells.get(f"{case}|{lv:g}|{d:g}"), ".1f") for d in cfgs] for lv in lvs]
            lines += _md_table(["σ \\ d"] + [f"{d:g}" for d in cfgs], body)
    if bun["noise"]:
        lines += ["**Noise estimation under blur: Bias / Std / RMS [DN] (σ > 0; like Fig. 5.12a)**", ""]
        hdr = ["method"] + [f"{BUN_LABELS[c]} {q}" for c in BUN_CASES for q in ("Bias", "Std", "RMS")]
        body = []
        for name, per_case in bun["noise"].items():
            cells = []
            for c in BUN_CASES:
                e = per_case.get(c)
                cells += [_f(e["bias"]), _f(e["std"]), _f(e["rms"])] if e else ["–"] * 3
            body.append([name] + cells)
        lines += _md_table(hdr, body)
    # --- Tab 5.3
    agg = report["aggregation"]
    ws = [w for w in cfg["agg_windows"] if w != 1]
    lines += ["## Uncertainty vs aggregation window (like Tab. 5.3)", "",
              f"Static combined noise (σ_Total ≈ {agg['_truth_median_dn']:.1f} DN median realised), fresh noise per frame; "
              "σ_σ̃1 = std of the patch-wise estimates, Δ_{1→n} = σ_σ̃1 − σ_σ̃n after the median over n frames (Eq. 5.4–5.5) [DN].", ""]  # fmt: skip
    body = []
    for name, tab in agg.items():
        if name.startswith("_"):
            continue
        body.append([name, _f(tab["1"]["std"]), _f(tab["1"]["median"])] + [_f(tab[str(w)]["delta"]) if str(w) in tab else "–" for w in ws])
    lines += _md_table(["method", "σ_σ̃1", "median σ̃1"] + [f"Δ 1→{w}" for w in ws], body)
    lines += ["The same for the error σ̃_n − σ_n (σ_n: median of the realised σ over the window), which removes the true "
              "patch-to-patch differences of the signal-dependent photon noise:", ""]  # fmt: skip
    body = []
    for name, tab in agg.items():
        if name.startswith("_"):
            continue
        body.append([name, _f(tab["1"]["err_std"]), _f(tab["1"]["err_median"])]
                    + [_f(tab[str(w)]["err_delta"]) if str(w) in tab else "–" for w in ws])  # fmt: skip
    lines += _md_table(["method", "σ of error, n = 1", "median error"] + [f"Δ 1→{w}" for w in ws], body)
    # --- speed
    lines += ["## Speed: every method in the same run", "",
              "Mean wall time per 128-px patch (noise), 192-px patch (learned MTF) or chart (slanted edge: 4 edge ROIs of "
              f"a {SLE_CHART}-px chart; Siemens star: {STAR_CHART}-px chart), batches of {cfg['batch']} patches / 8 charts, CPU.", ""]  # fmt: skip
    body = [[r["method"], _f(r["ms_per_item"], ".2f"), r["unit"], str(r["items"])] for r in report["speed"]]
    lines += _md_table(["method", "ms per item", "item", "items timed"], body, "---|---:|---|---:|")
    lines += ["## Summary", ""] + [f"- {s}" for s in report["summary"]] + [""]
    lines += ["Plots: " + ", ".join(f"`plots/{p}`" for p in report["plots"]), ""]
    return "\n".join(lines)


def _s(n: int) -> str:
    return "" if n == 1 else "s"


def _summary(report: dict) -> list[str]:
    out = []
    blur = report["blur"]["amae"]
    sle = blur.get("slanted edge")
    if sle:
        # a kernel without a value (NaN: the method measured nothing) fails the target, wherever it is in the list
        small = [sle[f"defocus {d:g}"] for d in BLUR_SIZES_PX if d <= 11]
        values = [v for v in small if not math.isnan(v)]
        missing = len(small) - len(values)
        worst = max(values) if values else float("nan")
        met = not missing and worst <= 2.0
        gaps = f" ({missing} kernel{_s(missing)} without a value)" if missing else ""
        out.append(f"slanted edge vs labels, defocus d ≤ 11 px: max AMAE {_f(worst)} % (target ≤ 2 %: "
                   f"{'met' if met else 'NOT met'}{gaps})")  # fmt: skip
        ex = blur.get("slanted edge vs. exact MTF at 5°/95°", {})
        if ex:
            allv = [v for v in ex.values() if not math.isnan(v)]
            missing = len(ex) - len(allv)
            if allv:
                out.append(f"slanted edge vs exact kernel MTF in the measured direction: max AMAE {max(allv):.2f} % over all "
                           "kernels" + (f" with a value ({missing} without one)" if missing else "")
                           + " — the MTF labels of the data pipeline agree with the standard measurement")  # fmt: skip
            else:
                out.append(f"slanted edge vs exact kernel MTF in the measured direction: no value for any of the {missing} "
                           f"kernel{_s(missing)} (the slanted edge measured none)")
    comb = report["noise"]["combined"].get("deadleaves", {})
    speed = {r["method"]: r["ms_per_item"] for r in report["speed"]}
    learned = [n for n in comb if n.startswith(("learned", "checkpoint"))]
    if comb:
        ref = {n: comb[n]["Total"]["rms"] for n in ("PCA", "B+F") if n in comb}
        for n in learned:
            rms = comb[n]["Total"]["rms"]
            beats = all(rms < v for v in ref.values())
            fast = all(speed.get(n, math.inf) <= 2.0 * speed.get(k, 0.0) for k in ref)
            if not ref:  # no classical baseline in this run: nothing to compare with
                out.append(f"{n} on dead leaves: total RMS {rms:.2f} DN (PCA and B+F not run: no comparison)")
                continue
            names = " and ".join(ref)
            out.append(f"{n} on dead leaves: total RMS {rms:.2f} DN vs " + ", ".join(f"{k} {v:.2f}" for k, v in ref.items())
                       + f" — {'beats' if beats else 'does NOT beat'} {names}; {speed.get(n, float('nan')):.2f} ms/patch vs "
                       + ", ".join(f"{k} {speed.get(k, float('nan')):.2f}" for k in ref)
                       + f" ({'comparable or better' if fast else 'slower'})")  # fmt: skip
        if not learned:
            out.append("no learned estimator was available in this run: the learned rows (and the comparison target "
                       "\"learned beats PCA and B+F on textured content\") are added when the weights exist")  # fmt: skip
    return out


def _plots(report: dict, cases: dict, results: dict, methods: list[Method], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from camhealth.physics import NORMALIZED_FREQUENCIES

    out.mkdir(parents=True, exist_ok=True)
    names = []
    # error vs time
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    speed = {r["method"]: r for r in report["speed"]}
    comb = report["noise"]["combined"].get("natural", {})
    for n, row in comb.items():
        if n in speed:
            axes[0].scatter(speed[n]["ms_per_item"], row["Total"]["rms"], marker="o" if not speed[n]["learned"] else "*", s=60)
            axes[0].annotate(n, (speed[n]["ms_per_item"], row["Total"]["rms"]), fontsize=8)
    axes[0].set(xscale="log", xlabel="ms per 128-px patch", ylabel="total-noise RMS [DN]", title="noise (combined, natural)")
    for n, row in report["blur"]["amae"].items():
        if n in speed:
            vals = [v for v in row.values() if not math.isnan(v)]
            if vals:
                axes[1].scatter(speed[n]["ms_per_item"], sum(vals) / len(vals), s=60)
                axes[1].annotate(f"{n} (per {speed[n]['unit']})", (speed[n]["ms_per_item"], sum(vals) / len(vals)), fontsize=8)
    axes[1].set(xscale="log", xlabel="ms per patch / chart", ylabel="mean AMAE [%]", title="blur (all kernels)")
    fig.tight_layout()
    fig.savefig(out / "error_vs_time.png", dpi=90)
    plt.close(fig)
    names.append("error_vs_time.png")
    # MTF curves (H, direction 0°) with min/median/max bands
    data = cases["blur"]
    rows = data["rows"]
    fn = list(NORMALIZED_FREQUENCIES)
    fig, axes = plt.subplots(len(FAMILIES), len(BLUR_SIZES_PX), figsize=(15, 8), sharex=True, sharey=True)
    for fi, fam in enumerate(FAMILIES):
        for di, d in enumerate(BLUR_SIZES_PX):
            ax = axes[fi, di]
            r = int(((rows[:, 0] == fi) & (rows[:, 1] == d) & (rows[:, 2] == 0)).nonzero()[0, 0])
            ax.plot(fn, data["labels"][r, :8].tolist(), "k-", lw=2, label="label (GT)")
            for m in methods:
                if m.kind == "noise":
                    continue
                est = results[("blur", m.name, "")]["mtf"]
                if m.kind == "mtf":
                    sel = est[data["patch_row"] == r][:, :8].double()
                    if len(sel):
                        q = torch.quantile(sel, torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64), dim=0)
                        ax.fill_between(fn, q[0].tolist(), q[2].tolist(), alpha=0.25)
                        ax.plot(fn, q[1].tolist(), "-o", ms=3, label=f"{m.name} (median, min–max)")
                else:
                    ax.plot(fn, est[r, :8].tolist(), "--", label=m.name)
            ax.set_title(f"{fam} d = {d:g} px (H, 0°)", fontsize=9)
            ax.set_ylim(-0.05, 1.1)
    axes[0, 0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("f / Nyquist")
    fig.tight_layout()
    fig.savefig(out / "mtf_curves.png", dpi=80)
    plt.close(fig)
    names.append("mtf_curves.png")
    # isolated noise estimates vs σ (median with min–max band)
    iso = report["noise"]["isolated_median"]
    if iso:
        fig, axes = plt.subplots(1, 3, figsize=(13, 4), sharey=True)
        for si, s in enumerate(SOURCES):
            ax = axes[si]
            lv = list(NOISE_LEVELS_DN)
            ax.plot(lv, lv, "k--", label="σ")
            for n, cells in iso.items():
                c = [cells[f"{SOURCE_LABELS[s]} {x:g}"] for x in lv]
                ax.fill_between(lv, [e["min"] for e in c], [e["max"] for e in c], alpha=0.2)
                ax.plot(lv, [e["median"] for e in c], "-o", ms=3, label=n)
            ax.set(title=f"{SOURCE_LABELS[s]} alone", xlabel="target σ [DN]")
        axes[0].set_ylabel("estimated σ [DN] (median, min–max)")
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "noise_isolated.png", dpi=80)
        plt.close(fig)
        names.append("noise_isolated.png")
    # aggregation
    agg = {k: v for k, v in report["aggregation"].items() if not k.startswith("_")}
    if agg:
        fig, ax = plt.subplots(figsize=(5.5, 4))
        for n, tab in agg.items():
            ws = sorted(int(k) for k in tab)
            ax.plot(ws, [tab[str(w)]["std"] for w in ws], "-o", label=n)
        ax.set(xscale="log", xlabel="aggregation window n [frames]", ylabel="σ of aggregated estimates [DN]")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "aggregation.png", dpi=90)
        plt.close(fig)
        names.append("aggregation.png")
    return names


def _jsonable(x: Any) -> Any:
    """NaN/inf → None (strict JSON), recursively."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def machine_description() -> str:
    from camhealth.bench.corruption import machine_description as md

    return md()


def run_evaluation(
    cfg: EvalConfig,
    out: Path,
    methods: list[Method],
    resume: bool = False,
    quick: bool = False,
    command: str = "python -m camhealth.evaluate",
    notes: Sequence[str] = (),
    progress: bool = True,
    plots: bool = True,
    log: Callable[[str], None] = print,
) -> dict:
    """Build the benchmark for ``cfg``, run ``methods`` on it, write ``results.md``/``results.json``/plots to
    ``out`` and return the report dict. With ``resume`` cached data and estimates of the same configuration
    are reused."""
    if not methods:
        raise ValueError("no method to evaluate")
    names = [m.name for m in methods]
    if len(set(names)) != len(names):
        raise ValueError(f"method names must be unique, got {names}")
    if not cfg.charts and any(m.kind.startswith("chart") for m in methods):
        raise ValueError("chart methods (slanted edge, Siemens star) need cfg.charts = True")
    for m in methods:  # (before any data is built)
        _check_patch_fits(m)
    from camhealth.corrupt import _check_out_folder

    out = Path(out)
    _check_out_folder(cfg.source, out, "out")  # a folder source would read the report's plots back as images
    t_start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    cache = out / "cache"
    cases = build_cases(cfg, cache, resume, log)
    runner = _Runner(cfg, cache, resume, log, progress)
    units = _units(cases, methods)
    results: dict[tuple[str, str, str], dict] = {}
    bar = None
    if progress:
        try:
            from tqdm import tqdm

            bar = tqdm(total=len(units), desc="evaluate", unit="unit", file=sys.stderr)
        except ImportError:
            bar = None
    for i, (case, m, variant) in enumerate(units):
        if bar is not None:
            bar.set_postfix_str(f"{case} · {m.name}{variant}", refresh=False)
        elif progress:
            log(f"[{i + 1}/{len(units)}] {case} · {m.name}{variant}")
        results[(case, m.name, variant)] = _run_unit(runner, cases, case, m, variant)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    excluded: dict[str, list[int]] = {}  # estimates left out of the noise tables (not finite), per method and case
    noise_tables = _noise_tables(cases, results, methods, excluded)
    bun_tables = _bun_tables(cases, results, methods, excluded)
    table_notes = [f"{what}: {k} of {n} estimates are not finite (patches the method cannot assess) and are left out of "
                   "its Bias/Std/RMS" for what, (k, n) in excluded.items() if k]
    report: dict[str, Any] = {
        "command": command,
        "machine": machine_description(),
        "date": _dt.datetime.now().isoformat(timespec="seconds"),
        "quick": quick,
        "config": dataclasses.asdict(cfg),
        "config_key": cfg.key(),
        "methods": [{"name": m.name, "kind": m.kind, "learned": m.learned} for m in methods],
        "notes": list(notes) + ([f"{runner.reused} of {len(units)} estimate sets were reused from the cache (--resume)"]
                                if runner.reused else []) + table_notes,
        "blur": {"amae": _blur_table(cases, results, methods)["amae"]},
        "noise": noise_tables,
        "blur_under_noise": bun_tables,
        "aggregation": _agg_table(cases, results, methods, cfg.agg_windows),
        "speed": _speed_rows(runner.timing),
    }
    report["summary"] = _summary(report)
    report["plots"] = _plots(report, cases, results, methods, out / "plots") if plots else []
    report["wall_s"] = time.perf_counter() - t_start
    (out / "results.json").write_text(json.dumps(_jsonable(report), indent=1), encoding="utf-8")
    (out / "results.md").write_text(_markdown(report), encoding="utf-8")
    return report


# ================================================================================================ CLI
CLASSICAL_NAMES = {"pca": "PCA", "bf": "B+F", "wavelet": "wavelet", "slanted_edge": "slanted edge", "siemens_star": "Siemens star"}


def _select(spec: str, checkpoints: Sequence[str], log: Callable[[str], None]) -> list[Method]:
    tokens = [t.strip().lower() for t in spec.split(",") if t.strip()]
    known = set(CLASSICAL_NAMES) | {"all", "classical", "learned"} | set(SHIPPED)
    bad = [t for t in tokens if t not in known]
    if bad or not tokens:
        raise SystemExit(f"--methods: unknown {bad or spec!r}; choose from {sorted(known)} (comma separated)")
    classical = {m.name: m for m in classical_methods()}
    chosen: list[Method] = []
    if "all" in tokens or "classical" in tokens:
        chosen += list(classical.values())
    chosen += [classical[CLASSICAL_NAMES[t]] for t in tokens if t in CLASSICAL_NAMES and classical[CLASSICAL_NAMES[t]] not in chosen]
    learned_names = [n for n in SHIPPED if "all" in tokens or "learned" in tokens or n in tokens]
    if learned_names or checkpoints:
        chosen += learned_methods(learned_names, checkpoints, log)
    return chosen


def build_parser():
    """jsonargparse parser: every option may also come from ``--config FILE``; ``--print_config`` shows them."""
    p = config_parser(prog="python -m camhealth.evaluate", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("--source", default="default", help="image source: 'default' (embedded), a folder or a video (default: default)")
    p.add_argument("--bit-depth", type=BitDepthOption(), default="auto",
                   help="significant bits of the images of a folder --source (or frames:<folder>): 'auto' (default: each "
                   "file's PNG sBIT chunk, else a guess from its largest value) or 1-16, e.g. 12 for a 12-bit camera's "
                   "frames in 16-bit files (DN/4095)")
    p.add_argument("--out", type=Path, default=Path("runs/evaluate"), help="output folder (default runs/evaluate)")
    p.add_argument("--quick", action="store_true", help="reduced benchmark (≤ 2 min on a 2-core CPU)")
    p.add_argument("--resume", action="store_true", help="reuse cached data/estimates of the same configuration in OUT/cache")
    p.add_argument("--methods", default="all", help="comma list: all, classical, learned, pca, bf, wavelet, slanted_edge, "
                   "siemens_star, mtf, drne, noise_source_min, noise_source_full (default all)")  # fmt: skip
    p.add_argument("--checkpoint", action="append", default=[], metavar="PATH", help="a learned estimator file to add (repeatable)")
    p.add_argument("--blur-scenes", choices=("rendered", "source"), default="rendered",
                   help="scenes of the learned MTF's blur patches: 'rendered' (exact pixel aperture, native MTF 1: the "
                   "kernel's MTF is the whole label) or 'source' (labels ignore the source's own blur); default rendered")
    p.add_argument("--seed", type=IntAtLeast(0), default=0, help="seed of the benchmark (default 0)")
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    p.add_argument("--docs", type=Path, default=None, metavar="FILE",
                   help="also write the Markdown report to FILE (e.g. docs/results.md), as the whole page: a FILE that "
                   "does not exist or is an earlier results page (first line '# camhealth evaluation: ...') is "
                   "(re)written whole; any other existing FILE is refused before the evaluation runs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    add_debug_flag(p)
    return p


def _check_docs_file(path: Path) -> None:
    """SystemExit (status 2) naming ``path`` unless ``--docs`` may write it whole: it does not exist, or its first line is
    :data:`RESULTS_TITLE` (an evaluate results page). Any other file is not overwritten."""
    if not path.exists():
        return
    first = None
    if path.is_file():
        try:
            with open(path, encoding="utf-8") as fh:
                first = fh.readline(len(RESULTS_TITLE) + 2).rstrip("\r\n")
        except (OSError, UnicodeDecodeError):
            first = None
    if first != RESULTS_TITLE:
        raise SystemExit(f"--docs {path}: not overwriting it: it is not an evaluate results page (its first line is not "
                         f"{RESULTS_TITLE!r}); --docs writes the whole page, so give a new file or an earlier results page")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.docs is not None:
        _check_docs_file(args.docs)  # (before anything runs)
    from camhealth.corrupt import _check_out_folder

    _check_out_folder(args.source, args.out, "--out")  # (the source is a folder: it would read the report back as images)
    if args.threads is not None:
        if args.threads < 1:
            raise SystemExit(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    notes: list[str] = []
    methods = _select(args.methods, args.checkpoint, lambda s: (print(s), notes.append(s)))
    if not methods:
        raise SystemExit("no method to evaluate (the selected learned estimators are not available)")
    cfg = dataclasses.replace(QUICK if args.quick else DEFAULT, source=str(args.source), seed=args.seed,
                              blur_scenes=args.blur_scenes, bit_depth=args.bit_depth,
                              charts=any(m.kind.startswith("chart") for m in methods))  # fmt: skip
    command = "python -m camhealth.evaluate " + " ".join(sys.argv[1:] if argv is None else list(argv))
    report = run_evaluation(cfg, args.out, methods, resume=args.resume, quick=args.quick, command=command.strip(),
                            notes=notes, progress=not args.no_progress, plots=not args.no_plots)  # fmt: skip
    text = (args.out / "results.md").read_text(encoding="utf-8")
    if args.docs is not None:
        args.docs.parent.mkdir(parents=True, exist_ok=True)
        args.docs.write_text(text, encoding="utf-8")
    print("\n".join(report["summary"]))
    print(f"wrote {args.out / 'results.md'}, {args.out / 'results.json'} and {len(report['plots'])} plot(s) in {report['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main, "python -m camhealth.evaluate"))
