"""``camhealth <tool> …`` (the console script) and ``python -m camhealth <tool> …``: the same as
``python -m camhealth.<tool> …`` for each tool, e.g. ``camhealth fit --config noise_source`` or
``camhealth monitor clip.mp4``. ``camhealth --help`` lists the tools."""

from __future__ import annotations

import runpy
import sys
from typing import Sequence

__all__ = ["TOOLS", "main"]

#: tool → (module run as ``__main__``, one line of help)
TOOLS: dict[str, tuple[str, str]] = {
    "fit": ("camhealth.fit", "train, validate, test an estimator from a YAML config (LightningCLI)"),
    "export": ("camhealth.export", "export a checkpoint to weights, .pt2 or ONNX"),
    "evaluate": ("camhealth.evaluate", "evaluate estimators on corrupted images"),
    "monitor": ("camhealth.monitor", "image-quality monitor of videos, folders, ROS recordings"),
    "corrupt": ("camhealth.corrupt", "corrupt images with blur and sensor noise"),
    "calibrate": ("camhealth.calibrate", "calibrate a camera's noise model"),
    "iopc": ("camhealth.iopc", "input-output performance curves of a detector"),
    "demo": ("camhealth.demo", "closed-loop exposure/gain demo"),
    "bench": ("camhealth.bench", "benchmarks"),
    "model-card": ("camhealth.model_card", "model card of a weights file"),
}


def _usage() -> str:
    width = max(map(len, TOOLS))
    lines = ["usage: camhealth <tool> [options]   (camhealth <tool> --help for a tool's options)", "", "tools:"]
    lines += [f"  {name:<{width}}  {text}" for name, (_, text) in TOOLS.items()]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the tool named first in ``argv`` (default ``sys.argv[1:]``) as ``python -m camhealth.<tool>`` would."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(_usage())
        return 0
    tool, rest = args[0], args[1:]
    tool = tool.replace("_", "-") if tool.replace("_", "-") in TOOLS else tool  # model_card, as its module is named
    if tool not in TOOLS:
        print(f"camhealth: error: unknown tool {tool!r}; choose from {', '.join(TOOLS)}", file=sys.stderr)
        return 2
    module = TOOLS[tool][0]
    # the tool sees the command line python -m would give it (a DDP run restarts its ranks with python -m <module>)
    sys.argv = [f"camhealth {tool}", *rest]
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        code = exc.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
