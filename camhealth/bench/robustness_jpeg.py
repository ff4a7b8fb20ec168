"""``python -m camhealth.bench robustness --task jpeg``: the JPEG grid test on the robustness benchmark's frames.

:func:`~camhealth.estimators.jpeg_quantisation.jpeg_grid` decides whether a lossy codec coded the noise that the
noise-source estimator reads (its reason "a lossy codec changed the noise"). Scored on the paired frames of
:func:`camhealth.bench.robustness.make_frames` (``--frames`` per condition, 16 patches of 128 px each; ``--seed``):

- every condition as that benchmark makes it — the ``jpeg`` condition coded per patch at quality 75–95, every other
  condition uncoded (8-bit, a share coded there is a false alarm);
- the matched (``reference``), strong-noise and white-noise frames coded again by this benchmark: each patch
  reflected out to 144 px, coded at quality 50, 75, 90, 95, 98 and 100 as a gray JPEG and as a colour one (4:2:0,
  decoded and converted to gray), and cut back at (5, 3) px, so that the grid does not start at the patch's corner;
- the matched frames' clean scene coded at quality 60 and their noise added afterwards (a photograph that was a JPEG,
  used as a simulator's clean scene): the noise was not coded, a share coded is a false alarm.

Each row gives the share of patches coded, the median zero excess and jitter ratio (module
:mod:`camhealth.estimators.jpeg_quantisation`), and ms per patch of the test (median over the frames, fp32).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import cv2
import numpy as np
import torch

from camhealth.bench import BenchResult, Row

__all__ = ["QUALITIES", "run"]

#: The qualities the matched, strong and white-noise frames are coded at again.
QUALITIES: tuple[int, ...] = (50, 75, 90, 95, 98, 100)
_RECODED = ("reference", "strong", "white_noise")
_PAD, _CUT = ((5, 11), (3, 13)), (5, 3)


def _code(u8: np.ndarray, quality: int, colour: bool) -> np.ndarray:
    if colour:
        bgr = np.stack([u8, np.clip(u8.astype(np.int16) + 12, 0, 255).astype(np.uint8), u8], -1)
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError("OpenCV could not encode a JPEG")
        return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2GRAY)
    ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("OpenCV could not encode a JPEG")
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)


def _recode(noisy: torch.Tensor, quality: int, colour: bool) -> torch.Tensor:
    """Each patch reflected out by (5, 11) × (3, 13) px, coded, cut back at (5, 3)."""
    out = []
    for p in noisy:
        big = np.pad((p[0].numpy() * 255.0).round().astype(np.uint8), _PAD, mode="reflect")
        coded = _code(big, quality, colour)[_CUT[0]:_CUT[0] + p.shape[-2], _CUT[1]:_CUT[1] + p.shape[-1]]
        out.append(torch.from_numpy(coded.astype(np.float32) / 255.0))
    return torch.stack(out).unsqueeze(1)


def _noise_after_coded_scene(clean: torch.Tensor, noisy: torch.Tensor) -> torch.Tensor:
    """The clean scene coded at quality 60 (gray), the frame's own noise added afterwards, 8-bit."""
    scene = torch.stack([torch.from_numpy(_code((c[0].numpy() * 255.0).round().astype(np.uint8), 60, False).astype(np.float32))
                         for c in clean]).unsqueeze(1)
    return ((scene + (noisy - clean) * 255.0).round().clamp(0, 255) / 255.0).float()


def run(args: argparse.Namespace) -> BenchResult:
    from camhealth.bench.robustness import make_frames
    from camhealth.estimators.jpeg_quantisation import jpeg_grid

    t0 = time.perf_counter()
    frames = make_frames(args.frames, args.seed, paired=True)
    made_so: dict[str, list[torch.Tensor]] = {}
    scene_coded: dict[str, list[torch.Tensor]] = {}
    recoded: dict[str, list[torch.Tensor]] = {}
    for fr in sorted(frames, key=lambda f: _RECODED.index(f.condition) if f.condition in _RECODED else -1):
        made_so.setdefault(f"{fr.condition}, as made", []).append(fr.noisy)
        if fr.condition in _RECODED:
            for q in QUALITIES:
                for colour in (False, True):
                    recoded.setdefault(f"{fr.condition}, coded again at quality {q}, {'colour' if colour else 'gray'}",
                                       []).append(_recode(fr.noisy, q, colour))
        if fr.condition == "reference":
            scene_coded.setdefault("reference, its scene a JPEG (quality 60) and the noise added afterwards", []).append(
                _noise_after_coded_scene(fr.clean, fr.noisy))
    sets = {**made_so, **scene_coded, **recoded}
    made = time.perf_counter() - t0
    lines = ["", "| frames | patches | coded | zero excess, median | jitter ratio, median | ms/patch |", "|---|---:|---:|---:|---:|---:|"]
    results: dict[str, Any] = {}
    times: list[float] = []
    for name, batches in sets.items():
        coded, excess, ratio, ms = [], [], [], []
        for x in batches:
            jpeg_grid(x[:1])  # warm
            t = time.perf_counter()
            g = jpeg_grid(x)
            ms.append((time.perf_counter() - t) * 1e3 / x.shape[0])
            coded.append(g.coded)
            excess.append(g.zero_excess)
            ratio.append(g.jitter_ratio)
        c, e, r = torch.cat(coded), torch.cat(excess), torch.cat(ratio)
        share, med_ms = float(c.double().mean()), float(np.median(ms))
        times += ms
        results[name] = {"patches": int(c.numel()), "coded": share, "zero_excess": float(e.median()),
                         "jitter_ratio": float(r.nanmedian()), "ms": med_ms}
        lines.append(f"| {name} | {c.numel()} | {100 * share:.1f} % | {float(e.median()):.3f} | {float(r.nanmedian()):.1f} | {med_ms:.2f} |")
    header = [f"{len(frames)} paired frames × 16 patches of 128 px ({args.frames} per condition), seed {args.seed}; "
              f"data made in {made:.0f} s", f"command: {args.command_line}"]
    summary = ["", "JPEG grid test (`jpeg_grid`): share of patches coded per set of frames, its statistics at the best grid "
                   "offset, and its time:", *lines]
    args_json = getattr(args, "json", None)
    if args_json is not None:
        import json

        args_json.write_text(json.dumps(results, indent=1), encoding="utf-8")
    rows = [Row("jpeg_grid", [float(np.median(times))], note="ms per 128-px patch, fp32")]
    return BenchResult(title="the JPEG grid test on the robustness frames", rows=rows, baseline="jpeg_grid", header=header,
                       summary=summary)
