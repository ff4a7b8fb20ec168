"""``camhealth.calibrate``: recovery of known cameras from small synthetic stacks, the output YAML accepted by
predict / the monitor / fit, the CLI with a manifest and with named files, and every bad input."""

import math
import re

import numpy as np
import pytest
import torch
import yaml

from camhealth.calibrate import FrameSet, Protocol, calibrate, parse_set_name, read_manifest, synthetic_sets
from camhealth.calibrate.__main__ import main
from camhealth.physics import CameraMetadata
from camhealth.physics.dark_current import dark_current_e_per_s
from camhealth.physics.metadata import FULL_FIELDS
from camhealth.physics.readout_noise import readout_sigma_e

DATASHEET = ("pixel_size_um", "pixel_clock_hz", "sense_node_gain_v_per_e", "is_cmos")
SMALL = Protocol(dark_temperatures_c=(40.0, 75.0), dark_exposures_s=(0.1, 0.2), flat_levels=(0.1, 0.3, 0.6), flat_gains_db=(0.0, 12.0))


def _datasheet(meta):
    return {f: float(getattr(meta, f)) for f in DATASHEET}


def _errors(true, cal):
    t = true.replace(temperature_c=float(cal.temperature_c)).to(dtype=torch.float64)
    c = cal.to(dtype=torch.float64)
    return (float(c.full_well_e / t.full_well_e) - 1, float(readout_sigma_e(c) / readout_sigma_e(t)) - 1,
            float(dark_current_e_per_s(c) / dark_current_e_per_s(t)) - 1)


@pytest.fixture(scope="module")
def icx_result():
    true = CameraMetadata.preset("ICX285")
    return true, calibrate(synthetic_sets(true, SMALL, frames=6, size=48, seed=3), camera=_datasheet(true))


@pytest.mark.parametrize("preset", ["ICX285", "EV76C661"])
def test_recovers_presets_from_small_stacks(preset, icx_result):
    true = CameraMetadata.preset(preset)
    res = icx_result[1] if preset == "ICX285" else calibrate(synthetic_sets(true, SMALL, frames=6, size=48, seed=3), camera=_datasheet(true))
    fw, rn, dc = _errors(true, res.metadata)
    assert abs(fw) < 0.02 and abs(rn) < 0.03
    # the dark current within 4σ of what the fit claims (small stacks measure it to a few %)
    assert abs(dc) < 4 * res.fields["dark_fom_na_per_cm2"].relative + 0.01
    assert res.fields["full_well_e"].source == "fitted" and 0 < res.fields["full_well_e"].relative < 0.02
    assert res.fits["dark"]["clipping_model"].startswith("clipped once")
    assert res.metadata.batch_size == 1 and bool(res.metadata.is_cmos) == (preset == "EV76C661")


def test_recovers_a_random_camera_and_a_stack_clipped_after_each_source():
    from camhealth.bench.sensor_variants import simulate_variant

    true = CameraMetadata.sample(1, generator=torch.Generator().manual_seed(5))
    res = calibrate(synthetic_sets(true, SMALL, frames=6, size=48, seed=1), camera=_datasheet(true))
    assert max(abs(e) for e in _errors(true, res.metadata)[:2]) < 0.03

    def variant(clean, meta, g):
        return simulate_variant(clean, meta, ("sequential_clip", "whole_electrons"), generator=g)[0]

    cam = CameraMetadata.preset("EV76C661")
    res = calibrate(synthetic_sets(cam, SMALL, frames=6, size=48, seed=2, simulate=variant), camera=_datasheet(cam))
    assert res.fits["dark"]["clipping_model"].startswith("charge clipped")
    fw, rn, dc = _errors(cam, res.metadata)
    assert abs(fw) < 0.03 and abs(rn) < 0.03 and abs(dc) < 0.08


def test_outputs_round_trip_into_predict_monitor_and_fit(icx_result, tmp_path):
    from camhealth.inference import _to_metadata
    from camhealth.monitor.api import load_metadata
    from datamodules import NoiseDataModule

    _, res = icx_result
    paths = res.save(tmp_path / "camera.yaml")
    text = paths["metadata"].read_text()
    data = yaml.safe_load(text)
    assert set(data) == set(FULL_FIELDS) and all(isinstance(v, float) for v in data.values())
    assert "± " in text and "fitted" in text  # uncertainties and sources as comments
    loaded = CameraMetadata.from_file(paths["metadata"])
    for f in FULL_FIELDS:
        assert float(getattr(loaded, f)) == pytest.approx(float(getattr(res.metadata, f)), rel=1e-5)
    assert float(load_metadata(str(paths["metadata"])).full_well_e) == pytest.approx(float(loaded.full_well_e))  # monitor --metadata
    assert float(_to_metadata(str(paths["metadata"]), 4, None).white_noise_v_per_rthz) == pytest.approx(float(loaded.white_noise_v_per_rthz))  # predict
    dm = NoiseDataModule(sensor=str(paths["metadata"]), source="deadleaves", source_kwargs={"n_images": 2, "size": 64})  # fit's sensor:
    meta, _, _ = dm.sample_metadata(8, torch.Generator().manual_seed(0))
    assert torch.allclose(meta.full_well_e, loaded.full_well_e.expand(8)) and meta.gain_db.unique().numel() > 1
    details = yaml.safe_load(paths["details"].read_text())
    assert details["metadata"]["full_well_e"]["uncertainty"] > 0 and details["emva1288"]["system_gain_k_dn_per_e_at_0db"] > 0
    maps = np.load(paths["maps"])
    assert {"hot_pixels", "dsnu_dn", "prnu", "master_bias_dn", "master_dark_dn", "master_flat_dn"} <= set(maps.files)
    assert maps["hot_pixels"].shape == (48, 48)
    from camhealth.monitor.defect_map import load_defect_map  # monitor --defect-map reads the maps as written

    assert torch.equal(load_defect_map(paths["maps"], shape=(48, 48)), torch.from_numpy(maps["hot_pixels"]))


def test_hot_pixels_are_found_and_left_out():
    true = CameraMetadata.preset("EV76C661")
    sets = synthetic_sets(true, SMALL, frames=6, size=48, seed=4)
    hot = [(5, 7), (30, 11)]
    for s in sets:
        if s.kind != "flat":
            for y, x in hot:
                s.frames[:, y, x] = np.clip(s.frames[:, y, x] + 0.3 * (s.exposure_s / 0.2), 0, 1)
    res = calibrate(sets, camera=_datasheet(true))
    assert {tuple(p) for p in np.argwhere(res.maps["hot_pixels"])} >= set(hot)
    assert abs(_errors(true, res.metadata)[1]) < 0.03


def test_dead_pixels_are_found_in_the_flats_and_join_the_monitors_defect_map(tmp_path):
    """Pixels that respond at 20 % in every flat (dead or dim) are in the maps' dead_pixels, hot pixels in hot_pixels,
    and no other pixel in either; the monitor's --defect-map reads camera.maps.npz as their union."""
    from camhealth.monitor.defect_map import load_defect_map

    true = CameraMetadata.preset("EV76C661")
    sets = synthetic_sets(true, SMALL, frames=6, size=48, seed=4)
    hot, dead = [(5, 7)], [(20, 30), (40, 2)]
    for s in sets:
        for y, x in hot:
            if s.kind != "flat":
                s.frames[:, y, x] = np.clip(s.frames[:, y, x] + 0.3 * (s.exposure_s / 0.2), 0, 1)
        if s.kind == "flat":  # the dead pixels keep a fifth of the light
            for y, x in dead:
                s.frames[:, y, x] = s.frames[:, y, x] * 0.2
    res = calibrate(sets, camera=_datasheet(true))
    assert {tuple(p) for p in np.argwhere(res.maps["dead_pixels"])} == set(dead)
    assert {tuple(p) for p in np.argwhere(res.maps["hot_pixels"])} == set(hot)
    assert res.emva["dead_pixels"] == 2 and res.emva["hot_pixels"] == 1
    paths = res.save(tmp_path / "camera.yaml")
    union = load_defect_map(paths["maps"], shape=(48, 48))
    assert {tuple(p) for p in union.nonzero().tolist()} == set(hot) | set(dead)


