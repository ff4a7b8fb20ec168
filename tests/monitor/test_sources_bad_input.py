"""open_source / the CLI's SOURCE on bad input: an empty SOURCE (an unset shell variable) is refused instead of
monitoring the current folder, a SOURCE that is no path is a TypeError naming it, and the files of a folder that are
no frame images (pickles, .pt, .npy) are never read."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest

from camhealth.monitor.sources import open_source
from tests.monitor.conftest import run_monitor_cli


class _Payload:
    """Unpickling it would create the file ``path``."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


@pytest.fixture
def frames_in_cwd(tmp_path, monkeypatch):
    import cv2

    cv2.imwrite(str(tmp_path / "a.png"), np.random.default_rng(0).integers(0, 256, (256, 256), dtype=np.uint8))
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_an_empty_source_is_refused_not_read_as_the_current_folder(frames_in_cwd, capsys):
    """open_source("") was Path("") = ".": the CLI given an empty SOURCE monitored the frames of the current folder."""
    with pytest.raises(ValueError, match=r"source is empty: give an image, a folder of frames, a video file, a recording"):
        open_source("")
    code, out, err = run_monitor_cli(["", "--sensor", "ICX285", "--no-progress", "--threads", "1"], capsys)
    assert code == 2 and out == "" and "error: source is empty" in err, err
    assert open_source(".").kind == "folder" and open_source(".").length == 1  # "." still names the folder


@pytest.mark.parametrize("source", [None, 3, b"a.png", ["a.png"]])
def test_a_source_that_is_no_path_is_a_type_error_naming_it(source):
    """open_source(None) failed in pathlib: "expected str, bytes or os.PathLike object, not NoneType"."""
    with pytest.raises(TypeError, match=rf"source = {source!r} must be a path .* or 'street', got {type(source).__name__}"
                       .replace("[", r"\[").replace("]", r"\]")):
        open_source(source)


def test_pickles_in_a_frame_folder_are_never_read(tmp_path, capsys):
    """A folder of frames holding .pt/.npy/.pkl files and a pickle named like a frame: the pickles are never unpickled
    (no code from them runs); the one named .png is an unreadable frame, the others are not frames at all."""
    import cv2

    hit = tmp_path / "unpickled"
    payload = pickle.dumps(_Payload(hit))
    folder = tmp_path / "frames"
    folder.mkdir()
    for name in ("model.pt", "weights.pth", "frame.npy", "state.pkl", "b.png"):
        (folder / name).write_bytes(payload)
    cv2.imwrite(str(folder / "a.png"), np.random.default_rng(0).integers(0, 256, (256, 256), dtype=np.uint8))
    src = open_source(folder)
    assert src.length == 2  # a.png and b.png: only image names are frames
    items = list(src)
    assert items[0].error is None and items[1].error is not None and "b.png" in items[1].error
    code, out, err = run_monitor_cli([str(folder), "--sensor", "ICX285", "--no-progress", "--threads", "1"], capsys)
    assert code == 0, err
    assert not hit.exists() and sorted(os.listdir(folder)) == sorted(
        ["a.png", "b.png", "model.pt", "weights.pth", "frame.npy", "state.pkl"])
