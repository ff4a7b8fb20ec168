"""Controllers: auto-exposure prefers exposure over gain; the IOPC controller applies the policy."""

import pytest
import torch

from camhealth.control import (
    AutoExposureController,
    CameraLimits,
    ExposurePolicy,
    FixedController,
    IOPCController,
    Observation,
    SimulatedCamera,
)
from camhealth.detection import Detection
from tests.control.test_policy import BLUR_HATER, FAST
from tests.iopc.fakes import smooth_frames


def _obs(cam, t, g, frame=0, boxes=((10.0, 10.0, 60.0, 50.0),)):
    cap = cam.capture(frame, t, g)
    det = Detection(boxes=torch.tensor(boxes), scores=torch.full((len(boxes),), 0.9),
                    labels=torch.ones(len(boxes), dtype=torch.long))
    return Observation(frame, cap[0], det, t, g)


def test_auto_exposure_uses_exposure_first_then_gain():
    limits = CameraLimits((0.001, 0.02), (0.0, 24.0))
    ae = AutoExposureController(0.5, limits, damping=1.0)
    cam = SimulatedCamera(smooth_frames(1, 64, 64), illumination_per_s=10.0, motion_px_per_s=0.0, sources=())
    t, g = ae.reset(0.005, 0.0)
    trace = []
    for _ in range(8):
        t, g = ae.update(_obs(cam, t, g))
        trace.append((t, g))
    # dark scene (mean ≈ 0.025 at 5 ms): exposure rises to its 20 ms limit before any gain is used
    assert trace[0][1] == 0.0 and trace[0][0] > 0.005
    assert all(g == 0.0 for t, g in trace if t < 0.02 - 1e-9)
    assert trace[-1][0] == pytest.approx(0.02) and trace[-1][1] > 0
    assert cam.capture(0, *trace[-1]).mean_intensity.item() == pytest.approx(0.5, rel=0.1)
    # too bright: gain goes first
    t, g = ae.allocate(0.02 * 10 ** (12 / 20) / 2)  # half the light at 20 ms, 12 dB
    assert t == pytest.approx(0.02) and g == pytest.approx(12 - 20 * torch.log10(torch.tensor(2.0)).item(), abs=1e-5)
    assert ae.allocate(0.005) == (pytest.approx(0.005), 0.0)


def test_fixed_controller():
    c = FixedController(0.008, 3.0)
    assert c.reset() == (0.008, 3.0)
    cam = SimulatedCamera(smooth_frames(1, 64, 64), sources=())
    assert c.update(_obs(cam, 0.008, 3.0)) == (0.008, 3.0)


@pytest.mark.parametrize("decide_every, n_decisions", [(None, 1), (2, 2)])
def test_iopc_controller_shortens_exposure_against_blur(decide_every, n_decisions):
    frames = smooth_frames(2, 192, 192)
    cam = SimulatedCamera(frames, illumination_per_s=60.0, motion_px_per_s=1200.0, temperature_c=25.0)
    ctrl = IOPCController(ExposurePolicy(BLUR_HATER, **FAST), "physics", "physics", decide_every=decide_every)
    t, g = ctrl.reset(0.01, 0.0)
    for k in range(3):
        t, g = ctrl.update(_obs(cam, t, g, frame=k % 2))
    assert len(ctrl.decisions) == n_decisions
    frame, d, med = ctrl.decisions[0]
    assert frame == 0 and med["n_regions"] == 1
    assert med["mtf_tilde"] == pytest.approx(0.5 * (1 + abs(float(torch.sinc(torch.tensor(0.6))))), abs=0.03)
    assert d.alpha > 1 and t < 0.01 and g > 0
    assert t * 10 ** (g / 20) == pytest.approx(0.01, rel=1e-6)  # intensity kept


