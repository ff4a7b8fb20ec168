"""JPEG's quantised block grid (camhealth.estimators.jpeg_quantisation): closed forms, coded and uncoded patches."""

import math

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from camhealth.estimators.jpeg_quantisation import (
    JITTER_RATIO_LIMIT,
    MIN_COEFFICIENTS,
    ZERO_EXCESS_LIMIT,
    codec_jitter_ratio,
    jpeg_grid,
    noise_jitter_ratio,
)


def _scene(b: int, size: int, seed: int) -> np.ndarray:
    """Smooth random scenes in 40…215 DN (float64, b×size×size): blurred white noise plus a ramp."""
    g = torch.Generator().manual_seed(seed)
    w = torch.randn(b, 1, size + 16, size + 16, generator=g, dtype=torch.float64)
    k = torch.exp(-torch.arange(-8, 9, dtype=torch.float64).square() / (2 * 3.0**2))
    k = k / k.sum()
    s = F.conv2d(F.conv2d(w, k.view(1, 1, 1, -1)), k.view(1, 1, -1, 1))[:, 0]
    s = s / s.std() * 25.0 + torch.linspace(-40, 40, size, dtype=torch.float64).view(1, 1, -1)
    return (s + 128.0).clamp(40, 215).numpy()


def _noisy(scene: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(np.round(scene + sigma * rng.standard_normal(scene.shape)), 0, 255).astype(np.uint8)


def _code(u8: np.ndarray, quality: int, colour: bool = False) -> np.ndarray:
    if colour:  # a colour JPEG (4:2:0 chroma) decoded and converted to gray, as a camera stream often is
        bgr = np.stack([u8, np.clip(u8.astype(int) + 12, 0, 255).astype(np.uint8), u8], -1)
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
        return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2GRAY)
    ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)


def _patches(images: list[np.ndarray]) -> torch.Tensor:
    return torch.from_numpy(np.stack(images).astype(np.float32) / 255.0).unsqueeze(1)


def test_jitter_ratios_are_the_closed_forms_and_match_sampled_coefficients():
    assert codec_jitter_ratio() == pytest.approx(math.erf(math.sqrt(6) / 2) / (math.erf(math.sqrt(6)) - math.erf(math.sqrt(6) / 2)))
    assert codec_jitter_ratio() == pytest.approx(11.08, abs=0.01)
    sig = torch.tensor([0.0, 0.3, 0.35, 0.5, 1.0, 3.0], dtype=torch.float64)
    r = noise_jitter_ratio(sig)
    assert (r[1:] < r[:-1]).all()  # quieter noise, narrower jitter
    assert float(r[2]) == pytest.approx(JITTER_RATIO_LIMIT, abs=0.01)  # the limit: noise of 0.35 DN
    g = torch.Generator().manual_seed(0)
    for s in (0.3, 0.5, 1.0):  # the ratio of sampled Gaussian coefficients of σ_t² = σ² + 1/12
        c = torch.randn(400_000, generator=g, dtype=torch.float64).abs() * math.sqrt(s * s + 1 / 12)
        sampled = float((c < 0.5).sum() / ((c >= 0.5) & (c < 1.0)).sum())
        assert sampled == pytest.approx(float(noise_jitter_ratio(s)), rel=0.02)
    with pytest.raises(ValueError, match="sigma_dn"):
        noise_jitter_ratio(-1.0)
    with pytest.raises(ValueError, match="sigma_dn"):
        noise_jitter_ratio(float("nan"))


