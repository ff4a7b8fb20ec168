"""``python -m camhealth.corrupt``: corrupt images with the camera physics and write them with labels.

Takes patches from an image source (the embedded default data, a folder, or a video), applies
:class:`~camhealth.augment.CameraCorruption` and writes, per patch, the clean and corrupted 8-bit PNG
and one JSON line of labels (16 MTF values, realised and expected σ per noise source, metadata). The labels describe
the PNG that is written: ``sigma_total_dn`` is the realised σ [DN] of (corrupted PNG − noise-free blurred image), the
unbiased standard deviation over the patch's pixels measured on the 8-bit values written (with their rounding, as
the training data's total with ``quantize`` is); ``sigma_dn`` gives each source's share of the clipped noise before
that rounding (the ±½ DN rounding error is no source's). With
``--overview`` it also draws one figure that shows each corruption of the first patch on its own with
its MTF curves and noise levels (the README's tour picture).

Example::

    python -m camhealth.corrupt default --n 8 --out runs/corrupt --overview
"""

from __future__ import annotations

import argparse
import json
import numbers
import os
import re
import sys
from pathlib import Path

import numpy as np
import torch

from camhealth._cli import BadValue, BitDepthOption, IntAtLeast, add_debug_flag, config_parser, run_cli
from camhealth.augment import CameraCorruption, RandomDefocusBlur, RandomMotionBlur, RandomSensorNoise
from camhealth.augment.blur import MAX_DIAMETER_PX, MAX_LENGTH_PX
from camhealth.physics.mtf import NORMALIZED_FREQUENCIES

__all__ = ["main", "random_patches"]


