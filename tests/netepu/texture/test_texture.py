"""NeTePu texture VAE: KLD, reparameterisation, crops, masking, codes, data, training, stage."""

from __future__ import annotations

import functools
import tempfile

import numpy as np
import pytest
import torch

from netepu.geometry.model import build_geometry_model
from netepu.texture.config import TextureConfig
from netepu.texture.crops import crop_grid, crop_windows, query_masked, sample_masked
from netepu.texture.encoding import encode_texture, surface_normals, texture_codes
from netepu.texture.losses import code_contrast_loss, kld, reparameterise, texture_loss
from netepu.texture.model import build_texture_model
from tests.netepu_world import TINY_MODEL

K_BIPED, R_BIPED = 17, 0.9
TINY_TEXTURE_SIZES = {
    "latent": 8, "features": 8, "crop_size": 16, "widths": [8, 16], "blocks_per_stage": 1,
    "dense_hidden": 32, "decoder_hidden": 32,
    "renderer": {"width": 16, "n_blocks_2d": 1, "k_2d": 4, "k": 6, "n_freq": 3, "hidden": 8,
                 "groups": 4, "head_hidden": 16, "head_blocks": 1},
}  # fmt: skip
# a whole netepu.texture.model section: the sizes above, NeTePu's encoder inputs otherwise
TINY_TEXTURE = {**TINY_TEXTURE_SIZES, "use_nnopcs": True, "use_normals": False,
                "local_features": True, "renderer_geometry": True, "crop_margin": 0.1,
                "reid_colour": False}  # fmt: skip
TINY_GEOMETRY_DATA = {
    "species": "biped", "radius": R_BIPED, "image_size": [64, 48], "train_poses": 2,
    "rig": {"kind": "ring", "rings": [{"count": 3, "radius": 5.0, "height": 1.5}]},
    "heldout_rig": {"kind": "ring",
                    "rings": [{"count": 2, "radius": 4.5, "height": 2.0, "start_deg": 30}]},
    "margin": 0.35,
}  # fmt: skip


def _models(seed: int = 0, **texture):
    torch.manual_seed(seed)
    geo = build_geometry_model(TINY_MODEL, K_BIPED, R_BIPED).eval()
    tex = build_texture_model({**TINY_TEXTURE, **texture}, geo).eval()
    return tex, geo


# the tiny texture data's caches, removed when the test session's interpreter exits
_SCRATCH = tempfile.TemporaryDirectory(prefix="netepu-texture-")


@functools.cache
def _tiny_data(textures: tuple[int, ...] = (0, 2), poses: int = 2, per_view: int = 2):
    from netepu.texture.data import build_texture_data

    cache = tempfile.mkdtemp(dir=_SCRATCH.name)
    return build_texture_data(
        {"textures": list(textures), "train_poses": poses, "textures_per_view": per_view,
         "eval_poses": 2, "psnr_cameras": 1, "pool": 200, "cache_dir": cache},
        TINY_GEOMETRY_DATA, 16, 0.1)  # fmt: skip


def _frame_batch(data, n: int = 3):
    """Full-frame-like inputs from the held-out set: image, mask, keypoints, camera."""
    h = data.heldout
    v = h["psnr_view"][:n]
    mask = torch.from_numpy(h["mask"][: len(v)])
    image = torch.from_numpy(h["colour"][: len(v), 0])
    return image, mask, torch.from_numpy(h["keypoints"][v]), data.heldout_camera_tensors(v)


# ----------------------------------------------------------------------------- KLD, sampling
def test_kld_matches_closed_form_of_torch_distributions():
    g = torch.Generator().manual_seed(0)
    mu = torch.randn(5, 7, generator=g, dtype=torch.float64)
    logvar = torch.randn(5, 7, generator=g, dtype=torch.float64)
    q = torch.distributions.Normal(mu, torch.exp(0.5 * logvar))
    p = torch.distributions.Normal(torch.zeros_like(mu), torch.ones_like(mu))
    expected = torch.distributions.kl_divergence(q, p).sum(-1).mean()
    torch.testing.assert_close(kld(mu, logvar), expected)
    assert float(kld(torch.zeros(3, 4), torch.zeros(3, 4))) == 0.0


def test_kld_gradient_float64():
    mu = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    lv = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(kld, (mu, lv))


