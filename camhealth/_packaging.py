"""Where camhealth's own files are, once installed: the packaged configs and the top-level packages.

* :func:`packaged_config` / :func:`resolve_config_args`: ``--config noise_source`` (a name, no folder) is the YAML
  shipped inside the package (``camhealth/configs/noise_source.yaml``), so the training commands work after a plain
  ``pip install`` from any folder; a path that exists is used as it is (an empty file is refused, naming it).
* :func:`check_top_level_packages`: ``datamodules`` and ``lightning_modules`` are top-level packages installed
  beside ``camhealth``; a user's own folder or module of the same name earlier on ``sys.path`` (the current
  folder, for ``python -m``) would shadow them, which Python reports as a missing submodule. The check names the
  folder that shadows them instead.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Sequence

__all__ = ["CONFIG_DIR", "check_top_level_packages", "config_names", "packaged_config", "resolve_config_args"]

#: The YAML configs shipped with the package.
CONFIG_DIR = Path(__file__).resolve().parent / "configs"

#: camhealth's top-level packages beside ``camhealth`` itself.
TOP_LEVEL = ("datamodules", "lightning_modules")


def config_names() -> list[str]:
    """Names of the packaged configs (``noise_source``, ``mtf``, …)."""
    return sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))


def packaged_config(name: str) -> Path:
    """The packaged config ``name`` (``noise_source`` or ``noise_source.yaml``); ValueError naming the ones there are."""
    stem = name[:-5] if name.endswith(".yaml") else name
    path = CONFIG_DIR / f"{stem}.yaml"
    if not path.is_file():
        raise ValueError(f"--config {name}: no such file, and no packaged config of that name (packaged: {', '.join(config_names())})")
    return path


def _resolve(value: str, option: str = "--config") -> str:
    from camhealth._cli import check_config_file

    check_config_file(value, option)  # (jsonargparse would say only "Unexpected config:")
    if Path(value).exists() or "/" in value or "\\" in value or value.lstrip().startswith(("{", "[")):
        return value  # an existing file, a path (its own error), or inline YAML
    return str(packaged_config(value))


def resolve_config_args(args: Sequence[str]) -> list[str]:
    """``args`` with every ``--config NAME`` / ``-c NAME`` / ``--config=NAME`` that names no existing file and no
    folder replaced by the packaged config of that name; ValueError naming an existing config file that is empty."""
    out: list[str] = []
    take = None
    for a in args:
        if take:
            out.append(_resolve(a, take))
            take = None
        elif a in ("--config", "-c"):
            out.append(a)
            take = a
        elif a.startswith("--config="):
            out.append("--config=" + _resolve(a[len("--config="):]))
        else:
            out.append(a)
    return out


def check_top_level_packages(names: Sequence[str] = TOP_LEVEL) -> None:
    """ImportError in one line when ``datamodules``/``lightning_modules`` would be imported from somewhere other than
    beside ``camhealth`` (a folder or module of that name in the current folder or on ``PYTHONPATH``)."""
    home = Path(__file__).resolve().parent.parent
    for name in names:
        spec = importlib.util.find_spec(name)
        expected = home / name
        if spec is None:
            raise ImportError(f"camhealth's package {name!r} is not installed beside camhealth ({expected}); reinstall camhealth")
        places = [Path(p).resolve() for p in (spec.submodule_search_locations or [])] or [Path(spec.origin or "?").resolve()]
        if expected.resolve() not in places:
            raise ImportError(
                f"'{name}' is imported from {places[0]}, which shadows camhealth's {expected}: rename your '{name}' "
                f"folder or module, or run from another folder"
            )
