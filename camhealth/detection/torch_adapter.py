"""Wrap any PyTorch ``nn.Module`` detector (e.g. the user's own weights) as a frozen camhealth detector.

The wrapped module is put in eval mode and every parameter gets ``requires_grad = False`` on wrapping;
eval mode is re-asserted on every call (on every sub-module: one switched back to train mode by other code is put in
eval mode again) and the forward pass runs under ``torch.inference_mode``, so the detector can never be trained
through camhealth (thesis Sec. 4.4.1: pre-trained detectors with default settings). :class:`TorchDetector` is
deliberately *not* an ``nn.Module``: stored on a LightningModule it is not a sub-module, so no optimizer sees it and
no checkpoint stores it.

Input: camhealth images ``B×1×H×W`` float in [0, 1] (any float dtype). The module gets its own copy, in the dtype of
its first floating parameter or buffer (float32 without one) on its device, so a ``forward`` that works in place
(``x.sub_(mean)``) never changes the caller's images. ``channels = 3`` repeats the gray channel for RGB detectors
(the thesis applied its detectors to grayscale images; a real copy, not a stride-0 view), ``input_scale = 255``
feeds DN.

Output parsing (before :func:`~camhealth.detection.protocol.validate_detections`), in this order:

1. ``postprocess(raw, images)`` if given — any custom format → list of {boxes, scores, labels};
2. a list/tuple of B mappings with ``boxes``/``scores``/``labels`` (torchvision-style);
3. a tensor (B, N, 6) of rows ``[x1, y1, x2, y2, score, label]``; rows with a negative score are padding
   and dropped;
4. a tuple ``(boxes (B, N, 4), scores (B, N), labels (B, N))``.

``box_format`` converts ``"xywh"`` (top-left + size) or ``"cxcywh"`` (centre + size) to xyxy, and
``normalized_boxes = True`` multiplies [0, 1] coordinates by the image width/height.
"""

from __future__ import annotations

import math
import numbers
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from camhealth._validation import check_choice, check_image
from camhealth.detection.protocol import Detection, validate_detections

__all__ = ["TorchDetector", "freeze"]

BOX_FORMATS = ("xyxy", "xywh", "cxcywh")


def freeze(module: torch.nn.Module) -> torch.nn.Module:
    """Put ``module`` in eval mode and switch off gradients of all its parameters (in place)."""
    if not isinstance(module, torch.nn.Module):
        raise TypeError(f"expected a torch.nn.Module, got {type(module).__name__}")
    module.eval()
    for p in module.parameters():
        p.requires_grad_(False)
    return module


def _to_xyxy(boxes: torch.Tensor, fmt: str) -> torch.Tensor:
    if fmt == "xyxy":
        return boxes
    if fmt == "xywh":
        return torch.cat([boxes[..., :2], boxes[..., :2] + boxes[..., 2:]], dim=-1)
    half = boxes[..., 2:] / 2
    return torch.cat([boxes[..., :2] - half, boxes[..., :2] + half], dim=-1)