def test_controllers_refuse_nan_instead_of_passing_it_on():
    """NaN settings or a NaN mean intensity came back as (nan, nan), and the camera refused them a frame later."""
    with pytest.raises(ValueError, match="must be a finite number > 0"):
        FixedController(float("nan"), 0.0)
    with pytest.raises(ValueError, match="gain_db = .* finite"):
        FixedController(0.01, float("inf"))
    ae = AutoExposureController()
    with pytest.raises(ValueError, match="must be finite numbers to clamp"):
        ae.reset(float("nan"), float("nan"))
    cam = SimulatedCamera(smooth_frames(1, 64, 64), illumination_per_s=10.0, motion_px_per_s=0.0, sources=())
    obs = _obs(cam, 0.005, 0.0)
    obs.capture.mean_intensity[:] = float("nan")
    with pytest.raises(ValueError, match="mean intensity nan, .* must be finite"):
        ae.update(obs)


def _dark_first_run(decide_every, n_frames=4):
    """The IOPC controller over ``n_frames`` frames whose first is black (lens cap, tunnel, start-up frame): Immerkær
    refuses tiles with more than 5 % of the pixels at 0 DN, so nothing is assessable on it."""
    from camhealth.iopc import ImmerkaerNoiseEstimator

    cam = SimulatedCamera(smooth_frames(2, 192, 192), illumination_per_s=60.0, motion_px_per_s=1200.0, temperature_c=25.0)
    ctrl = IOPCController(ExposurePolicy(BLUR_HATER, **FAST), ImmerkaerNoiseEstimator(), "physics",
                          decide_every=decide_every)
    t, g = ctrl.reset(0.01, 0.0)
    trace = []
    for k in range(n_frames):
        obs = _obs(cam, t, g, frame=k % 2)
        obs = Observation(k, obs.capture, obs.detections, t, g)
        if k == 0:
            obs.capture.image.zero_()
            obs.capture.mean_intensity.zero_()
        t, g = ctrl.update(obs)
        trace.append((t, g))
    return ctrl, trace


def test_iopc_controller_decides_on_the_first_assessable_frame():
    """decide_every=None (the demo's default) used its single decision on frame 0 even when nothing could be
    assessed there, and then kept 10 ms / 0 dB for good."""
    ctrl, trace = _dark_first_run(None)
    assert trace[0] == (0.01, 0.0)  # black frame: kept
    assert [f for f, _, _ in ctrl.decisions] == [1]  # then the first assessable frame, once
    assert trace[1][0] < 0.01 and trace[-1] == trace[1]


def test_iopc_controller_with_a_cadence_waits_for_the_next_due_frame():
    """decide_every=n keeps its cadence: the black frame 0 is skipped, the next decision is on frame n."""
    ctrl, trace = _dark_first_run(2, n_frames=5)
    assert [f for f, _, _ in ctrl.decisions] == [2, 4]
    assert trace[0] == trace[1] == (0.01, 0.0) and trace[2][0] < 0.01


@pytest.mark.parametrize("noise, mtf", [("immerkaer", "physics"), ("physics", "Physics"), (" IMMERKAER ", "physics")])
def test_iopc_controller_resolves_estimator_specs_when_built(noise, mtf):
    """The specs resolve_estimator documents ("immerkaer", "Physics") were stored as strings and failed on the first
    frame: 'str' object has no attribute 'patch_size'."""
    from camhealth.iopc import PHYSICS, ImmerkaerNoiseEstimator

    ctrl = IOPCController(ExposurePolicy(BLUR_HATER, **FAST), noise, mtf)
    assert isinstance(ctrl.noise, ImmerkaerNoiseEstimator) or ctrl.noise == PHYSICS
    assert ctrl.mtf == PHYSICS
    cam = SimulatedCamera(smooth_frames(1, 192, 192), illumination_per_s=60.0, motion_px_per_s=1200.0, temperature_c=25.0)
    t, g = ctrl.update(_obs(cam, 0.01, 0.0))
    assert len(ctrl.decisions) == 1 and t < 0.01
    with pytest.raises(ValueError, match="'immerkaer' is a noise estimator"):
        IOPCController(ExposurePolicy(BLUR_HATER, **FAST), "physics", "immerkaer")


