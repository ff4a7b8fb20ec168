"""``IOPCCallback``: measure the IOPCs of a frozen detector at the end of ``fit`` (thesis Sec. 4.4.1).

Attach it to the Trainer that trains a blur or noise estimator and, when training ends, it sweeps the
blur × noise grid (:mod:`camhealth.iopc.sweep`) with the *just-trained* module as that estimator — if
the module is one — and a configured estimator for the other quantity, then writes ``iopc.json`` /
``iopc.npz`` / ``iopc.png`` and logs the heat map and curves to every TensorBoard logger of the Trainer.

The module counts as an estimator if it has ``as_estimator()`` (returning an object with the
inference contract), itself has ``kind``, ``patch_size``, ``metadata_set`` and ``predict``, or is a
camhealth ``EstimatorModule`` (exported and re-loaded through ``camhealth.export`` /
``camhealth.inference``, see :func:`module_estimator`); its ``kind`` (``"mtf"`` or a noise kind) says
which role it takes. The module is switched to eval mode and run without gradients during the sweep,
and its training mode is restored afterwards.

Distribution. Inside a running ``fit`` a second Trainer cannot be started, so the callback splits the
cells over the ranks itself (rank r takes cells r, r + W, … of the grid, whatever the shared cache holds
when it gets there, and skips those already cached), each rank runs its share on its own device, the
ranks meet at a barrier and rank 0 reads all cells from the shared cache and writes the curves. With one
process this is a plain loop with a progress bar. For the standalone sweep use ``python -m camhealth.iopc``,
which runs the cells through ``Trainer.predict``.

Example::

    from lightning_modules.iopc_callback import IOPCCallback
    trainer = L.Trainer(callbacks=[IOPCCallback(noise_estimator="physics")])   # module = MTF estimator
    trainer.fit(mtf_module, datamodule=BlurDataModule())
"""

from __future__ import annotations

import math
import numbers
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback

from camhealth.iopc.curves import IOPC
from camhealth.iopc.estimation import NOISE_KINDS, resolve_estimator
from camhealth.iopc.sweep import IOPCSweep, SweepConfig, log_iopc

__all__ = ["IOPCCallback", "module_estimator"]


def module_estimator(module: Any, export_dir: str | Path | None = None) -> Any | None:
    """The estimator a LightningModule offers, or ``None`` if it is not an estimator.

    In this order: ``module.as_estimator()``; the module itself if it has ``kind``, ``patch_size``,
    ``metadata_set`` and ``predict``; a camhealth :class:`~lightning_modules.EstimatorModule` (non-empty
    ``kind`` and ``export_module``) exported with :func:`camhealth.export.export_weights` to
    ``export_dir`` and loaded back with :func:`camhealth.inference.load_estimator` (the public path of
    issue 4; the copy runs on the CPU and leaves the training module untouched).
    """
    as_est = getattr(module, "as_estimator", None)
    if callable(as_est):
        return as_est()
    if getattr(module, "kind", None) and all(hasattr(module, a) for a in ("patch_size", "metadata_set")) \
            and callable(getattr(module, "predict", None)):
        return module
    if getattr(module, "kind", "") and callable(getattr(module, "export_module", None)) and export_dir is not None:
        from camhealth.export import export_weights
        from camhealth.inference import load_estimator

        rank = getattr(getattr(module, "_trainer", None), "global_rank", 0) or 0
        was_training = module.training
        try:
            path = export_weights(module, Path(export_dir) / f"trained_{module.kind}_rank{rank}.pt")
        finally:
            module.train(was_training)  # export puts the module in eval mode
        return load_estimator(path)
    return None


def _check_estimator_spec(spec: Any, role: str, name: str) -> None:
    """An estimator spec of :class:`IOPCCallback` (``noise_estimator`` / ``mtf_estimator``) checked without loading
    anything: ``None``, ``"physics"``, ``"immerkaer"`` (noise only), a shipped estimator's name or an existing file for
    :func:`camhealth.inference.load_estimator`, or an object with the inference contract (checked as
    :func:`~camhealth.iopc.estimation.resolve_estimator` checks it). Errors name the argument and its value."""
    if spec is None:
        return
    if not isinstance(spec, str):
        try:
            resolve_estimator(spec, role)
        except (TypeError, ValueError) as err:
            raise type(err)(f"{name} = {spec!r:.80}: {err}") from None
        return
    key = spec.strip()
    if key.lower() == "physics":
        return
    if key.lower() == "immerkaer":
        if role != "noise":
            raise ValueError(f"{name} = {spec!r}: 'immerkaer' is a noise estimator; it cannot estimate the MTF")
        return
    from camhealth.inference import PHYSICS_NOISE_MODEL, RETIRED, shipped_models

    if key == PHYSICS_NOISE_MODEL:
        if role != "noise":
            raise ValueError(f"{name} = {spec!r} is a noise estimator; it cannot estimate the MTF")
        return
    if key in RETIRED:
        raise ValueError(f"{name} = {spec!r}: the shipped model is retired: {RETIRED[key]}")
    shipped = shipped_models()
    if key in shipped:
        return
    path = Path(key)
    if not path.is_file():
        names = sorted([*shipped, PHYSICS_NOISE_MODEL])
        stand_ins = "'physics' or 'immerkaer'" if role == "noise" else "'physics'"
        raise FileNotFoundError(f"{name} = {spec!r} is neither a shipped estimator ({names}), {stand_ins}, nor an existing "
                                "estimator file (.pt, .ckpt, .pt2, .onnx)")


