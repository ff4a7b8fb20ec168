import math

import pytest
import torch

from camhealth.physics.metadata import (
    FULL_FIELDS,
    METADATA_RANGES,
    MINIMAL_FIELDS,
    CameraMetadata,
    SensorConstants,
    celsius_to_kelvin,
    db_to_factor,
    factor_to_db,
    kelvin_to_celsius,
)


def test_gain_conversion_closed_form():
    assert db_to_factor(0.0).item() == pytest.approx(1.0)
    assert db_to_factor(24.0).item() == pytest.approx(15.8489, rel=1e-4)
    assert db_to_factor(20.0).item() == pytest.approx(10.0)
    g = torch.tensor([1.0, 2.0, 15.0])
    assert torch.allclose(db_to_factor(factor_to_db(g)), g)


def test_temperature_conversion():
    assert celsius_to_kelvin(0.0).item() == pytest.approx(273.15)
    assert kelvin_to_celsius(celsius_to_kelvin(80.0)).item() == pytest.approx(80.0)


@pytest.mark.parametrize("name", ["ICX285", "EV76C661", "icx285"])
def test_presets(name):
    m = CameraMetadata.preset(name, batch_size=3, gain_db=12.0)
    assert m.batch_size == 3
    assert torch.all(m.gain_db == 12.0)
    assert m.is_cmos[0].item() == (1.0 if name.upper() == "EV76C661" else 0.0)


def test_unknown_preset_lists_known():
    with pytest.raises(ValueError, match="ICX285"):
        CameraMetadata.preset("nope")


@pytest.mark.parametrize(
    "field,value",
    [("temperature_c", 90.0), ("temperature_c", -1.0), ("gain_db", 24.5), ("full_well_e", 1999.0), ("exposure_s", 0.0),
     ("is_cmos", 0.5), ("gain_db", float("nan")), ("pixel_clock_hz", float("inf")), ("full_well_e", 10**30),
     ("exposure_s", -(10**25))],
)
def test_out_of_range_names_field_value_and_range(field, value):
    lo, hi = METADATA_RANGES[field]
    with pytest.raises(ValueError) as err:
        CameraMetadata.preset("ICX285", **{field: value})
    msg = str(err.value)
    assert field in msg and f"{lo:g}" in msg and f"{hi:g}" in msg


@pytest.mark.parametrize("field", ["gain_db", "exposure_s", "temperature_c"])
def test_a_bool_is_no_physical_value(field):
    """``gain_db=True`` read as 1 dB; only the flag ``is_cmos`` takes a bool."""
    with pytest.raises(TypeError, match=rf"camera metadata {field} must be a number in .*, got bool True"):
        CameraMetadata.preset("ICX285", **{field: True})
    assert float(CameraMetadata.preset("ICX285", is_cmos=True).is_cmos) == 1.0


def test_extremes_are_valid():
    m = CameraMetadata.preset("EV76C661", batch_size=4, gain_db=[0.0, 24.0, 0.0, 24.0], temperature_c=[0.0, 80.0, 80.0, 0.0],
                              full_well_e=2000.0, exposure_s=[0.001, 0.2, 0.2, 0.001])
    assert m.batch_size == 4


def test_incompatible_batch_sizes():
    with pytest.raises(ValueError, match="incompatible batch"):
        CameraMetadata.preset("ICX285", gain_db=[0.0, 1.0], temperature_c=[1.0, 2.0, 3.0])


def test_normalize_roundtrip_full_and_minimal():
    m = CameraMetadata.sample(16, torch.Generator().manual_seed(1))
    full = m.normalize("full")
    assert full.shape == (16, len(FULL_FIELDS))
    assert full.min() >= 0 and full.max() <= 1
    back = CameraMetadata.denormalize(full, "full")
    for n in FULL_FIELDS:
        assert torch.allclose(getattr(back, n), getattr(m, n), rtol=1e-5, atol=1e-12), n
    mini = m.normalize("minimal")
    assert mini.shape == (16, len(MINIMAL_FIELDS))
    back = CameraMetadata.denormalize(mini, "minimal", base=m)
    assert torch.allclose(back.gain_db, m.gain_db, atol=1e-5)
    assert m.normalize("none").shape == (16, 0)


