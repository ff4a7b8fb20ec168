"""``camhealth.calibrate.pipeline`` on input that broke it: sets sharing a name, 14-bit data in the low bits of 16-bit
files and low-bit codes divided by 65535 in memory, dark sets whose exposure, gain or temperature contradicts the
others (or that were lit), and clipped darks given the wrong advice."""

import re

import numpy as np
import pytest
from PIL import Image

from camhealth.calibrate import FrameSet, Protocol, calibrate, resolve_sets, synthetic_sets
from camhealth.physics import CameraMetadata

SMALL = Protocol(dark_temperatures_c=(40.0, 75.0), dark_exposures_s=(0.1, 0.2), flat_levels=(0.1, 0.3, 0.6), flat_gains_db=(0.0, 12.0))
DATASHEET = ("pixel_size_um", "pixel_clock_hz", "sense_node_gain_v_per_e", "is_cmos")


def _icx(frames=4, size=32, **changes):
    true = CameraMetadata.preset("ICX285")
    sets = synthetic_sets(true, Protocol(**{**SMALL.__dict__, **changes}), frames=frames, size=size, seed=3)
    return sets, {f: float(getattr(true, f)) for f in DATASHEET}


def _like(fs, **changes):
    values = dict(kind=fs.kind, exposure_s=fs.exposure_s, gain_db=fs.gain_db, temperature_c=fs.temperature_c, frames=fs.frames,
                  name=fs.name)
    return FrameSet(**{**values, **changes})


# ------------------------------------------------------------------------------------------- set names
def test_sets_sharing_a_name_are_refused_naming_it():
    """Flats that all share the name 'flat' made the maps and the PRNU come from a flat the fit had left out as
    saturated (the maps matched the fit's flats by name): master flat 254 DN instead of 153, PRNU 0.53 % instead of 0."""
    sets, sheet = _icx(flat_levels=(0.1, 0.3, 0.6, 0.999))
    named = [_like(s, name="flat") if s.kind == "flat" else s for s in sets]
    with pytest.raises(ValueError, match=r"^8 sets are named 'flat' \(set 7: flat, 0\.01 s, 0 dB, 25 °C; .*; …\); every set needs a "
                                         r"name of its own"):
        calibrate(named, camera=sheet)


@pytest.mark.parametrize("how", ["the same path twice", "the same name twice"])
def test_a_manifest_giving_one_set_twice_is_refused_naming_it(how, tmp_path):
    for d in ("a", "b"):
        (tmp_path / d).mkdir()
    second = "{kind: dark, path: a, exposure_s: 0.2}" if how == "the same path twice" else "{kind: dark, path: b, exposure_s: 0.2, name: a}"
    (tmp_path / "m.yaml").write_text("defaults: {gain_db: 0, temperature_c: 25}\nsets:\n  - {kind: bias, path: a, exposure_s: 0.001}\n"
                                     f"  - {second}\n")
    with pytest.raises(ValueError, match=r"^2 sets are named 'a' \(set 1: bias, 0\.001 s, 0 dB, 25 °C \(manifest .*m\.yaml, set 1\); "
                                         r"set 2: dark, 0\.2 s, 0 dB, 25 °C \(manifest .*m\.yaml, set 2\)\)"):
        resolve_sets(tmp_path / "m.yaml")


# ---------------------------------------------------------------------------------------------- low bits
@pytest.mark.parametrize("bits", [13, 14])
def test_14_bit_data_in_the_low_bits_of_16_bit_files_are_refused_unless_the_bit_depth_is_given(bits, tmp_path):
    """14-bit codes in 16-bit PNGs without sBIT (flats up to 10 559 of 65 535, above the 4095 the check looked for) were
    read as value/65535: a full well 4× too large (+301 %) and no warning."""
    sets, sheet = _icx(frames=4, size=24)
    q = 2**bits - 1
    folders = []
    for s in sets:
        d = tmp_path / s.name
        d.mkdir()
        for i, f in enumerate(np.asarray(s.frames)):
            Image.fromarray(np.rint(f * q).astype(np.uint16)).save(d / f"{i:03d}.png")
        folders.append(FrameSet(s.kind, s.exposure_s, s.gain_db, s.temperature_c, paths=[d]))
    with pytest.raises(ValueError, match=r"hold values up to \d+ of 65535 only .*at most 16383 = 1/4 of full scale: these look like "
                                         r"14-bit data stored in the low bits .*a full well 4× too large.*--bit-depth 14"):
        calibrate(folders, camera=sheet)
    res = calibrate(folders, camera=sheet, bit_depth=bits)
    assert abs(res.fields["full_well_e"].value / 14000 - 1) < 0.05