def test_reparameterise_moments_and_given_noise():
    mu, logvar = torch.tensor([[1.0, -2.0]]), torch.tensor([[0.0, float(np.log(4.0))]])
    torch.testing.assert_close(
        reparameterise(mu, logvar, torch.tensor([[1.0, 1.0]])), torch.tensor([[2.0, 0.0]])
    )
    torch.manual_seed(0)
    z = reparameterise(mu.expand(20000, 2), logvar.expand(20000, 2))
    torch.testing.assert_close(z.mean(0), mu[0], atol=0.05, rtol=0)
    torch.testing.assert_close(z.var(0), torch.tensor([1.0, 4.0]), atol=0.1, rtol=0)


def test_texture_loss_weights():
    c, t = torch.zeros(2, 4, 3), torch.full((2, 4, 3), 0.5)
    mu, lv = torch.ones(2, 3), torch.zeros(2, 3)
    out = texture_loss(c, t, mu, lv, 5.0, 0.1)
    assert float(out["colour"]) == pytest.approx(0.25)
    assert float(out["kld"]) == pytest.approx(1.5)
    assert float(out["loss"]) == pytest.approx(5 * 0.25 + 0.1 * 1.5)


# ----------------------------------------------------------------------------- crops
def test_crop_windows_and_grid_known_values():
    mask = torch.zeros(1, 20, 30, dtype=torch.bool)
    mask[0, 5:15, 10:14] = True  # box x 10..14, y 5..15 (edges): w 4, h 10
    w = crop_windows(mask, 0.1)
    torch.testing.assert_close(w, torch.tensor([[12 - 6.0, 10 - 6.0, 12.0]], dtype=torch.float64))
    g = crop_grid(w, 4)  # 4 pixels of side 3: centres at x0 + 1.5 + 3 i - 0.5
    torch.testing.assert_close(g[0, 0, :, 0], torch.tensor([7.0, 10, 13, 16], dtype=torch.float64))
    torch.testing.assert_close(g[0, :, 0, 1], torch.tensor([5.0, 8, 11, 14], dtype=torch.float64))
    with pytest.raises(ValueError, match="empty visible masks at batch items \\[1\\]"):
        crop_windows(torch.cat([mask, torch.zeros_like(mask)]), 0.1)


def test_whole_frame_windows_cover_the_image_wherever_the_mask_is():
    # crop_margin None (NeTePu's encoder input): one square of side max(H, W), centred
    mask = torch.zeros(2, 20, 30, dtype=torch.bool)
    mask[0, 5:15, 10:14] = True
    mask[1, 0:2, 27:30] = True  # a corner: the same window
    w = crop_windows(mask, None)
    torch.testing.assert_close(w, torch.tensor([[0.0, -5.0, 30.0]] * 2, dtype=torch.float64))
    g = crop_grid(w, 30)  # one grid pixel per image pixel: the image's own pixel centres
    torch.testing.assert_close(g[0, 5:25, :, 0], torch.arange(30.0).double().expand(20, 30))
    torch.testing.assert_close(g[0, 5:25, 0, 1], torch.arange(20.0).double())
    img = torch.rand(2, 20, 30, 3, generator=torch.Generator().manual_seed(0))
    crop, inside = sample_masked(img, mask, g)
    assert torch.equal(inside[:, 5:25], mask) and not inside[:, :5].any()
    torch.testing.assert_close(crop[:, 5:25][mask], img[mask])
    with pytest.raises(ValueError, match="empty visible masks at batch items \\[0\\]"):
        crop_windows(torch.zeros_like(mask[:1]), None)


def test_crop_margin_accepts_null_and_names_a_bad_value():
    from netepu.texture.config import TextureConfig
    from nsd.core.errors import ConfigError

    assert TextureConfig.defaults(crop_margin=None).crop_margin is None
    for bad in (-0.1, "wide", True):
        with pytest.raises(ConfigError, match="crop_margin"):
            TextureConfig.defaults(crop_margin=bad)

def test_sample_masked_reads_only_mask_pixels():
    g = torch.Generator().manual_seed(1)
    img = torch.rand(2, 12, 10, 3, generator=g)
    mask = torch.rand(2, 12, 10, generator=g) > 0.5
    grid = torch.rand(2, 6, 6, 2, generator=g, dtype=torch.float64) * 11 - 0.5
    a, ia = sample_masked(img, mask, grid)
    other = torch.where(mask[..., None], img, torch.rand(2, 12, 10, 3, generator=g) * 100)
    b, ib = sample_masked(other, mask, grid)
    assert torch.equal(ia, ib) and ia.any()
    torch.testing.assert_close(a, b)
    # a constant colour inside the mask is reproduced exactly wherever a sample is inside
    const, inside = sample_masked(torch.full_like(img, 0.3), mask, grid)
    torch.testing.assert_close(const[inside], torch.full_like(const[inside], 0.3))
    assert (const[~inside] == 0).all()


