"""Fixtures of the ``python -m camhealth.bench`` command-line tests."""

from __future__ import annotations

import pytest

from camhealth.bench import __main__ as bench_cli


@pytest.fixture
def no_run(monkeypatch):
    """The benchmark's ``run`` fails the test: what is checked there must be refused before it (``bench monitor``'s
    mode checks, the first thing its ``run`` does, are run first)."""
    real = bench_cli.load

    class Module:
        def __init__(self, name):
            self._m = real(name)
            self.HELP, self.add_arguments = self._m.HELP, self._m.add_arguments

        def run(self, args):
            if args.benchmark == "monitor":  # its checks come first in run; the measurement must not start
                from camhealth.bench.monitor import check_mode_options

                check_mode_options(args)
            pytest.fail("the benchmark ran")

    monkeypatch.setattr(bench_cli, "load", Module)
