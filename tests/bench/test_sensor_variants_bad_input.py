"""simulate_variant on input the model cannot compute: overrides outside where the model is defined, empty images,
a variant name given as a bare string. Each is refused with a message naming the value and its allowed range."""

from __future__ import annotations

import pytest
import torch

from camhealth.bench.sensor_variants import VARIANTS, simulate_variant
from camhealth.physics import CameraMetadata


@pytest.fixture(scope="module")
def meta():
    return CameraMetadata.preset("ICX285", gain_db=12.0, exposure_s=0.05, temperature_c=40.0)


@pytest.mark.parametrize("variants", [(), ("whole_electrons",)])
@pytest.mark.parametrize("field, value, match", [
    ("full_well_e", 0.0, r"override full_well_e = 0 is out of the allowed range \(0, inf\)"),
    ("sense_node_gain_v_per_e", 0.0, r"override sense_node_gain_v_per_e = 0 is out of the allowed range \(0, inf\)"),
    ("pixel_size_um", 0.0, r"override pixel_size_um = 0 is out of the allowed range \(0, inf\)"),
    ("temperature_c", -300.0, r"override temperature_c = -300 is out of the allowed range \(-273\.15, inf\) °C"),
    ("temperature_c", -273.15, r"override temperature_c = -273\.15 is out of the allowed range \(-273\.15, inf\) °C"),
    ("pixel_clock_hz", 0.0, r"override pixel_clock_hz = 0 is out of the allowed range \(0\.001, 2e\+10\] Hz"),
    ("pixel_clock_hz", 1e12, r"override pixel_clock_hz = 1e\+12 is out of the allowed range \(0\.001, 2e\+10\] Hz"),
])
def test_an_override_the_model_is_not_defined_for_is_refused(meta, variants, field, value, match):
    """These gave an all-NaN image with NaN labels (only NumPy's RuntimeWarnings), NumPy's own errors, or a quadrature
    of 1e8 nodes."""
    with pytest.raises(ValueError, match=match):
        simulate_variant(torch.full((1, 1, 8, 8), 0.5), meta, variants, torch.Generator().manual_seed(0), {field: value})


@pytest.mark.parametrize("overrides, match", [
    ({"gain_db": -400.0}, r"gain_db = -400 gives a full scale of 1\.4e\+24 e⁻ .*gain_db must be ≥ -277\.1 dB"),
    ({"gain_db": -300.0}, r"gain_db = -300 gives a full scale of 1\.4e\+19 e⁻ .*gain_db must be ≥ -277\.1 dB"),
    ({"exposure_s": 1e30}, r"the dark signal is [\d.]+e\+31 e⁻ \(temperature_c = 40, exposure_s = 1e\+30"),
])
def test_whole_electrons_refuses_poisson_means_it_cannot_draw(meta, overrides, match):
    """NumPy's "lam value too large" came instead of a message naming the field."""
    with pytest.raises(ValueError, match=r"whole_electrons draws Poisson counts of at most 1e\+18 e⁻, but .*" + match):
        simulate_variant(torch.full((1, 1, 8, 8), 0.5), meta, ("whole_electrons",), torch.Generator().manual_seed(0),
                         overrides)


@pytest.mark.parametrize("shape", [(0, 1, 8, 8), (1, 1, 0, 8), (2, 1, 8, 0)])
def test_an_empty_image_is_refused_naming_its_shape(meta, shape):
    """NumPy's "zero-size array to reduction operation minimum" came instead."""
    shown = ", ".join(str(v) for v in shape)
    with pytest.raises(ValueError, match=rf"clean must hold at least one pixel, got shape \({shown}\)"):
        simulate_variant(torch.zeros(shape), meta)


@pytest.mark.parametrize("name", list(VARIANTS))
def test_a_variant_given_as_a_bare_string_is_refused(meta, name):
    """``variants="round8"`` reported the unknown variants ['r', 'o', 'u', 'n', 'd', '8']."""
    with pytest.raises(TypeError, match=rf"variants = '{name}' must be a sequence of variant names, not a single string"):
        simulate_variant(torch.full((1, 1, 8, 8), 0.5), meta, name)
