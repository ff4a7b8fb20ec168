"""Every corruption module documents itself as Kornia's do (Args, Shape, Examples with a replay), and the examples run."""

import doctest
import importlib

import pytest

MODULES = ("camhealth.augment.blur", "camhealth.augment.sensor_noise", "camhealth.augment.camera")
CLASSES = (("camhealth.augment.blur", "RandomDefocusBlur"), ("camhealth.augment.blur", "RandomMotionBlur"),
           ("camhealth.augment.sensor_noise", "RandomSensorNoise"), ("camhealth.augment.camera", "CameraCorruption"))


@pytest.mark.parametrize("module", MODULES)
def test_the_docstring_examples_run(module):
    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0


@pytest.mark.parametrize("module, name", CLASSES)
def test_every_module_has_kornias_docstring_blocks(module, name):
    doc = getattr(importlib.import_module(module), name).__doc__
    for block in ("Args:", "Shape:", "Examples:"):
        assert block in doc, f"{name} lacks a {block} block"
    assert "params=" in doc and ">>>" in doc.split("Examples:")[1]
