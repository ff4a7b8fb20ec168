"""Input–output performance curves (IOPCs): detector AP as a function of estimated noise and blur.

Thesis Sec. 4.4.1. Every grid cell of a sweep (one blur × one noise corruption applied to N_I images)
yields one tuple (σ̃, MTF̃, AP): σ̃ and MTF̃ are the medians of the patch-wise estimates over the patches
that overlap ground-truth boxes (Eq. 4.4), AP the detector's average precision on the corrupted images.
The tuples are quantised into bins

    σ̃ ∈ {0, 5, …, 30} DN,   MTF̃ ∈ {0.1, 0.2, …, 1.0}   (MTF̃ = mean of H and V MTF at f_n = 0.1)

— a tuple goes to the *nearest* bin; a value farther than half a bin spacing beyond the first/last bin is
outside the curve and the cell is *marked* (not clipped into the edge bin) — and collected as

* the **2-D IOPC** ``ap_2d[i, j]`` = mean AP of the cells in σ-bin i and MTF-bin j (NaN where empty),
  with ``count_2d``;
* the **1-D IOPCs** of isolated corruptions (thesis Fig. 7.1): ``ap_sigma`` from the cells without blur
  (motion length 0) and ``ap_mtf`` from the cells without noise (noise level 0), with counts;
* the **MTF → motion-length relation** MB_L used by the policy (Eq. 4.7): for every swept length L the
  median MTF̃ over directions (and images) of the unmarked cells at the *lowest swept noise level*, made
  non-increasing in L. That level is noise-free (0 DN) only when the grid sweeps σ = 0; it is stored as
  ``blur_noise_level_dn`` [DN] so that a relation measured on noisy cells is recognisable.

Cells are kept as ``records`` (one dict per cell, the full sweep result) with a ``marked`` flag and a
``reason`` when a cell's corruption lies outside the estimators' valid range, its noise level cannot be
produced by the sensor within the metadata ranges, no patch was assessable, or its σ̃/MTF̃ falls outside the
bins. Marked cells never enter the curves — nothing is silently filled. :meth:`IOPC.surface` gives a
dense 2-D surface for the policy, with a ``measured`` mask that says which bins were filled from the
nearest measured bin.

Files: JSON (human-readable, NaN → null) and NPZ (arrays + the JSON of records/provenance), both
round-trip exactly through :meth:`IOPC.save` / :meth:`IOPC.load`. ``provenance`` records how the curves
were made (detector, estimators, frames, grid, sensor, seed, versions, git commit, date).
"""

from __future__ import annotations

import json
import math
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = [
    "SIGMA_BINS_DN",
    "MTF_BINS",
    "IOPC",
    "bin_index",
    "blur_relation",
    "blur_relation_noise_level",
    "FORMAT_VERSION",
]

#: Noise bins of the thesis [DN].
SIGMA_BINS_DN: tuple[float, ...] = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0)
#: Blur-indicator bins of the thesis (MTF̃ at f_n = 0.1, dimensionless).
MTF_BINS: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
#: Version of the file layout written by :meth:`IOPC.save`.
FORMAT_VERSION = 1


#: Allowed values of the bin centres: σ̃ is a standard deviation [DN] (>= 0), MTF̃ an MTF value in [0, 1].
_BIN_RANGES: dict[str, tuple[float, float, str]] = {"sigma": (0.0, math.inf, ">= 0 DN"), "mtf": (0.0, 1.0, "in [0, 1]")}


def _is_number(v: Any) -> bool:
    """A real number (Python or numpy), not a bool and not text."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


#: Largest count an IOPC holds: every whole number up to 2^53 is exact in float64 (and fits int64); a larger one is
#: not a count of sweep cells but a corrupt file.
_MAX_COUNT = 2**53


def _fits_float(v: Any) -> bool:
    """False for an integer beyond float64's range (JSON reads 1 followed by 400 zeros as a Python int)."""
    try:
        float(v)
    except OverflowError:
        return False
    except (TypeError, ValueError):
        pass
    return True


def _short(v: Any) -> str:
    """``v`` for an error message; an integer too large for a float as its number of digits."""
    return repr(v) if _fits_float(v) else f"an integer of {len(str(abs(int(v))))} digits"


def _leaves(x: Any, field: str, max_depth: int) -> Any:
    """(index, value) of every leaf of nested lists/tuples (a scalar is its own leaf, index ()), walked without
    recursion; nesting deeper than ``max_depth`` (the field's number of dimensions) is refused, naming the field."""
    stack: list[tuple[tuple[int, ...], Any]] = [((), x)]
    while stack:
        where, v = stack.pop()
        if isinstance(v, (list, tuple)):
            if len(where) >= max_depth:
                raise ValueError(f"IOPC.{field}{list(where)} is nested deeper than the field's {max_depth} "
                                 f"dimension(s); allowed: a {max_depth}-D array of numbers")
            stack.extend(((*where, i), item) for i, item in reversed(list(enumerate(v))))
        else:
            yield where, v


