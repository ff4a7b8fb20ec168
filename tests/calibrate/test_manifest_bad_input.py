"""``camhealth.calibrate.manifest`` on input that broke it: YAML keys given twice, CSV files with a byte-order mark or
more values than their header, paths too long to look up or missing under a long name, files that cannot be read,
and a manifest that is a folder or a FIFO."""

import os
import re

import pytest

from camhealth.calibrate import read_manifest

SET = "{kind: dark, path: d, exposure_s: 0.2, gain_db: 0, temperature_c: 25}"
SET_ROW = "bias,d,0.001,0,25,b"


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "d").mkdir()
    return tmp_path


@pytest.mark.parametrize("text, line, key, first, second", [
    ("sets:\n  - {kind: dark, path: d, exposure_s: 0.2, exposure_s: 0.4, gain_db: 0, temperature_c: 25}\n", "line 2",
     "exposure_s", "0.2", "0.4"),
    ("sets:\n  - kind: dark\n    path: d\n    exposure_s: 0.2\n    gain_db: 0\n    temperature_c: 25\n    gain_db: 12\n",
     "lines 5 and 7", "gain_db", "0", "12"),
    (f"defaults: {{gain_db: 0}}\nsets:\n  - {SET}\ndefaults: {{gain_db: 12}}\n", "lines 1 and 4", "defaults",
     "a mapping", "a mapping"),
    (f"camera:\n  pixel_size_um: 5.3\n  pixel_size_um: 6.45\nsets:\n  - {SET}\n", "lines 2 and 3", "pixel_size_um", "5.3", "6.45"),
])
def test_a_yaml_key_given_twice_is_refused_naming_the_line_the_key_and_both_values(text, line, key, first, second, folder):
    """YAML keeps the last of two equal keys silently: exposure_s 0.2 then 0.4 calibrated at 0.4 s (dark current −51 %)."""
    p = folder / "m.yaml"
    p.write_text(text)
    with pytest.raises(ValueError, match=rf"^manifest {re.escape(str(p))}: {line}: key '{key}' is given twice in one mapping "
                                         rf"\('?{first}'? and '?{second}'?\)"):
        read_manifest(p)


@pytest.mark.parametrize("header", ["kind,path,exposure_s,gain_db,temperature_c,name", "path,kind,exposure_s,gain_db,temperature_c"])
def test_a_csv_with_a_utf8_byte_order_mark_is_read(header, folder):
    """Excel saves CSV with a byte-order mark; the header's first column was read as '\\ufeffkind' and refused."""
    p = folder / "m.csv"
    row = {"kind": "dark", "path": "d", "exposure_s": "0.2", "gain_db": "0", "temperature_c": "25", "name": "dk"}
    p.write_text(header + "\n" + ",".join(row[h] for h in header.split(",")) + "\n", encoding="utf-8-sig")
    (fs,) = read_manifest(p).sets
    assert fs.kind == "dark" and fs.exposure_s == 0.2 and fs.paths == [folder / "d"]


@pytest.mark.parametrize("row, n, extra", [("dark,d,0.2,0,25,dk,12", 1, "['12']"), ("dark,d,0.2,0,25,,x,y", 2, "['x', 'y']")])
def test_a_csv_row_with_more_values_than_the_header_is_refused_naming_the_row_and_the_values(row, n, extra, folder):
    """A value beyond the header (a bit_depth without its column) was dropped silently."""
    p = folder / "m.csv"
    p.write_text("kind,path,exposure_s,gain_db,temperature_c,name\n" + f"{SET_ROW}\n" + row + "\n")
    with pytest.raises(ValueError, match=rf"^manifest {re.escape(str(p))}, set 2 \(line 3\): {n} value\(s\) beyond the header's 6 "
                                         rf"columns \(kind,path,exposure_s,gain_db,temperature_c,name\): {re.escape(extra)}"):
        read_manifest(p)
    # empty fields beyond the header (a trailing comma, as spreadsheets write them) hold nothing: accepted
    p.write_text("kind,path,exposure_s,gain_db,temperature_c,name\n" + SET_ROW + ",,\n")
    assert read_manifest(p).sets[0].name == "b"


@pytest.mark.parametrize("path, error, message", [
    ("a" * 5000, ValueError, r"set 1: path a{60}…a{59} \(5000 characters\) cannot be used: File name too long$"),
    ("d/" * 1500 + "x", FileNotFoundError, r"names 1 missing file\(s\)/folder\(s\):\n  manifest .*, set 1 \(dark\): .{60}….{59} "
                                           r"\(\d+ characters\)$"),
], ids=["a name of 5000 characters", "a missing path of 3001 characters"])
def test_a_very_long_path_is_named_shortened_with_the_manifest_and_the_set(path, error, message, folder):
    """A 5000-character path raised a bare OSError ([Errno 36] File name too long) echoing all of it, naming neither the
    manifest nor the set; a missing path was listed whole, however long."""
    p = folder / "m.yaml"
    p.write_text(f"sets:\n  - {{kind: dark, path: '{path}', exposure_s: 0.2, gain_db: 0, temperature_c: 25}}\n")
    with pytest.raises(error, match=rf"^manifest {re.escape(str(p))}(, set 1: path| names).*") as info:
        read_manifest(p)
    assert re.search(message, str(info.value)) and len(str(info.value)) < 400


@pytest.mark.parametrize("path", ["d", "f.png", "*.png"])
def test_a_file_or_folder_that_cannot_be_read_is_named_with_the_manifest_and_the_set(path, folder, monkeypatch):
    """Files the process may not read were accepted, and failed later without naming the manifest or the set."""
    (folder / "f.png").write_bytes(b"")
    p = folder / "m.yaml"
    p.write_text(f"sets:\n  - {{kind: dark, path: '{path}', exposure_s: 0.2, gain_db: 0, temperature_c: 25}}\n")
    monkeypatch.setattr(os, "access", lambda *a, **k: False)  # as for a user without read permission
    name = "d" if path == "d" else "f.png"
    with pytest.raises(ValueError, match=rf"^manifest {re.escape(str(p))} names 1 file\(s\)/folder\(s\) it cannot read "
                                         rf"\(permission\):\n  manifest .*, set 1 \(dark\): {re.escape(str(folder / name))} \(not readable\)$"):
        read_manifest(p)


@pytest.mark.parametrize("kind", ["folder", "fifo"])
def test_a_manifest_that_is_not_a_regular_file_is_named_so(kind, tmp_path):
    """A folder or a FIFO named m.yaml was reported as "manifest not found", although it exists."""
    p = tmp_path / "m.yaml"
    p.mkdir() if kind == "folder" else os.mkfifo(p)
    with pytest.raises(ValueError, match=rf"^manifest {re.escape(str(p))} is not a regular file \(a folder, FIFO or device\)"):
        read_manifest(p)
