"""IOPC binning, 1-D/2-D curves, marked cells, MTF→length relation, JSON/NPZ round trip."""

import json
import math
import re

import numpy as np
import pytest
import torch

from camhealth.iopc import IOPC, MTF_BINS, SIGMA_BINS_DN, bin_index


def _records():
    """Noise 0/5/10 DN × motion 0/7/15 px; AP falls with both; MTF̃ from the sinc at f = 0.05 c/px."""
    recs = []
    for s in (0.0, 5.0, 10.0):
        for L, mtf in ((0.0, 1.0), (7.0, 0.81), (15.0, 0.62)):
            recs.append({"index": len(recs), "key": f"L{L}_s{s}", "length_px": L, "angle_deg": 0.0,
                         "noise_level_dn": s, "sigma_tilde": s + 0.3, "mtf_tilde": mtf,
                         "ap": max(0.0, 1.0 - 0.05 * s - 0.03 * L), "marked": False, "reason": ""})
    recs.append({"index": 9, "key": "far", "length_px": 0.0, "angle_deg": 0.0, "noise_level_dn": 40.0,
                 "sigma_tilde": 41.0, "mtf_tilde": 1.0, "ap": 0.0})
    recs.append({"index": 10, "key": "pre", "length_px": 0.0, "angle_deg": 0.0, "noise_level_dn": 50.0,
                 "sigma_tilde": float("nan"), "mtf_tilde": float("nan"), "ap": float("nan"), "marked": True,
                 "reason": "noise level not reachable"})
    return recs


def test_bin_index_nearest_and_outside():
    idx, inside = bin_index([0.0, 2.4, 2.6, 31.0, 32.6, -3.0, float("nan")], SIGMA_BINS_DN)
    assert idx.tolist()[:4] == [0, 0, 1, 6]
    assert inside.tolist() == [True, True, True, True, False, False, False]
    idx, inside = bin_index([0.04, 0.06, 1.0, 1.06], MTF_BINS)
    assert inside.tolist() == [False, True, True, False] and idx[1] == 0


def test_from_records_curves_and_marks():
    iopc = IOPC.from_records(_records(), provenance={"who": "test"}, name="AP test")
    assert iopc.ap_2d.shape == (7, 10) and iopc.count_2d.sum() == 9
    assert iopc.ap_2d[0, 9] == 1.0 and iopc.ap_2d[2, 5] == pytest.approx(1.0 - 0.5 - 0.45)
    assert iopc.ap_2d[0, 7] == pytest.approx(1 - 0.21)  # MTF̃ 0.81 → bin 0.8
    assert np.isnan(iopc.ap_2d[3, 0])
    # 1-D curves: isolated noise (L = 0) and isolated blur (σ = 0)
    assert iopc.count_sigma.tolist() == [1, 1, 1, 0, 0, 0, 0]
    assert iopc.ap_sigma[:3].tolist() == pytest.approx([1.0, 0.75, 0.5])
    assert iopc.count_mtf[[5, 7, 9]].tolist() == [1, 1, 1]
    marked = {r["key"]: r["reason"] for r in iopc.marked_records}
    assert set(marked) == {"far", "pre"} and "outside the IOPC bins" in marked["far"]
    assert marked["pre"] == "noise level not reachable"
    # MTF → motion-length relation from the noise-free cells, non-increasing
    assert iopc.blur_length_px.tolist() == [0.0, 7.0, 15.0]
    assert iopc.blur_mtf.tolist() == pytest.approx([1.0, 0.81, 0.62])
    assert iopc.length_from_mtf(0.81) == pytest.approx(7.0)
    assert iopc.mtf_from_length(iopc.length_from_mtf(0.7)) == pytest.approx(0.7)


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_round_trip(tmp_path, suffix):
    iopc = IOPC.from_records(_records(), provenance={"grid": [1, 2], "nested": {"a": None}}, name="AP x")
    back = IOPC.load(iopc.save(tmp_path / f"curves{suffix}"))
    assert back.to_dict() == iopc.to_dict()
    np.testing.assert_array_equal(back.count_2d, iopc.count_2d)
    np.testing.assert_allclose(back.ap_2d, iopc.ap_2d, equal_nan=True)
    assert back.name == "AP x" and back.provenance["grid"] == [1, 2]
    assert math.isnan(next(r for r in back.records if r["key"] == "pre")["ap"])


