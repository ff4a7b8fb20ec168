"""``camhealth.monitor.defect_map``: a camera's known defective pixels read from calibration's ``camera.maps.npz``,
a ``.npy`` array, a mask image or an array; bad and malicious files refused with a message that names what is
wrong; the monitor counting the defects on the map as ``known`` and alarming on the others only."""

import json
import pickle

import numpy as np
import pytest
import torch

from camhealth.monitor.defect_map import MAX_DEFECT_SHARE, load_defect_map


def _mask(h=6, w=8, at=((1, 2), (4, 7))):
    m = np.zeros((h, w), dtype=bool)
    for y, x in at:
        m[y, x] = True
    return m


# ------------------------------------------------------------------ reading
def test_calibration_maps_npz_is_read_by_its_hot_pixels(tmp_path):
    """camera.maps.npz with calibration's arrays (tests/calibrate reads the file calibrate writes): the hot pixels
    taken."""
    m = _mask()
    path = tmp_path / "camera.maps.npz"
    np.savez_compressed(path, hot_pixels=m, dsnu_dn=np.zeros(m.shape), prnu=np.zeros(m.shape))
    out = load_defect_map(path)
    assert out.dtype == torch.bool and out.shape == m.shape and torch.equal(out, torch.from_numpy(m))
    assert torch.equal(load_defect_map(str(path), shape=m.shape), out)


@pytest.mark.parametrize("form", ["npz_single", "npy", "png", "pgm", "tiff16", "numpy_uint8", "torch_bool", "torch_float"])
def test_every_accepted_form_gives_the_same_map(form, tmp_path):
    import cv2

    m = _mask()
    if form == "npz_single":
        src = tmp_path / "m.npz"
        np.savez(src, mask=m.astype(np.uint8))
    elif form == "npy":
        src = tmp_path / "m.npy"
        np.save(src, m)
    elif form in ("png", "pgm"):
        src = tmp_path / f"m.{form}"
        assert cv2.imwrite(str(src), m.astype(np.uint8) * 255)
    elif form == "tiff16":
        src = tmp_path / "m.tiff"
        assert cv2.imwrite(str(src), m.astype(np.uint16) * 1000)
    elif form == "numpy_uint8":
        src = m.astype(np.uint8)
    elif form == "torch_bool":
        src = torch.from_numpy(m)
    else:
        src = torch.from_numpy(m).double()
    assert torch.equal(load_defect_map(src), torch.from_numpy(m))


def test_a_map_without_defects_is_allowed():
    """A calibration that found no hot pixels: every defect the monitor flags is then new."""
    assert not bool(load_defect_map(np.zeros((4, 5), dtype=bool)).any())


class _Payload:
    """Pickling this object would run code on loading: it must never be unpickled."""

    def __init__(self, target):
        self.target = target

    def __reduce__(self):
        return (open, (self.target, "w"))


def test_pickled_arrays_are_refused_and_never_run(tmp_path):
    target = tmp_path / "pwned.txt"
    obj = np.empty(1, dtype=object)
    obj[0] = _Payload(str(target))
    npz = tmp_path / "evil.npz"
    np.savez(npz, hot_pixels=obj)
    with pytest.raises(ValueError, match="pickled arrays are refused"):
        load_defect_map(npz)
    npy = tmp_path / "evil.npy"
    np.save(npy, obj, allow_pickle=True)
    with pytest.raises(ValueError, match="pickled arrays are refused"):
        load_defect_map(npy)
    raw = tmp_path / "evil.pkl"
    raw.write_bytes(pickle.dumps(_Payload(str(target))))
    with pytest.raises(ValueError, match="suffix '.pkl' is not one of"):
        load_defect_map(raw)
    assert not target.exists()


