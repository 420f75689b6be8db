"""NSD training: a tiny run lowers the loss and stays finite; resume is bit-for-bit exact."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module

from nsd.core.trainer import Trainer, TrainerConfig, seed_everything
from nsd.io.scene_data import SceneData
from nsd.model.build import build_model
from nsd.training.task import NSDTask

TINY = [
    "model.num_windows=2",
    "model.crop_size=16",
    "model.detector.input_size=16",
    "model.detector.widths=[8,8]",
    "model.detector.hidden=32",
    "model.encoder.widths=[8,16]",
    "model.encoder.app_dims=16",
    "model.encoder.points=8",
    "model.decoder.widths=[16,8]",
    "batch_size=4",
    "eval_frames=2",
    "data.image_size=[32,24]",
    "data.val_fraction=0.25",
]


def tiny_cfg(*overrides: str):
    """The tiny config, trained by Bi-NVS (the paper's cross-view path, which most model and
    prior tests exercise) unless ``overrides`` say ``model.mode=autoencoder``, the default;
    ``TINY`` alone (the pipeline's tests) keeps the default mode."""
    with initialize_config_module("nsd.conf", version_base="1.3"):
        return compose("train", overrides=[*TINY, "model.mode=bi_nvs", *overrides])


@pytest.fixture
def tiny_data(tiny_scene):
    return SceneData(tiny_scene, (32, 24), val_fraction=0.25)


def _trainer(cfg, data, out, steps):
    seed_everything(3)  # model initialisation, as nsd.training.train.train does
    tc = TrainerConfig.defaults(
        max_steps=steps, log_every=5, checkpoint_every=0, progress=False, seed=3
    )
    return Trainer(NSDTask(cfg, data), tc, out)


def test_tiny_run_lowers_loss_and_stays_finite(tiny_data, tmp_path):
    cfg = tiny_cfg()
    task = NSDTask(cfg, tiny_data)
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    batch = tiny_data.sample(np.random.default_rng(123), 8)
    with torch.no_grad():
        task.model.eval()
        before = task.losses(batch)["loss"].item()
        task.model.train()
    for step in range(60):
        task.opt.zero_grad()
        losses = task.training_step(step, rng)
        losses["loss"].backward()
        for p in task.model.parameters():
            assert p.grad is None or torch.isfinite(p.grad).all()
        task.opt.step()
        assert all(torch.isfinite(v) for v in losses.values())
    with torch.no_grad():
        task.model.eval()
        after = task.losses(batch)["loss"].item()
    assert after < 0.8 * before, (before, after)
    assert all(torch.isfinite(p).all() for p in task.model.parameters())


def test_resume_is_bit_for_bit(tiny_data, tmp_path):
    cfg = tiny_cfg()
    straight = _trainer(cfg, tiny_data, tmp_path / "a", 12)
    straight.fit()
    first = _trainer(cfg, tiny_data, tmp_path / "b", 5)
    first.fit()
    resumed = _trainer(cfg, tiny_data, tmp_path / "b", 12)  # same folder: resumes at step 5
    resumed.fit()
    assert resumed.step == 12
    a = straight.task.model.state_dict()
    b = resumed.task.model.state_dict()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert (tmp_path / "b" / "metrics.csv").is_file()
    assert (tmp_path / "b" / "checkpoint.pt").is_file()


def test_stage_switch_reinitialises_encoder_and_decoder(tiny_data):
    cfg = tiny_cfg("model.depth_from_step=3")
    task = NSDTask(cfg, tiny_data)
    rng = np.random.default_rng(0)
    task.training_step(0, rng)
    assert task.model.cfg.depth is False
    dec_before = [p.clone() for p in task.model.decoder.parameters()]
    det_before = [p.clone() for p in task.model.detector.parameters()]
    task.training_step(3, rng)
    assert task.model.cfg.depth is True
    assert any(
        not torch.equal(a, b)
        for a, b in zip(dec_before, task.model.decoder.parameters(), strict=True)
    )
    assert all(
        torch.equal(a, b) for a, b in zip(det_before, task.model.detector.parameters(), strict=True)
    )


def test_build_model_rejects_bad_sizes():
    from nsd.core.errors import ConfigError

    cfg = tiny_cfg("model.crop_size=18")
    with pytest.raises(ConfigError, match="divisible"):
        build_model(cfg.model)


def test_association_prior_on_appearance_ignores_the_geometric_term(tiny_data):
    """``prior_association.score=appearance`` pulls on the appearance-only softmax: the
    prior's value does not change with the (detached) ray-distance weight, while the
    ``full`` score, the association used for re-synthesis, does."""

    def prior(score: str, geometry: float) -> float:
        cfg = tiny_cfg(f"prior_association.score={score}", f"model.association_geometry={geometry}")
        torch.manual_seed(0)
        task = NSDTask(cfg, tiny_data)  # computes the proposals the batch carries
        task.model.eval()
        batch = tiny_data.sample(np.random.default_rng(5), 4)
        with torch.no_grad():
            return task.losses(batch)["prior_association"].item()

    assert prior("appearance", 0.0) == pytest.approx(prior("appearance", 5.0), abs=1e-6)
    assert prior("full", 0.0) == pytest.approx(prior("appearance", 0.0), abs=1e-6)
    assert abs(prior("full", 5.0) - prior("full", 0.0)) > 1e-3


def test_association_prior_score_is_validated(tiny_data):
    from nsd.core.errors import ConfigError

    with pytest.raises(ConfigError, match=r"prior_association\.score"):
        NSDTask(tiny_cfg("prior_association.score=geometry"), tiny_data)


def test_same_view_pairs_share_and_default_draws(tiny_scene):
    """data.same_view: that share of the pairs re-synthesises a view from itself; at 0 the
    draws are exactly the Bi-NVS pairs (v != w); out-of-range values are config errors."""
    from nsd.core.errors import ConfigError
    from nsd.io.scene_data import SceneData

    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    a = data.sample(np.random.default_rng(0), 400)
    b = data.sample(np.random.default_rng(0), 400, same_view=0.0)
    assert torch.equal(a.image_v, b.image_v) and torch.equal(a.image_w, b.image_w)
    assert not torch.equal(a.image_v, a.image_w)
    same = data.sample(np.random.default_rng(0), 400, same_view=1.0)
    assert torch.equal(same.image_v, same.image_w)
    eye = torch.eye(3).expand_as(same.rotation_vw)
    torch.testing.assert_close(same.rotation_vw, eye, atol=1e-6, rtol=0)
    half = data.sample(np.random.default_rng(1), 400, same_view=0.5)
    share = (half.image_v == half.image_w).flatten(1).all(1).float().mean().item()
    assert 0.4 < share < 0.6
    with pytest.raises(ConfigError, match="same_view"):
        data.sample(np.random.default_rng(0), 4, same_view=1.5)


def test_hull_mask_prior_trains_the_compositor_masks_towards_the_hull_owners(tiny_data):
    """``prior_mask=hull``: the batch carries the hull's pixel owners, the term is the
    prior of nsd.priors.mask on the rendered composites, and it needs the multi-view hull."""
    from nsd.core.errors import ConfigError
    from nsd.cues.proposals import match_proposals
    from nsd.priors.mask import hull_mask_prior

    torch.manual_seed(0)
    task = NSDTask(tiny_cfg("prior_mask=hull"), tiny_data)
    assert tiny_data.owners is not None and tiny_data.owners.shape[:2] == tiny_data.frames.shape[:2]
    batch = tiny_data.sample(np.random.default_rng(5), 4)
    assert batch.owners_v.shape == batch.image_v.shape[:1] + batch.image_v.shape[-2:]
    task.model.eval()
    with torch.no_grad():
        out = task.losses(batch)
        assert torch.isfinite(out["prior_mask"]) and out["prior_mask"] > 0
        cams = tiny_data.cameras
        rv, rw, wv, ww = task.model(batch.image_v, batch.image_w, batch.background_v,
                                    batch.background_w, batch.rotation_vw,
                                    cams[batch.view_v], cams[batch.view_w])
        boxes = torch.cat([wv.det.boxes, ww.det.boxes])
        valid = torch.cat([batch.valid_v, batch.valid_w])
        matching = match_proposals(boxes, torch.cat([batch.proposals_v, batch.proposals_w]),
                                   valid, None)
        expect = hull_mask_prior(torch.cat([rv.composite.weights, rw.composite.weights]),
                                 torch.cat([batch.owners_v, batch.owners_w]), matching, valid)
    assert out["prior_mask"].item() == pytest.approx(expect.item(), rel=1e-5)
    with pytest.raises(ConfigError, match=r"prior_mask=hull needs prior_proposal\.source"):
        NSDTask(tiny_cfg("prior_mask=hull", "prior_proposal=residual"), tiny_data)


def test_hull_proposals_cluster_by_the_inference_mixture_keys(tiny_data, monkeypatch):
    """Training's hull proposals decide the 3D mixture by ``inference.mixture_*`` (the keys
    nsd-eval and the export read), and a bad value stops the task before any work."""
    from nsd.core.errors import ConfigError
    from nsd.cues.clustering import MixtureRules
    from nsd.io import scene_data

    seen = []

    def recorded(*args, rules=None, **kw):
        seen.append(rules)
        return real(*args, rules=rules, **kw)

    real = scene_data.scene_track
    monkeypatch.setattr(scene_data, "scene_track", recorded)
    NSDTask(tiny_cfg("inference.mixture_gain=inf", "inference.mixture_scene_sample=3"), tiny_data)
    assert seen == [MixtureRules.defaults(mixture_gain=float("inf"), mixture_scene_sample=3)]
    with pytest.raises(ConfigError, match=r"inference\.mixture_scene_sample"):
        NSDTask(tiny_cfg("inference.mixture_scene_sample=0"), tiny_data)
    assert len(seen) == 1


def _one_step(scene, out, caplog, *overrides: str, level: str = "WARNING"
              ) -> tuple[list[str], dict]:
    """What ``nsd.training.train.train`` logs at ``level`` and above (its window count's
    messages included) for one step on ``scene`` with the tiny config and ``overrides``, and
    the checkpoint's config."""
    from nsd.core.trainer import load_checkpoint
    from nsd.training.train import train

    cfg = tiny_cfg(f"data.scene={scene}", "trainer.max_steps=1", "trainer.progress=false",
                   "trainer.checkpoint_every=0", *overrides)
    with caplog.at_level(level, logger="nsd.training"):
        train(cfg, out)
    return ([r.getMessage() for r in caplog.records if r.levelno >= getattr(logging, level)],
            load_checkpoint(out / "checkpoint.pt")["config"])


def _warnings_of_one_step(scene, out, caplog, *overrides: str) -> list[str]:
    return _one_step(scene, out, caplog, *overrides)[0]


def _three_apart(tmp_path, frames: int = 80, individuals: int = 3):
    """Three (``individuals``) walking apart, 4 cameras, 64 x 64, the ground truth removed
    (as footage): the hull shows 3 bodies (nsd.cues.count) when there are 60 frames or more."""
    import shutil

    from nsd.synth import tiny_config, write_scene

    scene = write_scene(tiny_config(
        num_individuals=individuals, num_frames=frames, image_size=[64, 64],
        rig={"kind": "ring", "count": 4, "radius": 4.0, "height": 2.0, "fov_deg": 50.0,
             "start_deg": 30.0},
        motion={"interaction": "free", "area_radius": 1.5}), tmp_path / "scene")
    shutil.rmtree(scene / "gt")
    return scene


@pytest.mark.parametrize(("overrides", "warned"), [
    (["model.num_windows=2"], True),  # a fixed count above the scene's one individual
    (["model.num_windows=1"], False),
    (["model.num_windows=3", "model.detector.presence=true"], False),  # an upper bound
])
def test_a_window_count_other_than_the_declared_individuals_warns_before_training(
        overrides, warned, tmp_path, caplog):
    from nsd.synth import tiny_config, write_scene

    scene = write_scene(tiny_config(num_individuals=1), tmp_path / "scene")
    said = [m for m in _warnings_of_one_step(scene, tmp_path / "run", caplog,
                                             "data.image_size=[48,48]", *overrides)
            if "declares 1 individual " in m]
    assert bool(said) == warned, said
    if warned:
        assert "model.num_windows=2" in said[0] and "set model.num_windows=1" in said[0]


@pytest.mark.parametrize(("windows", "warned"), [(2, True), (3, False)])
def test_footage_whose_hull_shows_more_bodies_than_windows_warns_before_training(
        windows, warned, tmp_path, caplog):
    scene = _three_apart(tmp_path)
    said = [m for m in _warnings_of_one_step(scene, tmp_path / "run", caplog,
                                             "data.image_size=[64,64]", "eval_frames=0",
                                             f"model.num_windows={windows}")
            if "separate bodies" in m]
    assert bool(said) == warned, said
    if warned:
        assert "shows 3 separate bodies" in said[0] and "model.num_windows=2" in said[0]


def test_auto_windows_are_the_individuals_the_scene_declares(tmp_path, caplog):
    """``num_windows=auto`` on a scene of one individual: one window, kept in the checkpoint
    (what export and evaluation build the model from), said where it came from, no warning."""
    from nsd.synth import tiny_config, write_scene

    scene = write_scene(tiny_config(num_individuals=1), tmp_path / "scene")
    said, config = _one_step(scene, tmp_path / "run", caplog, "data.image_size=[48,48]",
                             "model.num_windows=auto", level="INFO")
    assert config["model"]["num_windows"] == 1
    assert any("num_windows=auto: 1, the individuals the scene declares" in m for m in said)
    assert not [m for m in said if "declares 1 individual " in m]  # the count warning


@pytest.mark.parametrize(("frames", "individuals", "windows", "why"), [
    (80, 3, 3, "the visual hull shows 3 separate bodies"),
    (80, 1, 1, "the visual hull shows 1 separate body"),  # one window for one performer
    (40, 3, 2, "too few frames or cameras"),  # too short to count: the default before auto
])
def test_auto_windows_on_footage_are_the_bodies_the_hull_shows(frames, individuals, windows,
                                                                why, tmp_path, caplog):
    scene = _three_apart(tmp_path, frames, individuals)
    said, config = _one_step(scene, tmp_path / "run", caplog, "data.image_size=[64,64]",
                             "eval_frames=0", "model.num_windows=auto", level="INFO")
    assert config["model"]["num_windows"] == windows
    assert any(f"num_windows=auto: {windows}, {why}" in m for m in said), said


def test_a_window_count_that_is_no_count_is_refused_before_training(tiny_data):
    from nsd.core.errors import ConfigError

    for bad in ("some", "0", "true"):
        with pytest.raises(ConfigError, match=r"model\.num_windows must be auto or an integer"):
            NSDTask(tiny_cfg(f"model.num_windows={bad}"), tiny_data)