class TorchDetector:
    """A frozen ``nn.Module`` detector behind the camhealth detector protocol.

    Args:
        module: the detector; frozen in place (eval, ``requires_grad = False``).
        channels: 1 (gray input) or 3 (gray repeated to RGB).
        input_scale: factor applied to the [0, 1] input (255 for detectors that expect DN).
        box_format: ``"xyxy"``, ``"xywh"`` or ``"cxcywh"`` of the module's boxes.
        normalized_boxes: boxes are in [0, 1] of the image width/height.
        postprocess: optional ``f(raw_output, images) -> list of dicts`` for other output formats.
        device: device to run on (the module is moved there); ``None``: the module's current device.
        name: name used in provenance and error messages.
    """

    frozen = True

    def __init__(
        self,
        module: torch.nn.Module,
        channels: int = 1,
        input_scale: float = 1.0,
        box_format: str = "xyxy",
        normalized_boxes: bool = False,
        postprocess: Callable[[Any, torch.Tensor], Sequence[Mapping[str, Any]]] | None = None,
        device: torch.device | str | None = None,
        name: str | None = None,
    ) -> None:
        self.module = freeze(module)
        if isinstance(channels, (bool, np.bool_)) or not isinstance(channels, numbers.Integral) or (
                channels not in (1, 3)):
            raise ValueError(f"channels = {channels!r} must be 1 (gray) or 3 (gray repeated to RGB)")
        self.channels = int(channels)
        scale = input_scale
        if isinstance(scale, (torch.Tensor, np.ndarray)) and scale.ndim == 0:
            scale = scale.item()
        if isinstance(scale, (bool, np.bool_)) or not isinstance(scale, numbers.Real) or not (
                math.isfinite(scale) and scale > 0):
            raise ValueError(f"input_scale = {input_scale!r} must be a finite number > 0")
        self.input_scale = float(scale)
        self.box_format = check_choice(box_format, "box_format", BOX_FORMATS)
        self.normalized_boxes = bool(normalized_boxes)
        if postprocess is not None and not callable(postprocess):
            raise TypeError(f"postprocess must be callable, got {type(postprocess).__name__}")
        self.postprocess = postprocess
        self.name = name or type(module).__name__
        if device is not None:
            self.to(device)

    @property
    def dtype(self) -> torch.dtype:
        """The module's input dtype: that of its first floating parameter or buffer, float32 without one."""
        for t in (*self.module.parameters(), *self.module.buffers()):
            if t.is_floating_point():
                return t.dtype
        return torch.float32

    @property
    def device(self) -> torch.device:
        p = next(iter(self.module.parameters()), None)
        if p is None:
            b = next(iter(self.module.buffers()), None)
            return b.device if b is not None else torch.device("cpu")
        return p.device

    def to(self, device: torch.device | str) -> "TorchDetector":
        """Move the wrapped module to ``device`` (still frozen)."""
        self.module.to(device)
        return self

    def config(self) -> dict[str, Any]:
        """Settings, for provenance records and the IOPC sweep's cache fingerprint: ``weights`` is a hash of the
        module's parameters and buffers, so another training of the same architecture is another detector."""
        import hashlib

        n = sum(p.numel() for p in self.module.parameters())
        h = hashlib.blake2b(digest_size=8)
        for key, t in sorted(self.module.state_dict().items()):
            h.update(key.encode())
            h.update(t.detach().cpu().reshape(-1).contiguous().view(torch.uint8).numpy().tobytes() if t.numel() else b"")
        return {
            "name": self.name,
            "module": f"{type(self.module).__module__}.{type(self.module).__qualname__}",
            "parameters": n,
            "weights": h.hexdigest(),
            "channels": self.channels,
            "input_scale": self.input_scale,
            "box_format": self.box_format,
            "normalized_boxes": self.normalized_boxes,
        }

    def _parse(self, raw: Any, b: int) -> list[Any]:
        if isinstance(raw, torch.Tensor):
            if raw.ndim != 3 or raw.shape[0] != b or raw.shape[2] != 6:
                raise ValueError(
                    f"{self.name} returned a tensor of shape {tuple(raw.shape)}; a tensor output must be "
                    f"(B={b}, N, 6) rows [x1, y1, x2, y2, score, label] (or pass postprocess=...)"
                )
            out = []
            for rows in raw:
                rows = rows[~(rows[:, 4] < 0)]  # negative scores are padding; NaN goes on to the finiteness check
                out.append({"boxes": rows[:, :4], "scores": rows[:, 4], "labels": rows[:, 5]})
            return out
        if isinstance(raw, tuple) and len(raw) == 3 and all(isinstance(t, torch.Tensor) for t in raw):
            boxes, scores, labels = raw
            if boxes.ndim != 3 or boxes.shape[0] != b:
                raise ValueError(
                    f"{self.name} returned (boxes, scores, labels) with boxes of shape {tuple(boxes.shape)}; "
                    f"expected (B={b}, N, 4)"
                )
            n = boxes.shape[1]
            for key, t in (("scores", scores), ("labels", labels)):
                if t.ndim < 2 or tuple(t.shape[:2]) != (b, n):
                    raise ValueError(
                        f"{self.name} returned (boxes, scores, labels) with {key} of shape {tuple(t.shape)}; expected "
                        f"(B={b}, N={n}) to match boxes of shape {tuple(boxes.shape)}"
                    )
            return [{"boxes": boxes[i], "scores": scores[i], "labels": labels[i]} for i in range(b)]
        if isinstance(raw, (list, tuple)):
            return list(raw)
        raise TypeError(
            f"{self.name} returned {type(raw).__name__}; expected a list of dicts {{boxes, scores, labels}}, "
            "a (B, N, 6) tensor or a (boxes, scores, labels) tuple — or pass postprocess=..."
        )

    def __call__(self, images: torch.Tensor) -> list[Detection]:
        """Run the frozen module on ``images`` (B×1×H×W float in [0, 1], any float dtype) — a copy in the module's
        dtype (:attr:`dtype`), never the caller's tensor; one dict per image."""
        check_image(images, "images")
        lo, hi = torch.aminmax(images.detach())
        if lo < 0 or hi > 1:
            raise ValueError(f"images must lie in [0, 1] (DN/255), got values in [{lo.item():g}, {hi.item():g}]")
        self.module.eval()  # every call, recursively: a sub-module switched to train mode is put back too
        b, _, h, w = images.shape
        x = images.detach().to(device=self.device, dtype=self.dtype, copy=True)  # the module may work in place
        if self.channels == 3:
            x = x.repeat(1, 3, 1, 1)
        if self.input_scale != 1.0:
            x = x * self.input_scale
        with torch.inference_mode():
            raw = self.module(x)
            dets = self.postprocess(raw, images) if self.postprocess is not None else self._parse(raw, b)
        dets = validate_detections(dets, b, image_size=None, name=f"{self.name} output", check_box_order=False)
        for d in dets:  # leave inference mode: plain tensors the caller may modify in place
            d["scores"], d["labels"] = d["scores"].clone(), d["labels"].clone()
            boxes = _to_xyxy(d["boxes"].clone(), self.box_format)
            if self.normalized_boxes:
                boxes = boxes * torch.tensor([w, h, w, h], dtype=boxes.dtype)
            d["boxes"] = boxes
        return validate_detections(dets, b, image_size=(h, w), name=f"{self.name} output")

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name}, channels={self.channels}, box_format={self.box_format!r})"