@pytest.mark.parametrize("setup, error, match", [
    (lambda p: p / "missing.npz", FileNotFoundError, "does not exist"),
    (lambda p: (p / "junk.npz").write_bytes(b"not a zip") and p / "junk.npz", ValueError, "not a readable .npz|cannot be read"),
    (lambda p: (p / "junk.png").write_bytes(b"not a png") and p / "junk.png", ValueError, "not a readable image"),
    (lambda p: p / "folder", FileNotFoundError, "does not exist"),
])
def test_missing_and_unreadable_files_are_named(setup, error, match, tmp_path):
    (tmp_path / "folder").mkdir()
    path = setup(tmp_path)
    with pytest.raises(error, match=match) as exc:
        load_defect_map(path)
    assert path.name in str(exc.value)


@pytest.mark.parametrize("dtype", [bool, np.uint8, np.int64, np.float32])
def test_calibration_hot_and_dead_pixels_give_their_union_in_every_accepted_dtype(dtype, tmp_path):
    """camera.maps.npz with ``hot_pixels`` and ``dead_pixels`` as bool or as whole numbers 0/1 (both allowed): the map
    marks the pixels of both."""
    hot, dead = _mask(at=((1, 2),)), _mask(at=((4, 7), (5, 0)))
    path = tmp_path / "camera.maps.npz"
    np.savez_compressed(path, hot_pixels=hot.astype(dtype), dead_pixels=dead.astype(dtype))
    out = load_defect_map(path)
    assert out.dtype == torch.bool and torch.equal(out, torch.from_numpy(hot | dead))


def test_calibration_hot_and_dead_pixels_of_different_shapes_or_values_are_refused(tmp_path):
    path = tmp_path / "camera.maps.npz"
    np.savez_compressed(path, hot_pixels=np.zeros((64, 64), np.uint8), dead_pixels=np.zeros((32, 32), np.uint8))
    with pytest.raises(ValueError, match=r"hot_pixels has shape \(64, 64\) but dead_pixels has shape \(32, 32\)"):
        load_defect_map(path)
    np.savez_compressed(path, hot_pixels=np.zeros((6, 8), np.uint8), dead_pixels=np.full((6, 8), 2, np.uint8))
    with pytest.raises(ValueError, match=r"dead_pixels\] holds the values 2: a defect map must be bool or 0/1"):
        load_defect_map(path)


def test_an_archive_without_hot_pixels_names_its_arrays(tmp_path):
    path = tmp_path / "two.npz"
    np.savez(path, a=_mask(), b=_mask())
    with pytest.raises(ValueError, match=r"holds the arrays \['a', 'b'\]: expected one of \['hot_pixels', 'dead_pixels', 'defective_pixels'\]"):
        load_defect_map(path)


