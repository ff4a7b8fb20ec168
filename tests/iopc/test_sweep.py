"""The IOPC sweep on a tiny grid through Lightning's predict loop: records, marks, cache/resume."""

import math

import lightning as L
import pytest
import torch

from camhealth.iopc import IOPCSweep, SensorSetting, SweepConfig, SweepGrid, make_cells, noise_gain_db
from camhealth.physics import CameraMetadata
from tests.iopc.fakes import FakeMTFEstimator, FakeNoiseEstimator, NoiseSensitiveDetector, smooth_frames

BOXES = [[10.0, 10.0, 60.0, 80.0]]


def _sweep(tmp_path, noise_levels=(0.0, 6.0, 40.0), lengths=(0.0, 5.0), cache=True, **cfg):
    frames = smooth_frames(2, 96, 128)
    det = NoiseSensitiveDetector(BOXES)
    gt = [{"boxes": torch.tensor(BOXES), "labels": torch.tensor([1])}] * 2
    config = SweepConfig(grid=SweepGrid(list(lengths), [0.0, 90.0], list(noise_levels)),
                         sensor=SensorSetting(), **cfg)
    sw = IOPCSweep(frames, gt, det, FakeNoiseEstimator(32), FakeMTFEstimator(0.8, 48), config,
                   cache_dir=tmp_path / "cache" if cache else None, frame_ids=["a", "b"])
    return sw, det


def _trainer():
    return L.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                     enable_progress_bar=False, enable_model_summary=False)


def test_cells_and_gain():
    cells = make_cells(SweepGrid([0.0, 3.0], [0.0, 45.0, 90.0, 135.0], [0.0, 5.0]))
    assert len(cells) == 2 * (1 + 4) and cells[0]["key"] == "L0_a0_s0" and cells[-1]["key"] == "L3_a135_s5"
    meta = CameraMetadata.preset("EV76C661", temperature_c=70.0, exposure_s=0.1)
    g = noise_gain_db(30.0, meta, ["dark", "readout"], 0.5)
    assert g == pytest.approx(23.56, abs=0.05)  # 30 DN / 1.99 DN at 0 dB
    g_pn = noise_gain_db(10.0, meta, ["photon", "dark", "readout"], 0.5)  # photon noise adds → lower gain
    assert 0 < g_pn < noise_gain_db(10.0, meta, ["dark", "readout"], 0.5)
    assert math.isnan(noise_gain_db(5.0, meta, [], 0.5))


def test_tiny_sweep_through_predict(tmp_path):
    sw, det = _sweep(tmp_path)
    iopc = sw.run(_trainer())
    recs = {r["key"]: r for r in iopc.records}
    assert len(recs) == 3 * 3
    clean = recs["L0_a0_s0"]
    assert clean["ap"] == pytest.approx(1.0) and clean["sigma_tilde"] < 0.5 and clean["mtf_tilde"] == pytest.approx(0.8)
    assert clean["mtf_true"] == 1.0 and clean["n_noise_tiles"] == 2 * 6  # 32-px tiles overlapping the box, 2 frames
    noisy = recs["L0_a0_s6"]
    assert noisy["ap"] == 0.0 and noisy["sigma_tilde"] == pytest.approx(6.0, rel=0.15)
    assert noisy["sigma_true_dn"] == pytest.approx(6.0, rel=0.05) and 0 < noisy["gain_db"] < 24
    assert recs["L5_a90_s0"]["mtf_true"] < 1.0
    unreachable = recs["L5_a0_s40"]
    assert unreachable["marked"] and "outside [0, 24] dB" in unreachable["reason"] and math.isnan(unreachable["ap"])
    assert iopc.count_2d.sum() == 6 and iopc.ap_2d[0, 7] == pytest.approx(1.0)
    assert iopc.provenance["frames"]["ids"] == ["a", "b"] and iopc.provenance["fingerprint"] == sw.fingerprint()
    n_calls = det.n_calls
    # resume: everything cached → no detector call, same curves
    sw2, det2 = _sweep(tmp_path)
    assert sw2.remaining_cells() == []
    iopc2 = sw2.run(_trainer())
    assert det2.n_calls == 0 and n_calls > 0
    assert iopc2.to_dict()["ap_2d"] == iopc.to_dict()["ap_2d"]