def random_patches(source, n: int, size: int, generator: torch.Generator) -> tuple[torch.Tensor, list[str]]:
    """``n`` random ``size``×``size`` crops (B×1×size×size) from random images of ``source``.

    Images smaller than ``size`` on a side are skipped: each crop comes from an image drawn uniformly from those
    at least ``size``×``size`` px (a drawn image that is too small is set aside and another one drawn).
    ValueError naming the patch size (``--size``) and the largest patch the images hold when none is large enough.
    ``n`` must be an integer >= 1 and ``size`` one >= :data:`MIN_SIZE` (the noise labels are standard deviations over a
    patch's pixels): a ``ValueError`` naming the value otherwise."""
    for name, value, low in (("n", n, 1), ("size", size, MIN_SIZE)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
            raise ValueError(f"{name} = {value!r} must be an integer >= {low}")
    n, size = int(n), int(size)
    if len(source) == 0:
        raise ValueError("the image source is empty")
    candidates = list(range(len(source)))  # images not yet known to be too small
    largest = 0  # the largest short side among the images set aside
    patches, ids = [], []
    for _ in range(n):
        while True:
            if not candidates:
                raise ValueError(f"every image of the source is smaller than the patch size {size}×{size} px (--size "
                                 f"{size}); the largest patch they hold is {largest}×{largest} px")
            k = int(torch.randint(len(candidates), (1,), generator=generator))
            img, img_id = source[candidates[k]]
            h, w = img.shape[-2:]
            if h >= size and w >= size:
                break
            largest = max(largest, min(h, w))
            del candidates[k]
        y = int(torch.randint(h - size + 1, (1,), generator=generator))
        x = int(torch.randint(w - size + 1, (1,), generator=generator))
        patches.append(img[..., y : y + size, x : x + size].reshape(1, size, size))
        ids.append(f"{img_id}@{y},{x}")
    return torch.stack(patches), ids


#: Smallest --size [px]: the noise labels are standard deviations over a patch's pixels (unbiased: at least two).
MIN_SIZE = 2


def _dn8(img: torch.Tensor) -> torch.Tensor:
    """The 8-bit values [DN] (float32, whole numbers 0…255) that :func:`_save_png` writes for ``img`` in [0, 1]."""
    return (img.detach().float().clamp(0, 1) * 255.0 + 0.5).floor()


def _save_png(path: Path, img: torch.Tensor) -> None:
    """``img`` (…×H×W in [0, 1]) as an 8-bit gray PNG of H×W px (also 1×1: no dimension is squeezed away)."""
    from skimage.io import imsave

    arr = _dn8(img).reshape(img.shape[-2:]).cpu().numpy().astype(np.uint8)
    imsave(path, arr, check_contrast=False)


def _written_sigma_total_dn(corrupted: torch.Tensor, noise_free: torch.Tensor) -> torch.Tensor:
    """Realised σ [DN] of the noise the written PNGs hold, (B,) float64: the unbiased standard deviation over each
    patch's pixels of its 8-bit values (:func:`_dn8`) minus the noise-free blurred image in DN (``noise_free`` in
    [0, 1]) — the definition of ``datamodules.noise.realised_sigma_dn``, on the rounded image."""
    d = _dn8(corrupted).double() - noise_free.detach().double() * 255.0
    return d.flatten(1).std(1)


def _overview(path: Path, clean: torch.Tensor, args: argparse.Namespace) -> None:
    """The most textured patch through each corruption alone and through the whole camera, with labels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    best = int(clean.flatten(1).std(1).argmax())
    x = clean[best : best + 1]
    torch.manual_seed(args.seed)
    steps = [
        ("defocus d=9 px", RandomDefocusBlur(diameter=9.0)),
        ("linear motion L=15 px, 30°", RandomMotionBlur(length=15.0, angle=30.0)),
        ("camera shake L=15 px", RandomMotionBlur(length=15.0, angle=30.0, intensity=1.0)),
        ("sensor noise (EV76C661, 24 dB, 60 °C)", RandomSensorNoise(metadata="EV76C661", ranges={"gain_db": (24.0, 24.0), "temperature_c": (60.0, 60.0), "exposure_s": (0.1, 0.1)})),
        ("full camera (Fig. 3.7)", _camera(args)),
    ]
    fig, axes = plt.subplots(2, len(steps) + 1, figsize=(3.0 * (len(steps) + 1), 6.4))
    axes[0, 0].imshow(x[0, 0].numpy(), cmap="gray", vmin=0, vmax=1)
    axes[0, 0].set_title("clean patch")
    axes[1, 0].axis("off")
    f = np.asarray(NORMALIZED_FREQUENCIES)
    for j, (title, aug) in enumerate(steps, start=1):
        y = aug(x)
        lab = aug.labels()
        axes[0, j].imshow(y[0, 0].numpy(), cmap="gray", vmin=0, vmax=1)
        axes[0, j].set_title(title, fontsize=9)
        ax = axes[1, j]
        if "mtf" in lab:
            m = lab["mtf"][0].numpy()
            ax.plot(f, m[:8], "o-", label="H")
            ax.plot(f, m[8:], "s--", label="V")
            ax.set_ylim(0, 1.05)
            ax.set_xlabel("frequency / Nyquist")
            ax.set_ylabel("MTF")
            ax.legend(fontsize=8)
        if "sigma_dn" in lab:
            s = lab["sigma_dn"][0].numpy()
            e = lab["sigma_expected_dn"][0].numpy()
            if "mtf" in lab:  # full camera: the MTF plot carries the noise levels as text
                ax.text(0.05, 0.05, "σ PN/DCSN/RN = " + "/".join(f"{v:.1f}" for v in s) + " DN",
                        transform=ax.transAxes, fontsize=8)
            else:
                pos = np.arange(3)
                ax.bar(pos - 0.2, s, width=0.4, color="tab:red", alpha=0.7, label="realised σ")
                ax.bar(pos + 0.2, e, width=0.4, color="tab:gray", alpha=0.7, label="expected σ")
                ax.set_xticks(pos, ["PN", "DCSN", "RN"])
                ax.set_ylabel("σ [DN]")
                ax.legend(fontsize=8)
    for ax in axes[0]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _camera(args: argparse.Namespace) -> CameraCorruption:
    noise = RandomSensorNoise(metadata=args.sensor, quantize=args.quantize) if args.sensor else RandomSensorNoise(quantize=args.quantize)
    return CameraCorruption(
        RandomDefocusBlur(diameter=tuple(args.defocus)) if args.defocus[1] > 0 else None,
        RandomMotionBlur(length=tuple(args.motion), intensity=tuple(args.shake)) if args.motion[1] > 0 else None,
        noise if not args.no_noise else None,
    )


#: The MIN MAX range options: name → (largest MAX or None, unit); MIN ≥ 0 and MIN ≤ MAX for each. The largest defocus
#: diameter and motion length are those the blur modules' largest kernel holds.
_RANGES = {"defocus": (MAX_DIAMETER_PX, "px"), "motion": (MAX_LENGTH_PX, "px"), "shake": (1.0, "")}


def _range_text(name: str, values) -> str:
    return f"--{name} {' '.join(f'{v:g}' if isinstance(v, (int, float)) else repr(v) for v in values)}"


def _check_ranges(args: argparse.Namespace) -> None:
    """ValueError naming the option when a MIN MAX range is not two numbers with 0 ≤ MIN ≤ MAX ≤ its largest value
    (253 px defocus, 252 px motion, 1 shake), or when --shake asks for camera shake with motion blur off; a negative
    range would otherwise switch the corruption off, and a shake without motion be dropped, without a word. Also
    ValueError naming the three options when --no-noise, --defocus 0 0 and --motion 0 0 leave nothing to corrupt."""
    for name, (top, unit) in _RANGES.items():
        values = list(getattr(args, name))
        text = _range_text(name, values)
        if len(values) != 2 or not all(isinstance(v, (int, float)) and np.isfinite(v) for v in values):
            raise ValueError(f"{text}: needs two finite numbers MIN MAX")
        lo, hi = values
        if lo < 0 or hi < 0:
            raise ValueError(f"{text}: MIN and MAX must be >= 0{' ' + unit if unit else ''} (0 0 disables it)")
        if lo > hi:
            raise ValueError(f"{text}: MIN must be <= MAX")
        if top is not None and hi > top:
            raise ValueError(f"{text}: MAX must be <= {top:g}{' ' + unit if unit else ''}")
    if args.shake[1] > 0 and args.motion[1] == 0:
        raise ValueError(f"{_range_text('shake', args.shake)}: camera shake needs motion blur; "
                         f"{_range_text('motion', args.motion)} switches it off")
    if args.no_noise and args.defocus[1] == 0 and args.motion[1] == 0:
        raise ValueError(f"--no-noise with {_range_text('defocus', args.defocus)} and {_range_text('motion', args.motion)} "
                         "corrupts nothing: keep the noise or give a defocus or motion range")


#: Working memory [bytes] per pixel of the patches (--n · --size²) that a run takes: all patches are corrupted in one
#: batch (one draw of the camera's random numbers), and the camera model keeps several float32 images of each (blurred,
#: electrons, each noise source, clipped); measured ≈ 57 B/px.
BYTES_PER_PIXEL = 64


def _memory_limit() -> int | None:
    """Bytes this process can use at most: the smaller of the machine's physical memory and the address-space limit
    (``ulimit -v``); None where neither is known."""
    limits = []
    try:
        limits.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        pass
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft not in (resource.RLIM_INFINITY, -1) and soft > 0:
            limits.append(int(soft))
    except (ImportError, AttributeError, ValueError, OSError):
        pass
    return min(limits) if limits else None


def _check_memory(args: argparse.Namespace) -> None:
    """ValueError naming --n and --size when their patches (one batch) need more memory than this process can have
    (:func:`_memory_limit`), before the source is read: the run would otherwise stop in an allocation deep inside the
    camera model (or be killed by the system) with a message that names neither."""
    need = args.n * args.size * args.size * BYTES_PER_PIXEL
    limit = _memory_limit()
    if limit is not None and need > limit:
        raise ValueError(f"--n {args.n} --size {args.size}: the {args.n} patches of {args.size}×{args.size} px are "
                         f"corrupted in one batch, which needs about {need / 2**30:.1f} GiB of memory ({BYTES_PER_PIXEL} "
                         f"bytes per pixel); this process can use {limit / 2**30:.1f} GiB. Give a smaller --n or --size "
                         "(several runs with different --seed give more patches)")


class _SeedOption:
    """Option type of ``--seed``: an integer torch's generators take, -2⁶³ … 2⁶⁴ − 1, else :class:`BadValue` naming the
    value and the range. Its ``repr`` is what ``--help`` shows."""

    low, high = -(2**63), 2**64 - 1

    def __call__(self, value) -> int:
        try:
            if isinstance(value, (bool, float)):
                raise ValueError
            seed = int(value)
        except (TypeError, ValueError):
            raise BadValue(f"must be an integer in [{self.low}, {self.high}], got {value!r}") from None
        if not self.low <= seed <= self.high:
            raise BadValue(f"must be an integer in [{self.low}, {self.high}] (the range of torch's random seeds), got {seed}")
        return seed

    def __repr__(self) -> str:
        return f"int in [{self.low}, {self.high}]"


#: Names of the files a run writes into --out (besides overview.png): the patch pairs and the labels.
_PAIR = re.compile(r"^\d{4,}_(clean|corrupted)\.png$")
_LABELS = "labels.jsonl"
_OVERVIEW = "overview.png"


def _earlier_outputs(out: Path) -> list[Path]:
    """The files of an earlier run in ``out`` (NNNN_clean.png, NNNN_corrupted.png, labels.jsonl, overview.png)."""
    if not out.is_dir():
        return []
    return sorted(f for f in out.iterdir() if (_PAIR.match(f.name) or f.name in (_LABELS, _OVERVIEW)) and not f.is_dir())


def _check_out_folder(source, out: Path, option: str = "--out") -> None:
    """ValueError naming both paths when the output folder ``out`` (the command's ``option``) is the folder of the image
    source ``source`` (a folder or ``frames:<folder>``), lies inside it or contains it: the run would write over the
    input images, or into a folder that a later run reads back as input (folder sources take the images of every
    sub-folder). Shared by ``python -m camhealth.corrupt`` and ``python -m camhealth.evaluate``."""
    spec = str(source)
    folder = Path(spec[len("frames:"):] if spec.startswith("frames:") else spec)
    if spec.strip().lower() not in ("default", "street", "skimage", "deadleaves") and folder.is_dir():
        src, res = folder.resolve(), Path(out).resolve()
        if res == src:
            raise ValueError(f"{option} {out} is the source folder {folder}; give another output folder")
        if res.is_relative_to(src):
            raise ValueError(f"{option} {out} is inside the source folder {folder}; give a folder outside it")
        if src.is_relative_to(res):
            raise ValueError(f"{option} {out} contains the source folder {folder}; give a folder outside it")


def _check_out(args: argparse.Namespace) -> None:
    """ValueError naming both paths when --out is the source folder, lies inside it or contains it
    (:func:`_check_out_folder`); ValueError naming --out and --overwrite when --out holds an earlier run's files and
    --overwrite is not given."""
    _check_out_folder(args.source, args.out)
    earlier = _earlier_outputs(args.out)
    if earlier and not args.overwrite:
        names = ", ".join(f.name for f in earlier[:3]) + (f" and {len(earlier) - 3} more" if len(earlier) > 3 else "")
        raise ValueError(f"--out {args.out} already holds the output of a run ({names}); pass --overwrite to replace it "
                         "or give another folder")


def build_parser():
    """jsonargparse parser: every option may also come from ``--config FILE``; ``--print_config`` shows them."""
    p = config_parser(
        prog="python -m camhealth.corrupt",
        description="Corrupt image patches with the camera physics (defocus, photon noise, motion blur, dark-current "
        "noise, readout noise, gain, clipping) and write PNGs plus JSON labels.",
    )
    p.add_argument("source", nargs="?", default=argparse.SUPPRESS,  # SUPPRESS: a --config file may give it
                   help="'default' (the default: embedded photos + street clip), 'street', 'skimage', 'deadleaves', a folder or a video file")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder (created); not the source folder, nor inside it, nor containing it")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier run's output in --out: all its NNNN_clean.png, NNNN_corrupted.png, "
                   "labels.jsonl and overview.png are deleted before this run writes its own, so none is left over "
                   "(patches beyond --n, overview.png without --overview); other files are kept. Without it an --out "
                   "that holds any of these files is refused")
    p.add_argument("--n", type=IntAtLeast(1), default=8, help="number of patches (default 8)")
    p.add_argument("--size", type=IntAtLeast(MIN_SIZE), default=192,
                   help=f"patch size in px (default 192; at least {MIN_SIZE}: the noise labels are standard deviations "
                   "over the patch's pixels)")
    p.add_argument("--defocus", type=float, nargs=2, default=[1.0, 21.0], metavar=("MIN", "MAX"),
                   help="defocus disk diameter range in px (default 1 21; 0 0 disables)")
    p.add_argument("--motion", type=float, nargs=2, default=[1.0, 21.0], metavar=("MIN", "MAX"),
                   help="motion length range in px (default 1 21; 0 0 disables)")
    p.add_argument("--shake", type=float, nargs=2, default=[0.0, 0.0], metavar=("MIN", "MAX"),
                   help="camera-shake intensity range in [0, 1] (default 0 0: linear motion)")
    p.add_argument("--sensor", default=None, help="sensor preset (ICX285, EV76C661); default: random cameras")
    p.add_argument("--no-noise", action="store_true", help="blur only")
    p.add_argument("--quantize", action="store_true",
                   help="round to whole DN inside the camera model (the PNGs are 8-bit either way, and sigma_total_dn "
                   "is measured on the 8-bit values written)")
    p.add_argument("--bit-depth", type=BitDepthOption(), default="auto",
                   help="significant bits of the images of a folder source (or frames:<folder>): 'auto' (default: "
                   "each file's PNG sBIT chunk, else a guess from its largest value) or 1-16, e.g. 12 for a 12-bit "
                   "camera's frames in 16-bit files (DN/4095)")
    p.add_argument("--seed", type=_SeedOption(), default=0, help="random seed (default 0)")
    p.add_argument("--overview", action="store_true", help="also write overview.png (each corruption of the most textured patch)")
    add_debug_flag(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if "source" not in args:
        args.source = "default"
    from camhealth.data import build_source

    _check_ranges(args)  # (before the source is read)
    _check_memory(args)
    _check_out(args)
    source = build_source(args.source, bit_depth=args.bit_depth)
    g = torch.Generator().manual_seed(args.seed)
    clean, ids = random_patches(source, args.n, args.size, g)
    torch.manual_seed(args.seed)
    cam = _camera(args)
    out = cam(clean)
    lab = cam.labels()
    args.out.mkdir(parents=True, exist_ok=True)
    for f in _earlier_outputs(args.out):  # (only with --overwrite: _check_out refused the folder otherwise)
        f.unlink()  # (all of them: a file left over from the earlier run is never listed or unlisted by this one)
    meta = lab.get("metadata")
    if meta is not None:  # the total σ of the PNG that is written, with its 8-bit rounding
        lab["sigma_total_dn"] = _written_sigma_total_dn(out, cam._formation.blurred)
    with open(args.out / "labels.jsonl", "w") as fh:
        for i, pid in enumerate(ids):
            stem = f"{i:04d}"
            _save_png(args.out / f"{stem}_clean.png", clean[i])
            _save_png(args.out / f"{stem}_corrupted.png", out[i])
            rec = {"index": i, "patch": pid, "clean": f"{stem}_clean.png", "corrupted": f"{stem}_corrupted.png"}
            if "mtf" in lab:
                rec["mtf_h"] = [round(v, 5) for v in lab["mtf"][i, :8].tolist()]
                rec["mtf_v"] = [round(v, 5) for v in lab["mtf"][i, 8:].tolist()]
            if meta is not None:
                rec["sigma_dn"] = dict(zip(("photon", "dark", "readout"), [round(v, 4) for v in lab["sigma_dn"][i].tolist()]))
                rec["sigma_expected_dn"] = dict(zip(("photon", "dark", "readout"), [round(v, 4) for v in lab["sigma_expected_dn"][i].tolist()]))
                rec["sigma_total_dn"] = round(float(lab["sigma_total_dn"][i]), 4)
                rec["metadata"] = {k: v[0] for k, v in meta[i].to_dict().items()}
            fh.write(json.dumps(rec) + "\n")
    if args.overview:
        _overview(args.out / "overview.png", clean, args)
    print(f"wrote {args.n} clean/corrupted patch pairs and labels.jsonl to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main, "python -m camhealth.corrupt"))