def _check_frame_slice(frame_slice: Any) -> tuple[int, int | None, int]:
    """``(start, stop, stride)``: integers (``stop`` may be None), ``stride`` >= 1; ``ValueError`` naming the value."""
    def integer(v: Any) -> bool:
        return isinstance(v, numbers.Integral) and not isinstance(v, bool)

    try:
        start, stop, stride = frame_slice
    except (TypeError, ValueError):
        raise ValueError(f"frame_slice = {frame_slice!r} must be (start, stop, stride): three values") from None
    if not (integer(start) and (stop is None or integer(stop)) and integer(stride) and stride >= 1):
        raise ValueError(f"frame_slice = {tuple(frame_slice)!r} must be (start, stop, stride): integers (stop may be None), "
                         "stride >= 1")
    return int(start), None if stop is None else int(stop), int(stride)


class IOPCCallback(Callback):
    """Run the IOPC sweep at the end of ``fit`` (and optionally every n epochs) and log the curves.

    Args:
        detector: the frozen detector: an object with the protocol, an ``nn.Module`` (wrapped in
            :class:`~camhealth.detection.TorchDetector`), or ``"hog"`` (OpenCV people detector).
        frames: clean frames N×1×H×W in [0, 1]; ``None`` loads ``source[start:stop:stride]``.
        source, frame_slice: image source spec and ``(start, stop, stride)`` used when ``frames`` is None.
        ground_truth: one {boxes, labels} per frame; ``None`` → pseudo ground truth (detector on the clean
            frames, score >= ``pseudo_score``).
        noise_estimator, mtf_estimator: estimator specs or objects for the roles the module does not take
            (default: the trained estimators ``noise_source_min`` / ``mtf``).
        use_module_estimator: use the trained module for its role when it is an estimator.
        config: :class:`~camhealth.iopc.sweep.SweepConfig` (grid, sensor, bins, …).
        out_dir: where to write the files (default ``<trainer.log_dir or default_root_dir>/iopc``).
        cache_dir: per-cell cache (default ``<out_dir>/cache``; must be shared by all ranks).
        every_n_epochs: also run after every n-th training epoch (``None``: only at the end of fit).
        progress: show a progress bar.

    The arguments are checked when the callback is built, before any training step: a detector other than ``"hog"``,
    an object or an ``nn.Module``; ``frames`` that are not N×1×H×W in [0, 1]; a ``source`` that names no image source
    (when ``frames`` is None); a ``frame_slice`` that is not three integers with stride >= 1; ``pseudo_score`` outside
    [0, 1]; an estimator name that is neither shipped nor an existing file (estimators are loaded at the sweep) — each
    a ``ValueError``, ``TypeError`` or ``FileNotFoundError`` naming the argument and its value.
    """

    def __init__(
        self,
        detector: Any = "hog",
        frames: torch.Tensor | None = None,
        source: str = "street",
        frame_slice: tuple[int, int | None, int] = (0, 25, 3),
        ground_truth: list[dict[str, torch.Tensor]] | None = None,
        pseudo_score: float = 0.6,
        noise_estimator: Any = None,
        mtf_estimator: Any = None,
        use_module_estimator: bool = True,
        config: SweepConfig | None = None,
        out_dir: str | Path | None = None,
        cache_dir: str | Path | None = None,
        every_n_epochs: int | None = None,
        progress: bool = True,
    ) -> None:
        super().__init__()
        if every_n_epochs is not None and (isinstance(every_n_epochs, bool) or not isinstance(every_n_epochs, numbers.Real)
                                           or not math.isfinite(every_n_epochs) or int(every_n_epochs) != every_n_epochs
                                           or every_n_epochs < 1):
            raise ValueError(f"every_n_epochs = {every_n_epochs!r} must be a positive integer or None")
        if isinstance(detector, str):
            if detector != "hog":
                raise ValueError(f"detector = {detector!r}: give 'hog', a detector object or an nn.Module")
        elif not (isinstance(detector, torch.nn.Module) or callable(detector)):
            raise TypeError(f"detector = {detector!r:.80}: give 'hog', a callable detector object or an nn.Module, got "
                            f"{type(detector).__name__}")
        if isinstance(pseudo_score, bool) or not isinstance(pseudo_score, numbers.Real) or not 0 <= pseudo_score <= 1:
            raise ValueError(f"pseudo_score = {pseudo_score!r} must lie in [0, 1] (the score a clean detection needs to "
                             "become pseudo ground truth)")
        frame_slice = _check_frame_slice(frame_slice)
        if frames is not None:
            from camhealth.estimators._common import check_patches

            check_patches(frames, "frames")
        else:
            from camhealth.data.sources import source_options

            try:
                source_options(source)  # what the source names (it is read at the sweep)
            except (FileNotFoundError, ValueError, TypeError) as err:
                raise type(err)(f"source = {source!r}: {err}") from None
        _check_estimator_spec(noise_estimator, "noise", "noise_estimator")
        _check_estimator_spec(mtf_estimator, "mtf", "mtf_estimator")
        self.detector_spec = detector
        self.frames = frames
        self.source, self.frame_slice = source, frame_slice
        self.ground_truth, self.pseudo_score = ground_truth, float(pseudo_score)
        self.noise_spec, self.mtf_spec = noise_estimator, mtf_estimator
        self.use_module_estimator = bool(use_module_estimator)
        self.config = (config or SweepConfig()).validate()
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.cache_dir = Path(cache_dir) if cache_dir is not None else None
        self.every_n_epochs = every_n_epochs
        self.progress = progress
        self.iopc: IOPC | None = None
        self._detector: Any = None
        self._ids: list[str] | None = None

    # ------------------------------------------------------------------ setup
    def _resolve_detector(self) -> Any:
        if self._detector is None:
            from camhealth.detection import HOGPeopleDetector, TorchDetector

            d = self.detector_spec
            if isinstance(d, str):
                if d != "hog":
                    raise ValueError(f"detector = {d!r}: give 'hog', a detector object or an nn.Module")
                d = HOGPeopleDetector()
            elif isinstance(d, torch.nn.Module):
                d = TorchDetector(d)
            if not callable(d):
                raise TypeError(f"detector must be callable, got {type(d).__name__}")
            self._detector = d
        return self._detector

    def _data(self) -> tuple[torch.Tensor, list[dict[str, torch.Tensor]], list[str]]:
        if self.frames is None:
            from camhealth.iopc.cli import FrameSelection, load_frames

            start, stop, stride = self.frame_slice
            self.frames, self._ids, _ = load_frames(self.source, FrameSelection(start, stop, stride))
        if self._ids is None:
            self._ids = [f"frame{i}" for i in range(self.frames.shape[0])]
        if self.ground_truth is None:
            from camhealth.detection import pseudo_ground_truth

            self.ground_truth = pseudo_ground_truth(self._resolve_detector(), self.frames, self.pseudo_score)
        return self.frames, self.ground_truth, self._ids

    def _estimators(self, pl_module: L.LightningModule, export_dir: Path) -> tuple[Any, Any, str]:
        own = None
        if self.use_module_estimator:
            was_training = pl_module.training
            try:
                own = module_estimator(pl_module, export_dir)
            finally:
                pl_module.train(was_training)
        noise_spec, mtf_spec, role = self.noise_spec, self.mtf_spec, "none"
        if own is not None:
            kind = getattr(own, "kind", None)
            if kind == "mtf":
                mtf_spec, role = own, "mtf"
            elif kind in NOISE_KINDS:
                noise_spec, role = own, "noise"
            else:
                raise ValueError(f"the trained module has estimator kind {kind!r}; expected 'mtf' or one of {list(NOISE_KINDS)}")
        return resolve_estimator(noise_spec, "noise"), resolve_estimator(mtf_spec, "mtf"), role

    def _out_dir(self, trainer: L.Trainer) -> Path:
        if self.out_dir is not None:
            return self.out_dir
        base = trainer.log_dir or trainer.default_root_dir
        return Path(base) / "iopc"

    # ------------------------------------------------------------------ hooks
    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.run(trainer, pl_module)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.every_n_epochs is not None and (trainer.current_epoch + 1) % self.every_n_epochs == 0:
            self.run(trainer, pl_module, tag=f"iopc/epoch{trainer.current_epoch}")

    def run(self, trainer: L.Trainer, pl_module: L.LightningModule, tag: str = "iopc") -> IOPC | None:
        """Sweep now; returns the IOPC on rank 0 (``None`` on the other ranks)."""
        frames, gt, ids = self._data()
        out = self._out_dir(trainer)
        noise, mtf, role = self._estimators(pl_module, out)
        cache = self.cache_dir or out / "cache"
        sweep = IOPCSweep(frames, gt, self._resolve_detector(), noise, mtf, self.config, cache_dir=cache,
                          frame_ids=ids, provenance={"trained_module_role": role,
                                                     "trained_module": type(pl_module).__name__,
                                                     "global_step": int(trainer.global_step)})
        was_training = pl_module.training
        pl_module.eval()
        try:
            with torch.no_grad():
                sweep.run_local(pl_module.device, trainer.global_rank, trainer.world_size,
                                progress=self.progress and trainer.is_global_zero)
        finally:
            pl_module.train(was_training)
        trainer.strategy.barrier("iopc_sweep")
        if not trainer.is_global_zero:
            return None
        iopc = sweep.to_iopc(sweep.collect())
        iopc.save_all(out)
        for logger in trainer.loggers:
            log_iopc(getattr(logger, "experiment", None), iopc, step=int(trainer.global_step), tag=tag)
        self.iopc = iopc
        return iopc
