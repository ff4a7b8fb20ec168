"""The generated documentation: CLI reference, API reference (pdoc), generated blocks, no development diary."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from camhealth.docs import CLI_COMMANDS, build_api, cli_help, command_key, generated_blocks, help_options, main, replace_generated

ROOT = Path(__file__).resolve().parents[1]
CLI_DOC = ROOT / "docs" / "cli.md"


def _sections(text: str) -> dict[str, str]:
    parts = re.split(r"^## `(.+)`$", text, flags=re.M)
    return {parts[i]: parts[i + 1] for i in range(1, len(parts), 2)}


def test_cli_reference_lists_exactly_each_commands_options():
    """docs/cli.md was generated from the parsers as they are: every option of every command is listed in its section,
    and nothing else (regenerate: python -m camhealth.docs cli --out docs/cli.md)."""
    sections = _sections(CLI_DOC.read_text(encoding="utf-8"))
    for module, args in CLI_COMMANDS:
        command = " ".join(["python -m", module, *args])
        assert command in sections, f"{command} missing from docs/cli.md"
        now, documented = help_options(cli_help(module, args)), help_options(sections[command])
        assert now == documented, f"{command}: not documented {sorted(now - documented)}, gone {sorted(documented - now)}"


def test_cli_help_of_an_unknown_subcommand_is_an_error():
    with pytest.raises(RuntimeError, match="no-such-benchmark"):
        cli_help("camhealth.bench", ("no-such-benchmark",))


def test_api_reference_builds_without_warnings(tmp_path):
    pytest.importorskip("pdoc", reason="the docs extra (pip install -e '.[docs]')")
    out = build_api(tmp_path / "api", strict=True)
    pages = {p.relative_to(out).as_posix() for p in out.rglob("*.html")}
    for page in ("camhealth/physics/readout_noise.html", "camhealth/estimators/physics_noise.html",
                 "camhealth/nets/mtf.html", "datamodules.html", "lightning_modules.html"):
        assert page in pages
    assert "readout_sigma_e" in (out / "camhealth/physics/readout_noise.html").read_text(encoding="utf-8")


def test_replace_generated_keeps_the_rest_of_the_page(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("# Title\n\nprose before\n\n<!-- generated: python -m x --a 1 -->\nold\n<!-- end generated -->\n\nafter\n")
    assert replace_generated(page, "python -m x --a 1", "| new |\n") is True
    assert page.read_text() == "# Title\n\nprose before\n\n<!-- generated: python -m x --a 1 -->\n| new |\n<!-- end generated -->\n\nafter\n"
    assert replace_generated(page, "python -m y", "other") is False  # another command: a new block at the end
    assert [c for c, _, _ in generated_blocks(page.read_text())] == ["python -m x --a 1", "python -m y"]
    page.write_text("<!-- generated: python -m z -->\nno end\n")
    with pytest.raises(ValueError, match="python -m z.*end marker"):
        generated_blocks(page.read_text())


def test_replace_generated_matches_the_command_not_its_spelling(tmp_path):
    """``--opt=value`` and ``--opt value``, option order and ``--markdown`` name the same block; other values do not."""
    page = tmp_path / "p.md"
    page.write_text("<!-- generated: python -m b robustness --frames 16 --threads 2 --markdown -->\nold\n<!-- end generated -->\n")
    assert replace_generated(page, "python -m b robustness --threads=2 --frames=16", "new") is True
    ((command, start, end),) = generated_blocks(page.read_text())
    assert command == "python -m b robustness --frames 16 --threads 2 --markdown"  # the marker as written
    assert page.read_text()[start:end] == "new\n"
    for other in ("python -m b robustness --frames 8 --threads 2", "python -m b robustness --frames 16",
                  "python -m b mtf_error --frames 16 --threads 2", "python -m b robustness --frames 16 --threads 2 --seed 3"):
        assert command_key(other) != command_key(command), other
    assert command_key("python -m b estimators --models a b --no-reference") == command_key(
        "python -m b estimators --no-reference --models a b")
    assert command_key("python -m b estimators --models a b") != command_key("python -m b estimators --models b a")


def test_docs_pages_name_the_command_of_each_generated_block(capsys):
    main(["tables", str(ROOT / "docs" / "benchmarks.md")])
    commands = capsys.readouterr().out.split("\n")
    assert "python -m camhealth.bench robustness --frames 16 --threads 2 --markdown" in commands


def test_bench_docs_flag_writes_the_block_of_its_command(tmp_path, monkeypatch):
    from camhealth.bench import __main__ as bench_main

    page = tmp_path / "b.md"
    page.write_text("intro\n")
    bench_main.main(["data", "--batch", "2", "--repeats", "1", "--warmup", "0", "--docs", str(page)])
    text = page.read_text()
    ((command, start, end),) = generated_blocks(text)
    assert command == "python -m camhealth.bench data --batch 2 --repeats 1 --warmup 0"
    assert text.startswith("intro\n") and "| row |" in text[start:end]


def test_no_development_diary_in_the_product():
    """README, docs, model cards, docstrings and tests speak of the product; history is in git and CHANGELOG.md."""
    out = subprocess.run(["git", "grep", "-n", "-i", "-E", r"session [0-9]", "--", ".", ":!CHANGELOG.md"],
                         cwd=ROOT, capture_output=True, text=True)
    if out.returncode not in (0, 1):
        pytest.skip("not a git checkout")
    assert out.stdout == "", out.stdout


def _generated(text: str, command_start: str) -> list[str]:
    """The contents of the generated blocks of ``text`` whose command starts with ``command_start``."""
    return [text[start:end] for command, start, end in generated_blocks(text) if command.startswith(command_start)]


def test_benchmark_prose_states_the_numbers_of_its_generated_tables():
    """docs/benchmarks.md's prose next to a generated table quotes that table: the largest RMS of the MTF error table
    (it said ≈ 0.18; the table peaks at 0.166) and the range of the recording-read rows in ms and % (it said
    0.7–1.1 ms, 1.6–2.4 %; the tables say 2.1–2.6 ms, 2.2–4.0 %)."""
    text = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    (mtf,) = _generated(text, "python -m camhealth.bench mtf_error")
    knots = re.search(r"^\| Ĥ \|(.*)\|$", mtf, re.M).group(1).split("|")
    rms = [float(v) for v in re.search(r"^\| RMS \|(.*)\|$", mtf, re.M).group(1).split("|")]
    top = max(range(len(rms)), key=rms.__getitem__)
    stated = re.search(r"at most ([0-9.]+) at Ĥ = ([0-9.]+) in the table below", text)
    assert stated, "the MTF error prose states the table's largest RMS"
    assert float(stated.group(1)) == rms[top] and float(stated.group(2)) == float(knots[top])
    rows = [m for block in _generated(text, "python -m camhealth.bench monitor --threads 2 --frames 16")
            for m in re.findall(r"\| reading the recording \(\.\w+\) \| ([0-9.]+) \|.*?; ([0-9.]+) % of", block)]
    assert len(rows) >= 6
    ms, pct = [float(a) for a, _ in rows], [float(b) for _, b in rows]
    claim = re.search(r"frame costs\s+\*\*([0-9.]+)–([0-9.]+) ms\*\*.*?\*\*([0-9.]+)–([0-9.]+) % of the adaptive", text, re.S)
    assert claim, "the recording-read prose states a range"
    assert (float(claim.group(1)), float(claim.group(2))) == (min(ms), max(ms))
    assert (float(claim.group(3)), float(claim.group(4))) == (min(pct), max(pct))


def test_the_readme_start_runs_and_says_what_it_returns():
    """The README's 2-minute start, as a user copies it (its GPU line left out): every patch is read, ξ is the gain
    mismatch it shows (−1.0 … −2.1 DN, the cause the gain), the σ per source are near the comment's, and with the right
    metadata the answer is the closed form."""
    import torch

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    block = re.search(r"## A 2-minute start.*?```python\n(.*?)```", text, flags=re.S).group(1)
    code = "\n".join(line for line in block.splitlines() if 'device="cuda"' not in line)
    env: dict = {}
    exec(compile(code, "README.md", "exec"), env)  # noqa: S102 - the project's own README
    out, noise = env["out"], env["noise"]
    assert out["assessable"].all() and set(out["reason"]) == {""}
    assert (out["xi"] > -2.2).all() and (out["xi"] < -0.95).all() and (out["cause"].argmax(1) == 0).all()
    assert torch.allclose(out["sigma"][0], torch.tensor([3.1, 0.11, 1.0]), atol=0.06)
    assert (out["p_match"] < 0.01).all() and out["sigma"].shape == (16, 3) and out["cause"].shape == (16, 4)
    right = noise.predict(env["patches_128"], env["camera"], pool=True)
    assert (right["xi"] == 0).all() and (right["p_match"] > 0.99).all()
    mtf = env["blur"].predict(env["patches_192"])
    assert mtf["mtf"].shape == (2, 16) and mtf["assessable"].all()
