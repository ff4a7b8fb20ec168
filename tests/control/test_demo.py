"""``python -m camhealth.demo closed-loop`` on two street crops with a synthetic IOPC."""

import json

import pytest

from camhealth.demo import main, parse_slice
from tests.control.test_policy import BLUR_HATER
from tests.iopc.test_cli import crop_folder  # noqa: F401  (fixture)


def test_closed_loop_writes_plot_table_and_json(tmp_path, crop_folder, capsys):  # noqa: F811
    iopc_path = BLUR_HATER.save(tmp_path / "iopc.json")
    out = tmp_path / "demo"
    rc = main(["closed-loop", "--iopc", str(iopc_path), "--source", str(crop_folder), "--frames", "0:2",
               "--illumination", "60", "--motion", "1500", "--repeats", "2", "--out", str(out)])
    assert rc == 0
    assert {p.name for p in out.iterdir()} == {"closed_loop.png", "closed_loop.json", "closed_loop.md"}
    res = json.loads((out / "closed_loop.json").read_text())
    names = [r["controller"] for r in res["results"]]
    assert names == ["fixed", "auto-exposure", "IOPC policy"]
    assert all(0.0 <= r["ap"] <= 1.0 and len(r["ap_runs"]) == 2 for r in res["results"])
    assert res["decisions_per_repeat"] == [1, 1]
    iopc_traj = res["results"][2]["trajectory"]
    assert iopc_traj[0]["exposure_ms"] == pytest.approx(8.0) and iopc_traj[1]["exposure_ms"] < 8.0  # blur-hating IOPC
    assert res["decisions"][0]["explanation"].startswith("σ̂ =")
    table = (out / "closed_loop.md").read_text()
    assert "| IOPC policy |" in table and "26.1 %" in table and "| IOPC policy |" in capsys.readouterr().out


@pytest.mark.parametrize("repeats", ["0", "-1"])
def test_repeats_below_one_is_refused_by_the_parser(repeats, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:  # (before the IOPC file is looked for)
        main(["closed-loop", "--iopc", str(tmp_path / "none.json"), "--repeats", repeats])
    assert info.value.code == 2 and f"argument --repeats: must be >= 1, got {repeats}" in capsys.readouterr().err


def test_missing_iopc_and_slices(tmp_path):
    with pytest.raises(SystemExit, match="python -m camhealth.iopc"):
        main(["closed-loop", "--iopc", str(tmp_path / "none.json")])
    assert parse_slice("25:50") == slice(25, 50) and parse_slice("::2") == slice(None, None, 2)
    assert parse_slice("3") == slice(3, 4)