def test_surface_fill_and_interpolation():
    iopc = IOPC.from_records(_records())
    surf, measured = iopc.surface()
    assert measured.sum() == 9 and np.isfinite(surf).all()
    assert surf[6, 9] == iopc.ap_2d[2, 9]  # nearest measured bin
    assert float(iopc.interpolate(10.0, 0.6)) == pytest.approx(iopc.ap_2d[2, 5])
    mid = float(iopc.interpolate(2.5, 1.0))
    assert mid == pytest.approx(0.5 * (iopc.ap_2d[0, 9] + iopc.ap_2d[1, 9]))
    assert iopc.interpolate(np.zeros((2, 3)), np.ones((2, 3))).shape == (2, 3)


def test_validation_errors(tmp_path):
    with pytest.raises(ValueError, match="missing 'ap'"):
        IOPC.from_records([{"sigma_tilde": 1, "mtf_tilde": 1, "length_px": 0, "noise_level_dn": 0}])
    with pytest.raises(ValueError, match="strictly increasing"):
        IOPC.from_records(_records(), sigma_bins=[0, 5, 5])
    iopc = IOPC.from_records(_records())
    with pytest.raises(ValueError, match=".json or .npz"):
        iopc.save(tmp_path / "x.txt")
    (tmp_path / "y.json").write_text('{"format": "other"}')
    with pytest.raises(ValueError, match="not a camhealth IOPC"):
        IOPC.load(tmp_path / "y.json")
    with pytest.raises(ValueError, match="no measured bin"):
        IOPC.from_records(_records()[-1:]).surface()


def test_figure():
    import matplotlib.pyplot as plt

    fig = IOPC.from_records(_records()).figure()
    assert len(fig.axes) >= 3
    plt.close(fig)


def test_npz_with_pickled_arrays_is_refused_naming_the_file(tmp_path):
    from tests._evil_files import Payload

    marker = tmp_path / "MARKER"
    path = tmp_path / "evil.npz"
    np.savez(path, meta_json=np.array([Payload(marker)], dtype=object), ap_2d=np.zeros((2, 2)))
    with pytest.raises(ValueError, match=f"{path}: holds pickled Python objects.*refuses pickled arrays"):
        IOPC.load(path)
    assert not marker.exists()