@pytest.mark.parametrize("value, used", [(-0.01, 0.0), (1.02, 1.0)])
def test_iopc_controller_clips_the_mtf_estimate_to_0_1(value, used):
    """An MTF̂ of 1.02 is clipped to 1; -0.01 (a regression undershoot under heavy blur) clipped to 0 lies beyond the
    blur the IOPC measured, so the loop goes on with the parameters kept (it used to stop: mtf_hat must lie in [0, 1])."""
    from tests.iopc.fakes import FakeMTFEstimator

    ctrl = IOPCController(ExposurePolicy(BLUR_HATER, **FAST), "physics", FakeMTFEstimator(value, 48))
    cam = SimulatedCamera(smooth_frames(1, 192, 192), illumination_per_s=60.0, motion_px_per_s=1200.0, temperature_c=25.0)
    t, g = ctrl.update(_obs(cam, 0.01, 0.0))
    if used == 0.0:  # blurrier than the IOPC's MTF → length relation reaches: no prediction, the parameters kept
        assert ctrl.decisions == [] and (t, g) == (0.01, 0.0)
        (_, why), = ctrl.refusals
        assert "blurrier than the MTF → motion-length relation" in why and "parameters kept" in why
        return
    (_, d, med), = ctrl.decisions
    assert med["mtf_tilde"] == pytest.approx(value) and d.details["mtf_hat"] == used


@pytest.mark.parametrize("illumination", [1e5, 1e-4])
def test_a_clipped_frame_keeps_the_parameters_with_the_simulators_labels(illumination):
    """The simulator's labels read σ̂ and MTF̂ off a saturated or black frame as if it were readable: the controller
    raised the gain on them (1 ms / 18 dB on a saturated frame). More than half clipped: kept, and said why."""
    from camhealth.control.controllers import MAX_CLIPPED_FRACTION

    ctrl = IOPCController(ExposurePolicy(BLUR_HATER, **FAST))
    cam = SimulatedCamera(smooth_frames(1, 192, 192), illumination_per_s=illumination, motion_px_per_s=1200.0,
                          temperature_c=25.0)
    obs = _obs(cam, 0.01, 0.0)
    assert float(obs.capture.clipped_fraction[0]) > MAX_CLIPPED_FRACTION
    assert ctrl.update(obs) == (0.01, 0.0) and ctrl.decisions == []
    (_, why), = ctrl.refusals
    assert "of the frame's pixels are clipped" in why


@pytest.mark.parametrize("kwargs, match", [
    ({"score_threshold": float("nan")}, r"score_threshold = nan is out of the allowed range: a number in \[0, 1\]"),
    ({"score_threshold": 5.0}, r"score_threshold = 5.0 is out of the allowed range"),
    ({"score_threshold": "0.5"}, r"score_threshold = '0.5' is out of the allowed range"),
    ({"use_sources": "no"}, r"use_sources = 'no' must be True or False"),
    ({"reference_intensity": True}, r"reference_intensity = True must be a number in \(0, 1\]"),
    ({"decide_every": float("nan")}, r"decide_every = nan must be a positive integer"),
    ({"decide_every": float("inf")}, r"decide_every = inf must be a positive integer"),
    ({"decide_every": True}, r"decide_every = True must be a positive integer"),
])
def test_iopc_controller_refuses_what_would_silently_change_its_estimates(kwargs, match):
    """A NaN or 5.0 score threshold kept no detection, and the estimates fell back to the whole frame unsaid."""
    pol = ExposurePolicy(BLUR_HATER, **FAST)
    with pytest.raises(ValueError, match=match):
        IOPCController(pol, **kwargs)
    with pytest.raises(TypeError, match="policy must be an ExposurePolicy, got NoneType"):
        IOPCController(None)
