"""The calibration result: metadata with an uncertainty per field, maps, and how they are written.

Files (:meth:`CalibrationResult.save`):

* ``camera.yaml`` — the 11 fields of :class:`~camhealth.physics.metadata.CameraMetadata` in physical units,
  one ``field: value`` per line and nothing else (``predict``, the monitor's ``--metadata`` and ``fit``'s
  ``sensor:`` read it as-is); each line's comment gives the 1σ uncertainty and where the value comes from
  (``fitted``, ``given``, ``assumed``, ``operating point``).
* ``camera.calibration.yaml`` — the same values machine-readable with uncertainty, unit, source and method,
  EMVA 1288 figures, every set's statistics and the fits' quality.
* ``camera.maps.npz`` — hot- and dead-pixel masks, DSNU map [DN], PRNU map [–], master bias/dark/flat [DN].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from camhealth.physics.metadata import FULL_FIELDS, UNITS, CameraMetadata

__all__ = ["FieldEstimate", "SetRecord", "CalibrationResult"]


@dataclass
class FieldEstimate:
    """One metadata field: value, 1σ uncertainty (0 when not measured), unit, source and method."""

    value: float
    uncertainty: float
    unit: str
    source: str  # fitted | given | assumed | operating point
    method: str = ""

    @property
    def relative(self) -> float:
        return self.uncertainty / abs(self.value) if self.value else float("nan")


@dataclass
class SetRecord:
    """A set as analysed: its operating point and statistics (see :class:`~camhealth.calibrate.statistics.SetStatistics`)."""

    name: str
    kind: str
    exposure_s: float
    gain_db: float
    temperature_c: float
    n_frames: int
    height: int
    width: int
    mean_dn: float
    sigma_dn: float
    sigma_err_dn: float
    method: str
    clipped_low: float
    clipped_high: float
    mirrored_sigma_dn: float
    spatial_sigma_dn: float
    step_dn: float
    used: bool = True
    note: str = ""


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def _fmt(v: float) -> str:
    """A float that YAML 1.1 (PyYAML) reads back as a float: always a '.' in the mantissa (``5.0e-06``,
    not ``5e-06``, which PyYAML reads as a string)."""
    text = f"{v:.6g}"
    mantissa, _, exponent = text.partition("e")
    if "." not in mantissa and mantissa.lstrip("-").isdigit():
        mantissa += ".0"
    return mantissa + ("e" + exponent if exponent else "")


@dataclass
class CalibrationResult:
    """What :func:`camhealth.calibrate.calibrate` returns.

    Attributes:
        metadata: the calibrated camera (batch 1), validated against ``METADATA_RANGES``.
        fields: field name → :class:`FieldEstimate` for all 11 fields.
        emva: EMVA 1288 figures (conversion gain, temporal dark noise, saturation capacity, dark current per
            temperature, doubling temperature, DSNU, PRNU, dynamic range, SNR max), plain floats.
        sets: every set with its statistics.
        fits: the fits' parameters and quality (χ²/dof, residuals).
        maps: ``hot_pixels`` (bool H×W), ``dead_pixels`` (bool H×W), ``dsnu_dn`` (H×W), ``prnu`` (H×W, relative), ``master_bias_dn``,
            ``master_dark_dn``, ``master_flat_dn``.
        warnings: what the user should know (assumed fields, sets left out, a dark current below detection …).
        photon_transfer, dark: the fit objects (for the report).
    """

    metadata: CameraMetadata
    fields: dict[str, FieldEstimate]
    emva: dict[str, Any]
    sets: list[SetRecord]
    fits: dict[str, Any]
    maps: dict[str, np.ndarray] = field(repr=False, default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    photon_transfer: Any = field(default=None, repr=False)
    dark: Any = field(default=None, repr=False)
    read_noise: Any = field(default=None, repr=False)

    # ------------------------------------------------------------------ YAML
    def metadata_dict(self) -> dict[str, float]:
        """The 11 fields as plain floats (what ``camera.yaml`` holds)."""
        return {n: float(getattr(self.metadata, n)[0]) for n in FULL_FIELDS}

    def yaml_text(self, header: str = "") -> str:
        """``camera.yaml``: one ``field: value`` line per metadata field, uncertainty and source as comments."""
        lines = ["# camhealth camera metadata (physical units, thesis Table 4.1) from python -m camhealth.calibrate."]
        if header:
            lines += [f"# {h}" for h in header.splitlines()]
        lines += [
            "# Comments: 1σ uncertainty and source (fitted | given | assumed | operating point); set gain_db,",
            "# exposure_s and temperature_c to the state the camera runs in (monitor: --set gain_db=12).",
        ]
        values = self.metadata_dict()
        width = max(len(n) for n in FULL_FIELDS) + 2
        for n in FULL_FIELDS:
            fe = self.fields[n]
            unit = UNITS.get(n, "")
            comment = fe.source
            if fe.source == "fitted" and fe.uncertainty > 0:
                rel = f" ({100 * fe.relative:.2g} %)" if math.isfinite(fe.relative) else ""
                comment = f"± {_fmt(fe.uncertainty)}{(' ' + unit) if unit else ''}{rel}, fitted: {fe.method}"
            elif fe.method:
                comment = f"{fe.source}: {fe.method}"
            if n == "is_cmos":
                comment += " (1 = CMOS, 0 = CCD)"
            lines.append(f"{(n + ':').ljust(width)}{_fmt(values[n]):<14} # {comment}")
        return "\n".join(lines) + "\n"

    def details(self) -> dict[str, Any]:
        """Everything of ``camera.calibration.yaml`` as a plain dict."""
        return _plain({
            "metadata": {n: {"value": fe.value, "uncertainty": fe.uncertainty, "unit": fe.unit, "source": fe.source, "method": fe.method}
                         for n, fe in self.fields.items()},
            "emva1288": self.emva,
            "fits": self.fits,
            "sets": [vars(s) for s in self.sets],
            "warnings": list(self.warnings),
        })

    def save(self, out: str | Path, maps: str | Path | None = None, details: str | Path | None = None, header: str = "") -> dict[str, Path]:
        """Write ``out`` (camera.yaml), the details YAML (default ``<stem>.calibration.yaml``) and the maps NPZ
        (default ``<stem>.maps.npz``) beside it. Returns the paths written."""
        import yaml

        out = Path(out)
        details = Path(details) if details is not None else out.with_name(out.stem + ".calibration.yaml")
        maps = Path(maps) if maps is not None else out.with_name(out.stem + ".maps.npz")
        for folder in {out.parent, details.parent, maps.parent}:  # (created where missing)
            folder.mkdir(parents=True, exist_ok=True)
        out.write_text(self.yaml_text(header), encoding="utf-8")
        details.write_text(yaml.safe_dump(self.details(), sort_keys=False, allow_unicode=True), encoding="utf-8")
        np.savez_compressed(maps, **self.maps)
        return {"metadata": out, "details": details, "maps": maps}
