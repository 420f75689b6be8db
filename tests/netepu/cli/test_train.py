"""netepu-train: configs, stage switch, a trained tiny model, exact resume, end-to-end run."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module

from netepu.cli.train import run
from netepu.geometry.evaluation import render_view_set
from netepu.geometry.losses import GeometryLossWeights
from netepu.geometry.maps import MapSettings
from netepu.geometry.model import build_geometry_model, load_geometry_model
from netepu.geometry.stage import GeometryStageConfig, GeometryTask
from nsd.core.errors import ConfigError
from nsd.core.trainer import Trainer, TrainerConfig, seed_everything
from nsd.evaluation.maps import silhouette_iou
from tests.netepu_world import K_TOY, RADIUS, TINY_MODEL, toy_data, trained_toy


def _compose(*overrides):
    with initialize_config_module("nsd.conf", version_base="1.3"):
        return compose("netepu_train", overrides=list(overrides))


@pytest.mark.parametrize("model", ["fast", "reference"])
@pytest.mark.parametrize("data", ["quadruped", "biped"])
def test_configs_compose(model, data):
    from omegaconf import OmegaConf

    cfg = _compose(f"netepu/model={model}", f"netepu/data={data}")
    net = OmegaConf.to_container(cfg.netepu, resolve=True)
    assert net["data"]["margin"] == net["render"]["margin"]
    assert cfg.trainer.grad_clip == 1.0 and cfg.stage == "geometry"
    MapSettings.from_config(net["render"]).validate()
    GeometryLossWeights.from_config(net["loss"])
    GeometryStageConfig.from_mapping(net["optim"], net["points"], net["eval"])
    if model == "fast":
        m = build_geometry_model(net["model"], 25, net["data"]["radius"])
        assert sum(p.numel() for p in m.parameters()) < 5e6


def test_texture_stage_needs_geometry_and_unknown_stage_fails(tmp_path):
    with pytest.raises(ConfigError, match="init_from"):
        run(_compose("stage=texture"), tmp_path)
    with pytest.raises(ConfigError, match="stage must be"):
        run(_compose("stage=colour"), tmp_path)


def test_bad_model_config():
    with pytest.raises(ConfigError, match=r"netepu\.model"):
        build_geometry_model({"encoder": {"width": 8, "latent": 8, "bogus": 1},
                              "decoder": {"features": 8}, "renderer": {}}, 5, 1.0)


def test_trained_tiny_model_reproduces_training_silhouettes():
    model, data, _ = trained_toy()
    views = data.evaluation["train"]
    maps = render_view_set(model, views, MapSettings.defaults())
    iou = silhouette_iou(maps.silhouette, views.mask)
    assert iou.min() > 0.75 and iou.mean() > 0.85, iou
    # an untrained model of the same size does not
    torch.manual_seed(0)
    fresh = build_geometry_model(TINY_MODEL, K_TOY, RADIUS).eval()
    assert silhouette_iou(render_view_set(fresh, views, MapSettings.defaults()).silhouette,
                          views.mask).mean() < 0.6


def _task(seed=0, lr=5e-4):
    seed_everything(seed)
    data = toy_data(n_poses=2, pool=100)
    model = build_geometry_model(TINY_MODEL, K_TOY, RADIUS)
    return GeometryTask(model, data, GeometryStageConfig.defaults(batch_size=2, near=40, far=40,
                                                         foreground=30, eval_views=2, lr=lr),
                        GeometryLossWeights.defaults(), MapSettings.defaults())


def test_exact_resume(tmp_path):
    def cfg(steps):
        return TrainerConfig.defaults(max_steps=steps, progress=False, checkpoint_every=0,
                                      grad_clip=1.0, log_every=0)

    Trainer(_task(), cfg(6), tmp_path / "straight").fit()
    a = Trainer(_task(), cfg(3), tmp_path / "resumed")
    a.fit()
    b_task = _task()
    Trainer(b_task, cfg(6), tmp_path / "resumed").fit()
    straight = torch.load(tmp_path / "straight" / "checkpoint.pt", weights_only=True)
    for k, v in b_task.model.state_dict().items():
        assert torch.equal(v, straight["modules"]["geometry"][k]), k


def test_loss_terms_decrease_on_one_batch():
    task = _task(lr=3e-3)
    rng = np.random.default_rng(0)
    from netepu.geometry.data import sample_batch

    batch = sample_batch(task.data, rng, 2, 40, 40, 30)
    first = None
    for _ in range(30):
        for o in task.optimizers().values():
            o.zero_grad()
        terms = task.losses(batch, np.random.default_rng(1))
        terms["loss"].backward()
        for o in task.optimizers().values():
            o.step()
        first = first or {k: float(v.detach()) for k, v in terms.items()}
    assert float(terms["loss"].detach()) < 0.6 * first["loss"]


def test_end_to_end_run_on_the_synthetic_world(tmp_path):
    """netepu-train's run() on a few tiny synthetic views: data, training, checkpoint, reload."""
    cfg = _compose(
        "netepu.data.train_poses=2", "netepu.data.eval_poses=1",
        "netepu.data.eval_views_per_pose=2", "netepu.data.image_size=[64,48]",
        "netepu.data.pool_near=64", "netepu.data.pool_far=64", "netepu.data.pool_foreground=64",
        "netepu.data.rig.kind=ring", "+netepu.data.rig.count=4",
        f"netepu.data.cache_dir={tmp_path / 'cache'}",
        "netepu.optim.batch_size=2", "netepu.points.near=16", "netepu.points.far=16",
        "netepu.points.foreground=16", "netepu.eval.eval_views=2",
        "trainer.max_steps=3", "trainer.progress=false", "trainer.eval_every=0",
        "trainer.grid_every=0",
        "netepu.model.encoder.width=16", "netepu.model.encoder.latent=32",
        "netepu.model.decoder.features=16", "netepu.model.renderer.width=16",
        "netepu.model.renderer.head_hidden=16",
    )
    metrics = run(cfg, tmp_path / "run")
    assert 0.0 <= metrics["heldout_poses/iou"] <= 1.0
    assert (tmp_path / "run" / "checkpoint.pt").is_file()
    assert list((tmp_path / "run" / "grids").glob("geometry_heldout_cameras_*.png"))
    model, config = load_geometry_model(tmp_path / "run" / "checkpoint.pt")
    assert model.n_keypoints == 25 and config["netepu"]["data"]["n_keypoints"] == 25
    assert list((tmp_path / "cache").glob("geometry-quadruped-*.npz"))


@pytest.mark.parametrize("reach", [False, True])
def test_render_losses_reach_the_encoder_only_when_asked(reach):
    task = _task()
    task.cfg.render_grad_to_encoder = reach
    from netepu.geometry.data import sample_batch

    batch = sample_batch(task.data, np.random.default_rng(0), 2, 40, 40, 30)
    task.weights = GeometryLossWeights.defaults(keypoints=0.0, latent=0.0)  # render terms only
    task.losses(batch, np.random.default_rng(1))["loss"].backward()
    enc = [p.grad for p in task.model.encoder.parameters()]
    pos = [p.grad for p in task.model.decoder.mlp_pos.parameters()]
    assert all(g is None or not g.any() for g in pos)  # positions: keypoint loss only
    assert any(g is not None and g.any() for g in enc) == reach
    assert set(task.optimizers()) == {"pose", "render"}
    n_pose = sum(p.numel() for g in task.optimizers()["pose"].param_groups for p in g["params"])
    assert n_pose == sum(p.numel() for p in [*task.model.encoder.parameters(),
                                              *task.model.decoder.mlp_pos.parameters()])