@pytest.mark.parametrize("name, data, why", [
    ("a.json", b"{x", r"not valid JSON: Expecting property name .* at line 1, column 2"),
    ("b.json", b"[1]", "it holds a JSON list, not an object"),
    ("c.json", b'{"format": "camhealth-iopc"}', "missing entry 'sigma_bins_dn'"),
    ("d.json", '{"format": "camhealth-iopc", "name": "caméra"}'.encode("latin-1"), "not UTF-8 text"),
    ("e.json", b'{"format": "camhealth-iopc", "version": "x"}', r"version = 'x' is out of the allowed range: an integer in \[0, 1\]"),
    ("f.npz", b"not a zip", "an .npz file is a zip archive; this one is not"),
    ("g.npz", b"", "an .npz file is a zip archive; this one is not"),
    ("h.npz", None, "missing entry 'meta_json'"),
    ("i.npz", "[1]", "meta_json holds a JSON list, not an object"),
])
def test_load_errors_name_the_file_and_why(name, data, why, tmp_path):
    """A file that is not an IOPC file is one ValueError naming it, never a raw parser error nor numpy's
    allow_pickle advice."""
    path = tmp_path / name
    if isinstance(data, bytes):
        path.write_bytes(data)
    else:
        np.savez(path, **({"a": np.zeros(3)} if data is None else {"meta_json": np.array(data)}))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: not a camhealth IOPC file \((.*){why}") as info:
        IOPC.load(path)
    assert "allow_pickle" not in str(info.value)


def _with(iopc, **fields):
    d = iopc.to_dict()
    for k, v in fields.items():
        d["blur_relation" if k in ("length_px", "mtf") else k] = (
            {**d["blur_relation"], k: v} if k in ("length_px", "mtf") else v)
    return IOPC.from_dict(d)


@pytest.mark.parametrize("fields, match", [
    ({"length_px": [15.0, 7.0, 0.0], "mtf": [0.62, 0.81, 1.0]}, "strictly increasing"),  # the relation listed backwards
    ({"length_px": [0.0, 7.0, 15.0], "mtf": [1.0, 0.81, 0.9]}, "must not increase"),
    ({"length_px": [0.0, 7.0, 15.0], "mtf": [1.0, None, 0.62]}, "must be finite"),
    ({"length_px": [-1.0, 7.0, 15.0], "mtf": [1.0, 0.81, 0.62]}, "≥ 0 px"),
])
def test_a_blur_relation_that_cannot_be_inverted_is_refused(fields, match):
    """A reversed, rising or non-finite MTF → length relation would make the policy decide wrong (the reversed one
    read MTF̃ 1 at 5 px): refused naming it."""
    with pytest.raises(ValueError, match=match):
        _with(IOPC.from_records(_records()), **fields)


@pytest.mark.parametrize("value, match", [(None, "be a number wherever the bin counts"), (float("inf"), r"must lie in \[0, 1\]"),
                                          (1.5, r"must lie in \[0, 1\]")])
def test_ap_of_a_counted_bin_must_be_a_number_in_0_1(value, match):
    d = IOPC.from_records(_records()).to_dict()
    d["ap_2d"][0][9] = value  # a bin with detections
    with pytest.raises(ValueError, match=r"IOPC.ap_2d\[0, 9\]"):
        IOPC.from_dict(d)
    with pytest.raises(ValueError, match=match):
        IOPC.from_dict(d)


def test_length_from_mtf_inverts_the_relation_across_a_flat_stretch():
    """L = 0, 5, 10, 15 px read MTF̃ 1, 0.8, 0.8, 0.5 (a running minimum's plateau): a value on the plateau is its
    smallest length; one below it interpolates from its largest, so the round trip holds (0.6 → 13.3 px → 0.6, where
    interpolating from the plateau's smallest length gave 11.7 px and read 0.7 back)."""
    iopc = _with(IOPC.from_records(_records()), length_px=[0.0, 5.0, 10.0, 15.0], mtf=[1.0, 0.8, 0.8, 0.5])
    assert float(iopc.length_from_mtf(0.6)) == pytest.approx(10.0 + 5.0 * 2.0 / 3.0)
    for v in (1.0, 0.9, 0.8, 0.7, 0.6, 0.5):
        assert float(iopc.mtf_from_length(iopc.length_from_mtf(v))) == pytest.approx(v)
    assert float(iopc.length_from_mtf(0.8)) == 5.0 and float(iopc.length_from_mtf(1.0)) == 0.0
    assert float(iopc.length_from_mtf(0.3)) == 15.0 and math.isnan(float(iopc.length_from_mtf(float("nan"))))
    assert iopc.length_from_mtf(np.array([[0.9, 0.6]])).shape == (1, 2)


def _set(d, path, value):
    *head, last = path
    for k in head:
        d = d[k]
    d[last] = value


@pytest.mark.parametrize("path, value, match", [
    (("count_2d", 0, 9), 0.9, r"IOPC.count_2d\[0, 9\] = 0.9 is out of the allowed range: a whole number >= 0"),
    (("count_2d", 0, 9), -5, r"IOPC.count_2d\[0, 9\] = -5 is out of the allowed range: a whole number >= 0"),
    (("count_2d", 0, 9), 1e19, r"IOPC.count_2d\[0, 9\] = 1e\+19 is out of the allowed range: a whole number >= 0 and <= 2\^53"),
    (("count_2d", 0, 9), 2**64 + 5, r"IOPC.count_2d\[0, 9\] = 1.84467e\+19 is out of the allowed range: .* <= 2\^53"),
    (("count_mtf", 9), 10**400, r"IOPC.count_mtf\[9\] = an integer of 401 digits is out of the allowed range"),
    (("ap_2d", 0, 9), 10**400, r"IOPC.ap_2d\[0, 9\] = an integer of 401 digits is out of the allowed range: a number in"),
    (("blur_relation", "noise_level_dn"), 10**400, r"IOPC.blur_noise_level_dn = an integer of 401 digits is out of the"),
    (("count_sigma", 0), True, r"IOPC.count_sigma\[0\] = True is not a number; allowed: a whole number >= 0"),
    (("ap_2d", 0, 9), "0.7", r"IOPC.ap_2d\[0, 9\] = '0.7' is not a number; allowed: a number in \[0, 1\]"),
    (("ap_mtf", 9), False, r"IOPC.ap_mtf\[9\] = False is not a number; allowed: a number in \[0, 1\]"),
    (("sigma_bins_dn", 0), -5.0, r"IOPC.sigma_bins = \[-5.0, 5.0, .*\] is out of the allowed range: .* >= 0 DN"),
    (("mtf_bins", 9), 1.5, r"IOPC.mtf_bins = \[0.1, .*, 1.5\] is out of the allowed range: .* in \[0, 1\]"),
    (("blur_relation", "mtf"), [5.0, 0.81, 0.62], r"IOPC.blur_mtf \[5.0, 0.81, 0.62\] is out of the allowed range \[0, 1\]"),
    (("blur_relation", "mtf"), [1.0, 0.81, -2.0], r"IOPC.blur_mtf \[1.0, 0.81, -2.0\] is out of the allowed range \[0, 1\]"),
    (("version",), 1.9, r"version = 1.9 is out of the allowed range: an integer in \[0, 1\]"),
    (("version",), True, r"version = True is out of the allowed range: an integer in \[0, 1\]"),
])
def test_load_refuses_wrong_typed_and_out_of_range_fields_naming_file_field_value_and_range(path, value, match, tmp_path):
    """A count of 0.9 was truncated to an empty bin (its AP replaced by a neighbour's in surface()), 1e19 wrapped to a
    negative int64 (the clean bin then read as empty), 10^400 escaped as an OverflowError, -5 and true were
    kept as counts, the AP "0.7" was read as a number, σ̃ bins below 0 DN, a relation MTF̃ of 5 and a version of 1.9
    or true were accepted: each is refused, naming the file, the field, the value and the allowed range."""
    d = IOPC.from_records(_records()).to_dict()
    _set(d, path, value)
    file = tmp_path / "bad.json"
    file.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(file))}: .*{match}"):
        IOPC.load(file)


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_blur_relation_records_the_noise_level_it_was_measured_at(tmp_path, suffix):
    """A sweep without σ = 0 cells measures the MTF → length relation on its lowest level (here 5 DN), not on
    noise-free cells: the IOPC says so, and the level survives the file round trip."""
    noisy = [r for r in _records() if r["noise_level_dn"] > 0]
    iopc = IOPC.from_records(noisy)
    assert iopc.blur_noise_level_dn == 5.0
    assert iopc.blur_mtf.tolist() == pytest.approx([1.0, 0.81, 0.62])
    back = IOPC.load(iopc.save(tmp_path / f"curves{suffix}"))
    assert back.blur_noise_level_dn == 5.0 and back.to_dict() == iopc.to_dict()
    assert IOPC.from_records(_records()).blur_noise_level_dn == 0.0