def test_partial_cache_resumes_and_results_are_seeded(tmp_path):
    sw, _ = _sweep(tmp_path, noise_levels=(6.0,), lengths=(0.0,))
    first = sw.run_cell(sw.cells[0])
    sw_full, det = _sweep(tmp_path, noise_levels=(6.0,), lengths=(0.0,))
    assert sw_full.remaining_cells() == []
    # no cache: recomputed from the same per-cell seed → identical numbers
    sw3, _ = _sweep(tmp_path, noise_levels=(6.0,), lengths=(0.0,), cache=False)
    again = sw3.run_cell(sw3.cells[0])
    assert again["sigma_true_dn"] == first["sigma_true_dn"] and again["sigma_tilde"] == first["sigma_tilde"]
    # a different seed is a different fingerprint (no stale reuse)
    sw4, _ = _sweep(tmp_path, noise_levels=(6.0,), lengths=(0.0,), seed=1)
    assert sw4.fingerprint() != sw.fingerprint() and len(sw4.remaining_cells()) == 1


def test_valid_range_marks_cells(tmp_path):
    sw, _ = _sweep(tmp_path, noise_levels=(0.0,), lengths=(5.0,), valid_length_px=[0.0, 3.0], cache=False)
    rec = sw.run_cell(sw.cells[0])
    assert rec["marked"] and "outside the MTF estimator's valid range" in rec["reason"]
    assert rec["ap"] == pytest.approx(1.0)  # computed anyway, just not binned


def test_config_and_input_errors(tmp_path):
    with pytest.raises(ValueError, match="out of the allowed range"):
        SweepConfig(grid=SweepGrid([-1.0], [0.0], [0.0])).validate()
    with pytest.raises(ValueError, match="not noise sources"):
        SweepConfig(sensor=SensorSetting(sources=["shot"])).validate()
    with pytest.raises(ValueError, match="unknown sensor preset"):
        SweepConfig(sensor=SensorSetting(preset="XYZ")).validate()
    frames = smooth_frames(2, 96, 128)
    gt = [{"boxes": torch.tensor(BOXES), "labels": torch.tensor([1])}]
    with pytest.raises(ValueError, match="1 ground-truth entries for 2 frames"):
        IOPCSweep(frames, gt, NoiseSensitiveDetector(BOXES), None, None)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        IOPCSweep(frames * 3, gt * 2, NoiseSensitiveDetector(BOXES), None, None)


def test_intensity_and_quantize_set_the_operating_point(tmp_path):
    sw, det = _sweep(tmp_path, noise_levels=(0.0,), lengths=(0.0,), intensity=0.5, quantize=True, cache=False)
    sw.run_cell(sw.cells[0])
    img = det.last_images
    torch.testing.assert_close(img.mean(), 0.5 * sw.frames.mean(), atol=2e-3, rtol=0)
    assert torch.equal(img * 255, (img * 255).round())
    with pytest.raises(ValueError, match="intensity"):
        SweepConfig(intensity=0.0).validate()


def test_the_fingerprint_covers_the_detectors_weights_and_every_ground_truth_field(tmp_path):
    """A TorchDetector retrained (same architecture, other weights) and ground truth that differs only in ``iscrowd``
    change a cell's AP; both changed the AP but not the fingerprint, so a cache reused the old cells."""
    from camhealth.detection import TorchDetector

    class Boxes(torch.nn.Module):
        def __init__(self, w):
            super().__init__()
            self.w = torch.nn.Parameter(torch.tensor([w]))

        def forward(self, x):
            return torch.tensor([[[10.0, 10.0, 60.0, 80.0, 0.9, 1.0]]]).expand(x.shape[0], 1, 6) * (self.w > 0)

    frames = smooth_frames(2, 96, 128)
    gt = [{"boxes": torch.tensor(BOXES), "labels": torch.tensor([1])}] * 2
    config = SweepConfig(grid=SweepGrid([0.0], [0.0], [0.0]), sensor=SensorSetting())

    def fp(det, truth):
        return IOPCSweep(frames, truth, det, None, None, config, frame_ids=["a", "b"]).fingerprint()

    one, other = TorchDetector(Boxes(1.0)), TorchDetector(Boxes(-1.0))
    assert fp(one, gt) == fp(TorchDetector(Boxes(1.0)), gt) and fp(one, gt) != fp(other, gt)
    crowd = [{**g, "iscrowd": torch.tensor([True])} for g in gt]
    assert fp(one, crowd) != fp(one, gt)