@pytest.mark.parametrize("bits, full_well", [(12, 14000.0), (12, 4000.0), (14, 14000.0)])
def test_low_bit_codes_divided_by_65535_in_memory_are_refused_naming_the_divisor(bits, full_well):
    """12-bit codes / 65535 in memory skipped the check files get: a camera of 4000 e⁻ came out at 64 000 e⁻ (+1506 %),
    one of 14 000 e⁻ was refused with the advice to check the flats' gain."""
    true = CameraMetadata.preset("ICX285").replace(full_well_e=full_well)
    sets = synthetic_sets(true, SMALL, frames=4, size=24, seed=3)
    sheet = {f: float(getattr(true, f)) for f in DATASHEET}
    q = 2**bits - 1
    low = [_like(s, frames=(np.rint(np.asarray(s.frames) * q) / 65535).astype(np.float32)) for s in sets]
    with pytest.raises(ValueError, match=rf"^the in-memory frames of 12 set\(s\) on the 16-bit grid \(k/65535\) hold values up to \d+ "
                                         rf"of 65535 only .*look like {bits}-bit data .*divide the camera's codes by 2\^bits − 1 "
                                         rf"\(x / {q} for {bits}-bit data\), not by 65535, or give their sets bit_depth=16"):
        calibrate(low, camera=sheet)
    right = [_like(s, frames=(np.rint(np.asarray(s.frames) * q) / q).astype(np.float32)) for s in sets]
    assert abs(calibrate(right, camera=sheet).fields["full_well_e"].value / full_well - 1) < 0.05
    if bits == 14:  # 16-bit data (k/65535) reaching the flats' levels are not taken for low-bit codes
        full = [_like(s, frames=(np.rint(np.asarray(s.frames) * 65535) / 65535).astype(np.float32)) for s in sets]
        assert abs(calibrate(full, camera=sheet).fields["full_well_e"].value / full_well - 1) < 0.05


# -------------------------------------------------------------------------------- contradictory darks
def _contradicting(case, sets):
    if case == "a lit set given as dark":
        lit = next(s for s in sets if s.kind == "flat" and s.gain_db == 12)
        return [_like(lit, kind="dark", exposure_s=0.2, temperature_c=40.0, name="odd") if s.name == "dark_200ms_12dB_40C" else s
                for s in sets], r"'odd' sits [\d.]+ DN above the level of 'bias_1ms_12dB_40C'"
    if case == "a dark's gain given as 0 dB":
        return [_like(s, gain_db=0.0, name="odd") if s.name == "dark_200ms_12dB_75C" else s for s in sets], ""
    return [_like(s, temperature_c=40.0, name="odd") if s.name == "dark_200ms_12dB_75C" else s for s in sets], ""


@pytest.mark.parametrize("case", ["a lit set given as dark", "a dark's gain given as 0 dB", "a dark's temperature given as 40 °C"])
def test_darks_that_contradict_each_other_are_warned_about_naming_the_set(case):
    """χ²/dof of the dark law of 156 … 795 passed without a word (dark current +11 … +38 %); the only warning, "longer
    or warmer darks measure it better", gave the wrong cause. The same sets without the contradiction fit well."""
    sets, sheet = _icx()
    res = calibrate(sets, camera=sheet)
    assert res.fits["dark"]["chi2_dof"] < 5 and not any(w.startswith("the dark fit") for w in res.warnings)
    odd, lit = _contradicting(case, sets)
    res = calibrate(odd, camera=sheet)
    poor = [w for w in res.warnings if w.startswith("the dark fit is poor")]
    assert len(poor) == 1, res.warnings
    assert re.search(r"χ²/dof = [\d.]+ \(above 5;.*largest normalised residuals: [^—]*'odd' [+-][\d.]+.* — check these sets' "
                     r"exposure_s, gain_db and temperature_c", poor[0]), poor[0]
    assert re.search(lit, poor[0]) if lit else "DN above the level" not in poor[0]
    assert res.fits["dark"]["chi2_dof"] > 5
    assert not any("longer or warmer" in w for w in res.warnings)



# ------------------------------------------------------------------------------------------ clipped darks
@pytest.mark.parametrize("where, advice", [
    ("0 DN", r"its noise is below one code at 0 DN: record it at a higher gain or bit depth, or with a camera offset"),
    ("the top code", r"it sits at the top code: record it at a lower gain"),
])
def test_a_clipped_dark_set_gets_the_advice_that_fits_where_it_is_clipped(where, advice):
    """An 8-bit dark at 0 dB (σ ≈ 0.23 DN, 98.6 % of its values at 0 DN) was told to use a lower gain, which makes it
    worse."""
    sets, sheet = _icx(dark_gain_db=0.0)
    if where == "0 DN":
        changed = [_like(s, frames=(np.rint(np.asarray(s.frames) * 255) / 255).astype(np.float32)) for s in sets]
    else:
        changed = [_like(s, frames=np.ones_like(np.asarray(s.frames))) if s.name.startswith("bias") else s for s in sets]
    with pytest.raises(ValueError, match=rf"^bias set 'bias_1ms_0dB_40C' .* is clipped: [\d.]+ % of its values at 0 DN and [\d.]+ % at "
                                         rf"[\d.]+ DN leave nothing to fit; {advice}"):
        calibrate(changed, camera=sheet)