def test_deeply_nested_files_are_a_value_error_naming_the_file(tmp_path):
    """200 kB of brackets, and a valid IOPC whose ap_2d is wrapped in 900 extra list levels, escaped IOPC.load as a
    RecursionError (from the JSON parser and from the constructor's recursive walk) instead of the documented
    ValueError."""
    brackets = tmp_path / "brackets.json"
    brackets.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(brackets))}: not a camhealth IOPC file \(nested too deeply"):
        IOPC.load(brackets)
    d = IOPC.from_records(_records()).to_dict()
    for _ in range(900):
        d["ap_2d"] = [d["ap_2d"]]
    deep = tmp_path / "deep.json"
    deep.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(deep))}: not a camhealth IOPC file \(IOPC.ap_2d\[0, 0\] is "
                                         r"nested deeper than the field's 2 dimension\(s\)"):
        IOPC.load(deep)
    with pytest.raises(ValueError, match=r"IOPC.ap_2d\[0, 0\] is nested deeper"):
        IOPC.from_dict(d)


@pytest.mark.parametrize("field, value, match", [
    ("records", "abc", r"records must be a list of objects \(one per sweep cell\), got str 'abc'"),
    ("records", [1, 2], r"records must be a list of objects"),
    ("provenance", [1, 2], r"provenance must be an object, got list \[1, 2\]"),
    ("provenance", {"estimator_specs": "physics"}, r"provenance.estimator_specs must be an object, got str 'physics'"),
    ("blur_relation", [0, 1], r"blur_relation must be an object with length_px and mtf"),
])
def test_a_malformed_section_of_an_iopc_file_is_named(field, value, match):
    d = IOPC.from_records(_records()).to_dict()
    d[field] = value
    with pytest.raises(ValueError, match=match):
        IOPC.from_dict(d)


