"""The network building blocks live in :mod:`camhealth.nets.blocks` (plain ``torch.nn`` modules, importable without
Lightning); this module keeps their names importable from ``lightning_modules``."""

from camhealth.nets.blocks import (  # noqa: F401
    ConvAct,
    FullyConnectedBlock,
    GlobalStatsPool,
    ResidualBlock,
    count_flops,
    count_parameters,
)

__all__ = ["ConvAct", "ResidualBlock", "FullyConnectedBlock", "count_flops", "count_parameters", "GlobalStatsPool"]
