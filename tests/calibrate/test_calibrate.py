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
    dm = NoiseDataModule(sensor=str(paths["metadata"]), source="deadleaves", source_kwargs={"n": 2, "size": 64})  # fit's sensor:
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
    with pytest.raises(ValueError, match="none of their 1 temperature"):
        calibrate([s for s in _sets(dark_temperatures_c=(40.0,)) if s.kind == "flat" or s.exposure_s == 0.2]
                  + [s for s in _sets(dark_temperatures_c=(40.0,)) if s.kind == "dark" and s.exposure_s == 0.2])


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
