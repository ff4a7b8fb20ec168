"""ImageFolderSource / list_images: links that cannot be resolved (they lead back to themselves or to nothing), FIFOs
and folders named as frames are named, not lost."""

from __future__ import annotations

import os

import numpy as np
import pytest
from PIL import Image

from camhealth.data import ImageFolderSource, list_images


def _symlink(target, link) -> None:
    try:
        os.symlink(target, link)
    except (OSError, NotImplementedError):
        pytest.skip("this file system does not take symbolic links")


@pytest.mark.parametrize("loop", ["self", "pair"])
def test_a_link_named_as_an_image_that_leads_back_to_itself_is_listed_and_reading_it_says_so(tmp_path, loop):
    """``self.png -> self.png`` (ELOOP when followed) is a link to nothing: listed where its name says it is a frame,
    named in the warning, and reading it says it loops, instead of vanishing from the listing."""
    root = tmp_path / "root"
    root.mkdir()
    Image.fromarray(np.full((4, 5), 9, np.uint8)).save(root / "real.png")
    if loop == "self":
        names = ["self.png"]
        _symlink(root / "self.png", root / "self.png")
    else:
        names = ["a.png", "b.png"]
        _symlink(root / "b.png", root / "a.png")
        _symlink(root / "a.png", root / "b.png")
    with pytest.warns(UserWarning) as caught:
        src = ImageFolderSource(root)
    assert src.ids == sorted([*names, "real.png"])
    (message,) = [str(w.message) for w in caught]
    assert ", ".join(f"{n} (a broken symbolic link)" for n in names) in message, message
    assert "broken link(s)" not in message
    with pytest.raises(FileNotFoundError, match=rf"{names[0]}: broken symbolic link \(it leads back to itself"):
        src[src.ids.index(names[0])]
    with pytest.warns(UserWarning, match=f"{names[0]} \\(a broken symbolic link\\)"):
        assert [p.name for p in list_images(root)] == sorted([*names, "real.png"])


def test_a_link_without_an_extension_that_leads_back_to_itself_is_skipped_and_named_as_broken(tmp_path):
    """``frames -> frames``, named as a link to a folder is, is no frame: skipped and named in the warning."""
    root = tmp_path / "root"
    root.mkdir()
    Image.fromarray(np.full((4, 5), 9, np.uint8)).save(root / "real.png")
    _symlink(root / "frames", root / "frames")
    with pytest.warns(UserWarning) as caught:
        src = ImageFolderSource(root)
    assert src.ids == ["real.png"]
    (message,) = [str(w.message) for w in caught]
    assert "skipped 1 broken link(s): frames" in message, message
    with pytest.warns(UserWarning, match=r"broken link\(s\): frames"):
        assert [p.name for p in list_images(root)] == ["real.png"]


# ------------------------------------------------------------------ entries named as frames that are no regular file
def _frames(folder, n=4):
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(1, n + 1):
        Image.fromarray(np.full((8, 8), 20 * i, np.uint8)).save(folder / f"frame_{i:04d}.png")


def _unblock_readers(path):
    """Opens ``path`` (a FIFO) for writing for a while, so that code that opens it for reading fails the test instead
    of hanging it."""
    import threading
    import time

    def run():
        for _ in range(250):
            try:
                os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))  # ENXIO while no reader waits
            except OSError:
                pass
            time.sleep(0.02)

    threading.Thread(target=run, daemon=True).start()


def test_a_dangling_frame_link_is_listed_in_its_place_and_reading_it_names_it(tmp_path):
    """``frame_0003.png`` whose target is gone dropped out of the sequence (frame 4 became the third): it is listed
    in its place and reading it raises FileNotFoundError naming the path, the broken link and where it leads."""
    from camhealth.data import FrameSequence

    d = tmp_path / "seq"
    _frames(d)
    (d / "frame_0003.png").unlink()
    _symlink(tmp_path / "gone" / "frame_0003.png", d / "frame_0003.png")
    with pytest.warns(UserWarning, match=r"listed 1 entry named as an image that is not a regular file \(reading it "
                                         r"fails\): frame_0003\.png \(a broken symbolic link\)"):
        names = [p.name for p in list_images(d, recursive=False)]
    assert names == ["frame_0001.png", "frame_0002.png", "frame_0003.png", "frame_0004.png"]
    with pytest.warns(UserWarning, match="frame_0003"):
        src = ImageFolderSource(d)
    assert src.ids[2] == "frame_0003.png" and src[3][0][0, 0, 0].item() == pytest.approx(80 / 255)
    with pytest.raises(FileNotFoundError, match=r"frame_0003\.png: broken symbolic link \(it leads to .*gone"):
        src[2]
    with pytest.warns(UserWarning, match="frame_0003"):
        assert FrameSequence(d).total_frames == 4


@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_a_fifo_or_a_folder_named_as_a_frame_is_listed_and_reading_it_names_it(tmp_path, kind):
    """A FIFO or (not recursive) a folder called ``frame_0003.png`` vanished from the listing without a word: it is
    listed, named in the warning, and reading it says what it is — a FIFO is never opened (no read blocks)."""
    d = tmp_path / "seq"
    _frames(d)
    target = d / "frame_0003.png"
    target.unlink()
    if kind == "fifo":
        if not hasattr(os, "mkfifo"):
            pytest.skip("no FIFOs on this platform")
        os.mkfifo(target)
        _unblock_readers(target)
        what, error = "not a regular file: a FIFO, socket or device", "not a regular file"
    else:
        target.mkdir()
        what, error = "a folder", "it is a directory, not an image file"
    with pytest.warns(UserWarning, match=rf"frame_0003\.png \({what}\)"):
        src = ImageFolderSource(d, recursive=False)
    assert src.ids == ["frame_0001.png", "frame_0002.png", "frame_0003.png", "frame_0004.png"]
    with pytest.raises(ValueError, match=rf"frame_0003\.png: {error}"):
        src[2]
    if kind == "folder":  # recursive: a folder is a folder to look in, whatever its name
        assert ImageFolderSource(d).ids == ["frame_0001.png", "frame_0002.png", "frame_0004.png"]


def test_a_sequence_reports_a_dangling_frame_link_and_a_fifo_as_unreadable_frames_in_their_place(tmp_path):
    """The monitor's folder source reads the entries in their place and reports each as a frame that cannot be read,
    naming the path and why; the other frames keep their indices."""
    from camhealth.monitor.sources import open_source

    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this platform")
    d = tmp_path / "seq"
    _frames(d, 5)
    (d / "frame_0002.png").unlink()
    _symlink(tmp_path / "gone.png", d / "frame_0002.png")
    (d / "frame_0004.png").unlink()
    os.mkfifo(d / "frame_0004.png")
    _unblock_readers(d / "frame_0004.png")
    with pytest.warns(UserWarning, match="listed 2 entries named as images that are not regular files"):
        items = list(open_source(str(d), 0, 1, None))
    assert [(i.index, os.path.basename(i.source_id)) for i in items] == [
        (k, f"frame_{k + 1:04d}.png") for k in range(5)]
    assert [i.error is None for i in items] == [True, False, True, False, True]
    assert "frame_0002.png: broken symbolic link (it leads to " in items[1].error
    assert "frame_0004.png: not a regular file" in items[3].error