def test_query_masked_equals_full_query_on_kept_points():
    g = torch.Generator().manual_seed(2)
    uv = torch.rand(3, 50, 2, generator=g)
    keep = torch.rand(3, 50, generator=g) > 0.6
    keep[1] = False  # an item without kept points

    def f(q):
        return torch.stack([q.sum(-1), q[..., 0] * 2, q[..., 1] ** 2], -1)

    out = query_masked(f, uv, keep)
    torch.testing.assert_close(out[keep], f(uv)[keep])
    assert (out[~keep] == 0).all()


# ----------------------------------------------------------------------------- codes
@pytest.mark.parametrize("normals", [False, True])
def test_codes_ignore_pixels_outside_the_mask_and_are_deterministic(normals):
    data = _tiny_data()
    tex, geo = _models(use_normals=normals)
    assert tex.encoder.stem[0].in_channels == (10 if normals else 7)
    image, mask, kps, cam = _frame_batch(data)
    mu = texture_codes(tex, geo, image, mask, kps, cam)
    assert mu.shape == (len(mask), tex.cfg.latent) and torch.isfinite(mu).all()
    noise = torch.randint(0, 256, image.shape, dtype=torch.uint8)
    garbled = torch.where(mask[..., None], image, noise)
    torch.testing.assert_close(texture_codes(tex, geo, garbled, mask, kps, cam), mu, rtol=0, atol=0)
    # deterministic (mu, eval-mode batch norm) and independent of the rest of the batch
    torch.testing.assert_close(texture_codes(tex, geo, image, mask, kps, cam), mu, rtol=0, atol=0)
    one = texture_codes(
        tex, geo, image[1:2], mask[1:2], kps[1:2], cam[1:2]
    )
    torch.testing.assert_close(one, mu[1:2], rtol=1e-5, atol=1e-6)
    # pixels inside the mask do change the code
    brighter = torch.where(mask[..., None], (image.float() * 0.5).to(torch.uint8), image)
    assert (texture_codes(tex, geo, brighter, mask, kps, cam) - mu).abs().max() > 1e-4


def test_encode_texture_ignores_nnopcs_outside_mask_and_rgb_only_needs_no_geometry():
    data = _tiny_data()
    tex, _ = _models()
    image, mask, _, _ = _frame_batch(data)
    nn = torch.rand(*mask.shape, 3)
    mu = encode_texture(tex, image, mask, nn)
    nn2 = torch.where(mask[..., None], nn, torch.rand_like(nn))
    torch.testing.assert_close(encode_texture(tex, image, mask, nn2), mu, rtol=0, atol=0)
    with pytest.raises(ValueError, match="NNOPCS"):
        encode_texture(tex, image, mask, None)
    rgb_only, _ = _models(use_nnopcs=False)
    assert rgb_only.encoder.stem[0].in_channels == 4
    assert texture_codes(rgb_only, None, image, mask, None, None).shape == (len(mask), 8)


def test_codes_of_a_crop_with_its_window_equal_codes_of_the_frame():
    """A crop cut at native scale, with its window, must give the frame's code (NNOPCS too)."""
    data = _tiny_data()
    tex, geo = _models()
    image, mask, kps, cam = _frame_batch(data)
    full = texture_codes(tex, geo, image, mask, kps, cam)
    side = 40
    crops, cmasks, windows = [], [], []
    for b in range(len(mask)):
        ys, xs = torch.nonzero(mask[b], as_tuple=True)
        x0, y0 = int(xs.min()) - 3, int(ys.min()) - 2
        pad_img = torch.zeros(side, side, 3, dtype=image.dtype)
        pad_mask = torch.zeros(side, side, dtype=torch.bool)
        H, W = mask.shape[1:]
        sy, sx = slice(max(y0, 0), min(y0 + side, H)), slice(max(x0, 0), min(x0 + side, W))
        ty = slice(sy.start - y0, sy.stop - y0)
        tx = slice(sx.start - x0, sx.stop - x0)
        pad_img[ty, tx], pad_mask[ty, tx] = image[b, sy, sx], mask[b, sy, sx]
        assert pad_mask.sum() == mask[b].sum()
        crops.append(pad_img)
        cmasks.append(pad_mask)
        windows.append([x0, y0, side])
    got = texture_codes(
        tex,
        geo,
        torch.stack(crops),
        torch.stack(cmasks),
        kps,
        cam,
        window=torch.tensor(windows, dtype=torch.float64),
    )
    torch.testing.assert_close(got, full, rtol=1e-4, atol=1e-5)


