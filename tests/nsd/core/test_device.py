"""The ``device`` setting: resolution, the device boundary of inference, and the training
steps of NSD and NeTePu placing every tensor on their model's device.

No GPU is needed to check the placement: the training steps run with the models on
torch's ``meta`` device, where an operation that mixes a meta tensor with a CPU tensor
(one created without ``device=``) raises, as it would on a GPU. The CUDA test at the
end runs a real training step and inference only where a CUDA GPU exists.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from nsd.core.device import call_on_device, model_device, move, on_cpu, resolve_device
from nsd.core.errors import ConfigError
from nsd.io.scene_data import SceneData
from nsd.training.task import NSDTask
from tests.nsd.training.test_train import tiny_cfg

META = torch.device("meta")
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def test_resolve_device_on_this_machine(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu")
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == expected
    assert resolve_device(" AUTO ").type == expected
    for bad in ("gpu", "cuda:x", "tpu", ""):
        with pytest.raises(ConfigError, match="use auto, cpu, cuda, cuda:N or mps"):
            resolve_device(bad)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(ConfigError, match=r"train.device=cuda:1: .* sees no CUDA GPU"):
        resolve_device("cuda:1", key="train.device")


def test_resolve_device_counts_gpus_and_follows_torchrun(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert resolve_device("auto") == torch.device("cuda", 1)  # one GPU per torchrun process
    assert resolve_device("cuda") == torch.device("cuda", 1)
    assert resolve_device("cuda:0") == torch.device("cuda", 0)
    with pytest.raises(ConfigError, match=r"2 CUDA device\(s\) \(0 to 1\)"):
        resolve_device("cuda:2")


def test_move_keeps_structure_and_types():
    @dataclasses.dataclass
    class Box:
        a: torch.Tensor
        b: list
        n: int = 3

    box = Box(torch.ones(2), [torch.zeros(1), "x"])
    box.extra = torch.ones(1)  # set after construction
    out = move({"box": box, "t": (torch.ones(1),)}, META)
    assert isinstance(out["box"], Box) and out["box"].n == 3 and out["box"].b[1] == "x"
    assert out["box"].a.device == META and out["box"].b[0].device == META
    assert out["box"].extra.device == META and out["t"][0].device == META
    assert box.a.device.type == "cpu"  # the original is untouched


def test_call_on_device_is_the_identity_on_the_cpu():
    lin = torch.nn.Linear(2, 2)
    x = torch.ones(1, 2)
    assert torch.equal(call_on_device(lin, lin, x), lin(x))


def test_on_cpu_puts_modules_back_even_on_error(monkeypatch):
    """A module on another device (stood in by a recorder: the meta device cannot copy
    to the CPU) goes to the CPU for the block and back to its device after, also when
    the block raises; the parameters stay the optimiser's objects."""
    import nsd.core.device as device_module

    calls = []

    class Recorder(torch.nn.Linear):
        def cpu(self):
            calls.append("cpu")
            return self

        def to(self, *args, **kwargs):
            calls.append(("to", *args))
            return self

    lin = Recorder(2, 2)
    opt = torch.optim.Adam(lin.parameters())
    monkeypatch.setattr(device_module, "model_device", lambda m: META)
    with pytest.raises(RuntimeError, match="inside"), on_cpu(lin):
        assert calls == ["cpu"]
        raise RuntimeError("inside")
    assert calls == ["cpu", ("to", META)]
    assert all(p is q for p, q in zip(lin.parameters(), opt.param_groups[0]["params"],
                                       strict=True))
    calls.clear()
    monkeypatch.setattr(device_module, "model_device", lambda m: torch.device("cpu"))
    with on_cpu(lin):
        pass
    assert calls == []  # already on the CPU: nothing moves


@pytest.fixture
def tiny_data(tiny_scene):
    return SceneData(tiny_scene, (32, 24), val_fraction=0.25)


# SSIM is left out: kornia's SSIM opens an autocast region, which the meta device lacks
@pytest.mark.parametrize("overrides", [
    [], ["model.mode=autoencoder"], ["prior_presence=hull"], ["prior_presence=marginal"],
    ["prior_depth=triangulation"], ["model.depth_from_step=0"],
])
def test_nsd_training_step_stays_on_the_model_device(tiny_data, overrides):
    cfg = tiny_cfg("loss.ssim_weight=0", *overrides)
    task = NSDTask(cfg, tiny_data, device=META)
    assert model_device(task.model) == META
    terms = task.training_step(0, np.random.default_rng(0))
    assert {t.device for t in terms.values()} == {META}
    terms["loss"].backward()
    assert all(p.grad is None or p.grad.device == META for p in task.model.parameters())


def test_geometry_training_step_stays_on_the_model_device(monkeypatch):
    import netepu.geometry.renderer as renderer
    from tests.netepu.cli.test_train import _task

    monkeypatch.setattr(renderer, "check_in_front", lambda depth: None)  # reads values
    task = _task().to(META)
    terms = task.training_step(0, np.random.default_rng(0))
    assert terms["loss"].device == META
    terms["loss"].backward()
    assert all(p.grad is None or p.grad.device == META for p in task.model.parameters())


def test_texture_training_step_stays_on_the_model_device(monkeypatch):
    import netepu.geometry.renderer as renderer
    from tests.netepu.texture.test_texture import _task

    monkeypatch.setattr(renderer, "check_in_front", lambda depth: None)  # reads values
    task = _task(cross_view=0.5, contrast_weight=0.1).to(META)
    terms = task.training_step(0, np.random.default_rng(0))
    assert terms["loss"].device == META
    terms["loss"].backward()
    assert any(p.grad is not None for p in task.texture.parameters())


def test_checkpoints_hold_cpu_tensors(tiny_data, tmp_path):
    from nsd.core.trainer import Trainer, TrainerConfig

    module = torch.nn.BatchNorm1d(2).state_dict()
    out = move(module, "cpu")
    assert type(out) is type(module) and out._metadata == module._metadata  # versions kept
    task = NSDTask(tiny_cfg(), tiny_data)
    tc = TrainerConfig.defaults(max_steps=1, progress=False, checkpoint_every=0, log_every=0)
    Trainer(task, tc, tmp_path).fit()
    saved = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert "torch_cuda" in saved["rng"]


@CUDA
def test_cuda_training_and_inference(tiny_data, tmp_path):
    """Where a CUDA GPU exists: NSD trains on it, its checkpoint loads on the CPU, and
    inference with the model on the GPU equals inference on the CPU."""
    from nsd.core.trainer import Trainer, TrainerConfig
    from nsd.inference.single import decompose
    from nsd.model.checkpoint import load_decomposition

    cuda = resolve_device("cuda")
    task = NSDTask(tiny_cfg(), tiny_data, device=cuda)
    tc = TrainerConfig.defaults(max_steps=3, progress=False, checkpoint_every=0, log_every=0)
    Trainer(task, tc, tmp_path).fit()
    assert model_device(task.model).type == "cuda"
    cpu = load_decomposition(tmp_path, "cpu").model
    gpu = load_decomposition(tmp_path, cuda).model
    views, bgs = tiny_data.views(0)
    a, b = decompose(cpu, views, bgs), decompose(gpu, views, bgs)
    assert b.masks.device.type == "cpu"
    torch.testing.assert_close(a.raw_masks, b.raw_masks, atol=1e-4, rtol=1e-4)