@pytest.mark.parametrize("intensity", [0.5, 2.0])
def test_provenance_mean_intensity_is_that_of_the_frames_as_swept(tmp_path, intensity):
    """With intensity 0.5 the detector saw a mean of 0.25 but the provenance recorded the clean frames' 0.5, so
    --normalize-intensity scaled σ̂ by twice what it should. Now: the mean after the scaling (and the clipping at 1),
    with the clean frames' mean kept as source_mean_intensity."""
    sw, det = _sweep(tmp_path, noise_levels=(0.0,), lengths=(0.0,), intensity=intensity, cache=False)
    sw.run_cell(sw.cells[0])  # no noise, no blur: the detector sees the scaled clean frames
    frames = sw.provenance()["frames"]
    assert frames["mean_intensity"] == pytest.approx(float(det.last_images.mean()), abs=1e-6)
    assert frames["mean_intensity"] == pytest.approx(float((sw.frames * intensity).clamp(max=1.0).mean()), abs=1e-6)
    assert frames["source_mean_intensity"] == pytest.approx(float(sw.frames.mean()), abs=1e-6)


@pytest.mark.parametrize("cfg, match", [
    ({"detector_batch_size": 0}, r"detector_batch_size = 0 is out of the allowed range: an integer >= 1"),
    ({"detector_batch_size": -1}, r"detector_batch_size = -1 is out of the allowed range: an integer >= 1"),
    ({"detector_batch_size": 2.5}, r"detector_batch_size = 2.5 is out of the allowed range: an integer >= 1"),
    ({"estimator_batch_size": 0}, r"estimator_batch_size = 0 is out of the allowed range: an integer >= 1"),
    ({"estimator_batch_size": True}, r"estimator_batch_size = True is out of the allowed range: an integer >= 1"),
    ({"sigma_bins_dn": [5]}, r"sigma_bins_dn = \[5.0\] needs at least 2 bin centres \(.*>= 0 DN"),
    ({"mtf_bins": [1.0, 0.5]}, r"mtf_bins = \[1.0, 0.5\] must be finite and strictly increasing \(.*in \[0, 1\]"),
    ({"sigma_bins_dn": [0.0, float("nan")]}, r"sigma_bins_dn = \[0.0, nan\] must be finite and strictly increasing"),
    ({"sigma_bins_dn": [-5.0, 0.0, 5.0]}, r"sigma_bins_dn = \[-5.0, 0.0, 5.0\] is out of the allowed range: .*>= 0 DN"),
    ({"mtf_bins": [0.5, 1.5]}, r"mtf_bins = \[0.5, 1.5\] is out of the allowed range: .*in \[0, 1\]"),
    ({"mtf_bins": ["0.5", 1.0]}, r"mtf_bins = \['0.5', 1.0\] is not allowed"),
    ({"seed": "abc"}, r"seed = 'abc' is not allowed: the noise seed must be an integer"),
])
def test_validate_refuses_bad_batch_sizes_bins_and_seed_before_any_cell(tmp_path, cfg, match):
    """Batch sizes of 0 or -1 failed inside the first cell (range() step 0, or 0 detections for 2 frames), bins the
    curves refuse failed only after every cell was computed, and a text seed was accepted."""
    with pytest.raises(ValueError, match=match):
        SweepConfig(**cfg).validate()
    with pytest.raises(ValueError, match=match):  # the sweep refuses it before any detector call
        _sweep(tmp_path, cache=False, **cfg)


def test_blurred_cells_with_photon_noise_reach_their_nominal_level():
    """Photon shot noise arises before the motion blur, which multiplies its variance by Σpsf² (0.14 at 7 px); the
    gain was solved for unblurred photon noise, so the closed-loop config's 2-DN cell at L = 7 px realised 1.00 DN
    (and 4 DN realised 2.54 DN, where it needs more than 24 dB and must be marked)."""
    frames = smooth_frames(2, 96, 128)
    gt = [{"boxes": torch.tensor(BOXES), "labels": torch.tensor([1])}] * 2
    sensor = SensorSetting(preset="ICX285", temperature_c=25.0, exposure_s=0.008, sources=["photon", "dark", "readout"])
    config = SweepConfig(grid=SweepGrid([0.0, 7.0], [0.0], [2.0, 4.0]), sensor=sensor, intensity=0.5)
    sw = IOPCSweep(frames, gt, NoiseSensitiveDetector(BOXES), FakeNoiseEstimator(32), FakeMTFEstimator(0.8, 48), config)
    recs = {c["key"]: sw.run_cell(c) for c in sw.cells}
    for key in ("L0_a0_s2", "L7_a0_s2", "L0_a0_s4"):
        assert recs[key]["sigma_true_dn"] == pytest.approx(recs[key]["noise_level_dn"], rel=0.1), key
        assert not recs[key]["marked"], key
    assert recs["L7_a0_s2"]["gain_db"] > recs["L0_a0_s2"]["gain_db"] + 5  # the blur averages the photon noise
    blurred4 = recs["L7_a0_s4"]
    assert blurred4["marked"] and "outside [0, 24] dB" in blurred4["reason"] and "Σpsf²" in blurred4["reason"]
    assert blurred4["gain_db"] > 24 and math.isnan(blurred4["sigma_true_dn"])