def _numeric(x: Any, field: str, allowed: str, null_ok: bool = False, integer: bool = False,
             ndim: int = 1) -> np.ndarray:
    """``x`` (nested lists or an array) as a float64 array (int64 with ``integer``), refusing what is not a number.

    Text and booleans are refused (numpy would turn ``"0.7"`` into 0.7 and ``true`` into 1); ``None`` becomes NaN
    where ``null_ok``; lists nested deeper than ``ndim`` are refused before they are walked. With ``integer`` every
    value must be a whole number in [0, 2^53] (a count: 0.9 is refused, not truncated to 0; 1e19 is refused, not
    wrapped to a negative int64). Errors name ``IOPC.<field>[index]``, the value and ``allowed``.
    """
    if isinstance(x, np.ndarray):
        if x.dtype.kind not in "iuf":
            raise ValueError(f"IOPC.{field} must hold numbers ({allowed}), got an array of {x.dtype}")
        arr = x.astype(np.float64)
    else:
        for where, v in _leaves(x, field, ndim):
            if not (_is_number(v) or (null_ok and v is None)):
                raise ValueError(f"IOPC.{field}{list(where)} = {v!r} is not a number; allowed: {allowed}")
            if not _fits_float(v):
                raise ValueError(f"IOPC.{field}{list(where)} = {_short(v)} is out of the allowed range: {allowed}")
        arr = np.asarray(_none_to_nan(x) if null_ok else x, dtype=np.float64)
    if integer:
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(arr) | (arr < 0) | (arr != np.round(arr)) | (arr > _MAX_COUNT)
        if bool(bad.any()):
            where = tuple(int(k) for k in np.argwhere(bad)[0]) if arr.ndim else ()
            raise ValueError(f"IOPC.{field}{list(where)} = {float(arr[where]):g} is out of the allowed range: {allowed}")
        return arr.astype(np.int64)
    return arr


def _bin_centres(bins: Any, name: str, kind: str) -> np.ndarray:
    """Bin centres an IOPC can use: at least 2 numbers (not text or bool), finite, strictly increasing, and inside
    the range of ``kind`` (``"sigma"``: >= 0 DN, ``"mtf"``: [0, 1]). Errors name ``name``, the value and the range.
    :class:`IOPC` and :meth:`camhealth.iopc.SweepConfig.validate` share it, so a sweep refuses up front the bins its
    curves would refuse after all cells are computed."""
    low, high, rng = _BIN_RANGES[kind]
    allowed = f"at least 2 finite numbers {rng}, strictly increasing"
    if isinstance(bins, np.ndarray):
        if bins.dtype.kind not in "iuf":
            raise ValueError(f"{name} = {bins.tolist()!r} is not allowed: {allowed}")
    else:
        vals = list(bins) if isinstance(bins, (list, tuple)) else [bins]
        if not all(_is_number(v) for v in vals):
            raise ValueError(f"{name} = {bins!r} is not allowed: {allowed}")
        huge = [v for v in vals if not _fits_float(v)]
        if huge:
            raise ValueError(f"{name} holds {_short(huge[0])}, out of the allowed range: {allowed}")
    b = np.asarray(bins, dtype=np.float64).reshape(-1)
    if b.size < 2:
        raise ValueError(f"{name} = {b.tolist()} needs at least 2 bin centres ({allowed})")
    if not np.all(np.isfinite(b)) or not np.all(np.diff(b) > 0):
        raise ValueError(f"{name} = {b.tolist()} must be finite and strictly increasing ({allowed})")
    if b[0] < low or b[-1] > high:
        raise ValueError(f"{name} = {b.tolist()} is out of the allowed range: {allowed}")
    return b


def _check_bins(bins: Sequence[float], name: str) -> np.ndarray:
    b = np.asarray(bins, dtype=np.float64).reshape(-1)
    if b.size < 2:
        raise ValueError(f"{name} needs at least 2 bin centres, got {b.tolist()}")
    if not np.all(np.isfinite(b)) or not np.all(np.diff(b) > 0):
        raise ValueError(f"{name} must be finite and strictly increasing, got {b.tolist()}")
    return b


def _query(x: Any, what: str, high: float = math.inf) -> np.ndarray:
    """A query of :meth:`IOPC.interpolate`, :meth:`IOPC.length_from_mtf` or :meth:`IOPC.mtf_from_length` as a float64
    array: numbers (a scalar, a sequence, a numpy array or a tensor) in [0, ``high``], or NaN (which stays NaN).
    Text, booleans and None are refused (numpy would read ``"0.7"`` as 0.7 and ``True`` as 1), and so are values out
    of range, which the curves would otherwise clamp to their outermost bin — a confident number for an impossible
    input. ``what`` names the query and its unit."""
    allowed = f"numbers in [0, {high:g}]" + (" (MTF values)" if math.isfinite(high) else "") + ", or NaN"
    if isinstance(x, (str, bytes, bool, np.bool_)) or x is None:
        raise TypeError(f"{what} = {x!r} is not a number; allowed: {allowed}")
    if _is_tensor(x):  # any floating dtype (numpy has no bfloat16); integer tensors as they are
        if x.dtype.is_floating_point:
            x = x.detach().cpu().double()
        x = x.detach().cpu().numpy()
    try:
        q = np.asarray(x)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{what} of type {type(x).__name__} cannot be read as numbers ({exc}); allowed: {allowed}") from None
    if q.dtype.kind not in "iuf":
        raise TypeError(f"{what} must hold numbers ({allowed}), got an array of {q.dtype}")
    q = q.astype(np.float64, copy=False)
    with np.errstate(invalid="ignore"):
        bad = (q < 0.0) | (q > high + (1e-6 if math.isfinite(high) else 0.0)) | np.isinf(q)
    if bool(bad.any()):
        v = q[bad].reshape(-1)[0]
        raise ValueError(f"{what} = {float(v):g} is out of the allowed range: {allowed}")
    return q


