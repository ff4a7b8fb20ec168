"""The physics-first noise estimator where it used to mislead or crash: a camera whose fixed SensorConstants are not
the defaults, extra noise the scene allowance hides on a quiet camera, and the public checks and settings it exposes
(the quiet-patch test, the patch size, the static pair's pool flag)."""

from pathlib import Path

import pytest
import torch

from camhealth.estimators.noise_features import physics_prior_dn
from camhealth.estimators.physics_noise import (
    PHYSICS_NOISE_COLUMNS, PhysicsNoiseEstimator, physics_noise_posterior, quieter_than_any_camera,
)
from camhealth.estimators.static_pair import pair_stillness, scene_leak
from camhealth.physics.image_formation import form_image
from camhealth.physics.metadata import FULL_FIELDS, CameraMetadata, SensorConstants

_COL = {c: i for i, c in enumerate(PHYSICS_NOISE_COLUMNS)}


def _with_constants(meta: CameraMetadata, constants: SensorConstants) -> CameraMetadata:
    return CameraMetadata(**{n: getattr(meta, n) for n in FULL_FIELDS}, constants=constants)


def _flat(level_dn: float, b: int = 2) -> torch.Tensor:
    return torch.full((b, 1, 128, 128), level_dn / 255.0)


_CONSTANT_CASES = [
    ("EV76C661", {"gain_db": 12.0}, SensorConstants(source_follower_gain=0.8)),
    ("ICX285", {"gain_db": 12.0, "exposure_s": 0.01, "temperature_c": 30.0}, SensorConstants(flicker_corner_hz=5e6)),
    ("EV76C661", {"gain_db": 12.0}, SensorConstants(flicker_corner_hz=1e8, cds_sample_time_s=1e-5)),
]


@pytest.mark.parametrize("pool", [False, True])
@pytest.mark.parametrize("preset, point, constants", _CONSTANT_CASES, ids=["A_SF 0.8", "flicker 5 MHz", "flicker 100 MHz, t_s 10 µs"])
def test_a_matched_camera_with_its_own_sensor_constants_reads_the_closed_form(preset, point, constants, pool):
    """The image is made with exactly the metadata the estimator is told, constants included: the closed form of those
    metadata (physics_prior_dn) with ξ = 0 — not that of the default constants, 2.6 xi_std low, nor a false "noisier
    than told" (ξ = −19.8 DN)."""
    meta = _with_constants(CameraMetadata.preset(preset, **point), constants)
    image = form_image(_flat(128.0), meta, generator=torch.Generator().manual_seed(1)).image
    out = PhysicsNoiseEstimator().predict(image, meta, pool=pool)
    closed = physics_prior_dn(image, meta, clipping=True)
    assert out["assessable"].all() and not out["follows_image"].any()
    assert torch.allclose(out["sigma"], closed[:, 4:7], atol=1e-4) and torch.allclose(out["sigma_total"], closed[:, 7], atol=1e-4)
    assert (out["xi"] == 0).all() and (out["p_match"] > 0.5).all()


@pytest.mark.parametrize("preset, point, constants", _CONSTANT_CASES, ids=["A_SF 0.8", "flicker 5 MHz", "flicker 100 MHz, t_s 10 µs"])
def test_one_camera_state_with_other_constants_is_not_given_the_cached_hypotheses_of_the_defaults(preset, point, constants):
    """The cached hypotheses of one camera state are keyed by its constants too: the same 11 fields read first with the
    default constants and then with others give each their own closed form."""
    default = CameraMetadata.preset(preset, **point)
    for meta in (default, _with_constants(default, constants), default):  # each camera's own image, matched
        image = form_image(_flat(128.0, 1), meta, generator=torch.Generator().manual_seed(2)).image
        raw = physics_noise_posterior(image, meta)
        assert torch.allclose(raw[:, :4], physics_prior_dn(image, meta, clipping=True)[:, 4:8], atol=1e-4)
        assert raw[0, _COL["xi_dn"]] == 0


@pytest.mark.parametrize("theirs, named", [
    (SensorConstants(), r"source_follower_gain = 1.0 \(this frame's 0.8\)"),
    (SensorConstants(source_follower_gain=0.8, flicker_corner_hz=2e6), r"flicker_corner_hz = 2000000.0 \(this frame's 1000000.0\)"),
])
def test_other_exposures_of_a_camera_with_other_constants_are_refused(theirs, named):
    """Another exposure whose fixed constants differ is another camera: refused, naming the constants that differ."""
    mine = _with_constants(CameraMetadata.preset("EV76C661", gain_db=12.0), SensorConstants(source_follower_gain=0.8))
    image = form_image(_flat(128.0), mine, generator=torch.Generator().manual_seed(3)).image
    other = _with_constants(CameraMetadata.preset("EV76C661", gain_db=12.0, exposure_s=0.05), theirs)
    with pytest.raises(ValueError, match=rf"other_exposures\[0\]: its SensorConstants differ from this frame's: {named}"):
        PhysicsNoiseEstimator().predict(image, mine, pool=True, other_exposures=[(image, other)])


