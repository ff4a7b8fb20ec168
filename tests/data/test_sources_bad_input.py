"""build_source / DefaultSource option values: a factor or a supersample that is not a whole number is refused,
naming the option, the value and the allowed range."""

from __future__ import annotations

import pytest

from camhealth.data import DefaultSource, build_source


@pytest.mark.parametrize("spec", ["street", "skimage", "deadleaves"])
@pytest.mark.parametrize("factor, shown", [(True, "True"), (1.0, "1.0"), (2.5, "2.5"), ("2", "'2'")])
def test_build_source_refuses_an_area_downsample_that_is_not_an_integer(spec, factor, shown):
    """``area_downsample=True`` built the source at full resolution without a word (``True != 1`` is False), and 1.0
    likewise; 2.5 failed with another option's name."""
    with pytest.raises(TypeError, match=rf"area_downsample = {shown} must be an integer in \[1, 8\]"):
        build_source(spec, area_downsample=factor)


@pytest.mark.parametrize("factor", [0, 9, -1])
def test_build_source_names_an_area_downsample_out_of_range(factor):
    with pytest.raises(ValueError, match=rf"area_downsample = {factor} is out of the allowed range \[1, 8\]"):
        build_source("street", area_downsample=factor)


@pytest.mark.parametrize("supersample, shown", [("x", "'x'"), (2.5, "2.5"), (True, "True"), (None, "None")])
def test_default_source_names_a_supersample_that_is_not_an_integer(supersample, shown):
    """``DefaultSource(deadleaves=2, deadleaves_antialiased=1, supersample="x")`` failed with int()'s "invalid literal";
    2.5 was read as 2."""
    with pytest.raises(TypeError, match=rf"supersample = {shown} must be an integer in \[1, 8\]"):
        DefaultSource(deadleaves=2, deadleaves_antialiased=1, supersample=supersample)
