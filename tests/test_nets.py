"""camhealth.nets: the plain networks, the split of the LightningModules' arguments, and load_net."""

from __future__ import annotations

import importlib
import inspect
import json
import re

import numpy as np
import pytest
import torch

import lightning_modules
from camhealth import nets
from camhealth.export import ALLOWED_CLASSES, export_weights, load_module, load_net
from camhealth.inference import WEIGHTS_DIR, shipped_models
from camhealth.nets.drne import NoiseLevelNet, ThesisNoiseNet
from camhealth.nets.mtf import MTFNet
from camhealth.nets.noise_source import NoiseSourceNet


def _plain(value):
    return tuple(value) if isinstance(value, (list, tuple)) else value


def _trainer_class(spec: nets.NetworkSpec):
    module, name = spec.class_path.rsplit(".", 1)
    return getattr(importlib.import_module(module), name)


@pytest.mark.parametrize("kind", sorted(nets.NETWORKS))
def test_spec_lists_exactly_the_arguments_of_its_lightning_module(kind):
    spec = nets.NETWORKS[kind]
    cls = _trainer_class(spec)
    params = inspect.signature(cls.__init__).parameters
    assert set(params) - {"self"} == set(spec.init_args)
    assert len(spec.init_args) == len(set(spec.init_args))
    assert cls.kind == kind and ALLOWED_CLASSES[spec.class_path] == kind
    # the LightningModule builds the same network class from the same arguments, with the same defaults
    module = cls()
    assert type(module.net) is spec.network
    net_params = inspect.signature(spec.network.__init__).parameters
    for arg in spec.network_args:
        assert arg in net_params, (kind, arg)
        assert _plain(params[arg].default) == _plain(net_params[arg].default), (kind, arg)
    assert nets.NetworkSpec.channels_last({}) == params["channels_last"].default


def test_lightning_modules_reexport_the_networks():
    for name in ("NoiseSourceNet", "NoiseTrunk", "NoiseLevelNet", "ThesisNoiseNet", "MTFNet", "MTFPreprocess"):
        assert getattr(lightning_modules, name) is getattr(nets, name)
    from lightning_modules.blocks import ResidualBlock, count_flops
    from lightning_modules.mtf import sobel
    from lightning_modules.noise_source import BRANCH_FIELDS

    assert ResidualBlock is nets.ResidualBlock and count_flops is nets.count_flops
    assert sobel is nets.mtf.sobel and BRANCH_FIELDS is nets.noise_source.BRANCH_FIELDS


@pytest.mark.parametrize("name", sorted(shipped_models()))
def test_load_net_gives_the_network_of_load_module(name):
    net, desc = load_net(WEIGHTS_DIR / f"{name}.pt")
    module, desc2 = load_module(WEIGHTS_DIR / f"{name}.pt")
    assert desc == desc2
    assert type(net) is nets.NETWORKS[desc["kind"]].network and not net.training
    assert all(p.dtype == torch.float32 for p in net.parameters())
    for batch in (1, 5):
        inputs = module.export_inputs(batch)
        with torch.no_grad():
            assert torch.equal(net(*inputs), module.export_module()(*inputs))


def test_load_net_reads_a_lightning_checkpoint_layout(tmp_path):
    """A Lightning checkpoint keeps the network under ``net.``; load_net strips it as load_module does."""
    torch.manual_seed(1)
    module = lightning_modules.NoiseLevelEstimator(patch_size=32, width=8)
    ckpt = {"state_dict": {f"net.{k}": v for k, v in module.net.state_dict().items()},
            "camhealth": {"format": "camhealth-estimator", "version": 1, **module.describe()}}
    torch.save(ckpt, tmp_path / "m.ckpt")
    net, desc = load_net(tmp_path / "m.ckpt")
    x = torch.rand(2, 1, 32, 32)
    with torch.no_grad():
        assert torch.equal(net(x), module.net.eval()(x))
    assert desc["init_args"]["width"] == 8