def test_file_name_convention():
    assert parse_set_name("dark_100ms_12dB_40C_L3") == {"kind": "dark", "exposure_s": pytest.approx(0.1), "gain_db": 12.0,
                                                         "temperature_c": 40.0, "label": "L3"}
    assert parse_set_name("bias_250us")["exposure_s"] == pytest.approx(250e-6)
    with pytest.raises(ValueError, match="must start with one of"):
        parse_set_name("frames_100ms")


def _write_set(folder, frames, bits=16):
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        arr = np.rint(f * (65535 if bits == 16 else 255)).astype(np.uint16 if bits == 16 else np.uint8)
        Image.fromarray(arr).save(folder / f"{i:03d}.png")


@pytest.fixture(scope="module")
def disk_stack(tmp_path_factory):
    """A small ICX285 stack as 16-bit PNG folders named by the convention, and a YAML manifest of the same."""
    root = tmp_path_factory.mktemp("stack")
    true = CameraMetadata.preset("ICX285")
    sets = synthetic_sets(true, SMALL, frames=5, size=32, seed=7)
    entries, folders = [], []
    for s in sets:
        name = f"{s.kind}_{s.exposure_s * 1e3:g}ms_{s.gain_db:g}dB_{s.temperature_c:g}C" + (f"_L{len(folders)}" if s.kind == "flat" else "")
        _write_set(root / name, s.frames)
        folders.append(root / name)
        entries.append({"kind": s.kind, "path": name, "exposure_s": s.exposure_s, "gain_db": s.gain_db, "temperature_c": s.temperature_c})
    manifest = {"camera": {"sensor_type": "CCD", "pixel_size_um": 6.45, "pixel_clock_hz": 28.64e6, "sense_node_gain_v_per_e": 5e-6},
                "operating_point": {"gain_db": 6.0, "exposure_s": 0.02, "temperature_c": 30.0}, "sets": entries}
    (root / "manifest.yaml").write_text(yaml.safe_dump(manifest))
    return root, folders, true


def test_cli_with_manifest_writes_metadata_maps_and_report(disk_stack, tmp_path, capsys):
    root, _, true = disk_stack
    out = tmp_path / "camera.yaml"
    assert main([str(root / "manifest.yaml"), "--out", str(out), "--report", str(tmp_path / "report")]) == 0
    printed = capsys.readouterr().out
    assert "full_well_e" in printed and "wrote report" in printed
    meta = CameraMetadata.from_file(out)
    assert float(meta.gain_db) == 6.0 and float(meta.temperature_c) == 30.0 and float(meta.is_cmos) == 0.0
    assert abs(float(meta.full_well_e) / 14000 - 1) < 0.05
    assert (tmp_path / "camera.maps.npz").is_file() and (tmp_path / "camera.calibration.yaml").is_file()
    report = (tmp_path / "report" / "report.md").read_text()
    assert "EMVA 1288" in report and (tmp_path / "report" / "calibration.png").stat().st_size > 10_000
    assert (tmp_path / "report" / "maps.png").is_file()


def test_cli_with_named_folders_and_datasheet_options(disk_stack, tmp_path, capsys):
    _, folders, _ = disk_stack
    out = tmp_path / "cam.yaml"
    assert main([str(f) for f in folders] + ["--out", str(out), "--sensor-type", "CCD", "--pixel-size-um", "6.45"]) == 0
    assert "assumed" in capsys.readouterr().out  # pixel clock and sense-node gain not given
    assert float(CameraMetadata.from_file(out).pixel_size_um) == pytest.approx(6.45)


# ------------------------------------------------------------------------------------------------ bad input
def _sets(**changes):
    true = CameraMetadata.preset("ICX285")
    return synthetic_sets(true, Protocol(**{**SMALL.__dict__, **changes}), frames=4, size=16, seed=0)


def test_too_few_frames():
    sets = _sets()
    sets[0].frames = sets[0].frames[:3]
    with pytest.raises(ValueError, match=r"has 3 frame\(s\); at least 4 are needed"):
        calibrate(sets)


def test_saturated_flats():
    sets = [s for s in _sets() if s.kind != "flat" or s.gain_db == 0.0]
    for s in sets:
        if s.kind == "flat" and "L0.1" not in s.name:
            s.frames = np.clip(s.frames + 0.7, 0, 1)
    with pytest.raises(ValueError, match=r"1 usable flat set\(s\) of 3, at least 2 are needed below saturation.*saturated"):
        calibrate(sets)


def test_exposures_that_do_not_span_a_range():
    with pytest.raises(ValueError, match=r"span only 2\.00×.*at least 4×"):
        calibrate(_sets(bias_exposure_s=0.15))
    with pytest.raises(ValueError, match="none of their 1 temperature"):  # (the second 0.2 s dark named apart: names are unique)
        calibrate([s for s in _sets(dark_temperatures_c=(40.0,)) if s.kind == "flat" or s.exposure_s == 0.2]
                  + [FrameSet(s.kind, s.exposure_s, s.gain_db, s.temperature_c, frames=s.frames, name=s.name + " again")
                     for s in _sets(dark_temperatures_c=(40.0,)) if s.kind == "dark" and s.exposure_s == 0.2])


def test_flats_that_do_not_span_a_range_and_too_few_sets():
    with pytest.raises(ValueError, match=r"signals span only 1\.0.*at least 2×"):
        calibrate(_sets(flat_levels=(0.3, 0.3), flat_gains_db=(0.0,)))
    with pytest.raises(ValueError, match=r"1 flat set\(s\) given; at least 2 are needed"):
        calibrate(_sets(flat_levels=(0.3,), flat_gains_db=(0.0,)))
    with pytest.raises(ValueError, match=r"1 bias/dark set\(s\) given.*at least 2 are needed"):
        calibrate([s for s in _sets() if s.kind == "flat" or s.name.startswith("bias_1ms_12dB_40C")])


def test_mixed_frame_sizes(tmp_path):
    sets = _sets()
    sets[-1].frames = np.zeros((4, 20, 16), np.float32)
    with pytest.raises(ValueError, match=r"has 20×16 px frames but .* has 16×16 px"):
        calibrate(sets)
    folder = tmp_path / "dark_100ms_0dB_25C"
    _write_set(folder, [np.zeros((16, 16))] * 3 + [np.zeros((8, 16))], bits=8)
    fs = FrameSet("dark", 0.1, paths=[folder])
    with pytest.raises(ValueError, match=r"mixes frame sizes \(16×16: 3 frame\(s\).*8×16: 1 frame"):
        calibrate([fs] + _sets())
    ragged = FrameSet("flat", 0.01, frames=[np.zeros((8, 8))] + [np.zeros((4, 8))] + [np.zeros((8, 8))] * 3)
    with pytest.raises(ValueError, match=r"mixes frame sizes \(8×8: 4 frame\(s\); 4×8: 1 frame\(s\)\)"):
        calibrate([ragged] + _sets())