# ----------------------------------------------------------------------------- data
def test_shaded_texture_equals_the_synthetic_renderer():
    from netepu.texture.data import shade_texture
    from nsd.synth import make_individual, render_views, ring_rig

    ind = make_individual("biped", texture_id=9, proportion_variation=0.0)
    r = render_views([ind], [ind.rest_pose()], ring_rig(3, size=(40, 30)), background=False)
    m = r["visible"][:, 0]
    ours = shade_texture(9, r["nnopcs"][m], r["normal"][m])
    torch.testing.assert_close(ours, r["rgb"][m], rtol=0, atol=1e-6)


def test_texture_data_is_balanced_and_consistent():
    data = _tiny_data()
    tr = data.train
    counts = np.bincount(tr["sample_texture"], minlength=2)
    assert counts.min() > 0 and counts.max() - counts.min() <= 2
    assert len(tr["sample_view"]) == 2 * len(tr["camera"])
    # the crops' masks are the views' masks: a crop is black outside its mask
    rgb = tr["rgb"][tr["sample_view"] == 0]
    assert (rgb[:, ~tr["inside"][0]] == 0).all() and rgb[:, tr["inside"][0]].max() > 0
    h = data.heldout
    assert h["rgb"].shape[:2] == (len(h["pose"]), 2)
    assert h["heldout_camera"].any() and (~h["heldout_camera"]).any()


# ----------------------------------------------------------------------------- training
def _task(textures=(0, 2), per_view=2, **optim):
    from netepu.texture.data import predicted_nnopcs_crops
    from netepu.texture.stage import TextureStageConfig, TextureTask

    data = _tiny_data(textures, 2, per_view)
    tex, geo = _models()
    tr, h = data.train, data.heldout
    cams = data.train_camera[torch.from_numpy(tr["camera"])]
    nn_tr = predicted_nnopcs_crops(geo, tr["keypoints"], cams, tr["window"], tr["inside"])
    nn_h = predicted_nnopcs_crops(
        geo,
        h["keypoints"],
        data.heldout_camera_tensors(np.arange(len(h["pose"]))),
        h["window"],
        h["inside"],
    )
    # NeTePu's recipe (no cross-view sources, no contrast, no whitening) unless ``optim`` says
    cfg = TextureStageConfig.defaults(
        **{"batch_size": 6, "points": 100, "lr": 3e-3, "occlusion": 0.0, "eval_views": 2,
           "cross_view": 0.0, "contrast_weight": 0.0, "reid_whitening_samples": 0,
           "reid_shrinkage": 0.01, **optim}
    )
    return TextureTask(tex, geo, data, cfg, nn_tr, nn_h)


@pytest.mark.slow
def test_tiny_model_overfits_one_individuals_views(tmp_path):
    """One individual (texture 6), its training views: the colour error falls far below start."""
    from nsd.core.trainer import Trainer, TrainerConfig, seed_everything

    seed_everything(0)
    task = _task(textures=(6,), per_view=1, batch_size=4, points=64)
    rng = np.random.default_rng(0)
    with torch.no_grad():
        task.texture.train()
        start = float(np.mean([task.training_step(0, rng)["colour"] for _ in range(3)]))
    out = tmp_path
    Trainer(
        task,
        TrainerConfig.defaults(max_steps=200, progress=False, log_every=0, checkpoint_every=0),
        out,
    ).fit()
    with torch.no_grad():
        end = float(np.mean([task.training_step(0, rng)["colour"] for _ in range(5)]))
    assert end < 0.25 * start, (start, end)
    assert 10 * np.log10(1 / end) > 17  # dB on the training views' in-mask points