@pytest.mark.parametrize(
    "edit,match",
    [
        (lambda a: a.__setitem__("highpass_gain", 5.0), r"\['highpass_gain'\] are not arguments of lightning_modules.drne"),
        (lambda a: a.__setitem__("width", -4), "do not build"),
        (lambda a: a.__setitem__("width", "wide"), "do not build"),
    ],
)
def test_load_net_refuses_a_description_its_lightning_module_would_refuse(tmp_path, edit, match):
    path = export_weights(lightning_modules.NoiseLevelEstimator(patch_size=32, width=8), tmp_path / "w.pt")
    payload = torch.load(path, weights_only=True)
    desc = json.loads(payload["description"])
    edit(desc["init_args"])
    payload["description"] = json.dumps(desc)
    torch.save(payload, path)
    with pytest.raises(ValueError, match=match) as info:
        load_net(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("bad", [0, 8, 24, -16, 32.5, float("nan"), True, "128", None])
def test_check_patch_size_names_the_value(bad):
    with pytest.raises(ValueError, match=r"patch_size = .* must be a positive multiple of 16 px"):
        nets.check_patch_size(bad)
    with pytest.raises(ValueError, match="patch_size"):
        nets.NETWORKS["mtf"].build({"patch_size": bad})


@pytest.mark.parametrize("bad", [1040, 10**9])
def test_check_patch_size_bounds_the_side(bad):
    with pytest.raises(ValueError, match=rf"patch_size = {bad} must be a multiple of 16 px in \[16, 1024\]"):
        nets.check_patch_size(bad)
    assert nets.check_patch_size(1024) == 1024


def test_check_patch_size_accepts_multiples_of_16():
    assert nets.check_patch_size(16) == 16 and nets.check_patch_size(192.0) == 192
    assert nets.check_patch_size(np.int64(128)) == 128 and type(nets.check_patch_size(np.int64(128))) is int


def test_network_for_an_unknown_class_lists_the_allowed_ones():
    with pytest.raises(ValueError, match="allowed:.*MTFEstimator"):
        nets.network_for("os.system")


@pytest.mark.parametrize("autocast", [False, True])
@pytest.mark.parametrize("kind", sorted(nets.NETWORKS))
def test_built_networks_run_in_fp32_and_under_bf16_autocast(kind, autocast):
    """The networks keep float32 weights and outputs; bf16 is CPU autocast (what ``predict(precision="bf16")`` does)."""
    torch.manual_seed(0)
    net = nets.NETWORKS[kind].build({"patch_size": 32})
    x = torch.rand(3, 1, 32, 32)
    args = (x, torch.rand(3, 11)) if kind == "noise_source" else (x,)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        out = net(*args)
    assert out.shape[0] == 3 and out.dtype == torch.float32 and bool(torch.isfinite(out).all())
    with torch.no_grad():
        ref = net(*args)
    assert torch.allclose(out, ref, rtol=0.1, atol=0.1 * float(ref.abs().max()))


@pytest.mark.parametrize("dtype", [torch.float64, torch.bfloat16])
@pytest.mark.parametrize("kind", sorted(nets.NETWORKS))
def test_a_network_cast_as_a_whole_runs_in_its_dtype(kind, dtype):
    """Plain ``nn.Module`` use: ``net.to(float64)`` (or bfloat16, Lightning's "64-true" / "bf16-true") takes inputs of
    that dtype and answers in it — the float64 answer equals the float32 one to float32 precision."""
    torch.manual_seed(0)
    net = nets.NETWORKS[kind].build({"patch_size": 32}).eval()
    x = torch.rand(3, 1, 32, 32)
    args = (x, torch.rand(3, 11)) if kind == "noise_source" else (x,)
    with torch.no_grad():
        ref = net(*args)
        out = net.to(dtype)(*(a.to(dtype) for a in args))
    assert out.dtype == dtype and out.shape == ref.shape and bool(torch.isfinite(out.float()).all())
    tol = 1e-4 if dtype == torch.float64 else 0.1
    assert torch.allclose(out.float(), ref, rtol=tol, atol=tol * float(ref.abs().max()))


def test_count_flops_and_describe_follow_the_network_to_its_device():
    # a network trained on a GPU is described (FLOPs) at every checkpoint with CPU example inputs; a network on the
    # meta device stands in for the GPU here: without the move, its forward refuses the CPU input
    from lightning_modules import MTFEstimator

    x = torch.rand(1, 1, 192, 192)
    cpu = nets.count_flops(nets.MTFNet(), x)
    assert cpu > 0
    assert nets.count_flops(nets.MTFNet().to("meta"), x) == cpu
    module = MTFEstimator()
    module.net.to("meta")
    assert module.describe()["flops_per_patch"] == cpu


@pytest.mark.parametrize("size", [192, 64, 8])
def test_mtf_preprocess_equals_pixel_unshuffle(size):
    """MTFPreprocess rearranges s×s cells into channels by one reshape; the values are nn.PixelUnshuffle's."""
    from camhealth.nets.mtf import MTFPreprocess, sobel

    g = torch.Generator().manual_seed(0)
    x = torch.rand(3, 2, size, size, generator=g)
    pre = MTFPreprocess(4)
    flat = x.reshape(6, 1, size, size)
    mean = flat.mean((2, 3), keepdim=True)
    std = (flat - mean).pow(2).mean((2, 3), keepdim=True).sqrt()
    z = (flat - mean) / (std + pre.contrast_floor)
    both = torch.cat([z, torch.rot90(z, 1, dims=(2, 3))], 0)
    gx, gy = sobel(both)
    want = torch.nn.functional.pixel_unshuffle(torch.cat([both, gx * 4.0, gy * 4.0], 1), 4)
    out = pre(x)
    assert out.shape == (12, 48, size // 4, size // 4)
    assert torch.equal(out, want) and out.is_contiguous()
    assert torch.equal(gx_gy_reference(both)[0], gx) and torch.equal(gx_gy_reference(both)[1], gy)


def gx_gy_reference(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sobel derivatives written out as (a + 2b + c)/8 with temporaries (the definition sobel must match bit for bit)."""
    xp = torch.nn.functional.pad(x, (1, 1, 1, 1), mode="replicate")
    dx = xp[..., :, 2:] - xp[..., :, :-2]
    dy = xp[..., 2:, :] - xp[..., :-2, :]
    return ((dx[..., :-2, :] + 2.0 * dx[..., 1:-1, :] + dx[..., 2:, :]) / 8.0,
            (dy[..., :, :-2] + 2.0 * dy[..., :, 1:-1] + dy[..., :, 2:]) / 8.0)


def test_mtf_preprocess_refuses_sizes_not_divisible_by_the_downsampling():
    from camhealth.nets.mtf import MTFPreprocess

    with pytest.raises(RuntimeError, match="divisible|30"):
        MTFPreprocess(4)(torch.rand(1, 1, 30, 30))


@pytest.mark.parametrize("dtype", [torch.float64, torch.bfloat16])
@pytest.mark.parametrize("kind", [*sorted(nets.NETWORKS), "thesis"])
def test_a_network_cast_as_a_whole_takes_float32_inputs_in_its_dtype(kind, dtype):
    """Lightning's "64-true" / "bf16-true" cast the module, not the inputs it describes itself with (example inputs,
    FLOP count at each checkpoint): every network casts a float32 input to its weights' dtype when autocast is off."""
    torch.manual_seed(0)
    net = nets.ThesisNoiseNet(width=8, layers=3) if kind == "thesis" else nets.NETWORKS[kind].build({"patch_size": 32})
    x = torch.rand(2, 1, 32, 32)
    args = (x, torch.rand(2, 11)) if kind == "noise_source" else (x,)
    with torch.no_grad():
        ref = net.eval()(*args)
        out = net.to(dtype)(*args)
    assert out.dtype == dtype and out.shape == ref.shape
    tol = 1e-4 if dtype == torch.float64 else 0.1
    assert torch.allclose(out.float(), ref, rtol=tol, atol=tol * float(ref.abs().max()))
    assert nets.count_flops(net, *args) > 0


@pytest.mark.parametrize("dilations", [(0, 2, 4), (1, -1, 4), (1.5,), (True,)])
def test_noise_level_net_refuses_dilations_below_one_naming_the_value(dilations):
    with pytest.raises(ValueError, match=rf"dilations = {re.escape(repr(tuple(dilations)))}: each must be an integer >= 1"):
        nets.NoiseLevelNet(8, dilations)


def _edited_file(tmp_path, module, edit):
    from tests._evil_files import redescribed

    path = export_weights(module, tmp_path / "w.pt")
    return redescribed(path, edit, path)


@pytest.mark.parametrize(
    "kind,edit,match",
    [
        ("drne", lambda d: d["init_args"].__setitem__("dilations", [-1, 2, 4]), r"dilations = \(-1, 2, 4\)"),
        ("noise_source", lambda d: d["init_args"].__setitem__("lr", -1), r"init_args: lr = -1 must be > 0"),
        ("noise_source", lambda d: d["init_args"].__setitem__("loss_weights", {"bogus": 1.0}),
         r"loss_weights has unknown key\(s\) \['bogus'\]"),
        ("drne", lambda d: d["init_args"].__setitem__("map_weight", "half"), r"map_weight = 'half' must be a finite number"),
        ("drne", lambda d: d["init_args"].__setitem__("channels_last", "false"), r"channels_last = 'false' must be true or false"),
        ("mtf", lambda d: d.__setitem__("mtf_error", {"x": 1}), r"mtf_error has unknown fields \['x'\]"),
    ],
)
def test_load_net_and_load_module_refuse_the_same_file_with_the_same_message(tmp_path, kind, edit, match):
    """One reader checks a file for both loaders: the network's and the training arguments, the MTF error table."""
    module = {"drne": lambda: lightning_modules.NoiseLevelEstimator(patch_size=32, width=8),
              "noise_source": lambda: lightning_modules.NoiseSourceEstimator(patch_size=32, width=8),
              "mtf": lambda: lightning_modules.MTFEstimator(patch_size=32)}[kind]()
    path = _edited_file(tmp_path, module, edit)
    messages = []
    for load in (load_net, load_module):
        with pytest.raises(ValueError, match=match) as info:
            load(path)
        assert str(path) in str(info.value)
        messages.append(str(info.value))
    assert messages[0] == messages[1]


@pytest.mark.parametrize(
    "cls,kwargs,match",
    [
        ("NoiseLevelEstimator", {"map_weight": 1.5}, r"map_weight = 1.5 must lie in \[0, 1\]"),
        ("NoiseSourceEstimator", {"loss_weights": {"pn": -1.0}}, r"loss_weights\['pn'\] = -1.0 must be ≥ 0"),
        ("MTFEstimator", {"max_figure_samples": -1}, r"max_figure_samples = -1 must be an integer ≥ 0"),
    ],
)
def test_lightning_modules_refuse_what_the_loaders_refuse(cls, kwargs, match):
    """What trains also loads: the LightningModules check their training arguments as the loaders check a file's."""
    with pytest.raises(ValueError, match=match):
        getattr(lightning_modules, cls)(patch_size=32, **kwargs)
    with pytest.raises(ValueError, match=match):
        nets.NETWORKS[getattr(lightning_modules, cls).kind].check_training_args(kwargs)


def test_a_tampered_width_is_refused_before_the_network_is_allocated(tmp_path, monkeypatch):
    """A one-number edit (width 32 → 100 000: ~0.4 TB of weights) is refused by comparing the file's tensor shapes with
    those of the network built on the meta device; no convolution is ever initialised in real memory for it."""
    path = _edited_file(tmp_path, lightning_modules.NoiseLevelEstimator(patch_size=32, width=32),
                        lambda d: d["init_args"].__setitem__("width", 100_000))
    reset = torch.nn.Conv2d.reset_parameters

    def on_meta_only(self):
        if not self.weight.is_meta and self.weight.numel() > 10**6:
            raise AssertionError(f"a {tuple(self.weight.shape)} convolution was allocated before the shapes were compared")
        reset(self)

    monkeypatch.setattr(torch.nn.Conv2d, "reset_parameters", on_meta_only)
    for load in (load_net, load_module):
        with pytest.raises(ValueError, match=r"state_dict entry 'stem.0.weight' has shape \(32, 8, 3, 3\), the network "
                                             r"described by the file has \(100000, 8, 3, 3\)") as info:
            load(path)
        assert str(path) in str(info.value)


def test_load_net_gives_plain_float32_tensors_of_the_file(tmp_path):
    """The network is built on the meta device and then filled: every tensor is the file's, float32 and contiguous
    (a float64 checkpoint of "64-true" training included), and nothing stays on the meta device."""
    torch.manual_seed(3)
    module = lightning_modules.NoiseLevelEstimator(patch_size=32, width=8)
    path = export_weights(module, tmp_path / "w.pt")
    net, _ = load_net(path)
    for key, value in net.state_dict().items():
        assert value.device.type == "cpu" and value.dtype == torch.float32 and value.is_contiguous(), key
        assert torch.equal(value, module.net.state_dict()[key]), key
    ckpt = {"state_dict": {f"net.{k}": v.double() for k, v in module.net.state_dict().items()},
            "camhealth": {"format": "camhealth-estimator", "version": 1, **module.describe()}}
    torch.save(ckpt, tmp_path / "m.ckpt")
    net64, _ = load_net(tmp_path / "m.ckpt")
    assert all(v.dtype == torch.float32 for v in net64.state_dict().values())


@pytest.mark.parametrize("module, net, size", [
    ("camhealth.nets.mtf", lambda: nets.MTFNet(), 192),
    ("camhealth.nets.drne", lambda: nets.NoiseLevelNet(), 128),
    ("camhealth.nets.noise_source", lambda: nets.NoiseSourceNet("minimal"), 128),
])
def test_module_docstring_gflop_figures_are_what_count_flops_gives(module, net, size):
    """The MTF module docstring said ≈ 0.6 GFLOP per 192-px patch; ``count_flops`` gives 0.778. Each module's
    "≈ X GFLOP per N-px patch" must be the computed figure to its stated digits."""
    doc = importlib.import_module(module).__doc__
    m = re.search(r"≈ (\d+\.\d+) GFLOP per (\d+)-px patch", doc)
    assert m and int(m.group(2)) == size, doc
    n = net()
    inputs = (torch.rand(1, 1, size, size),) + ((torch.rand(1, 11),) if isinstance(n, nets.NoiseSourceNet) else ())
    gflop = nets.count_flops(n, *inputs) / 1e9
    digits = len(m.group(1).split(".")[1])
    assert round(gflop, digits) == float(m.group(1)), (module, gflop, m.group(1))


def test_thesis_noise_net_size_is_the_documented_one():
    """docs/estimators.md listed ThesisNoiseNet as 0.56 M parameters; it has 518,209 (0.52 M), 16.9 GFLOP."""
    net = nets.ThesisNoiseNet()
    assert nets.count_parameters(net) == 518_209
    assert round(nets.count_flops(net, torch.rand(1, 1, 128, 128)) / 1e9, 1) == 16.9


@pytest.mark.parametrize("make, message", [
    (lambda: MTFNet(widths=(32, 64)), r"widths = \(32, 64\) must be 3 integers >= 1"),
    (lambda: MTFNet(downsample=0), r"downsample = 0 must be an integer >= 1"),
    (lambda: MTFNet(hidden=(128, 0)), r"hidden = \(128, 0\) must be integers >= 1"),
    (lambda: NoiseSourceNet(width=0), r"width = 0 must be an integer >= 1"),
    (lambda: NoiseSourceNet(hidden=[64, True]), r"hidden = \(64, True\) must be integers >= 1, got True"),
    (lambda: NoiseLevelNet(width=-3), r"width = -3 must be an integer >= 1"),
    (lambda: ThesisNoiseNet(layers=1), r"layers = 1 must be an integer >= 2"),
])
def test_layer_sizes_are_positive_integers(make, message):
    """A layer of 0 units makes an output that ignores the image; a wrong count a traceback: both are refused, named."""
    with pytest.raises(ValueError, match=message):
        make()


def test_an_mtf_patch_size_must_hold_whole_space_to_depth_cells():
    from lightning_modules.mtf import MTFEstimator

    with pytest.raises(ValueError, match=r"patch_size = 192 px must be a multiple of downsample = 5"):
        MTFEstimator(downsample=5)


def test_check_dilations_names_the_value_and_the_range():
    from camhealth.nets.drne import check_dilations

    assert check_dilations([1, 2, 4], 128) == (1, 2, 4) and check_dilations((63,), 128) == (63,)
    with pytest.raises(ValueError, match=r"dilations = \(1, 64\): 64 is too large for patch_size = 128.*\[1, 63\]"):
        check_dilations([1, 64], 128)
    with pytest.raises(TypeError, match=r"dilations = 4 must be a list of integers"):
        check_dilations(4)
    with pytest.raises(ValueError, match=r"each must be an integer >= 1, got 0"):
        NoiseLevelNet(8, (1, 0))
    assert check_dilations([200]) == (200,)  # without a patch size: the network alone (inference builds it so)


def test_a_file_whose_drne_dilations_reach_only_the_padding_is_refused_by_both_loaders(tmp_path):
    """load_module refuses what the LightningModule refuses; load_net (no LightningModule) refuses it too."""
    spec = nets.NETWORKS["drne"]
    with pytest.raises(ValueError, match=r"dilations = \(1, 2, 64\): 64 is too large for patch_size = 128"):
        spec.build({"patch_size": 128, "dilations": [1, 2, 64]})
    assert spec.build({"patch_size": 128, "dilations": [1, 2, 63]}) is not None