def test_manifest_naming_missing_files(tmp_path, capsys):
    (tmp_path / "bias").mkdir()
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"defaults": {"gain_db": 0, "temperature_c": 25}, "sets": [
        {"kind": "bias", "path": "bias", "exposure_s": 0.001},
        {"kind": "dark", "path": "dark_a", "exposure_s": 0.1},
        {"kind": "flat", "path": ["f1.png", "f2.png"], "exposure_s": 0.01},
    ]}))
    with pytest.raises(FileNotFoundError, match=r"names 3 missing file\(s\)/folder\(s\)(.|\n)*dark_a(.|\n)*f2.png"):
        read_manifest(tmp_path / "m.yaml")
    assert main([str(tmp_path / "m.yaml"), "--out", str(tmp_path / "c.yaml")]) == 2
    assert "missing" in capsys.readouterr().err


def test_manifest_never_executes_code_and_names_bad_keys(tmp_path):
    (tmp_path / "evil.yaml").write_text("sets: !!python/object/apply:os.system ['echo hacked']\n")
    with pytest.raises(ValueError, match="cannot parse manifest"):
        read_manifest(tmp_path / "evil.yaml")
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({"sets": [{"kind": "dark", "path": "x", "exposure": 0.1}]}))
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['exposure'\]"):
        read_manifest(tmp_path / "bad.yaml")
    (tmp_path / "m.csv").write_text("kind,path,exposure_s,gain_db\ndark,x,0.1,0\n")
    (tmp_path / "x").mkdir()
    with pytest.raises(ValueError, match="temperature_c is missing"):
        read_manifest(tmp_path / "m.csv")


@pytest.mark.parametrize("section, shown", [("camera: [1, 2]", "list [1, 2]"), ("defaults: abc", "str 'abc'"),
                                            ("operating_point: 5", "int 5")])
def test_manifest_section_of_the_wrong_type_is_named(section, shown, tmp_path):
    (tmp_path / "b").mkdir()
    p = tmp_path / "m.yaml"
    p.write_text(section + "\nsets:\n  - {kind: bias, path: b, exposure_s: 0.001, gain_db: 0, temperature_c: 25}\n")
    name = section.split(":")[0]
    with pytest.raises(ValueError, match=rf"manifest {re.escape(str(p))}: section '{name}' must be a mapping of field: "
                                         rf"value, got {re.escape(shown)}$"):
        read_manifest(p)


@pytest.mark.parametrize("name, text", [("m.yaml", "# caméra\nsets: []\n"),
                                        ("m.csv", "kind,path,exposure_s,gain_db,temperature_c\nbias,bïas,0.001,0,25\n")])
def test_manifest_that_is_not_utf8_is_named(name, text, tmp_path):
    p = tmp_path / name
    p.write_bytes(text.encode("latin-1"))
    with pytest.raises(ValueError, match=rf"cannot read manifest {re.escape(str(p))}: not UTF-8 text \(invalid "
                                         r"continuation byte at byte \d+\); save it as UTF-8"):
        read_manifest(p)


def test_name_without_exposure(tmp_path):
    folder = tmp_path / "dark_12dB_25C"
    _write_set(folder, [np.zeros((8, 8))] * 4, bits=8)
    with pytest.raises(ValueError, match="gives no exposure time"):
        calibrate([folder])