def test_other_exposures_with_the_same_constants_are_read():
    mine = _with_constants(CameraMetadata.preset("EV76C661", gain_db=12.0), SensorConstants(source_follower_gain=0.8))
    other = _with_constants(CameraMetadata.preset("EV76C661", gain_db=12.0, exposure_s=0.05), mine.constants)
    image = form_image(_flat(128.0), mine, generator=torch.Generator().manual_seed(3)).image
    second = form_image(_flat(128.0), other, generator=torch.Generator().manual_seed(4)).image
    out = PhysicsNoiseEstimator().predict(image, mine, pool=True, other_exposures=[(second, other)])
    assert out["exposures_read"] == 1 and (out["xi"] == 0).all()
    assert torch.allclose(out["sigma_total"], physics_prior_dn(image, mine, clipping=True)[:, 7], atol=1e-4)


_QUIET = {"gain_db": 0.0, "exposure_s": 0.005, "temperature_c": 20.0}  # ICX285: σ_Total 0.57 DN at 15 DN


def _quiet_camera_with_white_noise(level_dn: float, extra_dn: float, seed: int = 0) -> tuple[torch.Tensor, CameraMetadata]:
    meta = CameraMetadata.preset("ICX285", **_QUIET)
    camera = form_image(_flat(level_dn, 1), meta, generator=torch.Generator().manual_seed(seed)).image.double() * 255.0
    white = extra_dn * torch.randn(camera.shape, generator=torch.Generator().manual_seed(22 + seed), dtype=torch.float64)
    return ((camera + white).clamp(0, 255) / 255.0).float(), meta


@pytest.mark.parametrize("level_dn", [15.0, 30.0])
@pytest.mark.parametrize("extra_dn", [3.0, 5.0, 7.0])
def test_extra_noise_the_scene_allowance_keeps_at_the_closed_form_is_within_the_stated_uncertainty(level_dn, extra_dn):
    """ICX285 at 0 dB (σ_Total 0.57 DN), a flat dark patch with 3–7 DN of extra white noise: the scene allowance keeps
    the closed form (the decision is left as it is), and its error — the patch's realised σ is 3–7 DN — now lies within
    two of the stated xi_std (it was 2.5–4 of them): xi_std and every source's sigma_std are at least the excess the
    patch reads beyond the allowance (column excess_dn)."""
    x, meta = _quiet_camera_with_white_noise(level_dn, extra_dn)
    truth = float((x.double() * 255.0).std())
    out = PhysicsNoiseEstimator().predict(x, meta)
    raw = physics_noise_posterior(x, meta)
    closed = physics_prior_dn(x, meta, clipping=True)
    assert not out["follows_image"].any() and (out["xi"] == 0).all()  # kept: the posterior's decision
    assert torch.allclose(out["sigma_total"], closed[:, 7], atol=1e-4)
    assert abs(float(out["sigma_total"][0]) - truth) <= 2.0 * float(out["xi_std"][0])
    excess = raw[0, _COL["excess_dn"]]
    kept = float(raw[0, _COL["total_dn"]])  # the closed form
    assert excess > 0 and float(out["xi_std"][0]) >= float(excess) and (out["sigma_std"][0] >= excess).all()
    assert float(excess) >= 0.5 * (truth - kept)


@pytest.mark.parametrize("pool", [False, True])
@pytest.mark.parametrize("case", ["flat, quiet camera", "flat, loud camera", "dead leaves", "dead leaves, quiet camera"])
def test_matched_patches_keep_their_uncertainty(case, pool, textured):
    """Metadata right — flat and dead-leaves patches on a quiet and on a noisy camera: no bin reads beyond the scene
    allowance above the metadata, so nothing is raised (excess_dn 0: xi_std and sigma_std are the posterior's)."""
    scene = textured if case.startswith("dead leaves") else _flat(30.0 if "quiet" in case else 128.0, 4)
    if "quiet" in case:
        meta = CameraMetadata.preset("ICX285", **_QUIET)
    else:
        meta = CameraMetadata.preset("EV76C661", gain_db=24.0 if case.startswith("flat") else 18.0, exposure_s=0.05, temperature_c=40.0)
    x = form_image(scene, meta, generator=torch.Generator().manual_seed(1)).image
    raw = physics_noise_posterior(x, meta, pool=pool)
    assert (raw[:, _COL["follows_image"]] == 0).all() and (raw[:, _COL["xi_dn"]] == 0).all()
    assert (raw[:, _COL["excess_dn"]] == 0).all()
    assert torch.isfinite(raw[:, _COL["xi_std_dn"]]).all()