def test_a_colour_image_is_refused(tmp_path):
    import cv2

    path = tmp_path / "rgb.png"
    assert cv2.imwrite(str(path), np.zeros((6, 8, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match="has 3 channels"):
        load_defect_map(path)


@pytest.mark.parametrize("array, match", [
    (np.zeros((2, 3, 4), dtype=bool), r"shape \(2, 3, 4\): a defect map must be 2-D"),
    (np.zeros((0, 4), dtype=bool), "is empty"),
    (np.array([[0, 1], [2, 0]]), "holds the values 0, 1, 2: a defect map must be bool or 0/1"),
    (np.array([[0.0, float("nan")], [0.0, 0.0]]), "holds the values 0, nan"),
    (np.array([["a", "b"]]), "dtype <U1: expected bool"),
    (np.ones((4, 4), dtype=bool), r"marks 16 of 16 pixels \(100.0 %; a map must mark fewer than 50 %\)"),
])
def test_bad_arrays_are_refused_naming_the_value(array, match):
    with pytest.raises(ValueError, match=match):
        load_defect_map(array)


def test_the_share_limit_and_the_shape_check():
    m = np.zeros((4, 4), dtype=bool)
    m.flat[: int(MAX_DEFECT_SHARE * 16) - 1] = True
    assert int(load_defect_map(m).sum()) == 7  # just under half: accepted
    with pytest.raises(ValueError, match=r"is 4×4 px \(W×H\) but the frames are 5×4 px"):
        load_defect_map(m, shape=(4, 5))
    with pytest.raises(TypeError, match="must be a path or an H×W array, got list"):
        load_defect_map([[0, 1]])


# ------------------------------------------------------------------ the monitor
def _defect_frame(share=0.005, seed=6):
    """A ramp with the ICX285's own noise (8-bit) and ``share`` of its pixels moved by 40–140 DN, and the truth."""
    from camhealth.bench.sensor_variants import simulate_variant
    from camhealth.physics import CameraMetadata

    meta = CameraMetadata.preset("ICX285")
    ramp = torch.linspace(60.0, 200.0, 512).view(1, 1, 1, 512).expand(1, 1, 384, 512) / 255.0
    noisy, _ = simulate_variant(ramp.contiguous(), meta, ("round8",), torch.Generator().manual_seed(4))
    g = torch.Generator().manual_seed(seed)
    hit = torch.rand(noisy.shape, generator=g) < share
    sign = torch.where(torch.rand(noisy.shape, generator=g) < 0.5, 1.0, -1.0)
    bad = (noisy * 255 + hit * sign * (40 + 100 * torch.rand(noisy.shape, generator=g))).clamp(0, 255).round() / 255
    return bad[0, 0], hit[0, 0]


@pytest.mark.parametrize("mode", ["sampled", "map"])
def test_defects_on_the_map_are_known_and_do_not_alarm(mode):
    """With every defect on the map the monitor still counts them (``known`` = all) but neither the alarm nor the
    ROS diagnostics name them; with half of them on the map, ``known`` is the flagged ones the map marks and the
    alarm names the others; the summary lists the recurring positions the map does not mark."""
    from camhealth.monitor import DEFECT_ALARM_PPM, Monitor, new_defect_ppm
    from camhealth.monitor.api import DEFECT_LIST
    from camhealth.monitor.diagnostics import OK, WARN, frame_level, key_values

    frame, hit = _defect_frame()
    full = Monitor("noise_source_full", None, sensor="ICX285", mode=mode, warmup=False, adaptive=False, defect_map=hit)
    r = full.process(frame)
    d = r.noise.defects
    assert d["hot"] + d["dark"] == d["known"] > 0 and new_defect_ppm(d) == 0.0 and d["ppm"] >= DEFECT_ALARM_PPM
    assert "stand out" not in r.alarm["message"] and frame_level(r)[0] == OK
    assert dict(key_values(r, OK))["noise_defects_known"] == str(d["known"])
    full.process(frame)
    s = full.summary()["defects"]
    assert s["map_pixels"] == int(hit.sum()) and 0 < s["map_pixels_flagged"] <= s["map_pixels"]
    assert s["recurring_new_pixels"] == 0 and s["recurring_new_xy"] == []

    half = hit.clone()
    ys, xs = hit.nonzero(as_tuple=True)
    half[ys[::2], xs[::2]] = False  # every other defect off the map
    mon = Monitor("noise_source_full", None, sensor="ICX285", mode=mode, warmup=False, adaptive=False, defect_map=half)
    r = mon.process(frame)
    d = r.noise.defects
    flagged = d["hot"] + d["dark"]
    assert 0.3 * flagged < d["known"] < 0.7 * flagged
    assert new_defect_ppm(d) == pytest.approx(1e6 * (flagged - d["known"]) / d["checked"], abs=0.05)
    assert new_defect_ppm(d) >= DEFECT_ALARM_PPM
    assert f"{flagged - d['known']} not on the defect map" in r.alarm["message"] and f"{d['known']} on it" in r.alarm["message"]
    assert frame_level(r)[0] == WARN
    json.loads(r.to_json())  # "known" serialises
    mon.process(frame)
    s = mon.summary()["defects"]
    new_xy = s["recurring_new_xy"]
    assert s["recurring_new_pixels"] >= len(new_xy) == min(s["recurring_new_pixels"], DEFECT_LIST) > 0
    assert all(hit[y, x] and not half[y, x] and n == 2 for x, y, n in new_xy)


def test_without_a_map_nothing_changes():
    from camhealth.monitor import Monitor, new_defect_ppm
    from camhealth.monitor.diagnostics import WARN, frame_level, key_values

    frame, _ = _defect_frame()
    mon = Monitor("noise_source_full", None, sensor="ICX285", mode="sampled", warmup=False, adaptive=False)
    r = mon.process(frame)
    assert "known" not in r.noise.defects and new_defect_ppm(r.noise.defects) == r.noise.defects["ppm"]
    assert "defect map" not in r.alarm["message"] and frame_level(r)[0] == WARN
    assert dict(key_values(r, WARN))["noise_defects_known"] == "nan"
    assert "map_pixels" not in mon.summary()["defects"]


def test_a_map_of_another_size_or_without_noise_is_refused():
    from camhealth.monitor import Monitor

    frame, hit = _defect_frame()
    mon = Monitor("noise_source_full", None, sensor="ICX285", warmup=False, defect_map=hit[:, :500])
    with pytest.raises(ValueError, match=r"defect map is 500×384 px \(W×H\) but this frame is 512×384 px"):
        mon.process(frame)
    with pytest.raises(ValueError, match="give a noise_model"):
        Monitor(None, "mtf", defect_map=hit)


def test_a_frame_of_another_size_is_refused_alone_and_the_monitor_goes_on(tmp_path):
    """A frame that does not fit the map raises ``FrameSizeError`` naming the frame and both sizes and leaves the
    monitor as it was; ``Monitor.run`` reports it as that item's error and goes on with the next frame."""
    from PIL import Image

    from camhealth.monitor import Monitor
    from camhealth.monitor.api import FrameSizeError

    frame, hit = _defect_frame()
    mon = Monitor("noise_source_full", None, sensor="ICX285", warmup=False, defect_map=hit)
    mon.process(frame)
    with pytest.raises(FrameSizeError, match=r"defect map is 512×384 px \(W×H\) but frame small.png is 500×384 px"):
        mon.process(frame[:, :500], source_id="small.png")
    assert mon.frames == 1 and mon.process(frame).noise.coverage["frames"] == 2  # the window went on
    folder = tmp_path / "frames"
    folder.mkdir()
    pixels = (frame.numpy() * 255).round().astype(np.uint8)
    for name, arr in (("a", pixels), ("b", pixels[:, :500]), ("c", pixels)):
        Image.fromarray(arr).save(folder / f"{name}.png")
    out = list(Monitor("noise_source_full", None, sensor="ICX285", warmup=False, defect_map=hit).run(folder))
    assert [r is None for _, r in out] == [False, True, False]
    assert "but frame " + str(folder / "b.png") + " is 500×384 px" in out[1][0].error


@pytest.mark.parametrize("suffix", [".npz", ".npy"])
def test_a_file_that_declares_a_huge_array_is_refused_before_it_is_read(suffix, tmp_path):
    """A compressed archive can declare far more than it holds on disk: the header's shape is checked first."""
    import io
    import zipfile

    from camhealth.monitor.defect_map import MAX_MAP_PIXELS

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|b1", "fortran_order": False, "shape": (100_000, 100_000)})
    path = tmp_path / f"bomb{suffix}"
    if suffix == ".npz":
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("hot_pixels.npy", header.getvalue() + b"\0" * 64)
    else:
        path.write_bytes(header.getvalue())
    with pytest.raises(ValueError, match=rf"declares an array of shape \(100000, 100000\) \(10000000000 elements, at "
                                         rf"most {MAX_MAP_PIXELS} allowed\): not read$"):
        load_defect_map(path)


def _npy_v3(arr):
    """``arr`` as a .npy file with a 3.0 header (UTF-8 text; np.save writes it only for non-Latin-1 field names)."""
    import struct

    d = repr({"descr": np.lib.format.dtype_to_descr(arr.dtype), "fortran_order": False, "shape": arr.shape})
    h = (d + " " * (64 - (12 + len(d) + 1) % 64) + "\n").encode()
    return b"\x93NUMPY\x03\x00" + struct.pack("<I", len(h)) + h + arr.tobytes()


@pytest.mark.parametrize("form", ["npy_v3", "npz_v3", "png", "tiff"])
def test_the_size_limit_holds_for_every_header_version_and_for_images(form, tmp_path, monkeypatch):
    """.npy 3.0 headers are checked like 1.0 and 2.0; a mask image's size is read from its header before decoding."""
    import zipfile

    import cv2

    import camhealth.monitor.defect_map as dm

    monkeypatch.setattr(dm, "MAX_MAP_PIXELS", 1000)
    arr = np.zeros((32, 64), dtype=bool)
    path = tmp_path / {"npy_v3": "m.npy", "npz_v3": "m.npz", "png": "m.png", "tiff": "m.tiff"}[form]
    if form == "npy_v3":
        path.write_bytes(_npy_v3(arr))
    elif form == "npz_v3":
        with zipfile.ZipFile(path, "w") as zf:
            zf.writestr("defective_pixels.npy", _npy_v3(arr))
    else:
        assert cv2.imwrite(str(path), arr.astype(np.uint8))
    with pytest.raises(ValueError, match=r"'[^']*m\.(npy|npz|png|tiff)'.*2048.*at most 1000 allowed\): not read"):
        load_defect_map(path)
    monkeypatch.setattr(dm, "MAX_MAP_PIXELS", 2048)
    assert load_defect_map(path).shape == (32, 64)


@pytest.mark.parametrize("descr", ["|S100000", "<c16", "|V8"])
def test_a_dtype_that_is_not_bool_integer_or_float_is_refused_before_it_is_read(descr, tmp_path):
    """The header's dtype is checked with its shape: 10 × 10 strings of 100 kB are refused, not read."""
    import io
    import zipfile

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": descr, "fortran_order": False, "shape": (10, 10)})
    path = tmp_path / "big_items.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("defective_pixels.npy", header.getvalue())  # the data are missing: reading them would fail
    with pytest.raises(ValueError, match=r"big_items\.npz.*declares an array of dtype .* must be bool or whole "
                                         r"numbers 0/1 .*: not read$"):
        load_defect_map(path)


@pytest.mark.parametrize("mode", ["sampled", "map"])
def test_the_runs_recurring_defects_are_a_map_the_monitor_reads_back(mode, tmp_path):
    """found_defects: the pixels flagged in at least min_frames frames, in the frames' size; saved (defective_pixels
    and flagged_frames), read back by load_defect_map, and given to a new monitor every defect it flags is known."""
    from camhealth.monitor import Monitor
    from camhealth.monitor.defect_map import save_defect_map

    frame, hit = _defect_frame()
    mon = Monitor("noise_source_full", None, sensor="ICX285", mode=mode, warmup=False, adaptive=False)
    with pytest.raises(ValueError, match="no frame processed yet"):
        mon.found_defects()
    first = mon.process(frame).noise.defects
    once, counts = mon.found_defects(1)
    assert once.shape == frame.shape and int(once.sum()) == first["hot"] + first["dark"] and int(counts.max()) == 1
    assert not bool(mon.found_defects()[0].any())  # nothing recurs after one frame
    mon.process(frame)
    twice, counts = mon.found_defects()
    assert torch.equal(twice, once) and bool(hit[twice].all()) and int(counts[twice].min()) == 2
    with pytest.raises(ValueError, match="min_frames = 0 must be an integer >= 1"):
        mon.found_defects(0)
    path = save_defect_map(tmp_path / "run_defects", twice, counts)
    assert path.name == "run_defects.npz" and set(np.load(path).files) == {"defective_pixels", "flagged_frames"}
    assert torch.equal(load_defect_map(path, shape=tuple(frame.shape)), twice)
    again = Monitor("noise_source_full", None, sensor="ICX285", mode=mode, warmup=False, adaptive=False, defect_map=path)
    d = again.process(frame).noise.defects
    assert d["known"] == d["hot"] + d["dark"] > 0
    with pytest.raises(ValueError, match="must be a bool H×W array"):
        save_defect_map(tmp_path / "x.npz", counts)
    # a smaller frame: the positions of the old size are not its pixels (found_defects raised IndexError)
    small = frame[: frame.shape[0] // 2, : frame.shape[1] // 2].contiguous()
    mon.process(small)
    found, counts = mon.found_defects(1)
    assert found.shape == small.shape and int(counts.max()) <= 1


def test_the_monitor_counts_only_the_pixels_tested():
    """A frame half a 1-px grid pattern (not tested) and half a camera ramp with 1 % defects, both imaged by the same
    ICX285: the monitor's pixels tested exclude the pattern's patches, so the share per million is the ramp's own."""
    from camhealth.bench.sensor_variants import simulate_variant
    from camhealth.monitor import Monitor
    from camhealth.physics import CameraMetadata
    from tests.estimators.test_defective_pixels import _camera_ramp, _inject

    i = torch.arange(256) % 2
    pattern = ((i.view(-1, 1) + i.view(1, -1)).float() * 0.04 + 0.3).view(1, 1, 256, 256)
    grid = simulate_variant(pattern, CameraMetadata.preset("ICX285"), ("round8",), torch.Generator().manual_seed(2))[0][0, 0]
    ramp, truth = _inject(_camera_ramp(4), 160, (60.0, 120.0), seed=9)  # 4 patches of 128 px
    right = torch.cat([torch.cat([ramp[0, 0], ramp[1, 0]], 1), torch.cat([ramp[2, 0], ramp[3, 0]], 1)], 0)
    frame = torch.cat([grid, right], 1)  # 256 × 512: 2×2 patches of the grid, 2×2 of the ramps
    mon = Monitor("noise_source_full", None, sensor="ICX285", mode="map", warmup=False, adaptive=False)
    report = mon.process(frame).noise
    assert report.coverage["estimated"] == 8  # the grid's 4 patches were read too
    d = report.defects
    assert d["checked"] == 4 * 126 * 126  # but only the ramps' pixels were tested
    assert d["ppm"] >= 0.9 * 1e6 * 160 / (126 * 126)


def test_npz_members_without_the_npy_suffix_are_read_or_refused_as_defect_maps(tmp_path):
    """``np.load`` lists a member without the ``.npy`` suffix under its full name: a NumPy array stored so is read as
    the map it is; a member that is no NumPy array (a text file), or a corrupt or truncated archive, is a ValueError
    that names the defect map — never a KeyError or a zip error."""
    import io
    import zipfile

    buf = io.BytesIO()
    np.save(buf, _mask())
    with zipfile.ZipFile(tmp_path / "nosuffix.npz", "w") as z:
        z.writestr("hot_pixels", buf.getvalue())
    mask = load_defect_map(tmp_path / "nosuffix.npz")
    assert np.array_equal(np.asarray(mask), _mask())
    with zipfile.ZipFile(tmp_path / "notes.npz", "w") as z:
        z.writestr("readme.txt", b"hello")
    with pytest.raises(ValueError, match=r"defect map .*notes\.npz.*readme\.txt.* not a plain NumPy array"):
        load_defect_map(tmp_path / "notes.npz")
    (tmp_path / "cut.npz").write_bytes(b"PK\x03\x04" + b"x" * 40)
    with pytest.raises(ValueError, match=r"defect map .*cut\.npz.* not a readable \.npz archive"):
        load_defect_map(tmp_path / "cut.npz")