def test_noise_gain_solves_the_quadratic_with_the_psf_energy():
    meta = CameraMetadata.preset("ICX285", temperature_c=25.0, exposure_s=0.008)
    src = ["photon", "dark", "readout"]
    assert noise_gain_db(2.0, meta, src, 0.25, 1.0) == noise_gain_db(2.0, meta, src, 0.25)
    assert noise_gain_db(2.0, meta, src, 0.25, 0.143) > noise_gain_db(2.0, meta, src, 0.25) + 5
    # without photon noise the blur does not change the gain (DCSN and readout arise after it)
    assert noise_gain_db(2.0, meta, ["dark", "readout"], 0.25, 0.143) == noise_gain_db(2.0, meta, ["dark", "readout"], 0.25)
    for bad in (0.0, 1.5, float("nan"), True):
        with pytest.raises(ValueError, match=r"psf_energy = .* is out of the allowed range \(0, 1\]"):
            noise_gain_db(2.0, meta, src, 0.25, bad)


def test_ranks_cover_the_grid_whatever_the_cache_holds_when_each_lists_its_cells(tmp_path):
    """run_local sliced each rank's own list of *remaining* cells: with rank 0 one cell ahead, rank 1's slice shifted,
    cells L5_a0_s0, L0_a0_s6 and L5_a90_s6 were run by nobody and rank 0's collect() raised."""
    rank0, _ = _sweep(tmp_path, noise_levels=(0.0, 6.0))
    rank1, _ = _sweep(tmp_path, noise_levels=(0.0, 6.0))
    assert len(rank0.cells) == 6
    share0 = rank0.cells[0::2]
    rank0.run_cell(share0[0])  # rank 0 is ahead when rank 1 lists its cells
    ran1 = rank1.run_local(rank=1, world_size=2, progress=False)
    assert [r["key"] for r in ran1] == [c["key"] for c in rank0.cells[1::2]]
    ran0 = rank0.run_local(rank=0, world_size=2, progress=False)
    assert [r["key"] for r in ran0] == [c["key"] for c in share0[1:]]  # its cached cell is skipped
    assert len(rank0.collect()) == 6
    with pytest.raises(ValueError, match=r"rank = 2 is out of the allowed range: an integer in \[0, 1\]"):
        rank0.run_local(rank=2, world_size=2, progress=False)


class _FakeDDPTrainer:
    """Stands in for one rank of a 2-process Trainer: predict runs the rank's share of the loader's cells (the
    distributed sampler's split: items rank, rank + 2, …); the barrier runs ``at_barrier`` (the other rank)."""

    world_size = 2

    def __init__(self, rank, at_barrier=None):
        self.rank = rank
        self.strategy = self
        self._at_barrier = at_barrier

    def predict(self, module, dataloaders, return_predictions=True):
        cells = dataloaders.dataset.cells
        return [module.predict_step(cells[i], i) for i in range(self.rank, len(cells), self.world_size)]

    def barrier(self, *args):
        if self._at_barrier is not None:
            self._at_barrier()


def test_distributed_run_splits_the_grid_not_each_ranks_remaining_cells(tmp_path):
    """IOPCSweep.run gave the distributed sampler each rank's own list of remaining cells: with rank 0 one cell ahead,
    the shares overlapped and a cell was run by nobody, so collect() raised."""
    rank0, _ = _sweep(tmp_path, noise_levels=(0.0, 6.0))
    rank1, _ = _sweep(tmp_path, noise_levels=(0.0, 6.0))
    rank0.run_cell(rank0.cells[0])
    result = {}
    iopc1 = rank1.run(_FakeDDPTrainer(1, at_barrier=lambda: result.setdefault("rank0", rank0.run(_FakeDDPTrainer(0)))))
    assert len(result["rank0"].records) == 6 and len(iopc1.records) == 6