@pytest.mark.parametrize("gain", ["200", "1e9", "-5", "nan"])
def test_cli_gain_db_outside_the_metadata_range_is_refused_naming_the_range(gain, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main([str(tmp_path / "dark_200ms"), "--out", str(tmp_path / "c.yaml"), f"--gain-db={gain}"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and f"argument --gain-db: must lie in camhealth's gain range 0 … 24 dB, got {gain}" in err


def test_cli_output_paths_are_checked_before_the_frames_are_read(tmp_path, capsys):
    (tmp_path / "adir").mkdir()
    (tmp_path / "afile").write_text("x")
    frames = str(tmp_path / "never_read")  # a missing set: the output paths are refused first
    for argv, message in (
        (["--out", str(tmp_path / "adir")], f"argument --out: {tmp_path / 'adir'} is a folder"),
        (["--out", str(tmp_path / "c.yaml"), "--maps", str(tmp_path / "adir")], f"argument --maps: {tmp_path / 'adir'} is a folder"),
        (["--out", str(tmp_path / "afile" / "c.yaml")], f"{tmp_path / 'afile'} is a file, not a folder"),
        (["--out", str(tmp_path / "c.yaml"), "--report", str(tmp_path / "afile")], f"argument --report: {tmp_path / 'afile'} is a file"),
    ):
        with pytest.raises(SystemExit) as info:
            main([frames, *argv])
        err = capsys.readouterr().err
        assert info.value.code == 2 and message in err and "Traceback" not in err, (argv, err)


def test_cli_outputs_may_not_overwrite_an_input_or_each_other(tmp_path, capsys):
    """--out, --maps and the <stem>.calibration.yaml beside --out are refused when they name a FRAMES input (the
    manifest read) or another output, before anything is read or written."""
    man = tmp_path / "cal.yaml"
    man.write_text("sets: []\n")
    (tmp_path / "cam.calibration.yaml").write_text("sets: []\n")
    (tmp_path / "sub").mkdir()
    for frames, argv, message in (
        (man, ["--out", str(man)], f"argument --out: writing {man} would overwrite the input {man}"),
        (man, ["--out", str(tmp_path / "sub" / ".." / "cal.yaml")], "would overwrite the input"),
        (man, ["--out", str(tmp_path / "c.yaml"), "--maps", str(man)], f"argument --maps: writing {man} would overwrite"),
        (tmp_path / "cam.calibration.yaml", ["--out", str(tmp_path / "cam.yaml")],
         f"writing {tmp_path / 'cam.calibration.yaml'} would overwrite the input"),
        (man, ["--out", str(tmp_path / "c.yaml"), "--maps", str(tmp_path / "c.yaml")], "argument --maps: "),
    ):
        with pytest.raises(SystemExit) as info:
            main([str(frames), *argv])
        err = capsys.readouterr().err
        assert info.value.code == 2 and message in err and "Traceback" not in err, (argv, err)
    assert man.read_text() == "sets: []\n" and not (tmp_path / "c.yaml").exists()
    assert (tmp_path / "cam.calibration.yaml").read_text() == "sets: []\n"


# ------------------------------------------------------------------------------------------------ physics of odd stacks
def _simulator(offset_dn=0.0, bits=8, top_dn=255.0, flicker=0.0, prnu=0.0, dsnu_dn=0.0):
    """offset + DSNU + K·(Poisson photo-e·(1 + PRNU)·(1 + per-frame flicker) + Poisson dark-e − their mean) + N(0, K·σ_R) [DN],
    clipped to [0, top_dn] and quantised to ``bits`` (K = g·255/FW)."""
    def simulate(clean, meta, g):
        m = meta.to(dtype=torch.float64)
        gain, fw = float(10 ** (m.gain_db[0] / 20)), float(m.full_well_e[0])
        k = gain * 255 / fw
        s_d = float(dark_current_e_per_s(m)[0] * m.exposure_s[0])
        c = clean.double()
        fixed = torch.Generator().manual_seed(1)
        pattern = 1 + prnu * torch.randn(c.shape[-2:], generator=fixed, dtype=torch.float64)
        dsnu = dsnu_dn * torch.randn(c.shape[-2:], generator=fixed, dtype=torch.float64)
        light = 1 + flicker * torch.randn((c.shape[0], 1, 1, 1), generator=g, dtype=torch.float64)
        e = torch.poisson(c * fw / gain * pattern * light, generator=g) + torch.poisson(torch.full_like(c, s_d), generator=g) - s_d
        y = offset_dn + dsnu + k * e + k * float(readout_sigma_e(m)[0]) * torch.randn(c.shape, generator=g, dtype=torch.float64)
        y = torch.clamp(y, 0, top_dn)
        return (torch.round(y / 255 * (2**bits - 1)) / (2**bits - 1)).float()
    return simulate


def _icx(frames=6, size=48, **protocol_and_sim):
    sim = {k: protocol_and_sim.pop(k) for k in list(protocol_and_sim) if k not in Protocol.__dataclass_fields__}
    true = CameraMetadata.preset("ICX285")
    sets = synthetic_sets(true, Protocol(**{**SMALL.__dict__, **protocol_and_sim}), frames=frames, size=size, seed=3,
                          simulate=_simulator(**sim))
    return sets, _datasheet(true)


def test_a_repeated_bias_frame_is_refused_naming_the_set():
    """The same frame returned N times has no temporal noise; it was read as a read noise of 0 e⁻."""
    sets = _sets()
    bias = next(s for s in sets if s.name == "bias_1ms_12dB_40C")
    bias.frames = np.repeat(bias.frames[:1], len(bias.frames), 0)
    with pytest.raises(ValueError, match=r"bias set 'bias_1ms_12dB_40C' .*: its 4 frames are identical"):
        calibrate(sets)


@pytest.mark.parametrize("value", [0.0, 0.3])
def test_a_blank_frame_in_a_set_is_refused_naming_the_set_and_the_frame(value):
    """One constant frame (a dropped frame filled with zeros, a stuck buffer) in a dark set: its step from the
    other frames read as temporal noise (read noise 0 e⁻, W at its floor, D_FM ±100 %)."""
    sets = _sets()
    dark = next(s for s in sets if s.kind == "dark")
    dark.frames = dark.frames.copy()
    dark.frames[2] = value
    with pytest.raises(ValueError, match=rf"dark set '{dark.name}' .*frame 2 of its 4 .* holds one value throughout "
                                         rf"\({value * 255:g} DN\) while the others vary .*remove it from the set"):
        calibrate(sets)


@pytest.mark.parametrize("offset", [10.0, 10.5])
def test_darks_below_half_a_code_step_are_refused(offset):
    """ICX285's darks at 0 dB in 8 bits: σ ≈ 0.23 DN, on 1–2 codes. σ² − 1/12 DN² gave a read noise of 0 e⁻ (offset 10)
    or 24 e⁻ (10.5) for the true 12.5 e⁻."""
    sets, sheet = _icx(frames=4, size=16, dark_gain_db=0.0, offset_dn=offset)
    with pytest.raises(ValueError, match=r"bias set 'bias_1ms_0dB_40C' .* is quantisation-limited: .*higher gain or bit depth"):
        calibrate(sets, camera=sheet)


def test_flats_saturating_below_255_dn_are_left_out():
    """The pixels clip at 230 DN (a full well below the ADC's range): the 90 % flats pile up at 230 DN and are left
    out as saturated (they gave a full well 60 % too high with χ²/dof 443)."""
    sets, sheet = _icx(flat_levels=(0.1, 0.3, 0.6, 0.9), top_dn=230.0)
    res = calibrate(sets, camera=sheet)
    assert abs(res.fields["full_well_e"].value / 14000 - 1) < 0.02
    assert {s.name for s in res.sets if not s.used} == {"flat_10ms_0dB_25C_L0.9", "flat_10ms_12dB_25C_L0.9"}
    assert all("saturated" in s.note for s in res.sets if not s.used)


def test_frame_to_frame_flicker_does_not_bias_the_gain():
    """0.5 % rms light change between frames: its variance of the frame means entered the temporal variance."""
    sets, sheet = _icx(flicker=0.005)
    fw = calibrate(sets, camera=sheet).fields["full_well_e"]
    assert abs(fw.value / 14000 - 1) < 0.02 and abs(fw.value - 14000) < 3 * fw.uncertainty


def test_partly_clipped_flats_are_left_out_with_the_reason():
    """Flats at 241 DN with 1 % PRNU: a few of their values at 255 DN sent them to the censored fit, whose pooled σ²
    includes the PRNU (full well −3.6 %, χ²/dof 196)."""
    sets, sheet = _icx(flat_levels=(0.1, 0.3, 0.6, 0.945), prnu=0.01)
    res = calibrate(sets, camera=sheet)
    assert abs(res.fields["full_well_e"].value / 14000 - 1) < 0.01 and res.photon_transfer.chi2_dof < 5
    left_out = [s for s in res.sets if not s.used]
    assert left_out and all(s.name.endswith("L0.945") and s.note.startswith("partly clipped") for s in left_out)


def test_a_poor_photon_transfer_fit_is_warned_about():
    sets, sheet = _icx()
    flat = next(s for s in sets if s.name == "flat_10ms_0dB_25C_L0.3")
    master = flat.frames.mean(0, keepdims=True)
    flat.frames = np.clip(master + 1.4 * (flat.frames - master), 0, 1)  # its noise 1.4× too large
    res = calibrate(sets, camera=sheet)
    assert res.photon_transfer.chi2_dof > 5
    assert any(w.startswith("the photon transfer fits poorly") and "flat_10ms_0dB_25C_L0.3" in w for w in res.warnings)


def test_flats_whose_gain_contradicts_k_proportional_to_g_are_refused():
    sets, sheet = _icx()
    for s in sets:
        if s.kind == "flat" and s.gain_db == 12.0:
            s.gain_db = 6.0  # the 12 dB flats labelled 6 dB
    with pytest.raises(ValueError, match=r"flats at 0 dB and 6 dB give K0 .*σ apart .*check the flats' gain_db"):
        calibrate(sets, camera=sheet)


def test_a_dsnu_pooled_into_clipped_darks_is_warned_about():
    sets, sheet = _icx(dsnu_dn=0.5)
    res = calibrate(sets, camera=sheet)
    assert any("fixed pattern (DSNU)" in w and "censored fit pools the pixels" in w for w in res.warnings)
    assert not any("DSNU" in w for w in calibrate(*_icx()).warnings)


@pytest.mark.parametrize("gain", [40.0, -5.0])
def test_frame_set_gain_outside_the_metadata_range_is_refused_naming_the_range(gain):
    with pytest.raises(ValueError, match=rf"set d: gain_db = {gain:g} dB is outside camhealth's gain range \[0, 24\] dB"):
        FrameSet("dark", 0.1, gain_db=gain, frames=np.zeros((4, 8, 8), np.float32), name="d")


@pytest.mark.parametrize("max_frames", [-3, 0, 2, 4.5])
def test_max_frames_below_the_minimum_is_refused(max_frames):
    with pytest.raises(ValueError, match=rf"max_frames = {max_frames!r} must be None \(every frame\) or an integer ≥ 4"):
        calibrate(_sets(), max_frames=max_frames)


# ------------------------------------------------------------------------------------------------ inputs and physics
def test_clipped_darks_of_a_camera_with_an_offset_give_the_dark_current():
    """A 5000 e⁻ camera with an 8 DN offset: a few % of its dark values reach 0 DN (censored estimator), and the Poisson
    refit, started at o = 0 where every bin's likelihood is floored, converged to no dark current (−100 %, read noise
    +11 %) with only a "no dark current detected" warning."""
    true = CameraMetadata.preset("ICX285").replace(full_well_e=5000.0)
    sets = synthetic_sets(true, SMALL, frames=8, size=64, seed=3, simulate=_simulator(offset_dn=8.0, bits=16))
    res = calibrate(sets, camera=_datasheet(true))
    assert {r.method for r in res.sets if r.kind != "flat"} == {"censored"}
    fw, rn, dc = _errors(true, res.metadata)
    assert abs(fw) < 0.02 and abs(rn) < 0.02 and abs(dc) < 4 * res.fields["dark_fom_na_per_cm2"].relative + 0.02
    assert not any("dark current" in w or "refit" in w for w in res.warnings)


def _lsb(frames, bits):
    """The same codes as b-bit data read as value/(2^b − 1) (a PNG with sBIT, or data in the low bits)."""
    q = 2**bits - 1
    return (np.rint(frames * q) / q).astype(np.float32)


@pytest.mark.parametrize("bits", [10, 12])
def test_b_bit_codes_read_as_value_over_2b_minus_1_give_the_msb_aligned_numbers(bits):
    """10/12-bit codes read as k/(2^b − 1) lost their quantisation step (read noise +5.4 % at 10 bits, −2.7 % at 12
    bits against the same codes MSB-aligned in 16 bits)."""
    true = CameraMetadata.preset("ICX285")
    base = synthetic_sets(true, SMALL, frames=8, size=64, seed=3)
    q = 2**bits - 1
    msb = [FrameSet(s.kind, s.exposure_s, s.gain_db, s.temperature_c, frames=(np.rint(s.frames * q) * 2 ** (16 - bits) / 65535).astype(np.float32),
                    name=s.name) for s in base]
    lsb = [FrameSet(s.kind, s.exposure_s, s.gain_db, s.temperature_c, frames=_lsb(s.frames, bits), name=s.name) for s in base]
    a, b = calibrate(msb, camera=_datasheet(true)), calibrate(lsb, camera=_datasheet(true))
    assert all(r.step_dn == pytest.approx(255 / q) for r in b.sets)
    for f in ("full_well_e", "white_noise_v_per_rthz", "dark_fom_na_per_cm2"):
        assert b.fields[f].value == pytest.approx(a.fields[f].value, rel=0.3 * a.fields[f].relative), f


def _png(path, codes, sbit=None):
    """A gray PNG of integer ``codes`` (uint8 or uint16), with an sBIT chunk of ``sbit`` bits."""
    import struct
    import zlib
    from PIL import Image

    Image.fromarray(codes).save(path)
    if sbit is not None:
        data = path.read_bytes()
        chunk = b"sBIT" + bytes([sbit])
        path.write_bytes(data[:33] + struct.pack(">I", 1) + chunk + struct.pack(">I", zlib.crc32(chunk) & 0xFFFFFFFF) + data[33:])


def test_a_png_with_sbit_is_read_with_its_step(tmp_path):
    from camhealth.calibrate.frames import load_frames_with_depth
    from camhealth.calibrate.pipeline import _load_checked

    rng = np.random.default_rng(0)
    for i in range(4):
        _png(tmp_path / f"{i}.png", rng.integers(1000, 1100, (8, 8)).astype(np.uint16), sbit=12)
    fs = FrameSet("dark", 0.1, paths=sorted(tmp_path.glob("*.png")))
    x, depth = load_frames_with_depth(fs)
    assert depth.depth.bits == 12 and depth.depth.source == "sBIT" and x.max() < 1100 / 4095 + 1e-6
    assert _load_checked(fs, None, None, "")[1] == pytest.approx(255 / 4095)


def test_a_set_mixing_8_and_16_bit_files_is_refused_naming_them(disk_stack, tmp_path, capsys):
    """Every other frame of a set saved as 8-bit PNG: accepted, with the 16-bit step (0.0039 DN) for the whole set, so
    the 8-bit frames' q²/12 = 0.083 DN² stayed in the variance (full well −2.9 %, dark current −11 %)."""
    from camhealth.calibrate.frames import load_frames

    rng = np.random.default_rng(1)
    files = []
    for i in range(4):
        f = np.clip(rng.normal(0.3, 0.01, (32, 32)), 0, 1)
        p = tmp_path / f"dark_100ms_0dB_25C_{i:04d}.png"
        _png(p, np.rint(f * 65535).astype(np.uint16) if i % 2 == 0 else np.rint(f * 255).astype(np.uint8))
        files.append(p)
    with pytest.raises(ValueError, match=r"dark set .* mixes bit depths \(16-bit: 2 frame\(s\) \(.*_0000\.png, .*_0002\.png\); "
                                         r"8-bit: 2 frame\(s\) \(.*_0001\.png, .*_0003\.png\)\)"):
        load_frames(FrameSet("dark", 0.1, paths=files))
    root, _, _ = disk_stack
    manifest = yaml.safe_load((root / "manifest.yaml").read_text())
    for entry in manifest["sets"]:
        entry["path"] = str(root / entry["path"])
    manifest["sets"].append({"kind": "dark", "path": [f.name for f in files], "exposure_s": 0.1, "gain_db": 0, "temperature_c": 25})
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(manifest))
    assert main([str(tmp_path / "m.yaml"), "--out", str(tmp_path / "o" / "c.yaml")]) == 2
    assert "mixes bit depths" in capsys.readouterr().err and not (tmp_path / "o").exists()


def _disk_copy(sets, root, lsb_bits=None):
    """Sets as 16-bit PNG folders named by the convention (``lsb_bits``: b-bit codes in the low bits, no sBIT)."""
    folders = []
    for i, s in enumerate(sets):
        name = f"{s.kind}_{s.exposure_s * 1e3:g}ms_{s.gain_db:g}dB_{s.temperature_c:g}C" + (f"_L{i}" if s.kind == "flat" else "")
        (root / name).mkdir(parents=True)
        q = 65535 if lsb_bits is None else 2**lsb_bits - 1
        for j, f in enumerate(s.frames):
            _png(root / name / f"{j:03d}.png", np.rint(f * q).astype(np.uint16))
        folders.append(root / name)
    return folders


def test_12_bit_data_in_the_low_bits_of_16_bit_files_are_refused_unless_the_bit_depth_is_given(tmp_path, capsys):
    """12-bit codes in 16-bit PNGs without sBIT (OpenCV, many SDKs) were read as value/65535: every value below 16 DN,
    a full well 16× too large (ICX285: 220 000 e⁻ for 14 000 e⁻) and no warning."""
    true = CameraMetadata.preset("ICX285")
    folders = _disk_copy(synthetic_sets(true, SMALL, frames=4, size=32, seed=7), tmp_path / "stack", lsb_bits=12)
    sheet = _datasheet(true)
    with pytest.raises(ValueError, match=r"hold values up to \d+ of 65535 only .* look like 12-bit data stored in the low bits.*--bit-depth 12"):
        calibrate(folders, camera=sheet, gain_db=None)
    res = calibrate(folders, camera=sheet, gain_db=None, bit_depth=12)
    assert abs(res.fields["full_well_e"].value / 14000 - 1) < 0.05
    assert all(r.step_dn == pytest.approx(255 / 4095) for r in res.sets)
    out = tmp_path / "out" / "c.yaml"
    assert main([*map(str, folders), "--out", str(out), "--sensor-type", "CCD"]) == 2
    assert "low bits" in capsys.readouterr().err and not out.parent.exists()
    assert main([*map(str, folders), "--out", str(out), "--sensor-type", "CCD", "--bit-depth", "12"]) == 0
    with pytest.raises(SystemExit) as info:
        main([*map(str, folders), "--out", str(out), "--bit-depth", "20"])
    assert info.value.code == 2 and "argument --bit-depth: must lie in [8, 16] bits, got 20" in capsys.readouterr().err


def test_a_flat_saturated_at_one_code_below_255_dn_is_left_out():
    """A flat whose every value sits at the pixels' full well (200 DN): EMVA 1288's series runs up to saturation, but it
    aborted the calibration as a "frozen image"."""
    sets, sheet = _icx(flat_levels=(0.1, 0.3, 0.6, 0.95), top_dn=200.0)
    res = calibrate(sets, camera=sheet)
    assert abs(res.fields["full_well_e"].value / 14000 - 1) < 0.02
    left_out = {s.name: s.note for s in res.sets if not s.used}
    assert set(left_out) == {"flat_10ms_0dB_25C_L0.95", "flat_10ms_12dB_25C_L0.95"}
    assert all(n.startswith("saturated: 100.0 %") for n in left_out.values())


def test_dead_pixels_at_0_dn_are_left_out_of_the_flats_and_flagged():
    """One pixel at 0 DN in every flat frame (0.043 % of a 48×48 frame: above the 0.01 % clipping limit) sent every flat
    to the censored estimator and out of the photon transfer: "0 usable flat set(s) of 6"."""
    true = CameraMetadata.preset("ICX285")
    sets = synthetic_sets(true, SMALL, frames=6, size=48, seed=4)
    for s in sets:
        if s.kind == "flat":
            s.frames[:, 20, 30] = 0.0
    res = calibrate(sets, camera=_datasheet(true))
    assert all(r.used and r.method == "temporal" for r in res.sets if r.kind == "flat")
    assert abs(_errors(true, res.metadata)[0]) < 0.02
    assert {tuple(p) for p in np.argwhere(res.maps["dead_pixels"])} == {(20, 30)} and res.emva["dead_pixels"] == 1
    assert any(w.startswith("1 pixel(s) read 0 DN in every frame of 6 flat set(s)") for w in res.warnings)


def test_a_lossy_video_is_refused_naming_its_codec(tmp_path, capsys):
    """MJPEG (or H.264, MPEG-4 …) removes part of the temporal noise: 12 dB flats only gave a full well +13 % and a read
    noise −47 % with one generic warning. A lossless FFV1 video of the same frames is read as they are."""
    import cv2

    from camhealth.calibrate.frames import load_frames

    rng = np.random.default_rng(2)
    frames = np.clip(np.rint(rng.normal(60, 3, (4, 32, 32))), 0, 255).astype(np.uint8)
    for name, codec in (("flat_10ms_12dB_25C_L1.avi", "MJPG"), ("flat_10ms_12dB_25C_L2.mkv", "FFV1")):
        w = cv2.VideoWriter(str(tmp_path / name), cv2.VideoWriter_fourcc(*codec), 10, (32, 32), isColor=False)
        for f in frames:
            w.write(f)
        w.release()
    lossless = load_frames(FrameSet("flat", 0.01, paths=[tmp_path / "flat_10ms_12dB_25C_L2.mkv"]))
    assert np.array_equal(np.rint(lossless * 255), frames)
    with pytest.raises(ValueError, match=r"flat_10ms_12dB_25C_L1\.avi uses the codec 'MJPG', which is not lossless.*FFV1"):
        load_frames(FrameSet("flat", 0.01, paths=[tmp_path / "flat_10ms_12dB_25C_L1.avi"]))
    out = tmp_path / "o" / "c.yaml"
    assert main([str(tmp_path / "flat_10ms_12dB_25C_L1.avi"), "--out", str(out), "--temperature-c", "25"]) == 2
    assert "codec 'MJPG', which is not lossless" in capsys.readouterr().err and not out.parent.exists()


def test_outputs_may_not_overwrite_files_a_manifest_names_nor_the_report_go_into_a_frame_folder(disk_stack, tmp_path, capsys):
    """The overwrite check compared the outputs with the command line's FRAMES only: --out onto a frame the manifest
    names overwrote it (exit 0), and --report onto a set's folder put calibration.png and maps.png among its frames."""
    import shutil

    src, _, _ = disk_stack
    root = tmp_path / "stack"
    shutil.copytree(src, root)
    man = root / "manifest.yaml"
    folder = root / yaml.safe_load(man.read_text())["sets"][3]["path"]
    frame = folder / "000.png"
    before = frame.read_bytes()
    for argv, message in (
        (["--out", str(frame)], f"argument --out: writing {frame} would overwrite the input {frame}"),
        (["--out", str(folder / "cam.yaml")], f"argument --out: {folder / 'cam.yaml'} lies in the frame folder {folder}"),
        (["--out", str(tmp_path / "c.yaml"), "--maps", str(folder / "001.png")], "argument --maps: writing"),
        (["--out", str(tmp_path / "c.yaml"), "--report", str(folder)], f"argument --report: {folder} is the frame folder"),
        (["--out", str(tmp_path / "c.yaml"), "--report", str(folder / "rep")], "argument --report: "),
    ):
        with pytest.raises(SystemExit) as info:
            main([str(man), *argv])
        err = capsys.readouterr().err
        assert info.value.code == 2 and message in err and "Traceback" not in err, (argv, err)
    assert frame.read_bytes() == before and sorted(p.name for p in folder.iterdir()) == [f"{i:03d}.png" for i in range(5)]
    assert not (tmp_path / "c.yaml").exists()
    loose = tmp_path / "loose"  # image files named on the command line: the report may not go into their folder
    loose.mkdir()
    files = []
    for i in range(4):
        p = loose / f"dark_100ms_0dB_25C_{i:04d}.png"
        _png(p, np.full((8, 8), 10 + i, np.uint8))
        files.append(str(p))
    with pytest.raises(SystemExit) as info:
        main([*files, "--out", str(tmp_path / "c.yaml"), "--report", str(loose)])
    assert info.value.code == 2 and f"argument --report: {loose} holds the input" in capsys.readouterr().err


@pytest.mark.parametrize("name, message", [
    ("flat_10ms_-6dB_25C_L1", r"token '-6dB' gives a gain of -6 dB, outside camhealth's gain range \[0, 24\] dB; accepted spellings of the gain: 12dB"),
    ("dark_100ms_12dB_40C_200ms", r"tokens '100ms' and '200ms' both give the exposure"),
    ("dark_100ms_12,5dB_40C", r"token '12,5dB' looks like a gain but is not a number with that unit"),
    ("dark_100ms_12dB_200C", r"token '200C' gives a sensor temperature of 200 °C, outside \[-60, 150\] °C; accepted spellings of the temperature: 40C, 40°C, 40degC"),
    ("dark_100ms_6dB_25C_40degC", r"tokens '25C' and '40degC' both give the temperature"),
    ("dark_100 ms_6dB_40C", r"token '100 ms' splits a number from its unit"),
])
def test_malformed_name_tokens_are_refused_naming_them(name, message):
    """Such tokens became part of the label and the --gain-db default (0 dB) or the last exposure replaced them."""
    with pytest.raises(ValueError, match=message):
        parse_set_name(name)


def test_signed_and_degree_temperature_and_gain_tokens_are_read(tmp_path):
    assert parse_set_name("dark_100ms_+6dB_25°C") == {"kind": "dark", "exposure_s": pytest.approx(0.1), "gain_db": 6.0,
                                                     "temperature_c": 25.0, "label": ""}
    assert parse_set_name("dark_100ms_6dB_40degC")["temperature_c"] == 40.0
    assert parse_set_name("bias_1ms_0dB_-10C")["temperature_c"] == -10.0
    from camhealth.calibrate import sets_from_paths

    folder = tmp_path / "flat_10ms_-6dB_25C_L1"
    _write_set(folder, [np.zeros((8, 8))] * 4, bits=8)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(folder))}: 'flat_10ms_-6dB_25C_L1': token '-6dB'"):
        sets_from_paths([folder], gain_db=0.0)


