"""The networks of camhealth's learned estimators as plain ``torch.nn.Module``s, one module per network.

- :mod:`camhealth.nets.blocks` — building blocks (:class:`ConvAct`, :class:`ResidualBlock`, :class:`GlobalStatsPool`,
  :class:`FullyConnectedBlock`) and FLOP/parameter counting.
- :mod:`camhealth.nets.noise_source` — :class:`NoiseSourceNet` (σ of PN, DCSN, RN and ξ; w/o- and Min-Meta).
- :mod:`camhealth.nets.drne` — :class:`NoiseLevelNet` (pixel-wise total-noise σ map) and the thesis-size
  :class:`ThesisNoiseNet`.
- :mod:`camhealth.nets.mtf` — :class:`MTFNet` and its batched pre-processing :class:`MTFPreprocess`.

Inference (:func:`camhealth.load_estimator`, ``python -m camhealth.monitor``) builds these from a weights file or
checkpoint without importing a training framework. The LightningModules that train them (loss, metrics, logging,
figures) live in ``lightning_modules/`` and import the networks from here; a file names its LightningModule
(``class_path``) and that module's arguments (``init_args``). :data:`NETWORKS` says, per kind, which of those
arguments shape the network and which only shape training, so a file is turned into its network here.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from torch import nn

from camhealth.nets.blocks import ConvAct, FullyConnectedBlock, GlobalStatsPool, ResidualBlock, count_flops, count_parameters
from camhealth.nets.drne import NoiseLevelNet, ThesisNoiseNet, check_dilations
from camhealth.nets.mtf import MTFNet, MTFPreprocess
from camhealth.nets.noise_source import NoiseSourceNet, NoiseTrunk

__all__ = [
    "NoiseSourceNet", "NoiseTrunk", "NoiseLevelNet", "ThesisNoiseNet", "MTFNet", "MTFPreprocess", "ConvAct",
    "ResidualBlock", "GlobalStatsPool", "FullyConnectedBlock", "count_flops", "count_parameters", "NetworkSpec",
    "NETWORKS", "COMMON_TRAINING_ARGS", "LOSS_TERMS", "MAX_PATCH_SIZE", "check_patch_size", "network_for",
]

#: Arguments every estimator LightningModule takes that do not change its network (``channels_last`` is the memory
#: format the network runs in, read by :meth:`NetworkSpec.channels_last`).
COMMON_TRAINING_ARGS: tuple[str, ...] = ("lr", "weight_decay", "channels_last", "log_figures", "max_figure_samples")


#: The loss terms of the noise-source network (the keys ``loss_weights`` may set).
LOSS_TERMS: tuple[str, ...] = ("pn", "dcsn", "rn", "total", "xi")


def _finite(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError(f"{name} = {value!r} must be a finite number")
    return float(value)


def _positive(name: str, value: Any) -> None:
    if not _finite(name, value) > 0:
        raise ValueError(f"{name} = {value!r} must be > 0")


def _non_negative(name: str, value: Any) -> None:
    if _finite(name, value) < 0:
        raise ValueError(f"{name} = {value!r} must be ≥ 0")


def _fraction(name: str, value: Any) -> None:
    if not 0 <= _finite(name, value) <= 1:
        raise ValueError(f"{name} = {value!r} must lie in [0, 1]")


def _flag(name: str, value: Any) -> None:
    if not isinstance(value, bool):
        raise ValueError(f"{name} = {value!r} must be true or false")


def _count(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:
        raise ValueError(f"{name} = {value!r} must be an integer ≥ 0")


def _loss_weights(name: str, value: Any) -> None:
    if value is None:
        return
    if not isinstance(value, Mapping):
        raise ValueError(f"{name} = {value!r} must be a mapping of loss terms {list(LOSS_TERMS)} to weights, or null")
    unknown = sorted(str(k) for k in value if k not in LOSS_TERMS)
    if unknown:
        raise ValueError(f"{name} has unknown key(s) {unknown}; allowed {list(LOSS_TERMS)}")
    for key, weight in value.items():
        _non_negative(f"{name}[{key!r}]", weight)


#: How each training argument's value is checked (:meth:`NetworkSpec.check_training_args`).
_TRAINING_CHECKS = {
    "lr": _positive, "weight_decay": _non_negative, "channels_last": _flag, "log_figures": _flag,
    "max_figure_samples": _count, "huber_beta_dn": _non_negative, "map_weight": _fraction, "loss_weights": _loss_weights,
}


#: Largest patch side [px] a network is built or loaded for: a camera frame is tiled into patches, and a file that
#: claims a larger one (10⁹ px) would load and then find no patch in any frame.
MAX_PATCH_SIZE = 1024


def check_patch_size(patch_size: Any) -> int:
    """The estimators' patch side [px]: a positive multiple of 16 (the strided stages and space-to-depth folds of
    every network divide it by up to 16) of at most :data:`MAX_PATCH_SIZE`; ``ValueError`` naming the value
    otherwise."""
    if isinstance(patch_size, bool) or not isinstance(patch_size, numbers.Real) or not math.isfinite(patch_size) \
            or int(patch_size) != patch_size or patch_size < 16 or patch_size % 16:
        raise ValueError(f"patch_size = {patch_size!r} must be a positive multiple of 16 px")
    if patch_size > MAX_PATCH_SIZE:
        raise ValueError(f"patch_size = {patch_size!r} must be a multiple of 16 px in [16, {MAX_PATCH_SIZE}]")
    return int(patch_size)


@dataclass(frozen=True)
class NetworkSpec:
    """How a file of one estimator kind becomes its network.

    Attributes:
        kind: ``"noise_source"``, ``"drne"`` or ``"mtf"``.
        class_path: the LightningModule that trains the network, as files name it.
        network: the ``nn.Module`` class.
        network_args: arguments of the LightningModule handed on to ``network`` under the same name.
        training_args: its other arguments besides ``patch_size`` (loss, optimiser, logging): accepted, not used here.
        check: a further check of a file's ``init_args`` that the LightningModule makes too (the network alone cannot:
            it does not know the patch size), or None.
    """

    kind: str
    class_path: str
    network: type[nn.Module]
    network_args: tuple[str, ...]
    training_args: tuple[str, ...]
    check: Callable[[Mapping[str, Any]], None] | None = None

    @property
    def init_args(self) -> tuple[str, ...]:
        """Every argument of the LightningModule (what a file's ``init_args`` may hold)."""
        return ("patch_size", *self.network_args, *self.training_args, *COMMON_TRAINING_ARGS)

    def check_training_args(self, init_args: Mapping[str, Any]) -> None:
        """Refuse a value of a training argument (``lr``, ``weight_decay``, ``loss_weights``, ``map_weight``,
        ``huber_beta_dn``, ``channels_last``, …) that the LightningModule refuses: one ``ValueError`` naming the
        argument and its value. The LightningModules run it on their own arguments, and both loaders of
        :mod:`camhealth.export` on a file's, so ``load_net`` (no LightningModule built) refuses what ``load_module``
        refuses. Arguments the file does not give are not checked (they take the defaults)."""
        for key in (*self.training_args, *COMMON_TRAINING_ARGS):
            if key in init_args:
                _TRAINING_CHECKS[key](key, init_args[key])

    def build(self, init_args: Mapping[str, Any]) -> nn.Module:
        """The network (untrained, eval mode) for a file's ``init_args``; arguments it does not give take the
        network's defaults. ``ValueError`` for an argument the LightningModule does not take or a bad patch size;
        the network's constructor raises for values it refuses."""
        unknown = sorted(k for k in init_args if k not in self.init_args)
        if unknown:
            raise ValueError(f"init_args {unknown} are not arguments of {self.class_path}")
        if "patch_size" in init_args:
            check_patch_size(init_args["patch_size"])
        if self.check is not None:
            self.check(init_args)
        kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in init_args.items() if k in self.network_args}
        return self.network(**kwargs).eval()

    @staticmethod
    def channels_last(init_args: Mapping[str, Any]) -> bool:
        """Whether the network runs in channels-last memory format (the LightningModules' default: yes)."""
        return bool(init_args.get("channels_last", True))