def test_queries_refuse_what_is_not_a_value_of_their_axis():
    """σ < 0, an MTF outside [0, 1], a negative length, text and booleans were clamped or converted into a confident
    AP or length (σ −5 read as the 0-DN bin, MTF 7 as sharp, "0.7" as 0.7, a length of −5 px as MTF 1)."""
    iopc = IOPC.from_records(_records())
    for call, match in [
        (lambda: iopc.interpolate(-5.0, 0.5), r"sigma \[DN\] = -5 is out of the allowed range: numbers in \[0, inf\]"),
        (lambda: iopc.interpolate(float("inf"), 0.5), r"sigma \[DN\] = inf is out of the allowed range"),
        (lambda: iopc.interpolate(5.0, 7.0), r"mtf = 7 is out of the allowed range: numbers in \[0, 1\] \(MTF values\)"),
        (lambda: iopc.interpolate(np.array([1.0, -0.1]), 0.5), r"sigma \[DN\] = -0.1 is out"),
        (lambda: iopc.length_from_mtf(-1.0), r"mtf = -1 is out of the allowed range"),
        (lambda: iopc.length_from_mtf(2.0), r"mtf = 2 is out of the allowed range"),
        (lambda: iopc.mtf_from_length(-5.0), r"length_px \[px\] = -5 is out of the allowed range"),
    ]:
        with pytest.raises(ValueError, match=match):
            call()
    for bad in ("0.7", True, None, ["0.7"], np.array([True])):
        with pytest.raises(TypeError, match="number"):
            iopc.length_from_mtf(bad)
        with pytest.raises(TypeError, match="number"):
            iopc.interpolate(bad, 0.5)
        with pytest.raises(TypeError, match="number"):
            iopc.mtf_from_length(bad)
    # what stays allowed: NaN gives NaN, 1 + float rounding is MTF 1, tensors and integer arrays read as numbers
    assert math.isnan(float(iopc.interpolate(float("nan"), 0.5)))
    assert float(iopc.length_from_mtf(1.0 + 1e-9)) == float(iopc.length_from_mtf(1.0))
    assert float(iopc.mtf_from_length(torch.tensor(3.0))) == float(iopc.mtf_from_length(3))


def test_a_relation_that_does_not_fall_tells_no_length():
    """A flat relation (MTF̃ 1 at every swept length) is a valid IOPC file, but it read MTF 0.5 as 0 px of blur."""
    iopc = _with(IOPC.from_records(_records()), length_px=[0.0, 1.0], mtf=[1.0, 1.0])
    with pytest.raises(ValueError, match="does not fall with the motion length"):
        iopc.length_from_mtf(0.5)