def test_a_manifest_contradicting_its_folders_name_is_refused_naming_both(tmp_path):
    folder = tmp_path / "dark_200ms_12dB_40C"
    _write_set(folder, [np.full((8, 8), 0.1)] * 4, bits=8)
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"sets": [
        {"kind": "bias", "path": folder.name, "exposure_s": 0.001, "gain_db": 0, "temperature_c": 75}]}))
    with pytest.raises(ValueError, match=r"set 1: exposure_s = 0\.001 s \(the name: 0\.2 s\); gain_db = 0 dB \(the name: 12 dB\); "
                                         r"temperature_c = 75 °C \(the name: 40 °C\) contradict the name 'dark_200ms_12dB_40C'"):
        read_manifest(tmp_path / "m.yaml")
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"sets": [
        {"kind": "flat", "path": folder.name, "exposure_s": 0.2, "gain_db": 12, "temperature_c": 40}]}))
    with pytest.raises(ValueError, match=r"kind 'flat' contradicts the name 'dark_200ms_12dB_40C' \(dark\)"):
        read_manifest(tmp_path / "m.yaml")
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"sets": [  # agreeing values (bias/dark alike) are accepted
        {"kind": "bias", "path": folder.name, "exposure_s": 0.2, "gain_db": 12, "temperature_c": 40}]}))
    assert read_manifest(tmp_path / "m.yaml").sets[0].exposure_s == 0.2


