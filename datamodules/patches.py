"""Patch extraction from clean image sources, and the shared base of the corruption DataModules.

:class:`PatchDataset` cuts square patches from the (cached, in-memory) images of one split:

* ``stage="train"``: ``patches_per_image`` random crops per image and epoch, each with a random flip /
  rot90 (the 8 symmetries of the square) and a uniform brightness offset of ±``brightness_dn`` DN (the
  thesis's ±20 DN augmentation; the result is clipped to [0, 1]). Randomness: torch's global RNG (in
  DataLoader workers, PyTorch seeds each worker from the main process, so ``seed_everything`` makes runs
  reproducible), or the dataset's ``generator`` when set (the DataModule sets one per rank in a
  multi-process run without workers).
* ``stage="val"``/``"test"``: a FIXED list of crops decided at construction by a ``torch.Generator``
  seeded with ``seed`` (no flips, no brightness change), so the same seed gives the same patches.

Hard patches: a crop is *near-uniform* when its standard deviation is below ``min_std_dn`` DN and
*clipped* when more than ``max_clipped_fraction`` of its pixels are at 0 or 255 DN (after the brightness
offset). Unless ``keep_hard_patches`` is set, such crops are redrawn up to ``max_tries`` times; when an
image yields no acceptable crop in ``max_tries`` draws, the last draw is kept (counted in ``n_fallback`` and
marked ``fallback`` in its sample), so an epoch always has its full length. An image that gives no acceptable crop
at all (a flat, lens-cap or saturated frame: all its fixed val/test crops, or ``max_tries`` probe crops of a
training image, fail) is named in a ``UserWarning`` when the split is built.

:class:`PatchDataModule` is the shared machinery of :class:`~datamodules.NoiseDataModule` and
:class:`~datamodules.BlurDataModule`: source, leak-free split, image cache, loaders, the
``on_after_batch_transfer`` corruption hook and throughput measurement, and the state of the training data
stream that a checkpoint saves so that a resumed run continues it (:meth:`PatchDataModule.state_dict`).
"""

from __future__ import annotations

import hashlib
import math
import numbers
import time
import warnings
from typing import Any, Callable, Mapping, Sequence

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset, RandomSampler

from camhealth.physics.image_formation import check_rng
from camhealth.data import build_source, group_key, split_ids
from camhealth.data.sources import check_source_options

__all__ = ["PatchDataset", "PatchDataModule", "check_flag", "check_patch_options", "is_hard_patch", "STAGES", "rank_seed",
           "sample_seed", "MAX_SEED"]

#: Dataset stages. ``"predict"`` uses the test split.
STAGES = ("train", "val", "test")

_LOW = 0.5 / 255.0  # a pixel at 0 DN (after rounding to 8 bits)
_HIGH = 254.5 / 255.0  # a pixel at 255 DN

#: Largest ``seed`` of a DataModule: its validation and test crops are drawn by ``torch.Generator``s seeded with
#: ``seed + 1`` and ``seed + 2``, and a generator takes seeds below 2**64.
MAX_SEED = 2**64 - 3


def _check_seed(seed: Any, name: str = "seed", high: int = MAX_SEED) -> int:
    """``seed`` as an int in [0, ``high``]: ``TypeError`` for another type, ``ValueError`` naming the range otherwise."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise TypeError(f"{name} = {seed!r} must be an integer in [0, {high}], got {type(seed).__name__}")
    if not 0 <= seed <= high:
        raise ValueError(f"{name} = {seed} must be >= 0 and <= {high}, an integer in [0, {high}]"
                         + (" (2**64 − 3: the validation and test crops are seeded with seed + 1 and seed + 2)"
                            if high == MAX_SEED else ""))
    return int(seed)


def is_hard_patch(patch: torch.Tensor, min_std_dn: float = 2.0, max_clipped_fraction: float = 0.05) -> bool:
    """True if ``patch`` (C×H×W in [0, 1]) is near-uniform (std < ``min_std_dn`` DN) or clipped (more than
    ``max_clipped_fraction`` of its pixels at 0 or 255 DN)."""
    if float(patch.std()) * 255.0 < min_std_dn:
        return True
    clipped = ((patch <= _LOW) | (patch >= _HIGH)).float().mean()
    return float(clipped) > max_clipped_fraction


def _hash_seed(*parts: Any) -> int:
    key = "\x1f".join(str(p) for p in parts).encode()
    return int.from_bytes(hashlib.blake2b(key, digest_size=8).digest(), "big") >> 2


def sample_seed(seed: int, stage: str, index: int) -> int:
    """Seed of the fixed corruption of one validation/test patch: a hash of (seed, stage, dataset index of the
    patch), so a patch is corrupted identically in every epoch and run, whatever the batch size, the number of
    DataLoader workers or of devices."""
    return _hash_seed(int(seed), stage, int(index))


def rank_seed(draw: int, rank: int) -> int:
    """Seed of one training batch's corruption on one process of a multi-process run: a hash of a draw of
    torch's global generator (the same on every rank after ``seed_everything``) and the global rank."""
    return _hash_seed("train", int(draw), int(rank))