def test_geometry_stays_frozen_and_only_texture_is_optimised():
    task = _task()
    before = {k: v.clone() for k, v in task.geometry.state_dict().items()}
    rng = np.random.default_rng(1)
    for _ in range(2):
        task.opt.zero_grad()
        task.training_step(0, rng)["loss"].backward()
        task.opt.step()
    assert all(torch.equal(before[k], v) for k, v in task.geometry.state_dict().items())
    assert all(p.grad is None for p in task.geometry.parameters())
    params = {id(p) for g in task.opt.param_groups for p in g["params"]}
    assert params == {id(p) for p in task.texture.parameters()}


def test_occlusion_keeps_a_quarter_and_only_removes_pixels():
    from netepu.texture.stage import occlude

    inside = torch.zeros(50, 16, 16, dtype=torch.bool)
    inside[:, 2:14, 4:12] = True
    out = occlude(inside, np.random.default_rng(0), 1.0)
    assert not (out & ~inside).any()
    assert (out.flatten(1).sum(1) >= inside.flatten(1).sum(1) // 4).all()
    assert (out != inside).any()
    assert torch.equal(occlude(inside, np.random.default_rng(0), 0.0), inside)


@pytest.mark.parametrize("local_features", [True, False])
@pytest.mark.parametrize("renderer_geometry", [True, False])
def test_texture_code_reaches_the_colour(local_features, renderer_geometry):
    """The code always reaches the colour; the geometry's features and code only when the
    renderer reads them (``renderer_geometry: false`` is NeTePu's code: texture only)."""
    tex, geo = _models(local_features=local_features, renderer_geometry=renderer_geometry)
    data = _tiny_data()
    h = data.heldout
    kps = torch.from_numpy(h["keypoints"][:2])
    cam = data.heldout_camera_tensors(np.arange(2))
    code = geo.encode(kps)
    uv = torch.rand(2, 30, 2) * 20 + 20
    z = torch.randn(2, tex.cfg.latent)
    a = tex.query(tex.prepare(z, code.z, code.features, kps, cam), uv)
    b = tex.query(tex.prepare(z + 1, code.z, code.features, kps, cam), uv)
    assert a.shape == (2, 30, 3) and (a - b).abs().max() > 1e-4
    assert (tex.decoder is not None) == local_features
    c = tex.query(tex.prepare(z, code.z + 1, code.features + 1, kps, cam), uv)
    assert ((a - c).abs().max() > 1e-4) == renderer_geometry


def test_netepu_train_texture_stage_end_to_end(tmp_path):
    """netepu-train stage=texture on a tiny geometry checkpoint; load; resume does no work."""
    from hydra import compose, initialize_config_module

    from netepu.cli.train import run
    from netepu.texture.model import load_texture_model
    from nsd.core.atomic import atomic_save_torch

    _, geo = _models()
    data = {**TINY_GEOMETRY_DATA, "n_keypoints": K_BIPED}
    atomic_save_torch({"format": "nsd-netepu-checkpoint-v1",
                       "modules": {"geometry": geo.state_dict()},
                       "config": {"netepu": {"model": TINY_MODEL, "data": data}}},
                      tmp_path / "geo.pt")  # fmt: skip
    sizes = TINY_TEXTURE_SIZES
    m = {f"netepu.texture.model.{k}": v for k, v in sizes.items() if k != "renderer"}
    m |= {f"netepu.texture.model.renderer.{k}": v for k, v in sizes["renderer"].items()}
    ov = [f"{k}={v}".replace(" ", "") for k, v in m.items()] + [
        "stage=texture", f"init_from={tmp_path / 'geo.pt'}", "trainer.max_steps=3",
        "trainer.progress=false", "netepu.texture.data.textures=[0,2]",
        "netepu.texture.data.train_poses=2", "netepu.texture.data.textures_per_view=2",
        "netepu.texture.data.eval_poses=2", "netepu.texture.data.psnr_cameras=1",
        "netepu.texture.data.pool=200", f"netepu.texture.data.cache_dir={tmp_path / 'cache'}",
        "netepu.texture.optim.batch_size=4", "netepu.texture.optim.points=20"]  # fmt: skip
    with initialize_config_module("nsd.conf", version_base="1.3"):
        cfg = compose("netepu_train", overrides=ov)
    metrics = run(cfg, tmp_path / "run")
    for k in ("heldout_poses/psnr_reconstruction", "heldout_cameras/psnr_novel", "reid/rank1"):
        assert np.isfinite(metrics[k])
    _, geo2, config = load_texture_model(tmp_path / "run" / "checkpoint.pt")
    assert config["netepu"]["data"]["species"] == "biped"
    assert torch.equal(
        geo2.state_dict()["renderer.down.weight"], geo.state_dict()["renderer.down.weight"]
    )
    assert sorted((tmp_path / "run" / "grids").glob("texture_heldout_cameras_*.png"))
    # the final checkpoint holds the re-id whitening, fitted on the trained model's codes
    from netepu.texture.embedding import within_class_whitening
    from netepu.texture.stage import build_texture_stage

    tex2 = load_texture_model(tmp_path / "run" / "checkpoint.pt")[0]
    assert tex2.cfg.reid_colour and tex2.cfg.reid_dims == tex2.cfg.latent + 6  # the default
    assert not torch.equal(tex2.reid_projection, torch.eye(tex2.cfg.reid_dims))
    with initialize_config_module("nsd.conf", version_base="1.3"):
        task, _ = build_texture_stage(compose("netepu_train", overrides=ov))
    task.texture.load_state_dict(tex2.state_dict())
    codes, ids, cams, views = task.training_reid_inputs(task.cfg.reid_whitening_samples)
    assert len(np.unique(ids)) == 2 and codes.shape[1] == tex2.cfg.reid_dims
    assert cams.shape == views.shape == ids.shape
    # reid_shrinkage=auto: the whitening of these inputs at one of the candidate shrinkages
    fits = [within_class_whitening(codes, ids, s) for s in (0.1, 0.01, 0.001, 0.0001)]
    assert any(
        np.allclose(tex2.reid_mean.numpy(), m, atol=1e-5)
        and np.allclose(tex2.reid_projection.numpy(), p, rtol=1e-4, atol=1e-4)
        for m, p in fits
    )
    # refitting a finished checkpoint without the colour statistics: the code's whitening
    from netepu.texture.stage import add_reid_whitening
    from nsd.core.errors import ConfigError

    ckpt = tmp_path / "run" / "checkpoint.pt"
    before = ckpt.read_bytes()
    with pytest.raises(ConfigError, match="reid_shrinkage"):
        add_reid_whitening(ckpt, 64, "often")
    assert ckpt.read_bytes() == before  # a bad value writes nothing
    fit = add_reid_whitening(ckpt, 64, 0.01, colour=False)
    assert fit["colour"] is False and fit["shrinkage"] == 0.01
    tex3 = load_texture_model(ckpt)[0]
    assert tex3.cfg.reid_dims == tex3.cfg.latent and not tex3.cfg.reid_colour
    for k, v in tex2.state_dict().items():  # the weights are kept
        if not k.startswith("reid_"):
            assert torch.equal(tex3.state_dict()[k], v), k
    with initialize_config_module("nsd.conf", version_base="1.3"):
        task, _ = build_texture_stage(
            compose("netepu_train", overrides=[*ov, "netepu.texture.model.reid_colour=false"])
        )
    task.texture.load_state_dict(tex3.state_dict())
    codes, ids, _, _ = task.training_reid_inputs(64)
    m, p = within_class_whitening(codes, ids, 0.01)
    torch.testing.assert_close(tex3.reid_mean, torch.from_numpy(m).float())
    torch.testing.assert_close(tex3.reid_projection, torch.from_numpy(p).float())
    # the same cache with other crops (size, normals): the predicted crops are not reused
    for extra in (["netepu.texture.model.crop_size=24"], ["netepu.texture.model.use_normals=true"]):
        with initialize_config_module("nsd.conf", version_base="1.3"):
            task, _ = build_texture_stage(compose("netepu_train", overrides=ov + extra))
        S, C = task.texture.cfg.crop_size, task.texture.cfg.surface_channels
        assert task.nnopcs_train.shape[1:] == (S, S, C)
        assert task.nnopcs_heldout.shape[1:] == (S, S, C)
    # a finished run's task, and the same views with textures it never saw
    from netepu.texture.stage import load_texture_task

    task, state = load_texture_task(ckpt)
    assert list(task.data.textures) == [0, 2] and state["step"] == 3
    for k, v in tex3.state_dict().items():
        assert torch.equal(task.texture.state_dict()[k], v), k
    unseen, _ = load_texture_task(ckpt, first_texture=100)
    assert list(unseen.data.textures) == [100, 101]
    h, u = task.data.heldout, unseen.data.heldout
    assert np.array_equal(h["keypoints"], u["keypoints"])
    assert np.array_equal(h["camera"], u["camera"])
    assert not np.array_equal(h["rgb"], u["rgb"])


def test_texture_config_rejects_unknown_keys():
    from nsd.core.errors import ConfigError

    with pytest.raises(ConfigError, match="unknown keys \\['colour'\\]"):
        TextureConfig.defaults(colour=1)


def test_cross_view_sources_keep_the_texture_and_change_the_view():
    task = _task(textures=(0, 2), per_view=2, cross_view=1.0)
    tr = task.data.train
    idx = np.arange(len(tr["sample_view"]))
    src = task.cross_view_sources(idx, np.random.default_rng(0))
    assert (tr["sample_texture"][src] == tr["sample_texture"][idx]).all()
    assert (src != idx).mean() > 0.5
    task.cfg.cross_view = 0.0
    assert (task.cross_view_sources(idx, np.random.default_rng(0)) == idx).all()


def test_code_contrast_loss_known_values_and_limits():
    tau = 0.5
    eye = torch.eye(2, dtype=torch.bool)
    mu = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    # orthogonal unit codes, each matching only its partner: log(1 + e^(-1/tau))
    expect = np.log1p(np.exp(-1 / tau))
    assert abs(float(code_contrast_loss(mu, mu, eye, tau)) - expect) < 1e-12
    # invariant to the codes' length (cosine similarity)
    assert abs(float(code_contrast_loss(5 * mu, 0.1 * mu, eye, tau)) - expect) < 1e-12
    # every partner positive: nothing to separate, zero loss
    assert abs(float(code_contrast_loss(mu, mu, torch.ones(2, 2, dtype=torch.bool), tau))) < 1e-12
    # swapped partners are the worst case: log(1 + e^(1/tau))
    swapped = code_contrast_loss(mu, mu.flip(0), eye, tau)
    assert abs(float(swapped) - np.log1p(np.exp(1 / tau))) < 1e-12
    with pytest.raises(ValueError, match="temperature"):
        code_contrast_loss(mu, mu, eye, 0.0)


def test_code_contrast_loss_gradient_float64():
    g = torch.Generator().manual_seed(0)
    mu = torch.randn(5, 4, dtype=torch.float64, generator=g, requires_grad=True)
    partner = torch.randn(5, 4, dtype=torch.float64, generator=g, requires_grad=True)
    tex = torch.tensor([0, 1, 0, 2, 1])
    same = tex[:, None] == tex[None]
    assert torch.autograd.gradcheck(lambda a, b: code_contrast_loss(a, b, same, 0.2), (mu, partner))


def test_contrastive_step_pairs_views_of_one_texture_and_trains_the_encoder():
    task = _task(textures=(0, 2), per_view=2, contrast_weight=1.0)
    rng = np.random.default_rng(0)
    tr = task.data.train
    idx = np.arange(len(tr["sample_view"]))
    partner = task.partners(idx, rng)
    assert (tr["sample_texture"][partner] == tr["sample_texture"][idx]).all()
    terms = task.training_step(0, rng)
    assert torch.isfinite(terms["contrast"]) and terms["contrast"] > 0
    terms["loss"].backward()
    grads = [p.grad for p in task.texture.encoder.parameters() if p.grad is not None]
    assert grads and any(float(g.abs().sum()) > 0 for g in grads)


def test_contrast_settings_are_checked():
    from netepu.texture.stage import TextureStageConfig
    from nsd.core.errors import ConfigError

    with pytest.raises(ConfigError, match="contrast_temperature"):
        TextureStageConfig.defaults(contrast_temperature=0.0)


def test_texture_batches_hold_every_texture_of_the_pool():
    """batch_sampling=textures: a batch of >= T samples holds every texture, each
    texture at most ceil(B / T) times; random batches miss some."""
    task = _task(textures=(0, 2, 5), per_view=2, batch_sampling="textures", batch_size=7)
    tex = task.data.train["sample_texture"]
    rng = np.random.default_rng(0)
    for _ in range(20):
        counts = np.bincount(tex[task.batch_samples(rng)], minlength=3)  # pool indices
        assert counts.sum() == 7 and counts.min() >= 2 and counts.max() == 3
    task.cfg.batch_sampling, task.cfg.batch_size = "random", 3
    missed = [len(set(tex[task.batch_samples(rng)])) < 3 for _ in range(50)]
    assert any(missed)


def test_batch_sampling_is_checked():
    from netepu.texture.stage import TextureStageConfig
    from nsd.core.errors import ConfigError

    with pytest.raises(ConfigError, match=r"batch_sampling.*'identity'"):
        TextureStageConfig.defaults(batch_sampling="identity")


# ----------------------------------------------------------------------------- normals
def _rotation(axis, angle):
    from scipy.spatial.transform import Rotation

    return torch.from_numpy(Rotation.from_rotvec(np.asarray(axis) * angle).as_matrix())


def test_surface_normals_of_a_tilted_plane_in_the_world():
    """Depth of the plane n_c . X = d seen by a pinhole camera: every inside pixel gets
    R^T n_c (facing the camera), pixels outside or without tangents get 0."""
    S = 9
    K = torch.tensor([[80.0, 0, 40], [0, 90.0, 30], [0, 0, 1]], dtype=torch.float64)
    R = _rotation([0.3, 1.0, -0.2], 0.8)
    n_c = torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64)
    n_c = n_c / n_c.norm()
    d = -4.0  # n_c . X = d with X in front of the camera
    ys, xs = torch.meshgrid(
        torch.arange(S, dtype=torch.float64), torch.arange(S, dtype=torch.float64), indexing="ij"
    )
    uv = torch.stack([20 + 2.5 * xs, 10 + 2.5 * ys], -1)  # a crop grid with 2.5-pixel steps
    rays = torch.einsum(
        "ij,hwj->hwi",
        torch.linalg.inv(K),
        torch.cat([uv, torch.ones(S, S, 1, dtype=torch.float64)], -1),
    )
    depth = d / (rays @ n_c)
    inside = torch.ones(S, S, dtype=torch.bool)
    inside[0, 0] = inside[4, :] = False
    inside[7, 3] = True
    inside[8, :] = False
    inside[8, 5] = True  # an isolated pixel: no row neighbour inside
    got = surface_normals(depth[None], uv[None], inside[None], K[None], R[None])[0]
    expect = R.T @ n_c
    has = inside.clone()
    has[8, 5] = False
    torch.testing.assert_close(got[has], expect.expand(int(has.sum()), 3), rtol=0, atol=1e-9)
    assert (got[~has] == 0).all()


