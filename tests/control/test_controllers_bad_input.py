"""Controllers refuse settings that are not numbers, lie outside the camera limits, or contradict the capture."""

import re

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


def _det():
    return Detection(boxes=torch.tensor([[10.0, 10.0, 100.0, 100.0]]), scores=torch.tensor([0.9]),
                     labels=torch.ones(1, dtype=torch.long))


@pytest.fixture(scope="module")
def camera():
    return SimulatedCamera(smooth_frames(1, 192, 192), illumination_per_s=60.0, motion_px_per_s=1200.0,
                           temperature_c=25.0)


@pytest.mark.parametrize("args, match", [
    ((0.01, 100.0), r"gain_db = 100.0 dB is out of the allowed range \[0, 24\] dB"),
    ((1e9,), r"exposure_s = 1000000000.0 s is out of the allowed range \[0.001, 0.2\] s"),
    ((0.0005, 0.0), r"exposure_s = 0.0005 s is out of the allowed range \[0.001, 0.2\] s"),
    (("0.01", 0.0), r"exposure_s = '0.01' is not allowed: a number \[s\]"),
    ((0.01, True), r"gain_db = True is not allowed: a number \[dB\]"),
])
def test_fixed_controller_refuses_what_the_camera_cannot_take(args, match):
    """FixedController(0.01, 100.0) and FixedController(1e9) were accepted; ("0.01", True) became (0.01 s, 1 dB)."""
    with pytest.raises(ValueError, match=match):
        FixedController(*args)


def test_fixed_controller_checks_its_own_limits():
    limits = CameraLimits((0.005, 0.05), (0.0, 6.0))
    assert FixedController(0.01, 3.0, limits=limits).reset() == (0.01, 3.0)
    with pytest.raises(ValueError, match=r"gain_db = 12.0 dB is out of the allowed range \[0, 6\] dB"):
        FixedController(0.01, 12.0, limits=limits)


@pytest.mark.parametrize("kwargs, error, match", [
    ({"target_mean": "0.5"}, ValueError, r"target_mean = '0.5' is not allowed: a number"),
    ({"damping": True}, ValueError, r"damping = True is not allowed: a number"),
    ({"max_step": None}, ValueError, r"max_step = None is not allowed: a number"),
    ({"limits": ((0.001, 0.2), (0, 24))}, TypeError, r"limits must be a CameraLimits, got tuple"),
])
def test_auto_exposure_refuses_settings_that_are_not_numbers(kwargs, error, match):
    """target_mean="0.5" failed with "'<' not supported between instances of 'int' and 'str'"; a tuple as limits was
    accepted and allocate failed with "'tuple' object has no attribute 'exposure_s'"."""
    with pytest.raises(error, match=match):
        AutoExposureController(**kwargs)


@pytest.mark.parametrize("total", [float("nan"), float("inf"), -1.0, 0.0])
def test_auto_exposure_allocate_refuses_a_total_that_is_not_a_positive_number(total):
    """allocate(nan) returned (nan, nan)."""
    with pytest.raises(ValueError, match=re.escape(f"total exposure = {total!r} s is out of the allowed range")):
        AutoExposureController().allocate(total)


@pytest.mark.parametrize("told, match", [
    ((0.2, 0.0), r"observation exposure_s = 0.2 s contradicts the capture's exposure 0.0199999"),
    ((0.02, 6.0), r"observation gain_db = 6.0 dB contradicts the capture's gain 0 dB"),
])
def test_iopc_controller_refuses_parameters_that_contradict_the_capture(camera, told, match):
    """An observation saying 0.2 s for a capture taken at 0.02 s gave a decision computed from 0.2 s."""
    ctrl = IOPCController(ExposurePolicy(BLUR_HATER, **FAST))
    ctrl.reset(0.02, 0.0)
    cap = camera.capture(0, 0.02, 0.0)
    with pytest.raises(ValueError, match=match):
        ctrl.update(Observation(0, cap, _det(), *told))
    assert ctrl.decisions == []


@pytest.mark.parametrize("batch", [2, 3])
def test_iopc_controller_needs_a_capture_of_one_frame(camera, batch):
    """A capture of batch 2 failed with "1 region lists for 2 images", which did not say what is needed."""
    ctrl = IOPCController(ExposurePolicy(BLUR_HATER, **FAST))
    ctrl.reset(0.02, 0.0)
    cap = camera.capture([0] * batch, 0.02, 0.0)
    with pytest.raises(ValueError, match=rf"capture must be a batch of one .* got a batch of {batch}"):
        ctrl.update(Observation(0, cap, _det(), 0.02, 0.0))