class PatchDataset(Dataset):
    """Square patches from in-memory images of one split.

    Args:
        images: gray images ``1×H×W`` in [0, 1], each at least ``patch_size`` on both sides.
        ids: their source ids (same length), reported per sample as ``image_id``.
        patch_size: side P of the square patches [px].
        stage: ``"train"`` (random crops + augmentation) or ``"val"``/``"test"`` (fixed crops).
        patches_per_image: patches per image and epoch (train) / fixed crops per image (val, test).
        seed: seed of the fixed val/test crops, an integer in [0, 2**64 − 1] (for training only the seed of the probe
            crops that find featureless images; the training crops use torch's global RNG).
        flips: random horizontal/vertical flips (train only).
        rot90: random rotations by multiples of 90° (train only).
        brightness_dn: uniform brightness offset in [−b, b] DN, then clipped to [0, 255] DN (train only).
        min_std_dn: crops with a standard deviation below this [DN] are near-uniform.
        max_clipped_fraction: crops with more pixels than this fraction at 0 or 255 DN are clipped.
        keep_hard_patches: keep near-uniform and clipped crops (robustness tests) instead of redrawing.
        max_tries: redraws per patch before the last draw is kept.

    Each sample is a dict ``{"clean": 1×P×P float32, "index": int, "image_id": str, "stage": str, "fallback": bool}``
    (``fallback``: the crop is a near-uniform or clipped one, kept after ``max_tries`` draws).

    :attr:`featureless` lists the ids of the images that give no acceptable crop: for val/test those whose fixed
    crops all fell back, for training those of which ``max_tries`` probe crops (drawn at construction with a generator
    seeded by ``seed``, not torch's global one) all fail. Empty with ``keep_hard_patches``.
    """

    def __init__(
        self,
        images: Sequence[torch.Tensor],
        ids: Sequence[str],
        patch_size: int,
        stage: str = "train",
        patches_per_image: int = 64,
        seed: int = 0,
        flips: bool = True,
        rot90: bool = True,
        brightness_dn: float = 20.0,
        min_std_dn: float = 2.0,
        max_clipped_fraction: float = 0.05,
        keep_hard_patches: bool = False,
        max_tries: int = 20,
    ) -> None:
        if stage not in STAGES:
            raise ValueError(f"stage = {stage!r} must be one of {list(STAGES)}")
        if len(images) != len(ids):
            raise ValueError(f"got {len(images)} images but {len(ids)} ids")
        if not images:
            raise ValueError(f"the {stage} split has no images")
        _check_positive_int(patch_size, "patch_size")
        _check_positive_int(patches_per_image, "patches_per_image")
        _check_seed(seed, "seed", 2**64 - 1)
        check_patch_options(flips=flips, rot90=rot90, brightness_dn=brightness_dn, min_std_dn=min_std_dn,
                            max_clipped_fraction=max_clipped_fraction, keep_hard_patches=keep_hard_patches,
                            max_tries=max_tries)
        for img, image_id in zip(images, ids):
            if img.ndim != 3 or img.shape[0] != 1:
                raise ValueError(f"image {image_id!r} must be a gray 1×H×W tensor, got shape {tuple(img.shape)}")
            if min(img.shape[-2:]) < patch_size:
                raise ValueError(
                    f"image {image_id!r} is {img.shape[-2]}×{img.shape[-1]} px, smaller than the patch size {patch_size}"
                )
        self.images = list(images)
        self.ids = list(ids)
        self.patch_size = int(patch_size)
        self.stage = stage
        self.patches_per_image = int(patches_per_image)
        self.seed = int(seed)
        self.flips, self.rot90 = flips, rot90
        self.brightness_dn = float(brightness_dn)
        self.min_std_dn = float(min_std_dn)
        self.max_clipped_fraction = float(max_clipped_fraction)
        self.keep_hard_patches = keep_hard_patches
        self.max_tries = int(max_tries)
        self.n_fallback = 0
        #: generator of the training crops and augmentation (``None``: torch's global RNG)
        self.generator: torch.Generator | None = None
        #: fixed crops (N, 3): image, top, left (val/test only)
        self.crops: torch.Tensor | None = None
        #: whether each fixed crop is a fallback (val/test only)
        self.crop_fallback: list[bool] = []
        #: ids of the images that give no acceptable crop (see the class docstring)
        self.featureless: list[str] = []
        if stage != "train":
            self.crops = self._fixed_crops()
            per_image = [self.crop_fallback[i * self.patches_per_image:(i + 1) * self.patches_per_image]
                         for i in range(len(self.images))]
            self.featureless = [self.ids[i] for i, flags in enumerate(per_image) if all(flags)]
        elif not self.keep_hard_patches:
            self.featureless = self._probe_featureless()

    # ------------------------------------------------------------------ helpers
    def __len__(self) -> int:
        return len(self.images) * self.patches_per_image

    def _hard(self, patch: torch.Tensor) -> bool:
        return not self.keep_hard_patches and is_hard_patch(patch, self.min_std_dn, self.max_clipped_fraction)

    def _crop(self, i: int, top: int, left: int) -> torch.Tensor:
        p = self.patch_size
        return self.images[i][:, top : top + p, left : left + p]

    def _random_corner(self, i: int, generator: torch.Generator | None) -> tuple[int, int]:
        h, w = self.images[i].shape[-2:]
        top = int(torch.randint(h - self.patch_size + 1, (1,), generator=generator))
        left = int(torch.randint(w - self.patch_size + 1, (1,), generator=generator))
        return top, left

    def _fixed_crops(self) -> torch.Tensor:
        g = torch.Generator().manual_seed(self.seed)
        rows = []
        for i in range(len(self.images)):
            for _ in range(self.patches_per_image):
                for _ in range(self.max_tries):
                    top, left = self._random_corner(i, g)
                    if not self._hard(self._crop(i, top, left)):
                        self.crop_fallback.append(False)
                        break
                else:
                    self.n_fallback += 1
                    self.crop_fallback.append(True)
                rows.append((i, top, left))
        return torch.tensor(rows, dtype=torch.int64)

    def _probe_featureless(self) -> list[str]:
        """Ids of the training images of which ``max_tries`` crops (a generator of their own, seeded by ``seed``:
        torch's global one, which draws the training crops, is left alone) are all near-uniform or clipped."""
        g = torch.Generator().manual_seed(self.seed)
        out = []
        for i in range(len(self.images)):
            if all(self._hard(self._crop(i, *self._random_corner(i, g))) for _ in range(self.max_tries)):
                out.append(self.ids[i])
        return out

    def _augment(self, patch: torch.Tensor) -> torch.Tensor:
        if self.flips:
            if bool(torch.rand((), generator=self.generator) < 0.5):
                patch = patch.flip(-1)
            if bool(torch.rand((), generator=self.generator) < 0.5):
                patch = patch.flip(-2)
        if self.rot90:
            k = int(torch.randint(4, (1,), generator=self.generator))
            if k:
                patch = torch.rot90(patch, k, (-2, -1))
        if self.brightness_dn > 0:
            offset = (2.0 * float(torch.rand((), generator=self.generator)) - 1.0) * self.brightness_dn / 255.0
            patch = (patch + offset).clamp(0.0, 1.0)
        return patch

    # ------------------------------------------------------------------ access
    def __getitem__(self, index: int) -> dict[str, Any]:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"index {index} out of range for a {self.stage} PatchDataset of {n} patches")
        index %= n
        if self.crops is not None:
            i, top, left = (int(v) for v in self.crops[index])
            patch = self._crop(i, top, left)
            fallback = self.crop_fallback[index]
        else:
            i = index % len(self.images)
            fallback = False
            for _ in range(self.max_tries):
                top, left = self._random_corner(i, self.generator)
                patch = self._augment(self._crop(i, top, left))
                if not self._hard(patch):
                    break
            else:
                self.n_fallback += 1
                fallback = True
        return {
            "clean": patch.contiguous().clone(),
            "index": index,
            "image_id": self.ids[i],
            "stage": self.stage,
            "fallback": fallback,
        }

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(stage={self.stage!r}, images={len(self.images)}, patch_size={self.patch_size}, "
            f"patches={len(self)})"
        )