def test_sample_reproducible_and_in_range():
    a = CameraMetadata.sample(256, torch.Generator().manual_seed(3))
    b = CameraMetadata.sample(256, torch.Generator().manual_seed(3))
    for n in FULL_FIELDS:
        assert torch.equal(getattr(a, n), getattr(b, n))
        lo, hi = METADATA_RANGES[n]
        assert getattr(a, n).min() >= lo and getattr(a, n).max() <= hi
    # gain uniform in the factor: the median factor is near (1 + 15.85) / 2
    assert a.gain_factor.median().item() == pytest.approx((1 + 10 ** 1.2) / 2, rel=0.15)


def test_sample_with_fixed_preset_and_ranges():
    m = CameraMetadata.sample(8, torch.Generator().manual_seed(0), fixed="ICX285", ranges={"gain_db": (6.0, 12.0)})
    assert torch.all(m.full_well_e == 14000)
    assert m.gain_db.min() >= 6 and m.gain_db.max() <= 12
    with pytest.raises(ValueError, match="gain_db"):
        CameraMetadata.sample(2, ranges={"gain_db": (0.0, 30.0)})


def test_dict_roundtrip_and_sensor_type():
    m = CameraMetadata.preset("EV76C661", temperature_c=40.0)
    d = m.to_dict()
    assert CameraMetadata.from_dict(d).temperature_c.item() == pytest.approx(40.0)
    m2 = CameraMetadata.from_dict({"sensor_type": "CCD", "gain_db": 6.0}, base="EV76C661")
    assert m2.is_cmos.item() == 0.0 and m2.gain_db.item() == pytest.approx(6.0)
    with pytest.raises(ValueError, match="unknown metadata"):
        CameraMetadata.from_dict({"colour": 1}, base="ICX285")
    with pytest.raises(ValueError, match="missing"):
        CameraMetadata.from_dict({"gain_db": 1.0})


def test_indexing_cat_expand_to():
    m = CameraMetadata.sample(6)
    assert m[2].batch_size == 1 and m[:4].batch_size == 4
    assert CameraMetadata.cat([m[:2], m[2:]]).batch_size == 6
    assert m[0].expand(5).batch_size == 5
    with pytest.raises(ValueError):
        m.expand(3)
    assert m.to(dtype=torch.float64).dtype == torch.float64


def test_gain_factor_and_dn_per_electron():
    m = CameraMetadata.preset("ICX285", gain_db=20.0)
    assert m.dn_per_electron.item() == pytest.approx(10 * 255 / 14000, rel=1e-5)
    assert m.temperature_k.item() == pytest.approx(298.15)
    assert not math.isnan(m.gain_factor.item())


def test_float32_range_ends_survive_float64_conversion():
    m = CameraMetadata.preset("ICX285", exposure_s=0.2, pixel_size_um=0.9, gain_db=24.0)
    assert m.to(dtype=torch.float64).exposure_s.item() == pytest.approx(0.2)
    with pytest.raises(ValueError, match="exposure_s"):
        CameraMetadata.preset("ICX285", exposure_s=0.2001)


def test_from_file_and_lookup(tmp_path):
    import yaml

    meta = CameraMetadata.preset("EV76C661", gain_db=6.0)
    path = tmp_path / "cam.yaml"
    path.write_text(yaml.safe_dump({k: v[0] for k, v in meta.to_dict().items()}))
    loaded = CameraMetadata.lookup(str(path))
    assert torch.allclose(loaded.white_noise_v_per_rthz, meta.white_noise_v_per_rthz)
    assert float(CameraMetadata.lookup("ICX285").full_well_e) == 14000.0
    (tmp_path / "part.yaml").write_text("sensor: ICX285\ngain_db: 12\nsensor_type: CMOS\n")
    part = CameraMetadata.from_file(tmp_path / "part.yaml")
    assert float(part.gain_db) == 12.0 and float(part.is_cmos) == 1.0 and float(part.full_well_e) == 14000.0
    (tmp_path / "bad.yaml").write_text("gain_db: 12\n")
    with pytest.raises(ValueError, match=r"bad.yaml: metadata is missing field"):
        CameraMetadata.from_file(tmp_path / "bad.yaml")
    (tmp_path / "evil.yaml").write_text("gain_db: !!python/object/apply:os.system ['echo hacked']\n")
    with pytest.raises(ValueError, match="cannot parse metadata file"):
        CameraMetadata.from_file(tmp_path / "evil.yaml")
    with pytest.raises(FileNotFoundError):
        CameraMetadata.from_file(tmp_path / "missing.yaml")
    with pytest.raises(ValueError, match="unknown sensor preset"):
        CameraMetadata.lookup("nope")


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_denormalize_half_precision_values_with_a_preset_base(dtype):
    # fp16 cannot hold the 28.64 MHz pixel clock of the base (inf): the physical units are computed in float32
    m = CameraMetadata.preset("ICX285", exposure_s=0.05, gain_db=6.0)
    r = CameraMetadata.denormalize(m.normalize("minimal").to(dtype), "minimal", base="ICX285")
    assert r.pixel_clock_hz.item() == pytest.approx(28.64e6)
    assert r.sense_node_gain_v_per_e.item() == pytest.approx(m.sense_node_gain_v_per_e.item(), rel=1e-6)
    assert r.exposure_s.item() == pytest.approx(0.05, rel=2e-3) and r.gain_db.dtype == torch.float32


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("field,end", [("exposure_s", 0.2), ("exposure_s", 0.001), ("gain_db", 24.0),
                                       ("sense_node_gain_v_per_e", 1e-6), ("full_well_e", 2000.0)])
