"""The command-line entry points' error handling: one clear line, the traceback only with ``--debug``.

Every ``python -m camhealth.<tool>`` (``fit``, ``export``, ``evaluate``, ``monitor``, ``corrupt``, ``demo``,
``iopc``) runs its ``main`` through :func:`run_cli`: an error prints ``<prog>: error: <message>`` on stderr and
exits with status 2 (Ctrl-C: ``<prog>: interrupted``, status 130); ``--debug`` anywhere on the command line lets
the exception and its traceback through instead. Usage errors of the argument parser keep their own message
and status. A ``--config`` file that holds no options at all (empty, or only comments) is refused naming it
(:func:`check_config_file`), where jsonargparse would say only ``Unexpected config:``.
"""

from __future__ import annotations

import argparse
import functools
import math
import sys
import traceback
from typing import Any, Callable, Sequence

__all__ = [
    "DEBUG_FLAG", "BadValue", "FloatRange", "IntAtLeast", "IntRange", "add_debug_flag", "check_config_file", "config_action", "config_parser",
    "debugging", "one_line", "run_cli",
]

DEBUG_FLAG = "--debug"
_debug = False
_HELP = "on an error, show the Python traceback instead of one line"

#: Errors whose message says everything (the type name adds nothing for a user).
_PLAIN = (ValueError, TypeError, OSError, ImportError, KeyError, IndexError)
#: How jsonargparse begins the error of a value that none of an argument's types accepts.
_UNION_ERROR = "Does not validate against any of the Union subtypes"


class BadValue(argparse.ArgumentTypeError, ValueError):
    """A value an option's ``type`` refuses, with a message naming it. On the command line argparse prints the message
    as it is (``argument --x: <message>``); from a ``--config`` file jsonargparse's check catches it as a
    ``ValueError`` (``Parser key "x": <message>``): either way one line and exit status 2, never a traceback."""


class IntRange:
    """Option type: an integer in [lo, hi] (a config file's ``true`` or ``2.5`` is none), else :class:`BadValue` naming
    the value and the range, ``must be >= 1, got 0 (allowed: 1 … 64)``. Its ``repr`` (``int in [1, 64]``) is what
    ``--help`` shows as the type."""

    def __init__(self, lo: int, hi: int, hi_name: str | None = None) -> None:
        self.lo, self.hi, self.hi_name = lo, hi, hi_name  # hi_name: how ``--help`` names hi (a machine's own bound)

    def __call__(self, value: Any) -> int:
        allowed = f"(allowed: {self.lo} … {self.hi})"
        try:
            if isinstance(value, (bool, float)):
                raise ValueError
            n = int(value)
        except (TypeError, ValueError):
            raise BadValue(f"must be an integer, got {value!r} {allowed}") from None
        if n < self.lo:
            raise BadValue(f"must be >= {self.lo}, got {n} {allowed}")
        if n > self.hi:
            raise BadValue(f"must be <= {self.hi}, got {n} {allowed}")
        return n

    def __repr__(self) -> str:
        return f"int in [{self.lo}, {self.hi if self.hi_name is None else self.hi_name}]"


class FloatRange:
    """Option type: a finite number in (lo, hi] (``lo_open``, the default) or [lo, hi], else :class:`BadValue` naming
    the value and the range. Its ``repr`` is what ``--help`` shows as the type."""

    def __init__(self, lo: float, hi: float, lo_open: bool = True, unit: str = "") -> None:
        self.lo, self.hi, self.lo_open, self.unit = lo, hi, lo_open, unit

    def _allowed(self) -> str:
        return f"(allowed: {'>' if self.lo_open else '>='} {self.lo:g} … {self.hi:g}{self.unit})"

    def __call__(self, value: Any) -> float:
        try:
            if isinstance(value, bool):
                raise ValueError
            x = float(value)
        except (TypeError, ValueError):
            raise BadValue(f"must be a number, got {value!r} {self._allowed()}") from None
        typed = value.strip() if isinstance(value, str) else f"{x:g}"  # (the value as it was written)
        if not math.isfinite(x):
            raise BadValue(f"must be a finite number, got {typed} {self._allowed()}")
        if x < self.lo or (self.lo_open and x == self.lo):
            raise BadValue(f"must be {'>' if self.lo_open else '>='} {self.lo:g}, got {typed} {self._allowed()}")
        if x > self.hi:
            raise BadValue(f"must be <= {self.hi:g}, got {typed} {self._allowed()}")
        return x

    def __repr__(self) -> str:
        return f"float in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}]"


class IntAtLeast:
    """Option type: an integer >= ``lo`` (a config file's ``true`` or ``2.5`` is none), else :class:`BadValue` naming the
    value and the bound. Its ``repr`` (``int >= 1``) is what jsonargparse's ``--help`` shows as the type."""

    def __init__(self, lo: int) -> None:
        self.lo = lo

    def __call__(self, value: Any) -> int:
        try:
            if isinstance(value, (bool, float)):
                raise ValueError
            n = int(value)
        except (TypeError, ValueError):
            raise BadValue(f"must be an integer >= {self.lo}, got {value!r}") from None
        if n < self.lo:
            raise BadValue(f"must be >= {self.lo}, got {n}")
        return n

    def __repr__(self) -> str:
        return f"int >= {self.lo}"