def _check_positive_int(v: Any, name: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{name} = {v!r} must be a positive int")
    return v


def check_flag(v: Any, name: str) -> bool:
    """``v`` if it is a real bool, else a ``ValueError`` naming the option (``bool("false")`` would be True)."""
    if not isinstance(v, bool):
        raise ValueError(f"{name} = {v!r} must be true or false (a bool)")
    return v


def _check_number(v: Any, name: str, low: float, high: float = math.inf) -> float:
    """``v`` as a float if it is a finite real number in [low, high] (a bool is none), else a ``ValueError`` naming it."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or not low <= v <= high:
        allowed = f"[{low:g}, {high:g}]" if math.isfinite(high) else f">= {low:g}"
        raise ValueError(f"{name} = {v!r} must be a finite number {'in ' if math.isfinite(high) else ''}{allowed}")
    return float(v)


def check_patch_options(
    flips: Any = True,
    rot90: Any = True,
    brightness_dn: Any = 20.0,
    min_std_dn: Any = 2.0,
    max_clipped_fraction: Any = 0.05,
    keep_hard_patches: Any = False,
    max_tries: Any = 20,
) -> None:
    """The augmentation and rejection options of :class:`PatchDataset` (and of the DataModules, which check them at
    construction): a ``ValueError`` naming the first bad value and its allowed range."""
    check_flag(flips, "flips")
    check_flag(rot90, "rot90")
    _check_number(brightness_dn, "brightness_dn", 0.0, 255.0)
    _check_number(min_std_dn, "min_std_dn", 0.0)
    _check_number(max_clipped_fraction, "max_clipped_fraction", 0.0, 1.0)
    check_flag(keep_hard_patches, "keep_hard_patches")
    _check_positive_int(max_tries, "max_tries")


def _folder_group(image_id: str) -> str:
    """Group by sub-folder: ``"clipA/0001.png"`` → ``"clipA"``; files at the root are their own group."""
    return image_id.rsplit("/", 1)[0] if "/" in image_id else group_key(image_id)


GROUP_KEYS: dict[str, Callable[[str], str]] = {"id": group_key, "folder": _folder_group}


class _TrainStream:
    """Where the training data stream of a single-process run without workers stands (see
    :meth:`PatchDataModule.state_dict`). Each training batch is fetched, then corrupted, then trained on; nothing else
    draws from torch's global generator but the validation loader (one number when a validation begins)."""

    VERSION = 1

    def __init__(self) -> None:
        #: at the start of the last batch fetched: ``step`` (global step), ``batch`` (its place in the epoch),
        #: ``seed`` (the epoch's order; None for the first batch, which draws it), ``rng`` (the generator before it)
        self.last: dict[str, Any] | None = None
        self.epoch_seed: int | None = None
        self.patches = self.batch_size = 0
        #: the global step at which a validation (not the sanity check) last showed a batch
        self.val_step: int | None = None
        #: a checkpoint's stream, applied at the first training batch of the resumed run
        self.resume: Mapping[str, Any] | None = None

    def mark(self, step: int, batch: int, seed: int | None) -> None:
        self.last = {"step": step, "batch": batch, "seed": seed, "rng": torch.get_rng_state()}

    def state(self, trainer) -> dict[str, Any] | None:
        last = self.last
        if trainer is None or last is None or trainer.world_size > 1 or trainer.accumulate_grad_batches != 1:
            return None
        n_batches = trainer.num_training_batches
        if not isinstance(n_batches, int) or n_batches < 1:
            return None
        step = trainer.global_step
        common = {"version": self.VERSION, "step": step, "patches": self.patches, "batch_size": self.batch_size}
        if last["step"] == step:  # stopped within this step, after its batch was begun: fetch that batch again
            return {**common, "batch": last["batch"], "seed": last["seed"], "rng": last["rng"].clone(), "draws": 0}
        if last["step"] != step - 1:
            return None
        # between two steps: the next batch is not begun; the generator stands where the next fetch finds it, less
        # the number a validation due after the last step draws when it begins, if it has not begun yet
        draws = int(self._validation_pending(trainer, step))
        nxt = last["batch"] + 1
        if nxt >= n_batches:  # the epoch is over: the next one begins (its loader draws a number, then its order)
            return {**common, "batch": 0, "seed": None, "rng": torch.get_rng_state(), "draws": draws + 1}
        seed = last["seed"] if last["seed"] is not None else self.epoch_seed
        return {**common, "batch": nxt, "seed": seed, "rng": torch.get_rng_state(), "draws": draws}

    def _validation_pending(self, trainer, step: int) -> bool:
        """A validation is due after the last step and has not begun (the resumed run skips it: its draw is made for
        it)."""
        if trainer.validating or trainer.sanity_checking or self.val_step == step:
            return False
        dm = trainer.datamodule
        if dm is None or getattr(dm, "datasets", {}).get("val") is None:
            return False
        try:  # Lightning's own decision, as the resumed run makes it
            loop = trainer.fit_loop.epoch_loop
            return bool(loop._should_check_val_fx(trainer.fit_loop._data_fetcher))
        except Exception:  # pragma: no cover - another Lightning
            return False

    def take_resume(self, trainer, patches: int, batch_size: int) -> Mapping[str, Any] | None:
        """The checkpoint's stream if it continues here (same patches and batch size, at this step), else ``None`` —
        with a warning naming what differs."""
        resume, self.resume = self.resume, None
        if resume is None:
            return None
        where = (resume.get("version"), resume.get("patches"), resume.get("batch_size"), resume.get("step"))
        here = (self.VERSION, patches, batch_size, None if trainer is None else trainer.global_step)
        if where != here:
            warnings.warn(
                "the checkpoint's training data stream (version, patches per epoch, batch size, step "
                f"{where}) does not continue here {here}: the resumed run draws its batches afresh",
                UserWarning,
                stacklevel=3,
            )
            return None
        return resume


class _TrainSampler(RandomSampler):
    """The training sampler of a single-process run without DataLoader workers: what ``RandomSampler`` draws (one
    number from torch's global generator when an epoch begins, then the order of the patches from a generator seeded
    with it), recording where the stream stands when each batch is begun, and continuing a checkpoint's stream at the
    first batch of a resumed run (:meth:`PatchDataModule.state_dict`)."""

    def __init__(self, data_source: Dataset, batch_size: int, drop_last: bool, module: "PatchDataModule") -> None:
        super().__init__(data_source)
        self.batch_size = int(batch_size)
        self.n_batches = len(data_source) // self.batch_size if drop_last else -(-len(data_source) // self.batch_size)
        self.module = module

    def __iter__(self):
        n = len(self.data_source)
        stream = self.module._stream
        trainer = self.module.trainer
        stream.patches, stream.batch_size = n, self.batch_size
        resume = stream.take_resume(trainer, n, self.batch_size)
        first, seed = 0, None
        if resume is not None:
            torch.set_rng_state(resume["rng"])
            for _ in range(int(resume["draws"])):  # (a DataLoader's draw when it begins: torch's _BaseDataLoaderIter)
                torch.empty((), dtype=torch.int64).random_()
            first, seed = int(resume["batch"]), resume["seed"]
        step = trainer.global_step if trainer is not None else None
        if step is not None:
            stream.mark(step, first, seed)
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())  # as RandomSampler
        stream.epoch_seed = seed
        order = torch.randperm(n, generator=torch.Generator().manual_seed(seed)).tolist()
        for k in range(first * self.batch_size, n):
            j = k // self.batch_size
            if k % self.batch_size == 0 and j > first and j < self.n_batches and trainer is not None:
                stream.mark(trainer.global_step, j, seed)  # batch j is begun
            yield order[k]