@pytest.mark.parametrize("quality", [50, 75, 90, 95])
@pytest.mark.parametrize("colour", [False, True])
@pytest.mark.parametrize("sigma", [1.0, 2.6, 5.0])
def test_a_jpeg_of_a_noisy_frame_is_coded_at_any_crop_offset(quality, colour, sigma):
    """The frame is coded as a whole (grid at its corner); patches cut at offsets (dy, dx) find the grid at
    ((8 − dy) mod 8, (8 − dx) mod 8) — at quality 50 a smooth patch's blocks lose nearly every high frequency, so a
    grid shifted along one axis holds as many zeros, and only that the patch is coded is asserted."""
    frame = _code(_noisy(_scene(1, 160, 1)[0], sigma, 2), quality, colour)
    offsets = [(0, 0), (3, 5), (7, 1), (12, 20)]
    out = jpeg_grid(_patches([frame[dy:dy + 128, dx:dx + 128] for dy, dx in offsets]))
    assert out.coded.all(), (out.zero_excess, out.jitter_ratio)
    if quality > 50:
        assert out.offset.tolist() == [[(8 - dy) % 8, (8 - dx) % 8] for dy, dx in offsets]
    assert (out.zero_excess > ZERO_EXCESS_LIMIT).all() and (out.coefficients >= MIN_COEFFICIENTS).all()


@pytest.mark.parametrize("sigma", [0.5, 1.0, 3.0, 10.0, 30.0, 45.0])
def test_noise_that_no_codec_touched_is_not_coded(sigma):
    out = jpeg_grid(_patches([_noisy(s, sigma, 3) for s in _scene(8, 128, 4)]))
    assert not out.coded.any()
    assert (out.zero_excess < 0.05).all()
    if sigma <= 3.0:  # (under strong noise few coefficients lie within 1 DN, and their ratio is rough)
        assert (out.jitter_ratio < JITTER_RATIO_LIMIT).all()


@pytest.mark.parametrize("sigma", [0.6, 1.0, 3.0])
def test_a_jpeg_scene_exposed_to_noise_afterwards_is_not_coded(sigma):
    """A scene that was a JPEG (a photograph used as a simulator's clean scene) keeps its grid's zeros under noise
    added afterwards — the best offset holds more coefficients near 0 — but their jitter is the noise's, not the
    codec's rounding: the noise was not coded."""
    scenes = [_code(s.round().astype(np.uint8), 60) for s in _scene(8, 128, 5)]
    out = jpeg_grid(_patches([_noisy(s.astype(np.float64), sigma, 6) for s in scenes]))
    assert not out.coded.any()
    assert (out.jitter_ratio < JITTER_RATIO_LIMIT).all()  # the noise's bound: 1.8, 1.3 and 1.0 (sampled: a little more)


def test_quality_100_and_flat_and_clipped_patches_are_not_coded():
    scene = _noisy(_scene(1, 128, 7)[0], 2.0, 8)
    flat = np.full((128, 128), 100, np.uint8)
    out = jpeg_grid(_patches([_code(scene, 100), flat, _code(flat, 50), np.full((128, 128), 255, np.uint8),
                              np.zeros((128, 128), np.uint8)]))
    assert out.coded.tolist() == [False] * 5
    assert out.coefficients[3:].tolist() == [0, 0]  # every block clipped: nothing counted


def test_small_patches_hold_no_grid_and_batches_and_dtypes_agree():
    frame = _code(_noisy(_scene(1, 128, 9)[0], 2.6, 10), 85)
    one = _patches([frame])
    ref = jpeg_grid(one)
    assert ref.coded.tolist() == [True]
    many = one.expand(256, 1, 128, 128).contiguous()
    out = jpeg_grid(many)
    assert out.coded.all() and torch.equal(out.zero_excess, ref.zero_excess.expand(256))
    for dtype in (torch.float16, torch.bfloat16, torch.float64):
        assert torch.equal(jpeg_grid(one.to(dtype)).zero_excess, ref.zero_excess), dtype
    small = jpeg_grid(one[..., :14, :])
    assert small.coded.tolist() == [False] and small.coefficients.tolist() == [0]
    empty = jpeg_grid(torch.zeros(0, 1, 128, 128))
    assert empty.coded.shape == (0,) and empty.offset.shape == (0, 2)