def test_a_textured_matched_photograph_patch_keeps_its_uncertainty():
    """The photograph patch of the robustness benchmark that reads noisier than its camera through its texture: it is
    refused as textured, and its texture is not taken for noise the closed form misses (excess_dn 0)."""
    import cv2

    raw = cv2.imread(str(Path(__file__).parent / "data" / "textured_matched_patch.png"), cv2.IMREAD_UNCHANGED)
    x = torch.from_numpy(raw.astype("float32") / 65535.0).view(1, 1, 128, 128)
    told = {"gain_db": 4.591660499572754, "exposure_s": 0.17213797569274902, "temperature_c": 29.604312896728516,
            "dark_fom_na_per_cm2": 0.30853065848350525, "full_well_e": 2979.525634765625, "pixel_clock_hz": 35658232.0,
            "sense_node_gain_v_per_e": 2.9390023428277345e-06, "reset_factor": 0.6148049235343933,
            "pixel_size_um": 8.043506622314453, "is_cmos": 1.0, "white_noise_v_per_rthz": 6.241862582356816e-09}
    meta = CameraMetadata(**{k: torch.tensor([v]) for k, v in told.items()})
    out = physics_noise_posterior(x, meta)
    assert out[0, _COL["follows_image"]] == 0 and out[0, _COL["excess_dn"]] == 0


_PATCH = torch.full((1, 1, 64, 64), 0.4)


@pytest.mark.parametrize("patches, error, message", [
    ((_PATCH * 255).round().to(torch.uint8), TypeError, r"patches must be a floating tensor.*uint8"),
    (_PATCH * 255, ValueError, r"patches must lie in \[0, 1\].*102"),
    (torch.full((1, 1, 64, 64), float("nan")), ValueError, r"patches must be finite.*4096 of 4096"),
    (_PATCH[:, 0], ValueError, r"patches must have shape B×C×H×W.*\(1, 64, 64\)"),
    (_PATCH[..., :1, :], ValueError, r"patches must be at least 2×2 px, got 1×64"),
    (_PATCH.tolist(), TypeError, r"patches must be a torch.Tensor, got list"),
], ids=["uint8 DN", "float DN", "NaN", "B×H×W", "one row", "list"])
def test_the_quiet_patch_check_refuses_patches_it_cannot_read(patches, error, message):
    """quieter_than_any_camera checks its patches as every estimator function does, instead of an AttributeError for a
    list or False for an all-NaN patch. An empty batch and valid patches are read as before."""
    with pytest.raises(error, match=message):
        quieter_than_any_camera(patches)
    assert quieter_than_any_camera(torch.zeros(0, 1, 64, 64)).shape == (0,)
    noisy = (0.5 + 3.0 / 255.0 * torch.randn(1, 1, 64, 64, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    assert quieter_than_any_camera(torch.cat([torch.full((1, 1, 64, 64), 0.5), noisy])).tolist() == [True, False]


@pytest.mark.parametrize("patch_size, error", [(0, ValueError), (-1, ValueError), (7, ValueError), (True, TypeError),
                                               (128.0, TypeError), ("128", TypeError)])
def test_the_estimator_refuses_a_patch_size_its_fits_cannot_read(patch_size, error):
    """patch_size = 0 reached torch as an empty dimension, −1 asked for "−1×−1 px" patches; now the estimator is refused
    at construction, naming the value and the range."""
    with pytest.raises(error, match=rf"patch_size = {patch_size!r} must be an integer number of px ≥ 8"):
        PhysicsNoiseEstimator(patch_size=patch_size)


@pytest.mark.parametrize("pool", ["yes", "no", 1, None])
@pytest.mark.parametrize("fn", [scene_leak, pair_stillness])
def test_the_static_pair_pool_flag_must_be_a_bool(fn, pool):
    """pool="no" used to pool (a non-empty string is true)."""
    x = torch.full((2, 1, 64, 64), 0.5)
    with pytest.raises(TypeError, match=rf"pool = {pool!r} must be True or False"):
        fn(x, x, pool=pool)
