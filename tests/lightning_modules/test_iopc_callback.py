"""IOPCCallback: the sweep runs at the end of a (tiny) fit, with the trained module as the MTF estimator,
and its heat map is logged to TensorBoard."""

import json

import lightning as L
import pytest
import torch
from lightning.pytorch.loggers import TensorBoardLogger

from camhealth.iopc import SensorSetting, SweepConfig, SweepGrid
from lightning_modules.iopc_callback import IOPCCallback, module_estimator
from tests.iopc.fakes import FakeMTFEstimator, FakeNoiseEstimator, NoiseSensitiveDetector, smooth_frames

BOXES = [[10.0, 10.0, 60.0, 80.0]]


class TinyMTFEstimator(L.LightningModule):
    """A trainable 'MTF estimator' with the inference contract: one parameter → a constant MTF."""

    kind = "mtf"
    patch_size = 48
    metadata_set = "none"

    def __init__(self):
        super().__init__()
        self.logit = torch.nn.Parameter(torch.tensor(0.0))

    def predict(self, patches, metadata=None):
        assert not self.training and not torch.is_grad_enabled()
        value = torch.sigmoid(self.logit).detach().cpu()
        return {"mtf": value.expand(patches.shape[0], 16).clone(), "assessable": torch.ones(patches.shape[0], dtype=torch.bool)}

    def training_step(self, batch, batch_idx):
        return (torch.sigmoid(self.logit) - 0.9) ** 2 + 0 * batch.sum()

    def train_dataloader(self):
        return torch.utils.data.DataLoader(torch.zeros(4, 1), batch_size=2)

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=1.0)


class NotAnEstimator(TinyMTFEstimator):
    kind = None
    predict = None


def _callback(tmp_path, **kw):
    grid = SweepGrid([0.0, 5.0], [0.0], [0.0, 6.0])
    gt = [{"boxes": torch.tensor(BOXES), "labels": torch.tensor([1])}] * 2
    return IOPCCallback(detector=NoiseSensitiveDetector(BOXES), frames=smooth_frames(2, 96, 128), ground_truth=gt,
                        noise_estimator=FakeNoiseEstimator(32), config=SweepConfig(grid=grid, sensor=SensorSetting()),
                        out_dir=tmp_path / "iopc", progress=False, **kw)


def _trainer(tmp_path, cb):
    return L.Trainer(max_steps=2, accelerator="cpu", devices=1, logger=TensorBoardLogger(tmp_path, name="tb"),
                     log_every_n_steps=1,
                     callbacks=[cb], enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)


def test_sweep_at_fit_end_with_the_trained_module(tmp_path):
    cb = _callback(tmp_path)
    module = TinyMTFEstimator()
    _trainer(tmp_path, cb).fit(module)
    iopc = cb.iopc
    assert iopc is not None and len(iopc.records) == 4
    assert iopc.provenance["trained_module_role"] == "mtf" and "TinyMTFEstimator" in iopc.provenance["mtf_estimator"]
    trained_mtf = float(torch.sigmoid(module.logit.detach()))
    assert trained_mtf != pytest.approx(0.5)  # it did train
    assert all(r["mtf_tilde"] == pytest.approx(trained_mtf) for r in iopc.records)
    assert module.training  # mode restored
    assert json.loads((tmp_path / "iopc" / "iopc.json").read_text())["format"] == "camhealth-iopc"
    assert (tmp_path / "iopc" / "iopc.png").is_file()
    events = list((tmp_path / "tb").rglob("events.out.tfevents*"))
    assert events and sum(e.stat().st_size for e in events) > 1000  # figure + image + scalars


def test_configured_estimators_when_the_module_is_not_one(tmp_path):
    cb = _callback(tmp_path, mtf_estimator=FakeMTFEstimator(0.7, 48), every_n_epochs=None)
    assert module_estimator(NotAnEstimator()) is None
    _trainer(tmp_path, cb).fit(NotAnEstimator())
    assert cb.iopc.provenance["trained_module_role"] == "none"
    assert all(r["mtf_tilde"] == pytest.approx(0.7) for r in cb.iopc.records)


def test_callback_argument_errors(tmp_path):
    with pytest.raises(ValueError, match="every_n_epochs"):
        IOPCCallback(every_n_epochs=0)
    with pytest.raises(ValueError, match="give 'hog'"):  # refused when the callback is built, before training
        IOPCCallback(detector="yolo")


def test_camhealth_estimator_module_is_exported_and_reloaded(tmp_path):
    """An issue-4 EstimatorModule (no predict of its own) goes through export_weights → load_estimator."""
    lm = pytest.importorskip("lightning_modules")
    if not hasattr(lm, "MTFEstimator"):
        pytest.skip("lightning_modules.MTFEstimator not available")
    module = lm.MTFEstimator()
    module.train()
    est = module_estimator(module, tmp_path)
    assert module.training  # the caller (IOPCCallback) restores the mode; export must not break the module
    assert est.kind == "mtf" and est.patch_size == 192 and est.metadata_set == "none"
    out = est.predict(torch.rand(2, 1, 192, 192))
    assert out["mtf"].shape == (2, 16) and bool(((out["mtf"] >= 0) & (out["mtf"] <= 1)).all())
