"""ImageFolderSource / list_images: links that cannot be resolved (they lead back to themselves) are named, not lost."""

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


@pytest.mark.parametrize("loop", ["self", "pair", "folder"])
def test_a_link_that_leads_back_to_itself_is_named_as_broken(tmp_path, loop):
    """``self.png -> self.png`` (ELOOP when followed) is a link to nothing: skipped and named in the warning, as a link
    to a missing file is, instead of vanishing from the listing without a word."""
    root = tmp_path / "root"
    root.mkdir()
    Image.fromarray(np.full((4, 5), 9, np.uint8)).save(root / "real.png")
    if loop == "self":
        names = ["self.png"]
        _symlink(root / "self.png", root / "self.png")
    elif loop == "pair":
        names = ["a.png", "b.png"]
        _symlink(root / "b.png", root / "a.png")
        _symlink(root / "a.png", root / "b.png")
    else:  # a link without an extension, as a link to a folder is
        names = ["frames"]
        _symlink(root / "frames", root / "frames")
    with pytest.warns(UserWarning) as caught:
        src = ImageFolderSource(root)
    assert src.ids == ["real.png"]
    (message,) = [str(w.message) for w in caught]
    assert f"skipped {len(names)} broken link(s): {', '.join(names)}" in message, message
    with pytest.warns(UserWarning, match=f"broken link\\(s\\): {', '.join(names)}"):
        assert [p.name for p in list_images(root)] == ["real.png"]