def test_a_yaml_alias_bomb_is_refused_at_once_with_a_short_message(tmp_path):
    """Nested aliases in a set's path: str() of each item expanded them (a 296-byte manifest, a 73 kB error message;
    10× per level)."""
    import time

    nested = "&a0 [x]"
    for i in range(1, 4):
        nested = f"&a{i} [" + ", ".join([nested] + [f"*a{i - 1}"] * 9) + "]"
    p = tmp_path / "bomb.yaml"
    p.write_text("sets:\n  - {kind: dark, exposure_s: 0.1, gain_db: 0, temperature_c: 25, path: [" + ", ".join([nested] + ["*a3"] * 9) + "]}\n")
    t0 = time.perf_counter()
    with pytest.raises(ValueError) as info:
        read_manifest(p)
    assert time.perf_counter() - t0 < 1.0 and len(str(info.value)) < 400
    assert re.search(r"line \d+: YAML alias \*a0 refused", str(info.value))
    p.write_text("sets:\n  - {kind: dark, exposure_s: 0.1, gain_db: 0, temperature_c: 25, path: [[a, [b, [c, [d, [e]]]]]]}\n")
    with pytest.raises(ValueError, match=r"set 1: path items must be strings \(file, folder or glob names\), got list \['a', \[.*\]\]$"):
        read_manifest(p)


