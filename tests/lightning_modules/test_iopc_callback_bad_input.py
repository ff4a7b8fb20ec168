"""IOPCCallback checks its arguments when it is built, before any training step, each error naming the argument."""

from __future__ import annotations

import pytest
import torch

from lightning_modules.iopc_callback import IOPCCallback


@pytest.mark.parametrize("kwargs, error, match", [
    ({"detector": "yolo"}, ValueError, r"detector = 'yolo': give 'hog'"),
    ({"detector": 42}, TypeError, r"detector = 42: give 'hog', a callable detector object or an nn\.Module, got int"),
    ({"noise_estimator": "bogus"}, FileNotFoundError, r"noise_estimator = 'bogus' is neither a shipped estimator"),
    ({"mtf_estimator": "no/such/file.pt"}, FileNotFoundError, r"mtf_estimator = 'no/such/file\.pt' is neither a shipped"),
    ({"mtf_estimator": "immerkaer"}, ValueError, r"mtf_estimator = 'immerkaer': 'immerkaer' is a noise estimator"),
    ({"pseudo_score": 5.0}, ValueError, r"pseudo_score = 5\.0 must lie in \[0, 1\]"),
    ({"pseudo_score": float("nan")}, ValueError, r"pseudo_score = nan must lie in \[0, 1\]"),
    ({"frame_slice": (0, 25, 0)}, ValueError, r"frame_slice = \(0, 25, 0\) must be \(start, stop, stride\): integers"),
    ({"frame_slice": (0, 2.5, 1)}, ValueError, r"frame_slice = \(0, 2\.5, 1\) must be \(start, stop, stride\)"),
    ({"source": "no_such_source"}, FileNotFoundError, r"source = 'no_such_source': image source 'no_such_source' is neither"),
    ({"frames": torch.rand(2, 64, 64)}, ValueError, r"frames must have shape B×C×H×W \(4 dims\), got \(2, 64, 64\)"),
    ({"frames": torch.rand(2, 1, 64, 64) * 300}, ValueError, r"frames must lie in \[0, 1\] \(DN/255\)"),
    ({"every_n_epochs": float("nan")}, ValueError, r"every_n_epochs = nan must be a positive integer or None"),
])  # fmt: skip
def test_bad_arguments_are_refused_when_the_callback_is_built(kwargs, error, match):
    """Each of these was accepted, and failed only at on_fit_end, after the whole training."""
    with pytest.raises(error, match=match):
        IOPCCallback(**kwargs)


def test_estimator_files_are_checked_by_their_existence_only(tmp_path):
    """An estimator file is loaded at the sweep: when the callback is built it must exist, and nothing is read yet."""
    path = tmp_path / "mine.pt"
    path.write_bytes(b"")  # not a weights file: that is found when the sweep loads it
    cb = IOPCCallback(detector=torch.nn.Identity(), noise_estimator="physics", mtf_estimator=str(path), pseudo_score=1,
                      frame_slice=(0, None, 2), frames=torch.rand(2, 1, 32, 32))
    assert cb.frame_slice == (0, None, 2) and cb.pseudo_score == 1.0
    assert IOPCCallback(noise_estimator="immerkaer", mtf_estimator="mtf").source == "street"
    with pytest.raises(FileNotFoundError, match=rf"noise_estimator = '{tmp_path / 'gone.pt'}' is neither a shipped"):
        IOPCCallback(noise_estimator=str(tmp_path / "gone.pt"))