def _is_tensor(x: Any) -> bool:
    """A torch tensor (torch is imported only if the caller already has, so the curves stay importable without it)."""
    import sys

    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def bin_index(values: np.ndarray | Sequence[float] | float, bins: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-bin index of each value and whether it lies within the bins.

    A value is inside when it is at most half the first/last bin spacing beyond the first/last centre;
    NaN is never inside. Returns ``(index, inside)`` (index is clipped to a valid bin for outside values).
    """
    b = _check_bins(bins, "bins")
    v = np.asarray(values, dtype=np.float64)
    edges = np.concatenate([[b[0] - 0.5 * (b[1] - b[0])], 0.5 * (b[1:] + b[:-1]), [b[-1] + 0.5 * (b[-1] - b[-2])]])
    idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, b.size - 1)
    inside = np.isfinite(v) & (v >= edges[0]) & (v <= edges[-1])
    # a value exactly on an inner edge goes to the upper bin (searchsorted right); keep that convention
    return idx.astype(np.int64), inside


def blur_relation(records: Sequence[Mapping[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    """MTF → motion-length relation from sweep records: (lengths [px], MTF̃) with MTF̃ non-increasing.

    Uses the unmarked cells with finite MTF̃ at the lowest swept noise level (:func:`blur_relation_noise_level`;
    noise-free only if the sweep has σ = 0 cells); per length the median MTF̃ over directions. A running minimum
    makes it non-increasing so that it can be inverted (MB_L).
    """
    rows = _blur_rows(records)
    if not rows:
        return np.zeros(0), np.zeros(0)
    low = min(float(r["noise_level_dn"]) for r in rows)
    rows = [r for r in rows if float(r["noise_level_dn"]) == low]
    lengths = sorted({float(r["length_px"]) for r in rows})
    mtf = np.array([np.median([float(r["mtf_tilde"]) for r in rows if float(r["length_px"]) == L]) for L in lengths])
    # an estimate may read slightly above 1 on sharp frames; the relation holds MTF values
    return np.asarray(lengths, dtype=np.float64), np.minimum.accumulate(np.clip(mtf, 0.0, 1.0))


#: A sweep record's numeric fields: (lowest, highest, whether None/NaN is allowed — an undefined AP or a cell
#: without an estimate, which gets marked — and what is allowed, for the error).
_RECORD_FIELDS: dict[str, tuple[float, float, bool, str]] = {
    "sigma_tilde": (0.0, math.inf, True, "a number >= 0 DN, or null/NaN (no estimate: the cell is marked)"),
    # an estimated MTF̃ may read slightly above 1 on a sharp frame: the bins decide whether it is inside
    "mtf_tilde": (0.0, math.inf, True, "a number >= 0, or null/NaN (no estimate: the cell is marked)"),
    "ap": (0.0, 1.0, True, "a number in [0, 1], or null/NaN (no ground truth: the cell is marked)"),
    "length_px": (0.0, math.inf, False, "a finite number >= 0 px (the swept motion length)"),
    "noise_level_dn": (0.0, math.inf, False, "a finite number >= 0 DN (the swept noise level)"),
}


def _check_record(k: int, r: Mapping[str, Any]) -> None:
    """Refuse a record field that is not what a sweep writes (text, booleans, out-of-range numbers), naming the record,
    the field, the value and what is allowed. ``marked`` must be a boolean (the text "false" would read as True)."""
    for key, (low, high, null_ok, allowed) in _RECORD_FIELDS.items():
        v = r[key]
        if v is None and null_ok:
            continue
        if not _is_number(v) or not _fits_float(v):
            raise ValueError(f"record {k}: {key} = {_short(v)} is not allowed: {allowed}")
        f = float(v)
        if math.isnan(f) and null_ok:
            continue
        if not (math.isfinite(f) and low <= f <= high):
            raise ValueError(f"record {k}: {key} = {f:g} is out of the allowed range: {allowed}")
    if "marked" in r and not isinstance(r["marked"], (bool, np.bool_)):
        raise ValueError(f"record {k}: marked = {r['marked']!r} is not allowed: true or false")


def _blur_rows(records: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    return [r for r in records if not r.get("marked") and _finite(r.get("mtf_tilde"))]


def blur_relation_noise_level(records: Sequence[Mapping[str, Any]]) -> float:
    """The noise level [DN] whose cells :func:`blur_relation` uses (the lowest swept level among the unmarked cells
    with a finite MTF̃); NaN if there is none."""
    rows = _blur_rows(records)
    return min(float(r["noise_level_dn"]) for r in rows) if rows else float("nan")


def _finite(x: Any) -> bool:
    try:
        return x is not None and math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def _mean_by_bin(i: np.ndarray, j: np.ndarray | None, ap: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    total = np.zeros(shape)
    count = np.zeros(shape, dtype=np.int64)
    key = (i,) if j is None else (i, j)
    np.add.at(total, key, ap)
    np.add.at(count, key, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return mean, count


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def _none_to_nan(x: Any) -> Any:
    if isinstance(x, list):
        return [_none_to_nan(v) for v in x]
    return float("nan") if x is None else x


class _Refused(ValueError):
    """A file :meth:`IOPC.load` refuses with a message of its own (naming the file), not wrapped."""


@dataclass
class IOPC:
    """1-D and 2-D input–output performance curves of one application (detector), with provenance.

    Attributes:
        sigma_bins: (S,) σ̃ bin centres [DN].
        mtf_bins: (M,) MTF̃ bin centres [–].
        ap_2d: (S, M) mean AP per bin, NaN where no cell fell.
        count_2d: (S, M) cells per bin.
        ap_sigma, count_sigma: (S,) 1-D curve of isolated noise (cells without blur).
        ap_mtf, count_mtf: (M,) 1-D curve of isolated blur (cells without noise).
        blur_length_px, blur_mtf: (K,) the MTF → motion-length relation (see :func:`blur_relation`): swept motion
            lengths [px] (>= 0, increasing) and their MTF̃ (in [0, 1], non-increasing).
        records: every sweep cell (dicts with ``length_px``, ``angle_deg``, ``noise_level_dn``,
            ``sigma_tilde``, ``mtf_tilde``, ``ap``, ``marked``, ``reason``, …).
        provenance: how the curves were made.
        name: the application metric, e.g. ``"AP@0.5 opencv-hog-people"``.
        blur_noise_level_dn: the sweep noise level [DN] of the cells the MTF → motion-length relation was measured
            on (the lowest swept level; 0 = noise-free). NaN when unknown or there is no relation.

    Counts are whole numbers in [0, 2^53], AP values numbers in [0, 1] (NaN only in empty bins), σ̃ bins >= 0 DN and
    MTF̃ bins in [0, 1], each array nested no deeper than its dimensions; anything else (text, booleans, 0.9 cells,
    -5 cells, 1e19 cells) is refused with a ``ValueError`` naming the field, the value and the allowed range, never
    converted.
    """

    sigma_bins: np.ndarray
    mtf_bins: np.ndarray
    ap_2d: np.ndarray
    count_2d: np.ndarray
    ap_sigma: np.ndarray
    count_sigma: np.ndarray
    ap_mtf: np.ndarray
    count_mtf: np.ndarray
    blur_length_px: np.ndarray
    blur_mtf: np.ndarray
    records: list[dict[str, Any]] = field(default_factory=list)
    provenance: dict[str, Any] = field(default_factory=dict)
    name: str = "AP"
    blur_noise_level_dn: float = float("nan")

    def __post_init__(self) -> None:
        self.sigma_bins = _bin_centres(self.sigma_bins, "IOPC.sigma_bins", "sigma")
        self.mtf_bins = _bin_centres(self.mtf_bins, "IOPC.mtf_bins", "mtf")
        s, m = self.sigma_bins.size, self.mtf_bins.size
        for nm, shape in (
            ("ap_2d", (s, m)), ("count_2d", (s, m)), ("ap_sigma", (s,)), ("count_sigma", (s,)),
            ("ap_mtf", (m,)), ("count_mtf", (m,)),
        ):
            count = nm.startswith("count")
            allowed = ("a whole number >= 0 and <= 2^53 (cells per bin)" if count
                       else "a number in [0, 1], or null (NaN) in an empty bin")
            arr = _numeric(getattr(self, nm), nm, allowed, null_ok=not count, integer=count, ndim=len(shape))
            if arr.shape != shape:
                raise ValueError(f"IOPC.{nm} must have shape {shape} for {s} σ bins × {m} MTF bins, got {arr.shape}")
            setattr(self, nm, arr)
        for nm, cnt in (("ap_2d", "count_2d"), ("ap_sigma", "count_sigma"), ("ap_mtf", "count_mtf")):
            a, c = getattr(self, nm), getattr(self, cnt)
            bad = (~np.isnan(a) & ((a < 0) | (a > 1))) | ((c > 0) & ~np.isfinite(a))  # inf too; NaN only where empty
            if bool(bad.any()):
                where = tuple(int(k) for k in np.argwhere(bad)[0])
                raise ValueError(f"IOPC.{nm}{list(where)} = {a[where]} (count {c[where]}): AP must lie in [0, 1], and be a "
                                 "number wherever the bin counts detections (NaN only in empty bins)")
        self.blur_length_px = _numeric(self.blur_length_px, "blur_length_px", "finite numbers >= 0 px, strictly increasing",
                                       null_ok=True).reshape(-1)
        self.blur_mtf = _numeric(self.blur_mtf, "blur_mtf", "finite numbers in [0, 1], non-increasing",
                                 null_ok=True).reshape(-1)
        if self.blur_length_px.shape != self.blur_mtf.shape:
            raise ValueError("blur_length_px and blur_mtf must have the same length")
        L, m = self.blur_length_px, self.blur_mtf
        if not (np.isfinite(L).all() and np.isfinite(m).all()):
            raise ValueError(f"IOPC blur relation must be finite: blur_length_px {L.tolist()}, blur_mtf {m.tolist()}")
        if L.size and (L.min() < 0 or bool(np.any(np.diff(L) <= 0))):
            raise ValueError(f"IOPC.blur_length_px {L.tolist()} must be ≥ 0 px and strictly increasing (the swept "
                             "motion lengths in order)")
        if m.size and (m.min() < 0 or m.max() > 1):
            raise ValueError(f"IOPC.blur_mtf {m.tolist()} is out of the allowed range [0, 1] (MTF values)")
        if bool(np.any(np.diff(m) > 0)):
            raise ValueError(f"IOPC.blur_mtf {m.tolist()} must not increase with the motion length (blur_relation "
                             "makes it non-increasing)")
        lvl = float("nan") if self.blur_noise_level_dn is None else self.blur_noise_level_dn
        if not (_is_number(lvl) and _fits_float(lvl) and (math.isnan(lvl) or (math.isfinite(lvl) and lvl >= 0))):
            raise ValueError(f"IOPC.blur_noise_level_dn = {_short(self.blur_noise_level_dn)} is out of the allowed range: a "
                             "number >= 0 DN, or null (NaN) when unknown")
        self.blur_noise_level_dn = float(lvl)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_records(
        cls,
        records: Sequence[Mapping[str, Any]],
        sigma_bins: Sequence[float] = SIGMA_BINS_DN,
        mtf_bins: Sequence[float] = MTF_BINS,
        provenance: Mapping[str, Any] | None = None,
        name: str = "AP",
    ) -> "IOPC":
        """Bin sweep records (one per grid cell) into curves; cells outside the bins get marked.

        Each record needs ``sigma_tilde`` [DN], ``mtf_tilde``, ``ap`` in [0, 1], ``length_px`` and
        ``noise_level_dn``; ``marked`` records are kept but not binned. Returns a new IOPC whose
        ``records`` are copies with the bin indices (``sigma_bin``, ``mtf_bin``) filled in.
        """
        sb, mb = _bin_centres(sigma_bins, "sigma_bins", "sigma"), _bin_centres(mtf_bins, "mtf_bins", "mtf")
        if isinstance(records, (str, bytes, Mapping)) or not isinstance(records, Sequence):
            raise TypeError(f"records must be a list of sweep records (mappings), got {type(records).__name__}")
        recs = []
        for k, r in enumerate(records):
            if not isinstance(r, Mapping):
                raise TypeError(f"record {k} must be a mapping of its fields, got {type(r).__name__}: {_short(r)}")
            recs.append(dict(r))
        for k, r in enumerate(recs):
            for key in ("sigma_tilde", "mtf_tilde", "ap", "length_px", "noise_level_dn"):
                if key not in r:
                    raise ValueError(f"record {k} is missing {key!r}; it has {sorted(r)}")
            _check_record(k, r)
            r.setdefault("marked", False)
            r.setdefault("reason", "")
            r["sigma_bin"], r["mtf_bin"] = None, None
            if r["marked"]:
                continue
            if not _finite(r["ap"]):
                r["marked"], r["reason"] = True, "AP undefined (no ground truth)"
                continue
            if not (_finite(r["sigma_tilde"]) and _finite(r["mtf_tilde"])):
                r["marked"], r["reason"] = True, "no estimate (no assessable patch overlapping an object)"
                continue
            (i,), (ins_s,) = bin_index([r["sigma_tilde"]], sb)
            (j,), (ins_m,) = bin_index([r["mtf_tilde"]], mb)
            if not ins_s or not ins_m:
                r["marked"] = True
                r["reason"] = (
                    f"outside the IOPC bins (σ̃ = {float(r['sigma_tilde']):.2f} DN, MTF̃ = {float(r['mtf_tilde']):.3f})"
                )
                continue
            r["sigma_bin"], r["mtf_bin"] = int(i), int(j)
        used = [r for r in recs if not r["marked"]]
        i = np.array([r["sigma_bin"] for r in used], dtype=np.int64)
        j = np.array([r["mtf_bin"] for r in used], dtype=np.int64)
        ap = np.array([float(r["ap"]) for r in used], dtype=np.float64)
        ap2, c2 = _mean_by_bin(i, j, ap, (sb.size, mb.size))
        no_blur = np.array([float(r["length_px"]) == 0.0 for r in used], dtype=bool)
        no_noise = np.array([float(r["noise_level_dn"]) == 0.0 for r in used], dtype=bool)
        aps, cs = _mean_by_bin(i[no_blur], None, ap[no_blur], (sb.size,))
        apm, cm = _mean_by_bin(j[no_noise], None, ap[no_noise], (mb.size,))
        lengths, mtf = blur_relation(recs)
        return cls(sb, mb, ap2, c2, aps, cs, apm, cm, lengths, mtf, recs, dict(provenance or {}), name,
                   blur_relation_noise_level(recs))

    # ------------------------------------------------------------------ queries
    @property
    def marked_records(self) -> list[dict[str, Any]]:
        """The cells that were marked (not in the curves), each with its ``reason``."""
        return [r for r in self.records if r.get("marked")]

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """Dense (S, M) AP surface for the policy and the ``measured`` mask.

        Empty bins take the AP of the nearest measured bin (distance in bin steps, ties to the lower σ
        and higher MTF, i.e. the milder corruption); ``measured`` is False there. Raises ``ValueError``
        if no bin was measured.
        """
        key = (self.ap_2d.tobytes(), self.count_2d.tobytes())
        cache = getattr(self, "_surface_cache", None)
        if cache is not None and cache[0] == key:
            return cache[1].copy(), cache[2].copy()
        measured = self.count_2d > 0
        if not measured.any():
            raise ValueError(f"IOPC {self.name!r} has no measured bin; cannot build a surface")
        si, mj = np.nonzero(measured)
        gi, gj = np.meshgrid(np.arange(self.sigma_bins.size), np.arange(self.mtf_bins.size), indexing="ij")
        d = (gi[..., None] - si) ** 2 + (gj[..., None] - mj) ** 2 + 1e-6 * si - 1e-9 * mj  # ties: milder bin
        k = np.argmin(d, axis=-1)
        filled = self.ap_2d[si[k], mj[k]]
        surf = np.where(measured, self.ap_2d, filled)
        self._surface_cache = (key, surf, measured)
        return surf.copy(), measured.copy()

    def interpolate(self, sigma: np.ndarray | float, mtf: np.ndarray | float) -> np.ndarray:
        """AP at continuous (σ [DN], MTF̃): bilinear between bin centres of :meth:`surface`, clamped to
        the outermost bins. Vectorised over any broadcastable shapes. σ must be finite and >= 0, MTF̃ in [0, 1]
        (``TypeError``/``ValueError`` naming the value otherwise); NaN gives NaN."""
        surf, _ = self.surface()
        return _bilinear(surf, self.sigma_bins, self.mtf_bins, _query(sigma, "sigma [DN]"), _query(mtf, "mtf", 1.0))

    def length_from_mtf(self, mtf: np.ndarray | float) -> np.ndarray:
        """MB_L(MTF̃): motion length [px] of a blur indicator value, by inverting the relation (linear
        interpolation; clamped to the swept lengths), so that ``mtf_from_length(length_from_mtf(v)) = v`` within the
        relation's range. A value the relation holds over a flat stretch maps to the stretch's smallest length (the
        least blur that reads it); a value below the stretch interpolates from its largest length. NaN stays NaN.
        Values outside [0, 1], and a relation that does not fall at all, are refused (``ValueError``)."""
        if self.blur_length_px.size < 2:
            raise ValueError(f"IOPC {self.name!r} has no MTF → motion-length relation (needs ≥ 2 swept lengths)")
        L, m = self.blur_length_px, self.blur_mtf  # L increasing, m non-increasing (checked on construction)
        if not m[-1] < m[0]:
            raise ValueError(f"IOPC {self.name!r}: its MTF → motion-length relation {m.tolist()} does not fall with the "
                             "motion length, so no MTF value tells a length (sweep lengths that blur the frames)")
        q = _query(mtf, "mtf", 1.0)
        out = np.full(q.shape, L[0])  # at or above the first value: the shortest swept length
        # segments from the far end to the near one, so that where values repeat the smallest length is written last
        for i in range(L.size - 2, -1, -1):
            if m[i] > m[i + 1]:
                inside = (q <= m[i]) & (q >= m[i + 1])
                with np.errstate(invalid="ignore"):
                    t = (m[i] - q) / (m[i] - m[i + 1])
                out = np.where(inside, L[i] + t * (L[i + 1] - L[i]), out)
            else:
                out = np.where(q == m[i], L[i], out)
        out = np.where(q < m[-1], L[int(np.argmax(m == m[-1]))], out)  # below the range: the least length reading its end
        return np.where(np.isnan(q), np.nan, out)

    def mtf_from_length(self, length_px: np.ndarray | float) -> np.ndarray:
        """The relation's MTF̃ at a motion length [px] (linear interpolation, clamped to the swept lengths); lengths
        must be finite and >= 0 px (NaN gives NaN)."""
        if self.blur_length_px.size < 2:
            raise ValueError(f"IOPC {self.name!r} has no MTF → motion-length relation (needs ≥ 2 swept lengths)")
        return np.interp(_query(length_px, "length_px [px]"), self.blur_length_px, self.blur_mtf)

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (NaN → null)."""
        return _jsonable(
            {
                "format": "camhealth-iopc",
                "version": FORMAT_VERSION,
                "name": self.name,
                "sigma_bins_dn": self.sigma_bins,
                "mtf_bins": self.mtf_bins,
                "ap_2d": self.ap_2d,
                "count_2d": self.count_2d,
                "ap_sigma": self.ap_sigma,
                "count_sigma": self.count_sigma,
                "ap_mtf": self.ap_mtf,
                "count_mtf": self.count_mtf,
                "blur_relation": {"length_px": self.blur_length_px, "mtf": self.blur_mtf,
                                  "noise_level_dn": self.blur_noise_level_dn},
                "records": self.records,
                "provenance": self.provenance,
            }
        )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "IOPC":
        """Inverse of :meth:`to_dict`. The records are checked as :meth:`from_records` checks them (every record has
        ``sigma_tilde``, ``mtf_tilde``, ``ap``, ``length_px`` and ``noise_level_dn`` as numbers in their ranges, and
        ``marked``, where present, is a boolean); a ``ValueError`` names the record, the field, the value and what is
        allowed."""
        if data.get("format") != "camhealth-iopc":
            raise ValueError("not a camhealth IOPC file (missing format: camhealth-iopc)")
        version = data.get("version", 0)
        if not (isinstance(version, (int, np.integer)) and not isinstance(version, (bool, np.bool_)) and version >= 0):
            raise ValueError(f"version = {version!r} is out of the allowed range: an integer in [0, {FORMAT_VERSION}] "
                             "(the file layouts this camhealth reads)")
        if version > FORMAT_VERSION:
            raise ValueError(f"IOPC file version {version} is newer than this camhealth ({FORMAT_VERSION})")
        rel = data.get("blur_relation", {"length_px": [], "mtf": []})
        if not isinstance(rel, Mapping) or not {"length_px", "mtf"} <= set(rel):
            raise ValueError(f"blur_relation must be an object with length_px and mtf, got {_typed(rel)}")
        raw_records = data.get("records", [])
        if not isinstance(raw_records, list) or not all(isinstance(r, Mapping) for r in raw_records):
            raise ValueError(f"records must be a list of objects (one per sweep cell), got {_typed(raw_records)}")
        provenance = data.get("provenance", {})
        if not isinstance(provenance, Mapping):
            raise ValueError(f"provenance must be an object, got {_typed(provenance)}")
        for key in ("estimator_specs", "frames", "config"):
            if key in provenance and provenance[key] is not None and not isinstance(provenance[key], Mapping):
                raise ValueError(f"provenance.{key} must be an object, got {_typed(provenance[key])}")
        for what, value in (("provenance", provenance), ("records", raw_records)):
            if _nested_deeper(value, MAX_NESTING):  # it would load, and then fail to save (or print) by recursion
                raise ValueError(f"{what} is nested deeper than {MAX_NESTING} levels; a sweep writes a few")
        records = [{k: (float("nan") if v is None and k in ("sigma_tilde", "mtf_tilde", "ap") else v) for k, v in r.items()}
                   for r in raw_records]
        # the records as from_records checks them (a file edited by hand: "7" px, marked = 1 or "false")
        for k, r in enumerate(records):
            missing = [key for key in _RECORD_FIELDS if key not in r]
            if missing:
                raise ValueError(f"record {k} is missing {missing[0]!r}; it has {sorted(map(str, r))}")
            _check_record(k, r)
        # the arrays go to the constructor as read: it checks their types and ranges before any conversion
        return cls(
            sigma_bins=data["sigma_bins_dn"],
            mtf_bins=data["mtf_bins"],
            ap_2d=data["ap_2d"],
            count_2d=data["count_2d"],
            ap_sigma=data["ap_sigma"],
            count_sigma=data["count_sigma"],
            ap_mtf=data["ap_mtf"],
            count_mtf=data["count_mtf"],
            blur_length_px=rel["length_px"],
            blur_mtf=rel["mtf"],
            records=records,
            provenance=dict(provenance),
            name=str(data.get("name", "AP")),
            blur_noise_level_dn=rel.get("noise_level_dn"),
        )

    def save(self, path: str | Path) -> Path:
        """Write ``.json`` or ``.npz`` (by suffix). Returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.suffix == ".json":
            path.write_text(json.dumps(self.to_dict(), indent=1, ensure_ascii=False), encoding="utf-8")
        elif path.suffix == ".npz":
            d = self.to_dict()
            np.savez(
                path,
                sigma_bins_dn=self.sigma_bins, mtf_bins=self.mtf_bins, ap_2d=self.ap_2d, count_2d=self.count_2d,
                ap_sigma=self.ap_sigma, count_sigma=self.count_sigma, ap_mtf=self.ap_mtf, count_mtf=self.count_mtf,
                blur_length_px=self.blur_length_px, blur_mtf=self.blur_mtf,
                meta_json=np.array(json.dumps({**{k: d[k] for k in ("format", "version", "name", "records", "provenance")},
                                               "blur_noise_level_dn": d["blur_relation"]["noise_level_dn"]},
                                              ensure_ascii=False)),
            )
        else:
            raise ValueError(f"IOPC files are .json or .npz, got {path.name!r}")
        return path

    @classmethod
    def load(cls, path: str | Path) -> "IOPC":
        """Read a file written by :meth:`save` (JSON text in UTF-8). A file that is not one (not JSON or not a zip
        archive, a missing or malformed entry, JSON nested too deeply to read) is a ``ValueError``
        ``"<path>: not a camhealth IOPC file (<why>)"``; pickled arrays in a ``.npz`` are refused, never loaded."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"IOPC file not found: {path}")
        if path.suffix not in (".json", ".npz"):
            raise ValueError(f"IOPC files are .json or .npz, got {path.name!r}")
        try:
            d = json.loads(path.read_text(encoding="utf-8")) if path.suffix == ".json" else cls._npz_dict(path)
            if not isinstance(d, dict):
                raise TypeError(f"it holds a JSON {type(d).__name__}, not an object")
            return cls.from_dict(d)
        except _Refused as exc:
            raise ValueError(str(exc)) from None
        except (FileNotFoundError, PermissionError, IsADirectoryError):
            raise
        except RecursionError:  # the JSON parser's nesting limit
            raise ValueError(f"{path}: not a camhealth IOPC file (nested too deeply to read: an IOPC file's arrays "
                             "are at most 2-D)") from None
        except (OSError, EOFError, ValueError, TypeError, KeyError, AttributeError, IndexError, OverflowError,
                zipfile.BadZipFile, zlib.error) as exc:
            why = str(exc).splitlines()[0].strip() if str(exc).strip() else type(exc).__name__
            if why.startswith(("not a camhealth IOPC file (", "IOPC file version")):  # from_dict's own words
                raise ValueError(f"{path}: {why}") from None
            if isinstance(exc, KeyError):
                why = f"missing entry {exc.args[0]!r}"
            elif isinstance(exc, UnicodeDecodeError):
                why = f"not UTF-8 text: {exc.reason} at byte {exc.start}"
            elif isinstance(exc, json.JSONDecodeError):
                why = f"not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}"
            raise ValueError(f"{path}: not a camhealth IOPC file ({why})") from None

    @staticmethod
    def _npz_dict(path: Path) -> dict[str, Any]:
        """The :meth:`from_dict` mapping of an ``.npz`` file written by :meth:`save` (object arrays refused)."""
        if not zipfile.is_zipfile(path):
            raise ValueError("an .npz file is a zip archive; this one is not")
        _check_npz_sizes(path)
        with np.load(path, allow_pickle=False) as z:
            if "meta_json" not in z.files:
                raise KeyError("meta_json")
            try:
                meta = json.loads(str(z["meta_json"]))
                data = {k: z[k] for k in z.files if k != "meta_json"}
            except ValueError as exc:  # an object array: reading it would unpickle it
                if "allow_pickle" not in str(exc):
                    raise
                raise _Refused(f"{path}: holds pickled Python objects (object arrays); camhealth refuses pickled "
                               "arrays, an IOPC .npz holds plain numbers and a JSON string only") from None
        if not isinstance(meta, dict):
            raise TypeError(f"meta_json holds a JSON {type(meta).__name__}, not an object")
        d = dict(meta)
        d.update({k: v for k, v in data.items() if k not in ("blur_length_px", "blur_mtf")})
        d["blur_relation"] = {"length_px": data["blur_length_px"], "mtf": data["blur_mtf"],
                              "noise_level_dn": d.pop("blur_noise_level_dn", None)}
        for k in ("ap_2d", "ap_sigma", "ap_mtf", "sigma_bins_dn", "mtf_bins"):
            d[k] = d[k].tolist()
        return d

    # ------------------------------------------------------------------ plots
    def save_all(self, out_dir: str | Path) -> Path:
        """Write ``iopc.json``, ``iopc.npz`` and the heat-map figure ``iopc.png`` into ``out_dir``."""
        import matplotlib.pyplot as plt

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        self.save(out / "iopc.json")
        self.save(out / "iopc.npz")
        fig = self.figure()
        fig.savefig(out / "iopc.png", dpi=110)
        plt.close(fig)
        return out

    def figure(self, title: str | None = None):
        """Matplotlib figure: 2-D heat map (empty bins hatched, marked cells listed) and both 1-D curves."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 3, figsize=(14, 4.2), gridspec_kw={"width_ratios": [1.4, 1, 1]})
        ax = axes[0]
        data = np.ma.masked_invalid(self.ap_2d)
        im = ax.imshow(data, origin="lower", cmap="viridis", vmin=0, vmax=1, aspect="auto",
                       extent=(-0.5, self.mtf_bins.size - 0.5, -0.5, self.sigma_bins.size - 0.5))
        ax.set_facecolor("#dddddd")
        for (i, j), c in np.ndenumerate(self.count_2d):
            if c:
                ax.text(j, i, f"{self.ap_2d[i, j]:.2f}", ha="center", va="center", fontsize=7,
                        color="white" if self.ap_2d[i, j] < 0.6 else "black")
        ax.set_xticks(range(self.mtf_bins.size), [f"{v:.1f}" for v in self.mtf_bins])
        ax.set_yticks(range(self.sigma_bins.size), [f"{v:g}" for v in self.sigma_bins])
        ax.set_xlabel("MTF̃ (mean H/V at f_n = 0.1)")
        ax.set_ylabel("σ̃ [DN]")
        ax.set_title("2-D IOPC: AP (grey = no cell)")
        fig.colorbar(im, ax=ax, label="AP")
        ax = axes[1]
        ok = self.count_sigma > 0
        ax.plot(self.sigma_bins[ok], self.ap_sigma[ok], "o-")
        ax.set_xlabel("σ̃ [DN]"), ax.set_ylabel("AP"), ax.set_ylim(-0.02, 1.02), ax.set_title("isolated noise")
        ax.grid(alpha=0.3)
        ax = axes[2]
        ok = self.count_mtf > 0
        ax.plot(self.mtf_bins[ok], self.ap_mtf[ok], "o-")
        ax.set_xlabel("MTF̃"), ax.set_ylabel("AP"), ax.set_ylim(-0.02, 1.02), ax.set_title("isolated motion blur")
        ax.grid(alpha=0.3)
        n_marked = len(self.marked_records)
        fig.suptitle((title or self.name) + (f"  ({n_marked} marked cell(s) not in the curves)" if n_marked else ""))
        fig.tight_layout()
        return fig


#: Deepest nesting of objects and lists an IOPC file's ``provenance`` and ``records`` may have (a sweep writes 4).
MAX_NESTING = 32


def _nested_deeper(x: Any, limit: int) -> bool:
    """Whether objects/lists in ``x`` nest deeper than ``limit`` levels (walked without recursion)."""
    stack = [(x, 0)]
    while stack:
        v, depth = stack.pop()
        if isinstance(v, Mapping):
            children = list(v.values())
        elif isinstance(v, (list, tuple)):
            children = list(v)
        else:
            continue
        if depth >= limit:
            return True
        stack.extend((c, depth + 1) for c in children)
    return False


#: Largest array an IOPC ``.npz`` may hold, in bytes (an IOPC of 1000 × 1000 bins holds 8 MB per array).
MAX_NPZ_ARRAY_BYTES = 64 * 2**20


def _check_npz_sizes(path: Path) -> None:
    """Refuse an ``.npz`` whose members would be larger than :data:`MAX_NPZ_ARRAY_BYTES` once read — by the size the
    archive declares (a compressed "zip bomb") or by the shape an array's header claims (numpy allocates that shape
    before it reads) — before anything is decompressed or allocated (``ValueError``)."""
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if info.file_size > MAX_NPZ_ARRAY_BYTES + 4096:
                raise ValueError(f"member {info.filename!r} declares {info.file_size} bytes uncompressed, more than an "
                                 f"IOPC holds (at most {MAX_NPZ_ARRAY_BYTES} bytes per array)")
            if not info.filename.endswith(".npy"):
                continue
            with zf.open(info) as fh:
                try:
                    version = np.lib.format.read_magic(fh)
                    shape, _, dtype = (np.lib.format.read_array_header_1_0(fh) if version == (1, 0)
                                       else np.lib.format.read_array_header_2_0(fh))
                except ValueError as exc:
                    raise ValueError(f"member {info.filename!r} is not a numpy array file ({exc})") from None
            n = 1
            for d in shape:
                n *= int(d)
            if n * max(dtype.itemsize, 1) > MAX_NPZ_ARRAY_BYTES:
                raise ValueError(f"member {info.filename!r} claims an array of shape {tuple(shape)} ({dtype}), more than "
                                 f"an IOPC holds (at most {MAX_NPZ_ARRAY_BYTES} bytes per array)")


def _typed(value: Any) -> str:
    """A value as a file holds it, shortened for a message: its type and the start of its repr."""
    text = repr(value)
    return f"{type(value).__name__} {text[:60] + '…' if len(text) > 60 else text}"


def _bilinear(surf: np.ndarray, xs: np.ndarray, ys: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``surf[i, j]`` given at (xs[i], ys[j]); clamped outside."""
    x, y = np.broadcast_arrays(np.clip(x, xs[0], xs[-1]), np.clip(y, ys[0], ys[-1]))
    i = np.clip(np.searchsorted(xs, x, side="right") - 1, 0, xs.size - 2)
    j = np.clip(np.searchsorted(ys, y, side="right") - 1, 0, ys.size - 2)
    tx = (x - xs[i]) / (xs[i + 1] - xs[i])
    ty = (y - ys[j]) / (ys[j + 1] - ys[j])
    return (
        surf[i, j] * (1 - tx) * (1 - ty) + surf[i + 1, j] * tx * (1 - ty)
        + surf[i, j + 1] * (1 - tx) * ty + surf[i + 1, j + 1] * tx * ty
    )