def test_half_precision_range_ends_are_the_range_ends(dtype, field, end):
    # 0.2 s in bf16 is 0.2002 s: a range end given in half precision is accepted as that end
    given = torch.tensor([end], dtype=dtype)
    m = CameraMetadata.preset("ICX285", **{field: given})
    low, high = METADATA_RANGES[field]
    assert getattr(m, field).item() == pytest.approx(min(max(given.item(), low), high), rel=1e-7)


def test_half_precision_values_beyond_rounding_are_still_refused():
    with pytest.raises(ValueError, match=r"exposure_s\[0\] = 0.209961 s is out of the allowed range \[0.001, 0.2\] s"):
        CameraMetadata.preset("ICX285", exposure_s=torch.tensor([0.21], dtype=torch.bfloat16))
    with pytest.raises(ValueError, match=r"exposure_s\[0\] = -0.000100136 s is out"):
        CameraMetadata.preset("ICX285", exposure_s=torch.tensor([-1e-4], dtype=torch.bfloat16))


def test_from_file_errors_name_the_file_for_text_that_is_not_utf8_and_a_sensor_type_that_is_not_a_string(tmp_path):
    (tmp_path / "latin1.yaml").write_bytes("# caméra\nsensor: ICX285\ngain_db: 3\n".encode("latin-1"))
    with pytest.raises(ValueError, match=r"metadata file .*latin1\.yaml is not UTF-8 text: byte 0xe9 at position 5 "
                                         r"\(save it as UTF-8\)"):
        CameraMetadata.from_file(tmp_path / "latin1.yaml")
    (tmp_path / "st.yaml").write_text("sensor: ICX285\nsensor_type: 5\n")
    with pytest.raises(ValueError, match=r"metadata file .*st\.yaml: camera metadata sensor_type must be 'CCD' or "
                                         r"'CMOS', got int 5"):
        CameraMetadata.from_file(tmp_path / "st.yaml")


