"""Training at extreme but valid configs: finite losses and gradients, or a clear stop.

The tiny NSD config of ``test_nsd_train.py`` trains with every prior weight at
0 or 100 and every learning rate at 1e-6 or 1e-2. The trainer checks every
loss term and gradient at every step (``stop_on_nonfinite``) and would stop
with a FloatingPointError naming them; these runs must finish, with finite
weights and logs. A toy task shows the stop and its message, and anomaly
detection naming the operation that made a NaN.
"""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import torch
from torch import nn

from nsd.core.errors import NonFiniteError
from nsd.core.trainer import Trainer, TrainerConfig, seed_everything
from nsd.io.scene_data import SceneData
from nsd.training.task import NSDTask
from tests.nsd.training.test_train import tiny_cfg

PRIORS = (
    "prior_position",
    "prior_scale",
    "prior_aspect",
    "prior_presence",
    "prior_proposal",
    "prior_depth",
    "prior_association",
)
EXTREMES = [(w, lr) for w in (0.0, 100.0) for lr in (1e-6, 1e-2)]


def _extreme_cfg(weight: float, lr: float, *extra: str):
    return tiny_cfg(
        *(f"{p}.weight={weight}" for p in PRIORS),
        f"optim.lr_detector={lr}",
        f"optim.lr_encoder={lr}",
        f"optim.lr_decoder={lr}",
        "model.detector.presence=true",  # so that the presence prior acts
        "model.depth_from_step=5",  # both stages and the re-initialisation
        *extra,
    )


def _train(cfg, scene, out, steps: int, **trainer) -> Trainer:
    data = SceneData(scene, (32, 24), val_fraction=0.25)
    seed_everything(0)
    settings = {"log_every": 10, "checkpoint_every": 0, "progress": False, **trainer}
    tc = TrainerConfig.defaults(max_steps=steps, **settings)
    t = Trainer(NSDTask(cfg, data), tc, out)
    t.fit()
    return t


def _assert_finite_run(t: Trainer) -> None:
    for name, p in t.task.model.named_parameters():
        assert torch.isfinite(p).all(), name
    with (t.out_dir / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    train = [r for r in rows if r.get("train/loss")]
    assert train, "no training rows logged"
    for r in train:
        for k, v in r.items():
            if k.startswith("train/") and v:
                assert math.isfinite(float(v)), (k, r["step"], v)


@pytest.mark.parametrize(("weight", "lr"), EXTREMES, ids=lambda v: f"{v:g}")
def test_extreme_config_short(weight, lr, tiny_scene, tmp_path):
    _assert_finite_run(_train(_extreme_cfg(weight, lr), tiny_scene, tmp_path, 30))


@pytest.mark.slow
@pytest.mark.parametrize(("weight", "lr"), EXTREMES, ids=lambda v: f"{v:g}")
def test_extreme_config_hundreds_of_steps(weight, lr, tiny_scene, tmp_path):
    _assert_finite_run(_train(_extreme_cfg(weight, lr), tiny_scene, tmp_path, 300))


def test_anomaly_detection_on_a_real_run(tiny_scene, tmp_path):
    t = _train(_extreme_cfg(100.0, 1e-2), tiny_scene, tmp_path, 4, detect_anomaly=True,
               log_every=1)
    _assert_finite_run(t)
    assert not torch.is_anomaly_enabled()  # switched off again after fit


class _ToyTask:
    """One parameter w; ``loss`` is chosen to break in a known way."""

    def __init__(self, loss: str, lr: float = 0.1) -> None:
        self.w = nn.Parameter(torch.zeros(3))
        self.module = nn.ParameterList([self.w])
        self.opt = torch.optim.SGD([self.w], lr=lr)
        self.kind = loss

    def modules(self):
        return {"toy": self.module}

    def optimizers(self):
        return {"sgd": self.opt}

    def training_step(self, step: int, rng: np.random.Generator):
        if self.kind == "overflow":  # finite at first, then SGD with a huge rate blows up
            loss = ((self.w - 1e18) ** 2).sum()
        else:  # sqrt at 0: finite loss, infinite gradient; times 0: NaN gradient
            loss = torch.sqrt(self.w).sum() * (0.0 if self.kind == "nan_grad" else 1.0)
        return {"loss": loss, "toy": loss.detach()}

    def evaluate(self, step: int):
        return {}

    def image_grids(self, step: int):
        return {}


def _toy_trainer(task, tmp_path, **kw):
    tc = TrainerConfig.defaults(max_steps=5, log_every=0, checkpoint_every=0, progress=False, **kw)
    return Trainer(task, tc, tmp_path)


def test_non_finite_loss_stops_with_a_clear_message(tmp_path):
    t = _toy_trainer(_ToyTask("overflow", lr=1e10), tmp_path)
    with pytest.raises(FloatingPointError, match=r"non-finite loss terms \['loss', 'toy'\]"):
        t.fit()
    assert t.step == 1  # one step with a finite loss, then (2e28)^2 overflows float32


def test_non_finite_gradient_stops_with_a_clear_message(tmp_path):
    t = _toy_trainer(_ToyTask("inf_grad"), tmp_path)
    with pytest.raises(
        FloatingPointError,
        match=r"non-finite gradient of parameter 'toy.0' \(optimiser 'sgd', parameter group 0",
    ):
        t.fit()
    assert t.step == 0 and torch.equal(t.task.w.detach(), torch.zeros(3))  # no step taken


def test_weights_made_non_finite_by_a_step_stop_the_run_naming_the_parameter(tmp_path):
    """A NaN learning rate (here SGD's, unchecked by the toy task) keeps the loss and the
    gradient finite but turns the weights NaN: the guard names the parameter and its rate."""
    t = _toy_trainer(_ToyTask("overflow", lr=float("nan")), tmp_path)
    with pytest.raises(NonFiniteError, match=r"non-finite value of parameter 'toy.0'.*rate nan"):
        t.fit()
    assert t.step == 0  # stopped in the step that produced them, before the next forward


def test_a_non_finite_loss_stops_before_backward(tmp_path):
    """The loss check runs before backward(): no gradient is ever computed."""
    task = _ToyTask("overflow", lr=1e10)
    t = _toy_trainer(task, tmp_path)
    with pytest.raises(NonFiniteError):
        t.fit()
    assert task.w.grad is None


def test_anomaly_detection_names_the_operation(tmp_path):
    t = _toy_trainer(_ToyTask("nan_grad"), tmp_path, detect_anomaly=True)
    with (
        pytest.raises(RuntimeError, match=r"SqrtBackward0.*nan"),
        pytest.warns(UserWarning, match="Error detected in SqrtBackward0"),  # forward trace
    ):
        t.fit()
    assert not torch.is_anomaly_enabled()


@pytest.mark.parametrize(
    ("key", "value"),
    [("lr_detector", "nan"), ("lr_encoder", "-1e-3"), ("lr_decoder", "0"), ("weight_decay", "inf")],
)
def test_non_finite_or_negative_learning_rates_are_refused_before_training(
    key, value, tiny_scene
):
    """``optim.lr_detector=nan`` made every weight NaN in the first step and crashed inside
    backward(); it is now refused when the task is built, naming the key."""
    from nsd.core.errors import ConfigError

    cfg = tiny_cfg(f"optim.{key}={value}")
    data = SceneData(tiny_scene, cfg.data.image_size, None, cfg.data.val_fraction)
    with pytest.raises(ConfigError, match=rf"optim\.{key} must be a finite number"):
        NSDTask(cfg, data)