@pytest.mark.parametrize("key, value, match", [
    ("ap", True, r"record 2: ap = True is not allowed: a number in \[0, 1\]"),
    ("ap", "0.3", r"record 2: ap = '0.3' is not allowed"),
    ("ap", 1.5, r"record 2: ap = 1.5 is out of the allowed range: a number in \[0, 1\]"),
    ("sigma_tilde", -2.0, r"record 2: sigma_tilde = -2 is out of the allowed range: a number >= 0 DN"),
    ("mtf_tilde", -0.1, r"record 2: mtf_tilde = -0.1 is out of the allowed range"),
    ("length_px", True, r"record 2: length_px = True is not allowed: a finite number >= 0 px"),
    ("length_px", None, r"record 2: length_px = None is not allowed"),
    ("noise_level_dn", float("nan"), r"record 2: noise_level_dn = nan is out of the allowed range: a finite number >= 0 DN"),
    ("noise_level_dn", 10**400, r"record 2: noise_level_dn = an integer of 401 digits is not allowed"),
    ("marked", "false", r"record 2: marked = 'false' is not allowed: true or false"),
])
def test_from_records_refuses_a_field_no_sweep_writes(key, value, match):
    """Booleans and text were binned as numbers (ap True as AP 1), "false" marked a cell, and a NaN noise level in
    the first record emptied the blur relation."""
    recs = _records()
    recs[2] = {**recs[2], key: value}
    with pytest.raises(ValueError, match=match):
        IOPC.from_records(recs)


def test_from_records_refuses_what_is_not_a_list_of_records():
    with pytest.raises(TypeError, match="record 1 must be a mapping"):
        IOPC.from_records([_records()[0], 2])
    with pytest.raises(TypeError, match="records must be a list"):
        IOPC.from_records({"a": 1})


def test_an_estimate_slightly_above_1_stays_in_the_relation_as_1():
    """A sharp frame's MTF̃ of 1.02 falls inside the 1.0 bin, and the IOPC failed to build, naming neither record nor
    cause; the relation now holds it as 1."""
    recs = [dict(r) for r in _records()]
    for r in recs:
        if float(r["length_px"]) == 0.0:
            r["mtf_tilde"] = 1.02
    iopc = IOPC.from_records(recs)
    assert float(iopc.blur_mtf[0]) == 1.0


def test_an_npz_claiming_a_huge_array_is_refused_before_anything_is_allocated(tmp_path):
    """A header claiming shape (10^13,) raised a bare MemoryError (72.8 TiB) without the file's name."""
    import io
    import zipfile

    good = tmp_path / "good.npz"
    IOPC.from_records(_records()).save(good)
    bad = tmp_path / "bad.npz"
    with zipfile.ZipFile(good) as zin, zipfile.ZipFile(bad, "w") as zout:
        for info in zin.infolist():
            data = zin.read(info)
            if info.filename == "ap_2d.npy":
                buf = io.BytesIO()
                np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": (10**13,)})
                data = buf.getvalue() + b"\0" * 64
            zout.writestr(info.filename, data)
    with pytest.raises(ValueError, match=r"bad.npz.*ap_2d.npy.*claims an array of shape \(10000000000000,\)"):
        IOPC.load(bad)


def test_a_provenance_nested_too_deeply_is_refused_on_load(tmp_path):
    """It loaded, and then save() failed by recursion."""
    d = IOPC.from_records(_records()).to_dict()
    deep: dict = {}
    cur = deep
    for _ in range(900):
        cur["x"] = {}
        cur = cur["x"]
    d["provenance"] = {"config": deep}
    path = tmp_path / "deep.json"
    path.write_text(json.dumps(d), encoding="utf-8")
    with pytest.raises(ValueError, match="provenance is nested deeper than 32 levels"):
        IOPC.load(path)