def test_surface_normals_of_a_sphere_are_radial():
    """Camera-facing points of a sphere: the normal is (X - c) / r (up to O(step) error)."""
    S, r = 33, 1.0
    c = torch.tensor([0.1, -0.05, 5.0], dtype=torch.float64)
    K = torch.tensor([[200.0, 0, 32], [0, 200.0, 32], [0, 0, 1]], dtype=torch.float64)
    ys, xs = torch.meshgrid(
        torch.arange(S, dtype=torch.float64), torch.arange(S, dtype=torch.float64), indexing="ij"
    )
    uv = torch.stack([16 + xs, 16 + ys], -1)
    rays = torch.einsum(
        "ij,hwj->hwi",
        torch.linalg.inv(K),
        torch.cat([uv, torch.ones(S, S, 1, dtype=torch.float64)], -1),
    )
    # nearest intersection of X = Z ray (ray's z = 1) with |X - c| = r
    a, b, cc = (rays * rays).sum(-1), -2 * (rays @ c), c @ c - r * r
    disc = b * b - 4 * a * cc
    inside = disc > 1e-3
    Z = (-b - disc.clamp_min(0).sqrt()) / (2 * a)
    R = torch.eye(3, dtype=torch.float64)
    got = surface_normals(Z[None], uv[None], inside[None], K[None], R[None])[0]
    X = rays * Z[..., None]
    expect = (X - c) / r
    ok = (got.norm(dim=-1) > 0) & inside
    ok[1:-1, 1:-1] &= inside[:-2, 1:-1] & inside[2:, 1:-1] & inside[1:-1, :-2] & inside[1:-1, 2:]
    err = (got[ok] - expect[ok]).norm(dim=-1)
    assert ok.sum() > 200 and float(err.median()) < 0.02


def test_normals_need_the_nnopcs_encoder():
    from nsd.core.errors import ConfigError

    with pytest.raises(ConfigError, match="use_normals needs use_nnopcs"):
        TextureConfig.defaults(use_normals=True, use_nnopcs=False)
