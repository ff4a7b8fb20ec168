"""``python -m camhealth.iopc --config configs/iopc.yaml``: the standalone IOPC sweep.

The command line is a jsonargparse parser (the library LightningCLI is built on): every option below can
come from a YAML ``--config`` and be overridden on the command line in dotted form, e.g.
``--estimators.noise physics --sweep.grid.lengths_px [0,7,15] --trainer.accelerator gpu``;
``--print_config`` prints the full resolved configuration. Sections:

* ``source`` / ``frames`` — clean images (``camhealth.data.build_source`` spec: ``street`` is the
  embedded clip) and which of them (``start``, ``stop``, ``stride``); all must have the same size.
* ``ground_truth`` — a COCO annotation JSON (``annotations``, matched by file name) or, when ``null``,
  pseudo ground truth from the detector on the clean frames with score >= ``pseudo_score``.
* ``detector`` — ``kind: hog`` (OpenCV people detector, settings under ``hog``) or ``kind: torch``
  (``torch.class_path`` + ``init_args``, optional ``checkpoint`` state dict, see
  :class:`~camhealth.detection.TorchDetector`).
* ``estimators`` — ``noise`` and ``mtf``: names for ``camhealth.inference.load_estimator`` (defaults
  ``noise_source_min`` and ``mtf``), or the stand-ins ``physics`` / ``immerkaer``.
* ``sweep`` — :class:`~camhealth.iopc.sweep.SweepConfig` (grid, sensor, valid ranges, bins, seed).
* ``trainer`` — keyword arguments of the ``lightning.Trainer`` that runs the cells (``accelerator``,
  ``devices``, ``strategy``, ``num_nodes``, …).
* ``out_dir`` (``iopc.json``, ``iopc.npz``, ``iopc.png``, TensorBoard events under ``tensorboard/``) and
  ``cache_dir`` (per-cell results; rerunning the same command resumes).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import torch

from camhealth._cli import add_debug_flag, config_action
from camhealth.iopc.curves import IOPC
from camhealth.iopc.estimation import resolve_estimator
from camhealth.iopc.sweep import IOPCSweep, SweepConfig, log_iopc

__all__ = [
    "FrameSelection",
    "GroundTruthSettings",
    "HOGSettings",
    "TorchDetectorSettings",
    "DetectorSettings",
    "EstimatorSettings",
    "build_parser",
    "build_detector",
    "CategoryFilter",
    "load_frames",
    "main",
]


@dataclass
class FrameSelection:
    """Which images of the source: ``source[start:stop:stride]`` (``stride``: an integer >= 1)."""

    start: int = 0
    stop: Optional[int] = None
    stride: int = 1


@dataclass
class GroundTruthSettings:
    """``annotations``: COCO JSON path (``null``: pseudo ground truth); ``category_ids``: keep these
    categories only (``null``: all), in the ground truth — COCO annotations or pseudo ground truth alike — and in
    the detections the AP is computed from; ``pseudo_score``: score a clean detection needs to become pseudo
    ground truth."""

    annotations: Optional[str] = None
    category_ids: Optional[list[int]] = None
    pseudo_score: float = 0.6


@dataclass
class HOGSettings:
    """:class:`~camhealth.detection.HOGPeopleDetector` arguments."""

    win_stride: list[int] = field(default_factory=lambda: [8, 8])
    padding: list[int] = field(default_factory=lambda: [8, 8])
    scale: float = 1.05
    hit_threshold: float = 0.0
    group_threshold: int = 2
    upscale: float = 1.0


@dataclass
class TorchDetectorSettings:
    """A user's ``nn.Module`` detector: ``class_path`` (``package.module.Class``), ``init_args``, an
    optional ``checkpoint`` (state dict file, loaded with ``weights_only=True``), and the
    :class:`~camhealth.detection.TorchDetector` options."""

    class_path: Optional[str] = None
    init_args: dict = field(default_factory=dict)
    checkpoint: Optional[str] = None
    channels: int = 1
    input_scale: float = 1.0
    box_format: str = "xyxy"
    normalized_boxes: bool = False


@dataclass
class DetectorSettings:
    """``kind``: ``hog`` or ``torch``."""

    kind: str = "hog"
    hog: HOGSettings = field(default_factory=HOGSettings)
    torch: TorchDetectorSettings = field(default_factory=TorchDetectorSettings)


@dataclass
class EstimatorSettings:
    """Estimator specs (see :func:`camhealth.iopc.estimation.resolve_estimator`)."""

    noise: str = "noise_source_min"
    mtf: str = "mtf"


def _module_class(class_path: Optional[str]) -> type:
    """The ``torch.nn.Module`` subclass ``class_path`` (``package.module.Class``) names; anything else (a function, an
    object, a class that is no module) is refused before it is called."""
    if not class_path or "." not in class_path:
        raise ValueError("detector.torch.class_path must name the module class, e.g. 'mypkg.models.Detector'")
    mod_name, cls_name = class_path.rsplit(".", 1)
    cls = getattr(importlib.import_module(mod_name), cls_name, None)
    if cls is None:
        raise ValueError(f"detector.torch.class_path {class_path!r}: {mod_name} has no {cls_name!r}")
    if not (isinstance(cls, type) and issubclass(cls, torch.nn.Module)):
        raise ValueError(f"detector.torch.class_path {class_path!r} is a {type(cls).__name__}, not a torch.nn.Module "
                         "class; name the detector's nn.Module subclass")
    return cls


def _load_state_dict(path: str) -> Any:
    """The state dict in ``path`` (a bare one or a checkpoint's ``state_dict``), read as plain tensors only."""
    from camhealth.export import _load_refusal

    if not Path(path).is_file():
        raise FileNotFoundError(f"detector.torch.checkpoint {path}: no such file")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickled code, not a torch file, truncated file, ...
        raise ValueError(f"detector.torch.checkpoint {path}: not a state dict of plain tensors ({_load_refusal(exc)})") from None
    return state.get("state_dict", state) if isinstance(state, dict) else state


def build_detector(settings: DetectorSettings) -> Any:
    """The frozen detector described by ``settings``."""
    from camhealth.detection import HOGPeopleDetector, TorchDetector

    if settings.kind == "hog":
        h = settings.hog
        return HOGPeopleDetector(tuple(h.win_stride), tuple(h.padding), h.scale, h.hit_threshold, h.group_threshold,
                                 h.upscale)
    if settings.kind == "torch":
        t = settings.torch
        cls = _module_class(t.class_path)
        module = cls(**t.init_args)
        if t.checkpoint:
            module.load_state_dict(_load_state_dict(t.checkpoint))
        return TorchDetector(module, t.channels, t.input_scale, t.box_format, t.normalized_boxes,
                             name=cls.__name__)
    raise ValueError(f"detector.kind = {settings.kind!r} must be 'hog' or 'torch'")


class CategoryFilter:
    """A detector whose detections keep only the labels in ``category_ids`` (``ground_truth.category_ids``): the
    pseudo ground truth and the AP then cover only those categories. ``config()`` (the sweep's fingerprint and
    provenance) is the detector's own, with the categories added."""

    def __init__(self, detector: Any, category_ids: Sequence[int]) -> None:
        self.detector = detector
        self.category_ids = sorted({int(c) for c in category_ids})
        self.name = getattr(detector, "name", type(detector).__name__)

    def to(self, device: Any) -> "CategoryFilter":
        to = getattr(self.detector, "to", None)
        if callable(to):
            to(device)
        return self

    def config(self) -> dict[str, Any]:
        cfg = getattr(self.detector, "config", None)
        base = cfg() if callable(cfg) else {"name": self.name}
        return {**base, "category_ids": self.category_ids}

    def __call__(self, images: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        from camhealth.detection import Detection
        from camhealth.detection.protocol import validate_detections

        keep_ids = torch.tensor(self.category_ids, dtype=torch.int64)
        dets = validate_detections(self.detector(images), images.shape[0], tuple(images.shape[-2:]),
                                   name=f"{self.name} output")
        out = []
        for d in dets:
            keep = torch.isin(d["labels"].to(torch.int64), keep_ids.to(d["labels"].device))
            out.append(Detection(boxes=d["boxes"][keep], scores=d["scores"][keep], labels=d["labels"][keep]))
        return out


def _check_category_ids(ids: Any) -> None:
    """``ground_truth.category_ids``: ``None`` or a non-empty list of integers >= 0."""
    if ids is None:
        return
    ok = isinstance(ids, (list, tuple)) and len(ids) > 0 and all(
        isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in ids)
    if not ok:
        raise ValueError(f"ground_truth.category_ids = {ids!r} is out of the allowed range: null (all categories) or "
                         "a non-empty list of category ids (integers >= 0)")


def load_frames(source: str, selection: FrameSelection) -> tuple[torch.Tensor, list[str], list[str]]:
    """Frames N×1×H×W of ``build_source(source)[start:stop:stride]``, their ids and, where the source
    has files, their paths (for annotation matching; else the ids)."""
    from camhealth.data import build_source

    stride = selection.stride
    if not (isinstance(stride, int) and not isinstance(stride, bool) and stride >= 1):
        raise ValueError(f"frames.stride = {stride!r} is out of the allowed range: an integer >= 1")
    src = build_source(source)
    idx = list(range(len(src)))[selection.start : selection.stop : stride]
    if not idx:
        raise ValueError(f"frames {selection} select no image of {source!r} ({len(src)} images)")
    images, ids = [], []
    for i in idx:
        img, img_id = src[i]
        images.append(img)
        ids.append(img_id)
    sizes = {tuple(im.shape) for im in images}
    if len(sizes) != 1:
        raise ValueError(f"all frames of a sweep must have the same size, got {sorted(sizes)}")
    paths = [str(src.paths[i]) for i in idx] if hasattr(src, "paths") else list(ids)
    return torch.stack(images), ids, paths


#: jsonargparse parser mode of ``python -m camhealth.iopc``: YAML, read by :func:`_load_yaml`.
_PARSER_MODE = "camhealth_iopc"


def _load_yaml(text: str) -> Any:
    """jsonargparse's YAML loader (safe: no tags that run code), with a ``detector.torch`` section that holds only
    ``class_path`` (and ``init_args``) wrapped as the settings' own class spec: jsonargparse would read such a
    mapping as a subclass of :class:`TorchDetectorSettings` and refuse it, yet it is the form configs/iopc.yaml
    documents (the user's ``nn.Module`` class and its arguments)."""
    from jsonargparse import get_loader

    value = get_loader("yaml")(text)
    detector = value.get("detector") if isinstance(value, dict) else None
    torch_section = detector.get("torch") if isinstance(detector, dict) else None
    if isinstance(torch_section, dict) and "class_path" in torch_section and set(torch_section) <= {"class_path", "init_args"}:
        detector["torch"] = {"class_path": f"{__name__}.{TorchDetectorSettings.__name__}", "init_args": torch_section}
    return value


def build_parser():
    import yaml
    from jsonargparse import ArgumentParser, set_loader

    set_loader(_PARSER_MODE, _load_yaml, exceptions=(yaml.YAMLError,))
    p = ArgumentParser(prog="python -m camhealth.iopc", description=__doc__.split("\n\n")[0], parser_mode=_PARSER_MODE)
    p.add_argument("--config", action=config_action(), help="YAML config (configs/iopc.yaml)")
    p.add_argument("--source", type=str, default="street", help="image source spec (camhealth.data.build_source)")
    p.add_argument("--frames", type=FrameSelection, default=FrameSelection())
    p.add_argument("--ground_truth", type=GroundTruthSettings, default=GroundTruthSettings())
    p.add_argument("--detector", type=DetectorSettings, default=DetectorSettings())
    p.add_argument("--estimators", type=EstimatorSettings, default=EstimatorSettings())
    p.add_argument("--sweep", type=SweepConfig, default=SweepConfig())
    p.add_argument("--trainer", type=dict, default={"accelerator": "auto", "devices": 1})
    p.add_argument("--out_dir", type=str, default="runs/iopc")
    p.add_argument("--cache_dir", type=Optional[str], default="runs/iopc/cache")
    p.add_argument("--tensorboard", type=bool, default=True, help="log heat maps to out_dir/tensorboard")
    add_debug_flag(p)
    return p


def main(argv: Sequence[str] | None = None) -> IOPC:
    """Run the sweep described by the command line / config; returns the IOPC (also written to disk)."""
    from camhealth.detection import ground_truth_for, load_coco_annotations, pseudo_ground_truth

    parser = build_parser()
    cfg = parser.parse_args(list(argv) if argv is not None else None)
    instantiate = getattr(parser, "instantiate", None) or parser.instantiate_classes  # jsonargparse ≥ 4.49 / older
    init = instantiate(cfg)
    frames_sel: FrameSelection = init.frames
    gt_cfg: GroundTruthSettings = init.ground_truth
    sweep_cfg: SweepConfig = init.sweep.validate()  # before frames, detector and ground truth are loaded
    _check_category_ids(gt_cfg.category_ids)
    frames, ids, paths = load_frames(init.source, frames_sel)
    detector = build_detector(init.detector)
    if gt_cfg.category_ids is not None:  # the same categories in the ground truth and in the detections
        detector = CategoryFilter(detector, gt_cfg.category_ids)
    if gt_cfg.annotations:
        ann = load_coco_annotations(gt_cfg.annotations, gt_cfg.category_ids)
        gt = ground_truth_for(paths, ann)
        gt_note = {"ground_truth": f"COCO annotations {gt_cfg.annotations}"}
    else:
        gt = pseudo_ground_truth(detector, frames, gt_cfg.pseudo_score)
        gt_note = {"ground_truth": f"pseudo: detector on the clean frames, score >= {gt_cfg.pseudo_score:g}"}
    if gt_cfg.category_ids is not None:
        gt_note["ground_truth"] += f", categories {sorted(set(gt_cfg.category_ids))}"
    noise = resolve_estimator(init.estimators.noise, "noise")
    mtf = resolve_estimator(init.estimators.mtf, "mtf")
    sweep = IOPCSweep(frames, gt, detector, noise, mtf, sweep_cfg, cache_dir=init.cache_dir, frame_ids=ids,
                      provenance={**gt_note, "source": init.source, "frame_selection": vars(frames_sel),
                                  "estimator_specs": {"noise": init.estimators.noise, "mtf": init.estimators.mtf}})
    trainer_kw = {"logger": False, "enable_checkpointing": False, "enable_model_summary": False, **dict(init.trainer)}
    import lightning as L

    iopc = sweep.run(L.Trainer(**trainer_kw))
    out = Path(init.out_dir)
    if L.fabric.utilities.rank_zero.rank_zero_only.rank == 0:
        iopc.save_all(out)
        if init.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            with SummaryWriter(str(out / "tensorboard")) as w:
                log_iopc(w, iopc)
        _print_summary(iopc, out)
    return iopc


def _print_summary(iopc: IOPC, out: Path) -> None:
    n, marked = len(iopc.records), iopc.marked_records
    print(f"IOPC ({iopc.name}): {n} cells, {len(marked)} marked; written to {out}/iopc.json|.npz|.png")
    header = "σ̃\\MTF̃ " + " ".join(f"{m:5.1f}" for m in iopc.mtf_bins)
    print(header)
    for i, s in enumerate(iopc.sigma_bins):
        row = " ".join("    ·" if not c else f"{a:5.2f}" for a, c in zip(iopc.ap_2d[i], iopc.count_2d[i]))
        print(f"{s:6g}  {row}")
    for r in marked[:10]:
        print(f"  marked {r['key']}: {r['reason']}")
    if len(marked) > 10:
        print(f"  … and {len(marked) - 10} more marked cells (see records in iopc.json)")