@pytest.mark.parametrize("temperature", [500.0, -100.0])
def test_an_out_of_range_temperature_is_refused_naming_the_range(temperature, tmp_path, capsys):
    with pytest.raises(ValueError, match=rf"set d: temperature_c = {temperature:g} °C is not a sensor temperature: it must lie in "
                                         r"\[-60, 150\] °C \(the operating point written to the metadata is clipped to camhealth's 0 … 80 °C\)"):
        FrameSet("dark", 0.1, temperature_c=temperature, frames=np.zeros((4, 8, 8), np.float32), name="d")
    with pytest.raises(SystemExit) as info:
        main([str(tmp_path / "dark_200ms"), "--out", str(tmp_path / "c.yaml"), f"--temperature-c={temperature:g}"])
    assert info.value.code == 2 and f"argument --temperature-c: must lie in the sensor temperature range -60 … 150 °C, got {temperature:g}" in capsys.readouterr().err


def test_a_default_operating_point_outside_the_range_is_clamped_and_said_so():
    """Dark sets recorded hotter than camhealth's 0 … 80 °C: the default operating point (the median dark-set
    temperature, 100 °C) is written as 80 °C — and the field's note and a warning say that it was clamped, rather
    than calling 80 °C the median."""
    sets = _sets()
    for s in sets:
        if s.kind in ("bias", "dark"):
            s.temperature_c += 25.0  # 40 / 75 °C → 65 / 100 °C
    res = calibrate(sets)
    field = res.fields["temperature_c"]
    assert field.value == 80.0 and float(res.metadata.temperature_c) == 80.0
    assert "median dark-set temperature, clamped from 100 to the range [0, 80] °C" in field.method
    assert any("operating point temperature_c: the default (median dark-set temperature) is 100 °C, outside" in w
               and "--operating-point temperature_c=VALUE" in w for w in res.warnings)
    assert not any("operating point exposure_s" in w or "operating point gain_db" in w for w in res.warnings)


def test_colour_image_files_and_videos_are_refused_naming_the_file(tmp_path):
    """Flats saved as 8-bit RGB PNGs with each channel's own noise were read as their BT.601 luma, which averages three
    channels' noise: the ICX285's full well came out 34 091 e⁻ instead of 13 882 e⁻, without a word (only a set mixing
    colour and gray files was refused). Colour files (channels that differ) and colour video frames are refused naming
    the file; a gray image saved as RGB (three equal channels) is read as gray, beside gray files too."""
    import cv2
    from PIL import Image

    from camhealth.calibrate.frames import load_frames

    rng = np.random.default_rng(2)
    gray, rgb = [], []
    for i in range(6):
        g = np.clip(np.rint(rng.normal(80, 3, (16, 16))), 0, 255).astype(np.uint8)
        p = tmp_path / f"dark_100ms_0dB_25C_{i:04d}.png"
        Image.fromarray(np.stack([g] * 3, -1) if i in (1, 4) else g).save(p)  # 1 and 4: gray saved as RGB
        gray.append((p, g))
        c = np.clip(np.rint(rng.normal(80, 3, (16, 16, 3))), 0, 255).astype(np.uint8)
        q = tmp_path / f"flat_10ms_0dB_25C_{i:04d}.png"
        Image.fromarray(c).save(q)
        rgb.append(q)
    x = load_frames(FrameSet("dark", 0.1, paths=[p for p, _ in gray]))
    assert np.array_equal(np.rint(x * 255), np.stack([g for _, g in gray]))
    advice = r"is a colour image \(its red, green and blue samples differ\).*give the camera's raw or mono frames"
    with pytest.raises(ValueError, match=rf"flat set .*: {re.escape(str(rgb[0]))} {advice}"):
        load_frames(FrameSet("flat", 0.01, paths=rgb))
    with pytest.raises(ValueError, match=rf"dark set .*: {re.escape(str(rgb[3]))} {advice}"):  # one colour file among gray
        load_frames(FrameSet("dark", 0.1, paths=[p for p, _ in gray[:3]] + [rgb[3]]))
    c16 = tmp_path / "flat16.png"  # a 16-bit colour PNG (read by OpenCV, not Pillow)
    cv2.imwrite(str(c16), (np.clip(rng.normal(0.3, 0.01, (16, 16, 3)), 0, 1) * 65535).astype(np.uint16))
    with pytest.raises(ValueError, match=rf"{re.escape(str(c16))} {advice}"):
        load_frames(FrameSet("flat", 0.01, paths=[c16] * 4))
    video = tmp_path / "flat_10ms_0dB_25C_L1.mkv"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 10, (16, 16), isColor=True)
    for _ in range(4):
        w.write(np.clip(np.rint(rng.normal(80, 3, (16, 16, 3))), 0, 255).astype(np.uint8))
    w.release()
    with pytest.raises(ValueError, match=rf"frame 0 of video {re.escape(str(video))} {advice}"):
        load_frames(FrameSet("flat", 0.01, paths=[video]))