def test_bad_input_is_refused_with_what_was_given():
    with pytest.raises(ValueError, match="B×1×H×W"):
        jpeg_grid(torch.zeros(1, 128, 128))
    with pytest.raises(ValueError, match="B×1×H×W"):
        jpeg_grid(np.zeros((1, 1, 128, 128)))
    with pytest.raises(TypeError, match="uint8"):
        jpeg_grid(torch.zeros(1, 1, 128, 128, dtype=torch.uint8))
    with pytest.raises(ValueError, match="NaN"):
        jpeg_grid(torch.full((1, 1, 128, 128), float("nan")))
    with pytest.raises(ValueError, match=r"255.*\[0, 1\]"):
        jpeg_grid(torch.full((1, 1, 128, 128), 255.0))


@pytest.mark.parametrize("options", [{}, {"progressive": True}, {"optimize": True}, {"subsampling": 0}, {"subsampling": 2}])
def test_pillows_jpegs_are_coded_too(options):
    """Another encoder (Pillow's libjpeg build): baseline, progressive, optimised Huffman tables, colour 4:4:4 and
    4:2:0 decoded to gray — the quantised coefficients are the same model."""
    import io

    from PIL import Image

    u8 = _noisy(_scene(1, 160, 11)[0], 3.0, 12)
    colour = "subsampling" in options
    img = Image.fromarray(np.stack([u8, np.clip(u8.astype(int) + 15, 0, 255).astype(np.uint8), u8], -1) if colour else u8)
    buf = io.BytesIO()
    img.save(buf, "JPEG", quality=85, **options)
    gray = np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("L"))
    out = jpeg_grid(_patches([gray[7:135, 2:130]]))
    assert out.coded.tolist() == [True] and out.offset.tolist() == [[1, 6]]


def test_a_frame_is_coded_by_the_patches_it_samples():
    from camhealth.estimators.jpeg_quantisation import FRAME_SAMPLE, coded_frame

    scenes = _scene(10, 128, 13)
    coded = _patches([_code(_noisy(s, 2.0, 14), 80) for s in scenes])
    plain = _patches([_noisy(s, 2.0, 14) for s in scenes])
    clipped = torch.ones(10, 1, 128, 128)
    assert coded_frame(coded) and not coded_frame(plain) and not coded_frame(clipped)
    # evenly spaced: patches 0, 3, 6, 9 of 10 are read; a frame coded only there is coded, one coded elsewhere is not
    mixed = plain.clone()
    mixed[[0, 3, 6, 9]] = coded[[0, 3, 6, 9]]
    assert FRAME_SAMPLE == 4 and coded_frame(mixed)
    other = coded.clone()
    other[[0, 3, 6, 9]] = plain[[0, 3, 6, 9]]
    assert not coded_frame(other) and coded_frame(other, sample=10) is True  # 6 of 10 coded: at least half
    assert coded_frame(coded[:1]) and not coded_frame(torch.zeros(0, 1, 128, 128))
    with pytest.raises(ValueError, match="sample = 0"):
        coded_frame(coded, sample=0)
    with pytest.raises(ValueError, match="B×1×H×W"):
        coded_frame(torch.zeros(128, 128))


def test_the_jitter_ratio_must_exceed_its_limit_beyond_the_counts_sampling(monkeypatch):
    """The same ratio 6.4 is a comb from 700 and 110 coefficients, and not beyond doubt from 70 and 11
    (70 − 3·11 = 37 < 3·√(70 + 9·11) = 39)."""
    import camhealth.estimators.jpeg_quantisation as jq

    def fake(counts):
        def read(x):
            b = x.shape[0]
            near, ring = (torch.full((b,), float(v), dtype=torch.float64) for v in counts)
            return (torch.full((b,), 0.3, dtype=torch.float64), near, ring, torch.zeros(b, 2, dtype=torch.int64),
                    torch.full((b,), 1024, dtype=torch.int64))
        return read

    x = torch.full((1, 1, 128, 128), 0.5)
    monkeypatch.setattr(jq, "_read", fake((700, 110)))
    many = jpeg_grid(x)
    monkeypatch.setattr(jq, "_read", fake((70, 11)))
    few = jpeg_grid(x)
    assert float(many.jitter_ratio) == pytest.approx(float(few.jitter_ratio)) == pytest.approx(70 / 11)
    assert many.coded.tolist() == [True] and few.coded.tolist() == [False]