@pytest.mark.parametrize("field", ["dark_fom_na_per_cm2", "reset_factor", "gain_db", "temperature_c"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_range_end_at_zero_has_no_slack(field, dtype):
    """The rounding slack of 1e-6 × |range end| is 0 at an end of 0: −5e-7 nA/cm² (which gave σ_DCSN = NaN) and a
    reset factor of −1e-6 are refused with the field, the value and the range; 0 itself is fine."""
    lo, hi = METADATA_RANGES[field]
    assert lo == 0.0
    with pytest.raises(ValueError, match=rf"^camera metadata {field}\[0\] = -5e-07.* is out of the allowed range \[0, {hi:g}\]"):
        CameraMetadata.preset("ICX285", **{field: torch.tensor([-5e-7], dtype=dtype)})
    assert float(getattr(CameraMetadata.preset("ICX285", **{field: torch.tensor([0.0], dtype=dtype)}), field)) == 0.0


def test_nonzero_range_ends_keep_their_rounding_slack():
    m = CameraMetadata.preset("ICX285", exposure_s=torch.tensor([0.2], dtype=torch.float32).double(),
                              pixel_size_um=torch.tensor([0.9], dtype=torch.float32).double())
    assert float(m.exposure_s) > 0.2 and float(m.pixel_size_um) != 0.9  # float32 rounding of the ends, accepted
    with pytest.raises(ValueError, match="exposure_s"):
        CameraMetadata.preset("ICX285", exposure_s=0.2 * (1 + 1e-5))


@pytest.mark.parametrize("bounds", [(0.2, 0.3), (0.0, 0.4), (0.5, 1.0), (0.3, 0.3)])
def test_is_cmos_ranges_other_than_the_three_choices_are_refused(bounds):
    with pytest.raises(ValueError, match=r"range for is_cmos = .* must be \(0, 0\) \(CCD only\), \(1, 1\) \(CMOS only\) or \(0, 1\)"):
        CameraMetadata.sample(6, ranges={"is_cmos": bounds})


@pytest.mark.parametrize("bounds,allowed", [((0, 0), {0.0}), ((1, 1), {1.0}), ((0, 1), {0.0, 1.0})])
def test_is_cmos_ranges_of_the_three_choices(bounds, allowed):
    m = CameraMetadata.sample(64, torch.Generator().manual_seed(0), ranges={"is_cmos": bounds})
    assert set(m.is_cmos.tolist()) == allowed


def test_sample_reads_a_fixed_dict_as_from_dict_does():
    m = CameraMetadata.sample(3, torch.Generator().manual_seed(0), fixed={"sensor_type": "cmos", "gain_db": 6.0})
    assert m.is_cmos.tolist() == [1.0, 1.0, 1.0] and torch.all(m.gain_db == 6.0)
    with pytest.raises(ValueError, match=r"unknown metadata field\(s\) \['gain'\]; known fields: \['gain_db'"):
        CameraMetadata.sample(2, fixed={"gain": 6.0})
    with pytest.raises(ValueError, match="sensor_type = 'CCD' contradicts is_cmos"):
        CameraMetadata.sample(2, fixed={"sensor_type": "CCD", "is_cmos": 1.0})
    with pytest.raises(ValueError, match="sensor_type = 'CMOSS' is not one of"):
        CameraMetadata.sample(2, fixed={"sensor_type": "CMOSS"})


def test_presets_share_one_set_of_constants_and_concatenate():
    """Every preset carries the conventions' fixed constants (reference voltage 5 V, informative only), so metadata
    of both presets form one batch; constants that differ are refused by ``cat``, naming the field."""
    ev, icx = CameraMetadata.preset("EV76C661"), CameraMetadata.preset("ICX285")
    assert ev.constants == icx.constants == SensorConstants() and SensorConstants().reference_voltage_v == 5.0
    assert CameraMetadata.cat([ev, icx]).batch_size == 2
    other = ev.replace(constants=SensorConstants(reference_voltage_v=3.3))
    with pytest.raises(ValueError, match="different fixed SensorConstants: item 1 has reference_voltage_v = 3.3 vs 5.0"):
        CameraMetadata.cat([icx, other])


@pytest.mark.parametrize("name,text,match", [
    ("dup.yaml", "sensor: ICX285\ngain_db: 12\ntemperature_c: 40\ngain_db: 0\n",
     r"dup\.yaml: field gain_db is given twice \(lines 2 and 4\); give each field once"),
    ("flow.yaml", "{sensor: ICX285, gain_db: 12, gain_db: 0}\n", r"field gain_db is given twice \(on line 1\)"),
    ("dup.json", '{"sensor": "ICX285", "gain_db": 12, "gain_db": 0}',
     r"dup\.json: field gain_db is given twice \(12 and 0\); give each field once"),
])
def test_a_field_given_twice_in_a_metadata_file_is_refused(tmp_path, name, text, match):
    """YAML and JSON parsers keep the last of two equal keys without a word: ``gain_db: 12 … gain_db: 0`` ran at 0 dB."""
    from camhealth.physics.metadata import read_metadata_mapping

    (tmp_path / name).write_text(text)
    with pytest.raises(ValueError, match=match):
        read_metadata_mapping(tmp_path / name)
    with pytest.raises(ValueError, match="given twice"):
        CameraMetadata.from_file(tmp_path / name)


def test_a_yaml_merge_key_may_be_overridden(tmp_path):
    """YAML's merge (``<<:``) brings in defaults that the mapping's own keys override: that is no duplicate."""
    from camhealth.physics.metadata import read_metadata_mapping

    (tmp_path / "m.yaml").write_text("<<: {sensor: ICX285, gain_db: 3}\ngain_db: 12\n")
    assert read_metadata_mapping(tmp_path / "m.yaml") == {"sensor": "ICX285", "gain_db": 12}