class BitDepthOption:
    """Option type of ``--bit-depth``: ``'auto'`` or an integer number of bits 1…16 (as ``camhealth.data.read_image``
    checks it), else :class:`BadValue` naming the value. Its ``repr`` is what ``--help`` shows."""

    def __call__(self, value) -> int | str:
        from camhealth.data.io import _check_bit_depth

        try:
            return _check_bit_depth(value if value == "auto" or isinstance(value, (bool, int)) else int(str(value)))
        except (TypeError, ValueError):
            raise BadValue(f"must be 'auto' or an integer number of bits in [1, 16] (8, 10, 12, 14 or 16), got {value!r}") from None

    def __repr__(self) -> str:
        return "auto or int in [1, 16]"


def add_debug_flag(parser: Any) -> None:
    """List ``--debug`` in an argparse/jsonargparse parser's ``--help`` (:func:`run_cli` acts on it)."""
    parser.add_argument(DEBUG_FLAG, action="store_true", help=_HELP)


def check_config_file(value: Any, option: str = "--config") -> None:
    """ValueError naming ``value`` when it is an existing file whose YAML holds nothing (empty, only blanks or
    comments, a bare ``null``). Anything else (inline YAML, a missing file, a YAML error) is left to the parser, which
    has its own message for it. The file is read with PyYAML's safe loader: nothing in it runs."""
    from pathlib import Path

    if not isinstance(value, (str, Path)) or "\n" in str(value):
        return
    path = Path(value)
    try:
        if not path.is_file():
            return
        import yaml

        empty = yaml.safe_load(path.read_text(encoding="utf-8", errors="replace")) is None
    except Exception:  # noqa: BLE001 - unreadable or invalid: the parser reports it
        return
    if empty:
        raise BadValue(f"{option} {value}: the file is empty (no options in it)")


@functools.lru_cache(maxsize=None)
def config_action() -> Any:
    """jsonargparse's ``ActionConfigFile`` that refuses an empty config file naming it (:func:`check_config_file`)."""
    from jsonargparse import ActionConfigFile

    class ConfigFile(ActionConfigFile):
        def __call__(self, parser, cfg, values, option_string=None):
            try:
                check_config_file(values, option_string or "--config")
            except BadValue as exc:
                raise TypeError(str(exc)) from None  # jsonargparse: usage, "error: <message>", exit status 2
            super().__call__(parser, cfg, values, option_string)

    return ConfigFile


def config_parser(**kwargs: Any) -> Any:
    """A jsonargparse ``ArgumentParser`` (the parser LightningCLI and ``python -m camhealth.iopc`` use) with
    ``--config FILE`` (YAML or JSON of the options, keys as ``--print_config`` writes them; flags after it override
    it) and ``--print_config`` (the resolved options as YAML, then exit). ``kwargs`` go to the parser (``prog``,
    ``description``, ``formatter_class``, …); options are added as with argparse."""
    from jsonargparse import ArgumentParser

    parser = ArgumentParser(**kwargs)
    parser.add_argument("--config", action=config_action(),
                        help="YAML/JSON file of these options (keys as --print_config writes them); later flags override it")
    return parser


def debugging() -> bool:
    """Whether the running command was given ``--debug`` (a ``main`` that reports errors itself re-raises then)."""
    return _debug


def one_line(exc: BaseException) -> str:
    """The first line of ``exc``'s message (with its type where the message alone would be unclear)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    text = lines[0] if lines else ""
    if text.startswith(_UNION_ERROR):
        # jsonargparse wraps what a class named in a config raised (`model:`/`data:` are Optional[Class] arguments):
        # the class's own message names the option and its range; "Expected a <class 'NoneType'>" is the other subtype
        cause = exc.__cause__
        if cause is not None and str(cause).strip() and not str(cause).strip().startswith(_UNION_ERROR):
            return one_line(cause)
        errors = [ln[2:].strip() for ln in lines if ln.startswith("- ") and "Expected a <class 'NoneType'>" not in ln]
        if errors:
            return errors[0]
    if isinstance(exc, KeyError) and len(exc.args) == 1:
        text = f"missing key {exc.args[0]!r}"
    if isinstance(exc, (FileExistsError, NotADirectoryError)) and exc.filename:  # a folder was to be made or used there
        return f"{exc.filename} is a file, where a folder was to be made or written into: name a folder, or move the file"
    if not text:
        return type(exc).__name__
    return text if isinstance(exc, _PLAIN) else f"{type(exc).__name__}: {text}"


def run_cli(main: Callable[[list[str] | None], Any], prog: str, argv: Sequence[str] | None = None) -> int:
    """Run ``main`` on ``argv`` less ``--debug`` and return the exit status. Without ``argv`` the command line is
    ``sys.argv`` (the flag is taken out of it, and ``main`` gets ``None``, as when run directly)."""
    global _debug
    args = list(sys.argv[1:] if argv is None else argv)
    debug = DEBUG_FLAG in args or _debug  # (an outer run_cli may have taken the flag already)
    args = [a for a in args if a != DEBUG_FLAG]
    if argv is None:
        sys.argv[1:] = args
    before, _debug = _debug, debug
    try:
        result = main(None if argv is None else args)
    except SystemExit as exc:  # argparse usage errors and explicit exits keep their message and status
        if isinstance(exc.code, str):
            if debug:
                traceback.print_exc()
            print(f"{prog}: error: {exc.code}", file=sys.stderr)
            return 2
        return int(exc.code or 0)
    except KeyboardInterrupt:
        if debug:
            raise
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the point of this function
        if debug:
            raise
        print(f"{prog}: error: {one_line(exc)} (run with {DEBUG_FLAG} for the traceback)", file=sys.stderr)
        return 2
    finally:
        _debug = before
    return result if isinstance(result, int) and not isinstance(result, bool) else 0
