"""Every jsonargparse command line takes its options from ``--config FILE`` as well as from flags, and
``--print_config`` writes a file that ``--config`` reads back to the same options; flag names are as before."""

from __future__ import annotations

import contextlib
import io

import pytest

from camhealth import corrupt, demo, evaluate, export, model_card
from camhealth.calibrate import __main__ as calibrate_cli


def _export_parser():
    return _parser_of(export.main, ["w.pt"])


def _model_card_parser():
    return _parser_of(model_card.main, ["w.pt", "--command", "c"])


def _parser_of(main, argv):
    """The parser a ``main`` builds inside itself, caught at ``parse_args``."""
    from jsonargparse import ArgumentParser

    caught = {}
    real = ArgumentParser.parse_args

    def spy(self, args=None, *a, **k):
        caught["parser"] = self
        raise _Caught

    ArgumentParser.parse_args = spy
    try:
        with pytest.raises(_Caught):
            main(argv)
    finally:
        ArgumentParser.parse_args = real
    return caught["parser"]


class _Caught(Exception):
    pass


CASES = {
    "corrupt": (corrupt.build_parser, ["deadleaves", "--out", "o", "--n", "3", "--defocus", "2", "5", "--no-noise"]),
    "evaluate": (evaluate.build_parser, ["--quick", "--checkpoint", "a.pt", "--checkpoint", "b.pt", "--seed", "3", "--no-plots"]),
    "calibrate": (calibrate_cli.build_parser, ["a/", "b.mp4", "--out", "cam.yaml", "--max-frames", "4", "--sensor-type", "CMOS",
                                               "--operating-point", "gain_db=12", "--operating-point", "exposure_s=0.01"]),
    "export": (_export_parser, ["w.pt", "--format", "onnx", "--out", "m.onnx"]),
    "model_card": (_model_card_parser, ["w.pt", "--command", "python -m camhealth.fit", "--notes", "n"]),
    # a subcommand: its own --config / --print_config come after its name
    "demo": (demo.build_parser, ["closed-loop", "--frames", "0:2", "--limits-gain", "0", "12", "--normalize-intensity"]),
}


def _clean(d) -> dict:
    """Options as plain data, without the --config entries (a subcommand's options nested under its name)."""
    d = d.as_dict() if hasattr(d, "as_dict") else d
    return {k: (_clean(v) if isinstance(v, dict) else v if isinstance(v, (list, bool, int, float, type(None))) else str(v))
            for k, v in d.items() if k != "config"}


@pytest.mark.parametrize("name", sorted(CASES))
def test_print_config_round_trips_through_config(name, tmp_path):
    build, argv = CASES[name]
    parser = build()
    direct = parser.parse_args(argv)
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as info:
        build().parse_args(argv + ["--print_config"])
    assert info.value.code == 0
    path = tmp_path / "cli.yaml"
    path.write_text(out.getvalue())
    sub = argv[:1] if name == "demo" else []
    again = build().parse_args(sub + ["--config", str(path)])
    assert _clean(again) == _clean(direct)
    # flags after --config override it
    if name == "corrupt":
        assert build().parse_args(["--config", str(path), "--n", "7"]).n == 7


def test_optional_positional_from_config_and_default(tmp_path):
    """corrupt's optional SOURCE positional comes from a config file too, and defaults to 'default'."""
    path = tmp_path / "c.yaml"
    path.write_text("source: skimage\nout: o\n")
    assert corrupt.build_parser().parse_args(["--config", str(path)]).source == "skimage"
    assert "source" not in corrupt.build_parser().parse_args(["--out", "o"])  # main() fills in 'default'


def test_demo_config_before_the_subcommand_covers_it(tmp_path):
    path = tmp_path / "demo.yaml"
    path.write_text("closed-loop:\n  frames: '3:9'\n  repeats: 2\n")
    args = demo.build_parser().parse_args(["--config", str(path), "closed-loop", "--seed", "4"])
    assert args.demo == "closed-loop" and args["closed-loop"].frames == "3:9" and args["closed-loop"].repeats == 2
    assert args["closed-loop"].seed == 4


def test_bad_values_still_exit_2_with_the_message(capsys):
    with pytest.raises(SystemExit) as info:
        calibrate_cli.main(["a/", "--out", "c.yaml", "--operating-point", "gain"])
    assert info.value.code == 2 and "expected FIELD=VALUE, got 'gain'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        calibrate_cli.build_parser().parse_args(["a/", "--out", "c.yaml", "--max-frames", "0"])
    assert info.value.code == 2 and "must be >= 1, got 0" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        export.main(["w.pt", "--format", "tflite"])
    assert info.value.code == 2 and "tflite" in capsys.readouterr().err


def test_bad_value_in_a_config_file_exits_2_with_the_message(tmp_path, capsys):
    """A value an option's type refuses is the same one-line error from a --config file (no traceback)."""
    path = tmp_path / "c.yaml"
    path.write_text("frames: [a/]\nout: c.yaml\nmax_frames: 0\n")
    with pytest.raises(SystemExit) as info:
        calibrate_cli.main(["--config", str(path)])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "must be >= 1, got 0" in err and "Traceback" not in err
