"""``python -m camhealth.monitor`` and ``python -m camhealth.bench <benchmark>`` are jsonargparse command lines:
``--print_config`` writes a file that ``--config`` reads back to the same options, a bad value (flag or file) is
exit status 2 with a message naming it, and every such command line the docs show still parses as written."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path
from types import SimpleNamespace

import pytest

from camhealth.bench import BENCHMARKS
from camhealth.bench.__main__ import build_parser as bench_parser
from camhealth.bench.__main__ import main as bench_main
from camhealth.bench.__main__ import parse as bench_parse
from camhealth.monitor.__main__ import build_parser as monitor_parser
from camhealth.monitor.__main__ import main as monitor_main

ROOT = Path(__file__).resolve().parents[1]


def _plain(ns) -> dict:
    """Options as plain data, without the --config entries (a subcommand's options nested under its name)."""
    d = ns.as_dict() if hasattr(ns, "as_dict") else ns
    return {k: (_plain(v) if isinstance(v, dict) else v if isinstance(v, (list, bool, int, float, type(None))) else str(v))
            for k, v in d.items() if k != "config"}


def _print_config(build, argv) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as info:
        build().parse_args([*argv, "--print_config"])
    assert info.value.code == 0
    return out.getvalue()


MONITOR_ARGV = [
    "run.mcap", "--sensor", "ICX285", "--set", "gain_db=18", "--set", "exposure_s=0.02", "--iopc", "a.json",
    "--iopc", "b.json", "--iopc-weights", "1", "0.5", "--exposure-limits", "0.002", "0.1", "--bit-depth", "12",
    "--max-frames", "3", "--mode", "map", "--mtf-views", "2", "--out", "runs/x", "--topic", "/cam",
    "--gain-topic", "/cam/gain", "--gain-unit", "factor", "--diagnostics-out", "d.mcap", "--no-progress",
]


def test_monitor_print_config_round_trips_through_config(tmp_path):
    direct = monitor_parser().parse_args(MONITOR_ARGV)
    text = _print_config(monitor_parser, MONITOR_ARGV)
    assert "gain_db=18" in text and "source: run.mcap" in text
    path = tmp_path / "monitor.yaml"
    path.write_text(text)
    again = monitor_parser().parse_args(["--config", str(path)])  # SOURCE from the file too
    assert _plain(again) == _plain(direct)
    assert again.set == ["gain_db=18", "exposure_s=0.02"] and again.bit_depth == 12
    # flags after --config override it; --set appends to the file's list as on the command line
    over = monitor_parser().parse_args(["--config", str(path), "--bit-depth", "auto", "--set", "temperature_c=30"])
    assert over.bit_depth == "auto" and over.set == ["gain_db=18", "exposure_s=0.02", "temperature_c=30"]


def test_monitor_set_from_a_config_file_overrides_the_metadata(tmp_path):
    from camhealth.monitor.__main__ import _overrides

    path = tmp_path / "m.yaml"
    path.write_text("source: street\nset: gain_db=6\n")  # one string instead of a list
    assert _overrides(monitor_parser().parse_args(["--config", str(path)]).set) == {"gain_db": 6.0}
    path.write_text("source: street\nset: [gain_db=6, exposure_s=0.5]\n")
    assert _overrides(monitor_parser().parse_args(["--config", str(path)]).set) == {"gain_db": 6.0, "exposure_s": 0.5}


@pytest.mark.parametrize("argv,message", [
    (["x.png", "--set", "gain=3"], "unknown metadata field 'gain'"),
    (["x.png", "--set", "gain_db"], "expected FIELD=VALUE, got 'gain_db'"),
    (["x.png", "--set", "gain_db=loud"], "gain_db must be a number, got 'loud'"),
    (["x.png", "--bit-depth", "20"], "must be 'auto' or an integer 8…16, got 20"),
    (["x.png", "--window", "0"], "must be an integer 1…1000, got 0"),
    (["x.png", "--max-clipped", "-1"], "must be a finite number >= 0, got -1"),
    (["x.png", "--sensor", "IMX999"], "IMX999"),
])
def test_monitor_bad_flag_exits_2_naming_the_value(argv, message, capsys):
    assert monitor_main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


@pytest.mark.parametrize("content,message", [
    ("source: x.png\nset: [gain=3]\n", "unknown metadata field 'gain'"),
    ("source: x.png\nset: [gain_db]\n", "expected FIELD=VALUE, got 'gain_db'"),
    ("source: x.png\nbit_depth: 20\n", "must be 'auto' or an integer 8…16, got 20"),
    ("source: x.png\nwindow: 0\n", "must be an integer 1…1000, got 0"),
    ("source: x.png\nxi_sigmas: -2\n", "must be a finite number >= 0, got -2"),
    ("source: x.png\nwindow: 2.5\n", "must be an integer, got 2.5"),
    ("source: x.png\nsensor: IMX999\n", "IMX999"),
    ("source: x.png\nno_such_option: 1\n", "no_such_option"),
])
def test_monitor_bad_config_value_exits_2_naming_the_value(content, message, tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(content)
    assert monitor_main(["--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


@pytest.mark.parametrize("content", ["", "\n  \n", "# only a comment\n", "null\n"])
def test_an_empty_config_file_is_named(content, tmp_path, capsys):
    """jsonargparse alone says ``Unexpected config:`` and nothing after it."""
    path = tmp_path / "empty.yaml"
    path.write_text(content)
    assert monitor_main(["--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"error: --config {path}: the file is empty (no options in it)" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as info:  # a benchmark's own --config, after its name
        bench_main(["data", "--config", str(path)])
    assert info.value.code == 2 and f"--config {path}: the file is empty" in capsys.readouterr().err


def test_monitor_limits_from_a_config_file_need_two_values(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text("source: street\nsensor: ICX285\nexposure_limits: [0.01]\n")
    assert monitor_main(["--config", str(path), "--no-progress"]) == 2
    assert "--exposure-limits needs 2 values LO HI, got [0.01]" in capsys.readouterr().err


BENCH_ARGV = {
    "robustness": ["--task", "mtf", "--per-cell", "2", "--mtf-sizes", "3", "9", "--models", "mtf", "--json", "r.json"],
    "estimators": ["--models", "mtf", "--checkpoint", "a.pt", "--checkpoint", "b.pt", "--mtf-views", "1", "2",
                   "--sizes", "3", "9", "--xi-fields", "gain_db", "--no-reference"],
    "monitor": ["--motion", "--no-memory-probe", "--scene", "deadleaves", "--true-gain-db", "6", "--threads", "2"],
    "data": ["--default-malloc", "--workers", "1"],
    "calibrate": ["--variants", "", "--sensors", "2"],
}


@pytest.mark.parametrize("name", sorted(BENCHMARKS))
def test_bench_print_config_round_trips_through_config(name, tmp_path):
    argv = [name, "--batch", "4", "--repeats", "3", "--warmup", "0", "--markdown", "--out", "t.md", "--docs", "p.md",
            *BENCH_ARGV.get(name, [])]
    direct = bench_parser().parse_args(argv)
    path = tmp_path / "bench.yaml"
    path.write_text(_print_config(bench_parser, argv))  # after the name: the benchmark's own options
    again = bench_parser().parse_args([name, "--config", str(path)])
    assert _plain(again) == _plain(direct)
    assert bench_parse([name, "--config", str(path), "--batch", "8"]).batch == 8  # later flags override it
    # before the name, a config covers the whole command (the options nested under the benchmark's name)
    path.write_text(f"{name}:\n  batch: 5\n")
    assert bench_parse(["--config", str(path), name]).batch == 5


def test_bench_default_namespace_keeps_argparse_types():
    args = bench_parse(["estimators"])
    assert args.benchmark == "estimators" and args.batch == 32 and args.warmup == 2 and args.threads is None
    assert args.models is None and args.mtf_views == [1] and list(args.sizes) == [3.0, 21.0]
    assert bench_parse(["monitor"]).memory_probe is True and bench_parse(["monitor", "--no-memory-probe"]).memory_probe is False


@pytest.mark.parametrize("argv,message", [
    (["data", "--batch", "0"], "must be ≥ 1, got 0"),
    (["data", "--warmup", "-1"], "must be ≥ 0, got -1"),
    (["robustness", "--task", "blur"], "blur"),
    (["estimators", "--mtf-views", "3"], "3"),
    (["no-such-benchmark"], "no-such-benchmark"),
])
def test_bench_bad_flag_exits_2_naming_the_value(argv, message, capsys):
    with pytest.raises(SystemExit) as info:
        bench_main(argv)
    assert info.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize("content,message", [
    ("batch: 0\n", "must be ≥ 1, got 0"),
    ("warmup: -3\n", "must be ≥ 0, got -3"),
    ("batch: many\n", "many"),
    ("repeats: 2.5\n", "must be an integer, got 2.5"),
])
def test_bench_bad_config_value_exits_2_naming_the_value(content, message, tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(content)
    with pytest.raises(SystemExit) as info:
        bench_main(["data", "--config", str(path)])
    err = capsys.readouterr().err
    assert info.value.code == 2 and message in err and "Traceback" not in err


def test_bench_command_line_leaves_out_docs(monkeypatch):
    """``args.command_line`` (the name of a page's generated block) is the command without ``--docs FILE``."""
    from camhealth.bench import __main__ as bench_cli

    seen = {}

    class Stop(Exception):
        pass

    def fake_run(args):
        seen["args"] = args
        raise Stop

    real = bench_cli.load

    def load(name):
        module = real(name)
        return SimpleNamespace(HELP=module.HELP, add_arguments=module.add_arguments, run=fake_run)

    monkeypatch.setattr(bench_cli, "load", load)
    with pytest.raises(Stop):
        bench_cli.main(["data", "--repeats", "1", "--docs", "p.md", "--warmup", "0", "--docs=q.md"])
    args = seen["args"]
    assert args.command_line == "python -m camhealth.bench data --repeats 1 --warmup 0"
    assert str(args.docs) == "q.md" and args.repeats == 1 and args.benchmark == "data"


# -- every bench/monitor command line of the docs parses as written --------------------------------------------------

_COMMAND = re.compile(r"python -m camhealth\.(bench|monitor)(?![\w.])(.*)")


def documented_commands() -> list[tuple[str, str, str]]:
    """(page, tool, arguments) of every complete ``python -m camhealth.bench|monitor …`` of README.md and docs/*.md:
    generated-block names, lines of code blocks (with their ``\\`` continuations) and inline code spans. Synopses
    with placeholders ("…", "[--opt]", "auto|8…16") and the bare tool names of prose are not command lines."""
    found = []
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        texts = re.findall(r"<!-- generated: (.*?) -->", page.read_text(encoding="utf-8"))
        lines, fenced, i = page.read_text(encoding="utf-8").splitlines(), False, 0
        while i < len(lines):
            line = lines[i]
            if line.lstrip().startswith("```"):
                fenced = not fenced
            elif fenced and _COMMAND.match(line.strip()):
                while line.rstrip().endswith("\\") and i + 1 < len(lines):
                    i += 1
                    line = line.rstrip()[:-1] + " " + lines[i].strip()
                texts.append(line.strip())
            elif not fenced:
                texts += re.findall(r"`(python -m camhealth\.(?:bench|monitor)[^`]*)`", line)
            i += 1
        for text in texts:
            m = _COMMAND.match(text.strip())
            if not m:
                continue
            rest = m.group(2)
            if rest.startswith(":") or any(mark in rest for mark in ("…", "[", "|")):
                continue
            try:
                argv = shlex.split(rest, comments=True)
            except ValueError:
                continue
            if argv:
                found.append((page.name, m.group(1), rest.strip()))
    return sorted(set(found))


DOCUMENTED = documented_commands()


def test_the_docs_show_bench_and_monitor_command_lines():
    tools = {tool for _, tool, _ in DOCUMENTED}
    assert tools == {"bench", "monitor"} and len(DOCUMENTED) >= 30
    assert ("benchmarks.md", "bench", "robustness --frames 16 --threads 2 --markdown") in DOCUMENTED


@pytest.mark.parametrize("page,tool,rest", DOCUMENTED, ids=[f"{p}:{t} {r}"[:90] for p, t, r in DOCUMENTED])
def test_documented_command_line_parses(page, tool, rest, capsys):
    argv = shlex.split(rest, comments=True)
    if "--help" in argv:
        with pytest.raises(SystemExit) as info:
            (monitor_parser if tool == "monitor" else bench_parser)().parse_args(argv)
        assert info.value.code == 0
        return
    if tool == "monitor":
        args = monitor_parser().parse_args(argv)
        assert args.source == argv[0]
    else:
        args = bench_parse(argv)
        assert args.benchmark == argv[0]


@pytest.mark.filterwarnings("ignore:.*found in sys.modules after import of package")  # (runpy: already imported)
def test_bench_run_as_a_module_reports_a_bad_value_in_one_line(monkeypatch, capsys):
    """``python -m camhealth.bench monitor --frames 0`` (through the console script's dispatcher, which runs the module
    as ``__main__``): one error line naming the option, exit status 2, no traceback."""
    import sys

    from camhealth.__main__ import main as camhealth_main

    monkeypatch.setattr(sys, "argv", list(sys.argv))  # (the dispatcher sets the tool's command line)
    assert camhealth_main(["bench", "monitor", "--frames", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("python -m camhealth.bench: error: --frames must be >= 1, got 0"), err
