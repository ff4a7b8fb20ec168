"""Overlay PNGs and heat maps of the monitor's per-patch results.

:func:`heat_map` turns one per-patch quantity of a :class:`~camhealth.monitor.api.TaskReport` into a
per-pixel H×W map (NaN outside the grid and on patches without a value). :func:`render_overlay` draws
two panels side by side on the gray frame: the total noise σ [DN] of every 128-px patch and the blur
indicator MTF̃ (mean of the H and V MTF at f_n = 0.1, thesis Sec. 4.4) of every 192-px patch, each as a
colour map (viridis; fixed ranges so that frames compare: σ in [0, ``sigma_max_dn``], MTF̃ in [0, 1])
blended over the frame, with the value written in each patch, a letter for its status (``i``
interpolated, ``r`` reused, ``B`` black, ``S`` saturated, ``F`` featureless, ``E`` no edges, ``?`` not assessable, ``u`` not sampled in sampled mode;
skipped patches are hatched), a title line with the frame values and the ξ alarm, and a colour bar.
:func:`save_overlay` writes the panels as PNG. OpenCV draws (ASCII text only).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from camhealth.monitor.api import NOISE_FIELDS, FrameReport, TaskReport
from camhealth.monitor.tiling import SKIP_CODES, STATUS_NAMES

__all__ = ["heat_map", "render_overlay", "save_overlay", "STATUS_LETTERS"]

#: Letter drawn in a patch for each status (estimated patches get none).
STATUS_LETTERS: dict[str, str] = {
    "estimated": "", "interpolated": "i", "reused": "r", "black": "B", "saturated": "S", "featureless": "F",
    "not_assessable": "?", "unsampled": "u", "no_edges": "E",
}


def _patch_values(report: TaskReport, quantity: str) -> np.ndarray:
    if report.values is None or report.grid_obj is None:
        return np.zeros(0, dtype=np.float32)
    v = report.values.float()
    if report.task == "noise":
        if quantity not in NOISE_FIELDS:
            raise ValueError(f"quantity {quantity!r} of the noise task must be one of {list(NOISE_FIELDS)}")
        out = v[:, NOISE_FIELDS.index(quantity)]
    else:
        if quantity != "indicator":
            raise ValueError(f"quantity {quantity!r} of the MTF task must be 'indicator'")
        from camhealth.physics.mtf import mtf_indicator

        out = mtf_indicator(v)
    return out.numpy().astype(np.float32)


def heat_map(report: TaskReport, quantity: str | None = None) -> np.ndarray:
    """Per-pixel H×W float32 map of a per-patch quantity (``"total"``, ``"pn"``, … for noise [DN];
    ``"indicator"`` for MTF), NaN outside the grid and where a patch has no value."""
    if not isinstance(report, TaskReport):
        raise TypeError(f"report must be a TaskReport, got {type(report).__name__}")
    g = report.grid_obj
    if g is None:
        raise ValueError("the report carries no per-patch maps")
    quantity = quantity or ("total" if report.task == "noise" else "indicator")
    out = np.full((g.height, g.width), np.nan, dtype=np.float32)
    if g.empty:
        return out
    vals = _patch_values(report, quantity).reshape(g.rows, g.cols)
    block = np.kron(vals, np.ones((g.patch, g.patch), dtype=np.float32))
    out[g.y0 : g.y0 + g.rows * g.patch, g.x0 : g.x0 + g.cols * g.patch] = block
    return out


def _fmt(x: Any, spec: str) -> str:
    return "-" if x is None or not np.isfinite(x) else format(float(x), spec)


def _panel(gray: np.ndarray, report: TaskReport | None, quantity: str, vmax: float, scale: float, title: str) -> np.ndarray:
    import cv2

    h, w = gray.shape
    sh, sw = max(1, int(round(h * scale))), max(1, int(round(w * scale)))
    img = cv2.cvtColor(cv2.resize(gray, (sw, sh), interpolation=cv2.INTER_AREA), cv2.COLOR_GRAY2BGR)
    font, fs = cv2.FONT_HERSHEY_SIMPLEX, 0.5 * max(scale, 0.7)
    if report is not None and report.grid_obj is not None and not report.grid_obj.empty:
        g = report.grid_obj
        vals = _patch_values(report, quantity)
        code = report.code.numpy() if report.code is not None else np.zeros(g.n, dtype=np.int8)
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # a vmax beyond float32: 0 or inf there
            norm = np.nan_to_num(np.clip(np.nan_to_num(vals, nan=0.0) / vmax, 0, 1), nan=0.0)
        colours = cv2.applyColorMap((norm * 255).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_VIRIDIS)[:, 0]
        overlay = img.copy()
        for i in range(g.n):  # drawing is per patch (a few dozen rectangles)
            r, c = divmod(i, g.cols)
            x0, y0 = int(round((g.x0 + c * g.patch) * scale)), int(round((g.y0 + r * g.patch) * scale))
            x1, y1 = int(round((g.x0 + (c + 1) * g.patch) * scale)) - 1, int(round((g.y0 + (r + 1) * g.patch) * scale)) - 1
            if int(code[i]) in SKIP_CODES or not np.isfinite(vals[i]):
                rect = (x0, y0, x1 - x0 + 1, y1 - y0 + 1)
                for t in range(0, (x1 - x0) + (y1 - y0), max(6, int(12 * scale))):  # hatch: skipped
                    ok, p0, p1 = cv2.clipLine(rect, (x0 + t, y0), (x0, y0 + t))
                    if ok:
                        cv2.line(overlay, p0, p1, (60, 60, 60), 1)
            else:
                cv2.rectangle(overlay, (x0, y0), (x1, y1), tuple(int(v) for v in colours[i]), -1)
        img = cv2.addWeighted(overlay, 0.5, img, 0.5, 0)
        for i in range(g.n):
            r, c = divmod(i, g.cols)
            x0, y0 = int(round((g.x0 + c * g.patch) * scale)), int(round((g.y0 + r * g.patch) * scale))
            x1, y1 = int(round((g.x0 + (c + 1) * g.patch) * scale)) - 1, int(round((g.y0 + (r + 1) * g.patch) * scale)) - 1
            cv2.rectangle(img, (x0, y0), (x1, y1), (200, 200, 200), 1)
            letter = STATUS_LETTERS[STATUS_NAMES[int(code[i])]]
            number = _fmt(vals[i], ".1f" if report.task == "noise" else ".2f") if np.isfinite(vals[i]) else ""
            text = number + (f" {letter}" if letter else "")
            if text.strip():
                cv2.putText(img, text.strip(), (x0 + 3, y0 + int(16 * fs / 0.5)), font, fs, (255, 255, 255), 1, cv2.LINE_AA)
    # title band and colour bar
    band = np.zeros((int(24 * max(fs / 0.5, 1)), sw, 3), dtype=np.uint8)
    cv2.putText(band, title, (4, band.shape[0] - 7), font, fs, (255, 255, 255), 1, cv2.LINE_AA)
    bar_h = max(10, int(12 * scale))
    ramp = cv2.applyColorMap(np.linspace(0, 255, sw).astype(np.uint8)[None, :].repeat(bar_h, 0), cv2.COLORMAP_VIRIDIS)
    legend = np.zeros((band.shape[0], sw, 3), dtype=np.uint8)
    unit = " DN" if report is None or report.task == "noise" else ""
    cv2.putText(legend, f"0{unit}", (4, legend.shape[0] - 7), font, fs, (255, 255, 255), 1, cv2.LINE_AA)
    label = f"{vmax:g}{unit}"
    (tw, _), _ = cv2.getTextSize(label, font, fs, 1)
    cv2.putText(legend, label, (max(4, sw - tw - 4), legend.shape[0] - 7), font, fs, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([band, img, ramp, legend], axis=0)


def render_overlay(frame: Any, report: FrameReport, sigma_max_dn: float = 20.0, max_panel_width: int = 960,
                   bit_depth: int | None = None) -> np.ndarray:
    """Noise and blur panels side by side over the frame → H'×W'×3 uint8 **BGR** image (OpenCV order).

    Args:
        frame: the frame the report was made from (anything :func:`camhealth.monitor.as_frame` accepts).
        report: its :class:`FrameReport`.
        sigma_max_dn: top of the σ colour scale [DN] (default 20; the IOPC σ bins go to 30).
        max_panel_width: panels wider than this [px] are scaled down.
        bit_depth: significant bits of a uint16 ``frame``, as given to :meth:`~camhealth.monitor.Monitor.process`
            (:func:`~camhealth.monitor.as_frame`; ``None``: the full 16-bit word).
    """
    from camhealth.monitor.api import as_frame

    if not isinstance(report, FrameReport):
        raise TypeError(f"report must be a FrameReport, got {type(report).__name__}")
    if isinstance(sigma_max_dn, bool) or not isinstance(sigma_max_dn, (int, float, np.number)) or not (
            np.isfinite(sigma_max_dn) and sigma_max_dn > 0):
        raise ValueError(f"sigma_max_dn = {sigma_max_dn!r} must be a finite number > 0 [DN]")
    if isinstance(max_panel_width, bool) or not isinstance(max_panel_width, (int, np.integer)) or max_panel_width < 64:
        raise ValueError(f"max_panel_width = {max_panel_width!r} must be an integer ≥ 64 [px]")
    x = as_frame(frame, bit_depth)[0, 0]
    if (x.shape[0], x.shape[1]) != (report.height, report.width):
        raise ValueError(f"frame is {x.shape[1]}×{x.shape[0]} px but the report is for {report.width}×{report.height} px")
    gray = (x * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).numpy()
    scale = min(1.0, max_panel_width / max(1, report.width))
    panels = []
    n = report.noise
    if n is not None:
        al = report.alarm.get("state", "")
        title = (f"#{report.frame} sigma {_fmt(n.value('total'), '.2f')} DN (PN {_fmt(n.value('pn'), '.2f')} "
                 f"DCSN {_fmt(n.value('dcsn'), '.2f')} RN {_fmt(n.value('rn'), '.2f')}) xi {_fmt(n.value('xi'), '+.2f')} [{al}]")
        panels.append(_panel(gray, n, "total", float(sigma_max_dn), scale, title))
    m = report.mtf
    if m is not None:
        title = f"#{report.frame} blur indicator MTF~ (H/V at f_n = 0.1) {_fmt(m.value('indicator'), '.3f')}"
        panels.append(_panel(gray, m, "indicator", 1.0, scale, title))
    if not panels:
        raise ValueError("the report has neither a noise nor an MTF result")
    return np.concatenate(panels, axis=1)


def save_overlay(path: str | Path, frame: Any, report: FrameReport, **kwargs: Any) -> Path:
    """Write :func:`render_overlay` as a PNG (parent folders are created). Returns the path."""
    import cv2

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"overlay files are PNG, got {path.name!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), render_overlay(frame, report, **kwargs)):
        raise OSError(f"could not write overlay {path}")
    return path