class PatchDataModule(L.LightningDataModule):
    """Shared base of the corruption DataModules (see the subclasses for the options).

    The DataLoaders yield *clean* patches; :meth:`on_after_batch_transfer` corrupts them on the device
    the batch was moved to (so a GPU run corrupts on the GPU) and returns the labelled dict batch.
    Training batches draw their corruption from torch's global RNG (seeded by Lightning's
    ``seed_everything``); in a multi-process run (DDP: ``trainer.world_size > 1``) each batch draws one number from
    it and corrupts with a generator seeded by :func:`rank_seed` ``(draw, global rank)``, so every rank gets its own
    corruption. Validation/test patches are corrupted one by one, each with a generator seeded by
    :func:`sample_seed` ``(seed, stage, patch index)``: the held-out sets are the same in every epoch and run,
    whatever the batch size, worker count or device count. In a multi-process run the validation/test loaders
    split the patches without repeating any (Lightning's ``UnrepeatedDistributedSampler``), so the synced
    held-out metrics are those of a single-process run. ``train_rng: counter`` draws the training
    batches' noise fields with counter-based random numbers (:mod:`camhealth.physics.counter_rng`: the same
    physics, about half the noise time on CPU); validation and test batches always use torch's generators, so
    the held-out sets do not depend on it.

    Which split a batch belongs to is read from its ``stage`` entry (set by :class:`PatchDataset`), so the
    hook also works without a Trainer (tests, notebooks); a batch without it counts as training when a
    Trainer is training, else as validation.

    **Resuming.** In a single-process run without DataLoader workers (``num_workers: 0``, the configs' setting) a
    checkpoint holds the state of the training data stream (:meth:`state_dict`: torch's CPU generator, which draws the
    crops, augmentation and corruption, and the epoch's order of the patches at the step reached), and a run resumed
    from it continues that stream: it trains on the batches the uninterrupted run would have seen, and ends with the
    same weights (one gradient-accumulation step per batch). With workers or several processes the stream is not
    saved (the workers' and ranks' generators live in other processes): a resumed run then draws its batches afresh.
    """

    #: default patch size of the subclass
    default_patch_size = 128

    def __init__(
        self,
        source: str = "default",
        source_kwargs: dict[str, Any] | None = None,
        patch_size: int | None = None,
        batch_size: int = 32,
        num_workers: int = 0,
        patches_per_image: int = 64,
        val_patches_per_image: int = 8,
        val_fraction: float = 0.15,
        test_fraction: float = 0.15,
        seed: int = 0,
        group_by: str = "id",
        flips: bool = True,
        rot90: bool = True,
        brightness_dn: float = 20.0,
        min_std_dn: float = 2.0,
        max_clipped_fraction: float = 0.05,
        keep_hard_patches: bool = False,
        max_tries: int = 20,
        pin_memory: bool = False,
        train_rng: str = "torch",
    ) -> None:
        super().__init__()
        if group_by not in GROUP_KEYS:
            raise ValueError(f"group_by = {group_by!r} must be one of {list(GROUP_KEYS)}")
        self.source_spec = source
        # a key the source does not take is refused now (naming it and those it takes), not dropped silently
        check_source_options(source, {} if source_kwargs is None else source_kwargs, "source_kwargs")
        self.source_kwargs = dict(source_kwargs or {})
        self.patch_size = _check_positive_int(self.default_patch_size if patch_size is None else patch_size, "patch_size")
        self.batch_size = _check_positive_int(batch_size, "batch_size")
        if isinstance(num_workers, bool) or not isinstance(num_workers, int) or num_workers < 0:
            raise ValueError(f"num_workers = {num_workers!r} must be an int >= 0")
        self.num_workers = num_workers
        self.patches_per_image = _check_positive_int(patches_per_image, "patches_per_image")
        self.val_patches_per_image = _check_positive_int(val_patches_per_image, "val_patches_per_image")
        # the split's own checks (fractions in [0, 1] summing to <= 1), now rather than at setup; the seed also seeds
        # the val/test crops (seed + 1, seed + 2): at most MAX_SEED
        self.seed = _check_seed(seed)
        split_ids([], val_fraction, test_fraction, self.seed)
        self.val_fraction, self.test_fraction = val_fraction, test_fraction
        self.group_by = group_by
        self.pin_memory = check_flag(pin_memory, "pin_memory")
        self.train_rng = check_rng(train_rng)
        check_patch_options(flips=flips, rot90=rot90, brightness_dn=brightness_dn, min_std_dn=min_std_dn,
                            max_clipped_fraction=max_clipped_fraction, keep_hard_patches=keep_hard_patches,
                            max_tries=max_tries)
        self._patch_kwargs = dict(
            flips=flips,
            rot90=rot90,
            brightness_dn=brightness_dn,
            min_std_dn=min_std_dn,
            max_clipped_fraction=max_clipped_fraction,
            keep_hard_patches=keep_hard_patches,
            max_tries=max_tries,
        )
        self._source = None
        self.splits: dict[str, list[int]] | None = None
        self._cache: dict[int, torch.Tensor] = {}
        self.datasets: dict[str, PatchDataset | None] = {}
        self.stats = {"batches": 0, "patches": 0, "corruption_s": 0.0}
        self._stream = _TrainStream()

    # ------------------------------------------------------------------ data
    @property
    def source(self):
        """The image source (built on first use from ``source``/``source_kwargs``)."""
        if self._source is None:
            self._source = build_source(self.source_spec, **self.source_kwargs)
            if len(self._source) == 0:
                raise ValueError(f"image source {self.source_spec!r} has no images")
        return self._source

    def _split(self) -> dict[str, list[int]]:
        if self.splits is None:
            self.splits = split_ids(
                self.source.ids, self.val_fraction, self.test_fraction, self.seed, group_key=GROUP_KEYS[self.group_by]
            )
        return self.splits

    def _load(self, index: int) -> torch.Tensor:
        if index not in self._cache:
            image_id = self.source.ids[index]
            try:
                img, _ = self.source[index]
            except Exception as e:  # name the image (read_image names the file)
                raise ValueError(
                    f"cannot load image {image_id!r} (#{index}) of source {str(self.source_spec)!r}: {e}"
                ) from e
            self._cache[index] = img.float().contiguous()
        return self._cache[index]

    def _build(self, stage: str) -> PatchDataset | None:
        indices = self._split()[stage]
        images, ids = [], []
        small = []
        for i in indices:
            img = self._load(i)
            if min(img.shape[-2:]) < self.patch_size:
                small.append(f"{self.source.ids[i]} ({img.shape[-2]}×{img.shape[-1]})")
                continue
            images.append(img)
            ids.append(self.source.ids[i])
        if small:
            warnings.warn(
                f"{type(self).__name__}: skipping {len(small)} {stage} image(s) smaller than the patch size "
                f"{self.patch_size}: {', '.join(small[:5])}{' …' if len(small) > 5 else ''}",
                stacklevel=3,
            )
        if not images:
            if indices:
                raise ValueError(
                    f"no {stage} image of source {str(self.source_spec)!r} is at least {self.patch_size}×"
                    f"{self.patch_size} px (the patch size)"
                )
            if stage == "train":
                raise ValueError(
                    f"the train split of source {str(self.source_spec)!r} is empty ({len(self.source)} images, "
                    f"val_fraction={self.val_fraction}, test_fraction={self.test_fraction}, seed={self.seed})"
                )
            frac = self.val_fraction if stage == "val" else self.test_fraction
            if frac > 0:
                warnings.warn(
                    f"{type(self).__name__}: the {stage} split of source {str(self.source_spec)!r} is empty "
                    f"({len(self.source)} images); its DataLoader yields nothing. Use more images or another seed.",
                    stacklevel=3,
                )
            return None
        ppi = self.patches_per_image if stage == "train" else self.val_patches_per_image
        seed = self.seed + (1 if stage == "val" else 2 if stage == "test" else 0)
        ds = PatchDataset(images, ids, self.patch_size, stage, ppi, seed, **self._patch_kwargs)
        if ds.featureless:
            names = ", ".join(ds.featureless[:5]) + (" …" if len(ds.featureless) > 5 else "")
            crops = (f"{ds.n_fallback} of its {len(ds)} fixed crops are such crops" if stage != "train"
                     else f"its training patches from them are such crops")
            kw = self._patch_kwargs
            warnings.warn(
                f"{type(self).__name__}: {len(ds.featureless)} of {len(ids)} {stage} image(s) of source "
                f"{str(self.source_spec)!r} give no crop that passes the hard-patch check in max_tries = "
                f"{kw['max_tries']} draws (every crop near-uniform, std below min_std_dn = {kw['min_std_dn']:g} DN, or "
                f"clipped, more than max_clipped_fraction = {kw['max_clipped_fraction']:g} of its pixels at 0 or 255 DN): "
                f"{names}; {crops} (flat, lens-cap or saturated frames?). Use images with texture, or set "
                "keep_hard_patches: true to train on such patches on purpose",
                UserWarning,
                stacklevel=3,
            )
        return ds

    def setup(self, stage: str | None = None) -> None:
        """Split the source and load (once) the images of the splits ``stage`` needs."""
        need = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",), "predict": ("test",)}.get(
            stage or "", STAGES
        )
        for s in need:
            if s not in self.datasets:
                self.datasets[s] = self._build(s)

    def _loader(self, stage: str) -> DataLoader | list:
        if stage not in self.datasets:
            self.setup({"train": "fit", "val": "validate", "test": "test"}[stage])
        ds = self.datasets[stage]
        if ds is None:
            return []
        train = stage == "train"
        sampler = None
        trainer = self.trainer
        if train and trainer is not None and trainer.world_size <= 1 and self.num_workers == 0:
            # what shuffle=True samples, drawn the same way, and where the stream stands recorded (state_dict)
            sampler = _TrainSampler(ds, self.batch_size, len(ds) >= self.batch_size, self)
        if train and trainer is not None and trainer.world_size > 1 and self.num_workers == 0:
            # crops and flips in this process: a generator of this rank's own (DataLoader workers are seeded per
            # rank and worker by seed_everything(workers=True) already)
            ds.generator = torch.Generator().manual_seed(rank_seed(torch.initial_seed(), trainer.global_rank))
        if not train and trainer is not None and trainer.world_size > 1:
            # each held-out patch on exactly one rank (Lightning's DistributedSampler would pad with repeats)
            from lightning.pytorch.overrides.distributed import UnrepeatedDistributedSampler

            sampler = UnrepeatedDistributedSampler(ds, num_replicas=trainer.world_size, rank=trainer.global_rank, shuffle=False)
        return DataLoader(
            ds,
            batch_size=self.batch_size,
            shuffle=train and sampler is None,
            sampler=sampler,
            drop_last=train and len(ds) >= self.batch_size,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            pin_memory=self.pin_memory,
        )

    def train_dataloader(self):
        return self._loader("train")

    def val_dataloader(self):
        return self._loader("val")

    def test_dataloader(self):
        return self._loader("test")

    def predict_dataloader(self):
        return self._loader("test")

    # ------------------------------------------------------------------ resuming
    def state_dict(self) -> dict[str, Any]:
        """What a checkpoint keeps of this DataModule: the state of the training data stream at the step reached, so
        that a run resumed from the checkpoint continues it (``{}`` where it cannot: before the first step, with
        DataLoader workers, several processes, gradient accumulation or an endless epoch). Plain data
        (``torch.load(weights_only=True)``)."""
        state = self._stream.state(self.trainer)
        return {"train_stream": state} if state is not None else {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Continue the training data stream of a checkpoint (:meth:`state_dict`) at the first training batch of the
        resumed run: torch's CPU generator and the epoch's order of the patches are set to where the interrupted run
        stood (a stream it cannot continue, of other data or another batch size, is named in a warning and starts
        afresh)."""
        stream = state_dict.get("train_stream") if isinstance(state_dict, Mapping) else None
        self._stream.resume = stream if isinstance(stream, Mapping) else None
        trainer = self.trainer
        if self._stream.resume is not None and (self.num_workers > 0 or (trainer is not None and trainer.world_size > 1)):
            self._stream.resume = None
            warnings.warn(
                f"the checkpoint's training data stream is not continued with num_workers = {self.num_workers} / "
                f"{1 if trainer is None else trainer.world_size} process(es) (only with num_workers 0 on one process): "
                "the resumed run draws its batches afresh",
                UserWarning,
                stacklevel=2,
            )

    # ------------------------------------------------------------------ corruption
    def _stage_of(self, batch: Mapping[str, Any]) -> str:
        st = batch.get("stage")
        if st is not None:
            return st[0] if isinstance(st, (list, tuple)) else str(st)
        trainer = self.trainer
        return "train" if trainer is not None and trainer.training else "val"

    def train_generator(self) -> torch.Generator | None:
        """Generator of a training batch's corruption: ``None`` (torch's global RNG) in a single-process run, a CPU
        generator seeded by :func:`rank_seed` on each rank of a multi-process run."""
        trainer = self.trainer
        if trainer is None or trainer.world_size <= 1:
            return None
        draw = int(torch.randint(0, 2**62, (1,)))
        return torch.Generator().manual_seed(rank_seed(draw, trainer.global_rank))

    def sample_generator(self, stage: str, index: int) -> torch.Generator:
        """CPU generator of the fixed corruption of validation/test patch ``index``, seeded by :func:`sample_seed`."""
        return torch.Generator().manual_seed(sample_seed(self.seed, stage, index))

    def rng_for(self, batch: Mapping[str, Any]) -> str:
        """Random numbers of the batch's noise fields: ``train_rng`` for a training batch, else ``"torch"``."""
        return self.train_rng if self._stage_of(batch) == "train" else "torch"

    def corrupt_held_out(self, clean: torch.Tensor, stage: str, index: Sequence[int] | torch.Tensor | None) -> dict[str, torch.Tensor]:
        """Corrupt validation/test patches one by one, patch ``index[i]`` with :meth:`sample_generator`; without
        ``index`` the patches count as 0 … B−1."""
        b = int(clean.shape[0])
        indices = list(range(b)) if index is None else [int(i) for i in index]
        if len(indices) != b:
            raise ValueError(f"got {len(indices)} patch indices for a batch of {b} patches")
        parts = [self.corrupt(clean[i : i + 1], self.sample_generator(stage, indices[i]), rng="torch") for i in range(b)]
        return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}

    def corrupt(self, clean: torch.Tensor, generator: torch.Generator | None, rng: str = "torch") -> dict[str, torch.Tensor]:
        """Corrupt a clean batch B×1×P×P and return the labelled entries (implemented by subclasses)."""
        raise NotImplementedError

    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int = 0) -> Any:
        """Corrupt the clean patches on their device; returns the dict batch (see the subclass)."""
        if not isinstance(batch, Mapping) or "clean" not in batch or "image" in batch:
            return batch  # not ours, or already corrupted
        t0 = time.perf_counter()
        clean = batch["clean"]
        stage = self._stage_of(batch)
        trainer = self.trainer
        if stage == "val" and trainer is not None and not trainer.sanity_checking:
            self._stream.val_step = trainer.global_step  # the validation after this step has begun (state_dict)
        if stage == "train":
            out = self.corrupt(clean, self.train_generator(), rng=self.train_rng)
        else:
            out = self.corrupt_held_out(clean, stage, batch.get("index"))
        if clean.is_cuda:
            torch.cuda.synchronize(clean.device)
        self.stats["batches"] += 1
        self.stats["patches"] += int(clean.shape[0])
        self.stats["corruption_s"] += time.perf_counter() - t0
        result = {"image": out.pop("image"), "clean": clean, **out}
        for k in ("index", "image_id", "stage", "fallback"):
            if k in batch:
                result[k] = batch[k]
        return result

    # ------------------------------------------------------------------ throughput
    def measure_throughput(
        self, n_batches: int = 10, stage: str = "train", device: str | torch.device = "cpu", warmup: int = 1
    ) -> dict[str, float]:
        """Patches per second delivered by the ``stage`` loader *including* the corruption on ``device``.

        Iterates ``warmup + n_batches`` batches (cycling the loader if needed), moves each to ``device``,
        runs :meth:`on_after_batch_transfer` and times the last ``n_batches``. Returns
        ``{"patches_per_s", "corruption_patches_per_s", "loading_s", "corruption_s", "patches"}``.
        """
        device = torch.device(device)
        loader = self._loader(stage)
        if not loader:
            raise ValueError(f"the {stage} split is empty: nothing to measure")
        next_batch = cycle_batches(loader)
        load_s = corr_s = 0.0
        patches = 0
        for k in range(warmup + n_batches):
            t0 = time.perf_counter()
            batch = next_batch()
            batch = {key: v.to(device) if isinstance(v, torch.Tensor) else v for key, v in batch.items()}
            t1 = time.perf_counter()
            out = self.on_after_batch_transfer(batch, 0)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            t2 = time.perf_counter()
            if k >= warmup:
                load_s += t1 - t0
                corr_s += t2 - t1
                patches += int(out["image"].shape[0])
        total = load_s + corr_s
        return {
            "patches_per_s": patches / total if total > 0 else float("inf"),
            "corruption_patches_per_s": patches / corr_s if corr_s > 0 else float("inf"),
            "loading_s": load_s,
            "corruption_s": corr_s,
            "patches": float(patches),
        }

    def throughput_stats(self) -> dict[str, float]:
        """Running totals of the hook: batches and patches corrupted and the corruption's patches/s."""
        s = dict(self.stats)
        s["corruption_patches_per_s"] = s["patches"] / s["corruption_s"] if s["corruption_s"] > 0 else float("nan")
        return s


def cycle_batches(loader: Any) -> Callable[[], Any]:
    """A function returning the loader's next batch, restarting the loader when it is exhausted."""
    it = iter(loader)

    def next_batch() -> Any:
        nonlocal it
        try:
            return next(it)
        except StopIteration:
            it = iter(loader)
            return next(it)

    return next_batch