@pytest.mark.parametrize("camera, message", [
    ({"is_cmos": 0.5}, r"camera field is_cmos = 0\.5 must be 0 \(CCD\) or 1 \(CMOS\), or a bool"),
    ({"pixel_size_um": True}, r"camera field pixel_size_um = True must be a number in camhealth's range \[0\.9, 10\] µm, not a bool"),
    ({"pixel_size_um": "abc"}, r"camera field pixel_size_um = 'abc' must be a number in camhealth's range \[0\.9, 10\] µm$"),
    ({"pixel_clock_hz": 10**400}, r"camera field pixel_clock_hz = 1000.* must be a number in camhealth's range \[8e\+06, 1\.5e\+08\] Hz"),
    ({"sensor_type": None}, r"camera field sensor_type = None must be CCD or CMOS"),
])
def test_camera_fields_are_not_coerced(camera, message, monkeypatch):
    """is_cmos 0.5 was read as CMOS, pixel_size_um True as 1 µm, 'abc' failed without the field's name."""
    import camhealth.calibrate.pipeline as pipeline

    monkeypatch.setattr(pipeline, "load_frames_with_depth", lambda *a: pytest.fail("frames read before the camera was checked"))
    with pytest.raises(ValueError, match=message):
        calibrate(_sets(), camera=camera)


def test_is_cmos_is_a_bool_or_0_or_1(tmp_path):
    res = calibrate(_sets(), camera={"is_cmos": True})
    assert res.fields["is_cmos"].value == 1.0 and res.fields["is_cmos"].source == "given"
    (tmp_path / "b").mkdir()
    p = tmp_path / "m.yaml"
    p.write_text("camera: {is_cmos: false}\nsets:\n  - {kind: bias, path: b, exposure_s: 0.001, gain_db: 0, temperature_c: 25}\n")
    assert read_manifest(p).camera == {"is_cmos": False}  # a YAML bool: a flag, as camhealth's metadata takes it
    from camhealth.calibrate.pipeline import _camera_values

    assert _camera_values({"is_cmos": 0}) == {"is_cmos": 0.0} and _camera_values({"is_cmos": np.True_}) == {"is_cmos": 1.0}


@pytest.mark.parametrize("op, message", [
    ({"gain_db": None}, r"operating point gain_db = None must be a number in camhealth's range \[0, 24\] dB; leave it out for "
                        r"the default \(lowest flat gain\)"),
    ({"gain_db": 99}, r"operating point gain_db = 99 dB is outside camhealth's range \[0, 24\] dB"),
    ({"exposure_s": "abc"}, r"operating point exposure_s = 'abc' must be a number in camhealth's range \[0\.001, 0\.2\] s$"),
    ({"temperature_c": True}, r"operating point temperature_c = True must be a number in camhealth's range \[0, 80\] °C, not a bool"),
    ({"gain": 6}, r"unknown operating-point field\(s\) \['gain'\]"),
])
def test_the_operating_point_is_checked_before_any_frame_is_read(op, message, monkeypatch):
    """It was checked only after every frame had been processed (minutes for real stacks), and gain_db None gave a bare
    TypeError from float()."""
    import camhealth.calibrate.pipeline as pipeline

    monkeypatch.setattr(pipeline, "load_frames_with_depth", lambda *a: pytest.fail("frames read before the operating point was checked"))
    with pytest.raises(ValueError, match=message):
        calibrate(_sets(), operating_point=op)


def test_frame_set_values_are_not_coerced():
    """FrameSet('dark', True) was a 1 s exposure; paths='abc' three paths a, b, c."""
    from pathlib import Path

    frames = np.zeros((4, 8, 8), np.float32)
    with pytest.raises(ValueError, match=r"set dark: exposure_s = True must be a number of seconds > 0, not a bool"):
        FrameSet("dark", True, frames=frames)
    with pytest.raises(ValueError, match=r"set d: gain_db = np.True_ must be a number of dB in \[0, 24\], not a bool"):
        FrameSet("dark", 0.1, gain_db=np.True_, frames=frames, name="d")
    with pytest.raises(ValueError, match=r"set d: temperature_c = 1000.* must be a finite number of °C in \[-60, 150\]"):
        FrameSet("dark", 0.1, temperature_c=10**400, frames=frames, name="d")
    assert FrameSet("dark", 0.1, paths="abc").paths == [Path("abc")]
    assert FrameSet("dark", 0.1, paths=Path("a/b")).paths == [Path("a/b")]
    with pytest.raises(ValueError, match=r"set dark: paths = 5 must be a path \(str or Path\) or a list of them"):
        FrameSet("dark", 0.1, paths=5)
    with pytest.raises(ValueError, match=r"set dark: paths must be str or Path, got int 1"):
        FrameSet("dark", 0.1, paths=["a", 1])


@pytest.mark.parametrize("size", [0, 1, 4])
def test_frames_smaller_than_5x5_px_are_refused_naming_the_set_and_the_size(size):
    """1×1 px frames calibrated "successfully" with NaN DSNU and PRNU (the variance of one pixel); 0×0 px frames failed
    with "every pixel of the set is excluded (hot)"."""
    sets = _sets()
    for s in sets:
        s.frames = np.clip(s.frames[:, :size, :size] + 0.1, 0, 1)  # an offset: the darks' temporal estimator
    with pytest.raises(ValueError, match=rf"bias set 'bias_1ms_12dB_40C' \(0\.001 s, 12 dB, 40 °C\): its frames are {size}×{size} px; "
                                         r"a set needs frames of at least 5×5 px \(the dead-pixel test's 5×5 neighbourhood"):
        calibrate(sets)


def test_a_set_with_fewer_than_2_pixels_left_is_refused_naming_it():
    from camhealth.calibrate.statistics import set_statistics

    x = np.random.default_rng(0).uniform(0.2, 0.3, (4, 8, 8)).astype(np.float32)
    exclude = np.ones((8, 8), dtype=bool)
    exclude[3, 3] = False
    with pytest.raises(ValueError, match=r"^the dark: 63 of its 8×8 pixels are excluded \(hot or dead\), leaving 1; its statistics "
                                         r"need at least 2$"):
        set_statistics(x, exclude, name="the dark")


def test_a_manifest_nested_too_deeply_or_with_a_huge_number_is_refused_naming_it(tmp_path):
    """5000 levels of nesting raised a bare RecursionError, a 400-digit gain_db a bare OverflowError."""
    p = tmp_path / "m.yaml"
    p.write_text("sets: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ValueError, match=rf"^cannot parse manifest {re.escape(str(p))}: its values are nested too deeply"):
        read_manifest(p)
    (tmp_path / "b").mkdir()
    bias = "sets:\n  - {kind: bias, path: b, exposure_s: 0.001, gain_db: 0, temperature_c: 25%s}\n"
    for text, where, key in (("operating_point: {gain_db: %s}\n" % ("9" * 400) + bias % "", "operating_point", "gain_db"),
                             ("camera: {pixel_size_um: %s}\n" % ("9" * 400) + bias % "", "camera", "pixel_size_um"),
                             (bias.replace("0.001", "9" * 400) % "", "set 1", "exposure_s")):
        p.write_text(text)
        with pytest.raises(ValueError, match=rf"^manifest {re.escape(str(p))}, {where}: {key} = 9+\.\.\.9+ must be a finite number$"):
            read_manifest(p)
    p.write_text(bias % (", bit_depth: " + "9" * 400))
    with pytest.raises(ValueError, match=rf"^manifest {re.escape(str(p))}, set 1: bit_depth = 9{{57}}\.\.\. must be None"):
        read_manifest(p)
    p.write_text("operating_point: {gain_db: %s}\n" % ("9" * 5000) + bias % "")  # beyond int()'s 4300 digits
    with pytest.raises(ValueError, match=rf"^cannot parse manifest {re.escape(str(p))}: Exceeds the limit \(4300 digits\)"):
        read_manifest(p)