def _check_drne_args(init_args: Mapping[str, Any]) -> None:
    """The DRNE's dilations against its patch size (:func:`camhealth.nets.drne.check_dilations`), as
    :class:`lightning_modules.NoiseLevelEstimator` checks them."""
    if "dilations" in init_args and "patch_size" in init_args:
        check_dilations(init_args["dilations"], init_args["patch_size"])


#: The estimator kinds and their networks.
NETWORKS: dict[str, NetworkSpec] = {
    spec.kind: spec
    for spec in (
        NetworkSpec("noise_source", "lightning_modules.noise_source.NoiseSourceEstimator", NoiseSourceNet,
                    ("metadata_set", "width", "hidden"), ("loss_weights", "huber_beta_dn")),
        NetworkSpec("drne", "lightning_modules.drne.NoiseLevelEstimator", NoiseLevelNet,
                    ("width", "dilations"), ("map_weight", "huber_beta_dn"), _check_drne_args),
        NetworkSpec("mtf", "lightning_modules.mtf.MTFEstimator", MTFNet,
                    ("widths", "hidden", "downsample"), ()),
    )
}


def network_for(class_path: str) -> NetworkSpec:
    """The :class:`NetworkSpec` of the LightningModule a file names; ``ValueError`` listing the allowed ones."""
    for spec in NETWORKS.values():
        if spec.class_path == class_path:
            return spec
    raise ValueError(f"class {class_path!r} is not a camhealth estimator; allowed: {sorted(s.class_path for s in NETWORKS.values())}")