@pytest.mark.parametrize("cfg, match", [
    ({"valid_sigma_dn": ["0", "30"]}, r"valid_sigma_dn = \['0', '30'\] is out of the allowed range: \[low, high\]"),
    ({"valid_length_px": [None, None]}, r"valid_length_px = \[None, None\] is out of the allowed range: \[low, high\]"),
    ({"valid_length_px": [5.0, 1.0]}, r"valid_length_px = \[5.0, 1.0\] is out of the allowed range: .*low <= high"),
    ({"valid_sigma_dn": [0.0, float("nan")]}, r"valid_sigma_dn = \[0.0, nan\] is out of the allowed range"),
    ({"grid": SweepGrid([True], [0.0], [0.0])}, r"grid.lengths_px value True is out of the allowed range \[0, 63\]"),
    ({"grid": SweepGrid([0.0], [0.0], [False])}, r"grid.noise_levels_dn value False is out of the allowed range"),
    ({"quantize": "no"}, r"quantize = 'no' is not allowed: true or false"),
    ({"score_threshold": "0.5"}, r"score_threshold = '0.5' is out of the allowed range \[0, 1\]"),
    ({"iou_threshold": 1.0}, r"iou_threshold = 1.0 is out of the allowed range \(0, 1\)"),
])
def test_validate_refuses_bad_valid_ranges_grid_values_and_flags_naming_the_key(tmp_path, cfg, match):
    """Text valid ranges and boolean grid values passed validate() (text then failed inside the first cell, after the
    detector ran; True was swept as L = 1 px), [None, None] raised a bare TypeError, and quantize = "no" quantised."""
    with pytest.raises(ValueError, match=match):
        SweepConfig(**cfg).validate()


def test_frames_too_small_for_an_estimator_patch_are_refused_before_any_detector_call():
    """160-px frames with the 192-px physics MTF patch failed in the first cell, after the corruption and the
    detector had run."""
    det = NoiseSensitiveDetector(BOXES)
    gt = [{"boxes": torch.tensor(BOXES), "labels": torch.tensor([1])}]
    config = SweepConfig(grid=SweepGrid([0.0], [0.0], [0.0]))
    with pytest.raises(ValueError, match=r"frames of 256×160 px cannot hold one 192-px MTF estimator patch"):
        IOPCSweep(smooth_frames(1, 160, 256), gt, det, "physics", "physics", config)
    with pytest.raises(ValueError, match=r"frames of 128×96 px cannot hold one 128-px noise estimator patch"):
        IOPCSweep(smooth_frames(1, 96, 128), gt, det, FakeNoiseEstimator(128), FakeMTFEstimator(0.8, 48), config)
    assert det.n_calls == 0
    IOPCSweep(smooth_frames(1, 192, 256), gt, det, "physics", "physics", config)  # fits


def test_a_sigterm_stops_the_sweep_before_the_next_cell(tmp_path, capsys):
    """Lightning's SIGTERM handler only notes the signal, and its predict loop went on computing cells until SIGKILL:
    the sweep module now stops before the next cell with exit status 143."""
    from types import SimpleNamespace

    from camhealth.iopc.sweep import IOPCSweepModule

    sw, det = _sweep(tmp_path)
    module = IOPCSweepModule(sw)
    module._trainer = SimpleNamespace(_signal_connector=SimpleNamespace(received_sigterm=True))
    with pytest.raises(SystemExit) as info:
        module.predict_step(sw.cells[0], 3)
    assert info.value.code == 143 and det.n_calls == 0
    assert "terminated (SIGTERM) before cell 3" in capsys.readouterr().err


@pytest.mark.parametrize("kwargs, match", [
    ({"grid": SweepGrid(lengths_px=[0.0, 3.0, 3.0])}, r"grid.lengths_px = \[0.0, 3.0, 3.0\] repeats \[3.0\]"),
    ({"grid": SweepGrid(noise_levels_dn=[0.0, 5.0, 5])}, r"grid.noise_levels_dn = .* repeats \[5.0\]"),
    ({"valid_sigma_dn": [-50.0, -10.0]}, r"valid_sigma_dn = \[-50.0, -10.0\] is out of the allowed range: .* 0 <= low"),
    ({"valid_length_px": [math.inf, math.inf]}, r"valid_length_px = \[inf, inf\] is out of the allowed range"),
    ({"grid": None}, r"grid = None is not allowed"),
    ({"sensor": {"preset": "ICX285"}}, r"sensor = \{'preset': 'ICX285'\} is not allowed"),
    ({"sensor": SensorSetting(preset=None)}, r"sensor preset None is not a name"),
])
def test_a_grid_that_would_double_count_or_mark_every_cell_is_refused_up_front(kwargs, match):
    """Repeated grid values made cells with the same key and seed, computed and counted twice in the bins; a valid
    range no value reaches marked every cell only after the whole sweep."""
    with pytest.raises(ValueError, match=match):
        SweepConfig(**kwargs).validate()
