"""Re-identification: cross-camera rank-1 / mAP, triplet loss, figures, embeddings, netepu-embed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from netepu.reid.baseline import ReidCNN, batch_hard_triplet_loss
from netepu.reid.figures import separation_figure, tsne_kde_figure
from netepu.texture.embedding import within_class_whitening
from nsd.evaluation.reid import nearest_candidates, pairwise_distances, reid_metrics


def _reference(emb, ids, cams):
    """Slow reference: per query, sklearn's average precision over the cross-camera gallery."""
    from sklearn.metrics import average_precision_score

    hits, aps = [], []
    for q in range(len(ids)):
        g = [i for i in range(len(ids)) if cams[i] != cams[q]]
        d = np.array([1 - emb[q] @ emb[i] / np.linalg.norm(emb[q]) / np.linalg.norm(emb[i])
                      for i in g])  # fmt: skip
        y = np.array([ids[i] == ids[q] for i in g])
        if not y.any():
            continue
        hits.append(y[np.argmin(d)])
        aps.append(average_precision_score(y, -d))
    return float(np.mean(hits)), float(np.mean(aps))


def test_reid_metrics_match_a_slow_reference():
    rng = np.random.default_rng(0)
    ids = rng.integers(0, 5, 80)
    cams = rng.integers(0, 4, 80)
    emb = rng.normal(size=(80, 6)) + 1.5 * np.eye(6)[ids]
    got = reid_metrics(emb, ids, cams, chunk=17)
    r1, mAP = _reference(emb, ids, cams)
    assert got["rank1"] == pytest.approx(r1)
    assert got["map"] == pytest.approx(mAP)
    assert 0.2 < got["rank1"] < 1.0  # the case is neither trivial nor hopeless


def test_reid_metrics_known_values_and_same_camera_exclusion():
    # 1-D embeddings on a circle's arc: cosine distance orders by angle
    ang = np.array([0.0, 0.1, 0.2, 1.0, 1.05])
    emb = np.stack([np.cos(ang), np.sin(ang)], 1)
    ids = np.array([0, 1, 0, 1, 1])
    cams = np.array([0, 0, 1, 1, 0])
    m = reid_metrics(emb, ids, cams)
    # q0 (cam 0): gallery 2 (id 0), 3 (id 1) -> hit, AP 1
    # q1 (cam 0, id 1): gallery 2 (id 0, d .1), 3 (id 1, d .9) -> miss, AP 1/2
    # q2 (cam 1, id 0): gallery 1, 0, 4 -> nearest 1 (id 1) miss; match 0 at rank 2 -> AP 1/2
    # q3 (cam 1, id 1): gallery 4 (.05), 1, 0 -> hit; matches at ranks 1, 2 -> AP 1
    # q4 (cam 0, id 1): gallery 3 (.05), 2 -> hit; AP 1
    assert m["rank1"] == pytest.approx(3 / 5)
    assert m["map"] == pytest.approx((1 + 0.5 + 0.5 + 1 + 1) / 5)
    # a same-camera copy of the query never counts
    m2 = reid_metrics(np.concatenate([emb, emb[:1]]), np.r_[ids, 1], np.r_[cams, 0])
    assert m2["rank1"] == pytest.approx(3 / 5, abs=0.2) and m2["queries"] == 6


def test_queries_without_cross_camera_match_are_skipped():
    m = reid_metrics(np.eye(3), np.array([0, 1, 1]), np.array([0, 1, 2]))
    assert m["queries_without_match"] == 1 and m["queries"] == 2


def test_pairwise_distances():
    a = np.array([[1.0, 0.0], [0.0, 2.0]])
    np.testing.assert_allclose(pairwise_distances(a, a), [[0, 1], [1, 0]], atol=1e-12)
    np.testing.assert_allclose(
        pairwise_distances(a, a, "euclidean"), [[0, np.sqrt(5)], [np.sqrt(5), 0]], atol=1e-7
    )
    with pytest.raises(ValueError, match="metric"):
        pairwise_distances(a, a, "manhattan")


def test_batch_hard_triplet_loss_matches_loops():
    g = torch.Generator().manual_seed(0)
    emb = torch.randn(12, 5, generator=g, dtype=torch.float64)
    ids = torch.tensor([0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3])
    ref = []
    for a in range(12):
        pos = max(float((emb[a] - emb[p]).norm()) for p in range(12) if ids[p] == ids[a])
        neg = min(float((emb[a] - emb[n]).norm()) for n in range(12) if ids[n] != ids[a])
        ref.append(max(0.0, pos - neg + 0.3))
    assert float(batch_hard_triplet_loss(emb, ids, 0.3)) == pytest.approx(np.mean(ref))


def test_baseline_cnn_shapes_and_training_lowers_loss():
    from netepu.reid.baseline import train_reid_baseline

    torch.manual_seed(0)
    model = ReidCNN(3, [8, 16], 1, dims=16)
    x = torch.zeros(30, 4, 16, 16)
    ids = np.repeat(np.arange(3), 10)
    for i in range(3):  # identity = colour of a blob
        x[ids == i, i % 3, 4:12, 4:12] = 1.0
        x[ids == i, 3, 4:12, 4:12] = 1.0
    x += 0.05 * torch.randn_like(x)
    emb, logits = model(x[:4])
    assert emb.shape == (4, 16) and logits.shape == (4, 3)
    out = train_reid_baseline(
        model, lambda idx: x[torch.from_numpy(idx)], ids, steps=60, p_ids=3, k_per_id=4, lr=3e-3
    )
    assert out["steps"] == 60 and out["loss"] < 0.3
    with torch.no_grad():
        e = model(x)[0].numpy()
    assert reid_metrics(e, ids, np.arange(30) % 5)["rank1"] == 1.0


def test_figures_are_written_and_separation_summary(tmp_path):
    rng = np.random.default_rng(0)
    ids = np.repeat(np.arange(4), 30)
    cams = np.tile(np.arange(6), 20)
    emb = rng.normal(size=(120, 8)) * 0.05 + 3 * np.eye(8)[ids]
    tsne_kde_figure(emb, ids, cams >= 4, tmp_path / "tsne.png", "test")
    summary = separation_figure({"a": (emb, ids, cams)}, tmp_path / "sep.png")
    assert (tmp_path / "tsne.png").stat().st_size > 1000
    assert (tmp_path / "sep.png").stat().st_size > 1000
    assert summary["a"]["overlap"] == 0.0 and summary["a"]["margin_min"] > 1.0
    mixed = separation_figure({"b": (rng.normal(size=(120, 8)), ids, cams)}, tmp_path / "s2.png")
    assert mixed["b"]["overlap"] > 0.2


# ----------------------------------------------------------------------------- embeddings
def test_embedding_file_round_trip_with_texture_columns(tmp_path):
    from nsd.io.embeddings import EmbeddingWriter, add_columns, read_embeddings

    rng = np.random.default_rng(0)
    for fmt in ("parquet", "npz"):
        w = EmbeddingWriter(tmp_path / f"emb_{fmt}", format=fmt, row_group_size=7)
        ids = np.arange(20, dtype=np.int64)
        app = rng.normal(size=(20, 5)).astype(np.float32)
        w.write({"id": ids[:12], "app": app[:12]})
        w.write({"id": ids[12:], "app": app[12:]})
        path = w.close()
        tex = rng.normal(size=(20, 8)).astype(np.float32)
        add_columns(path, {"texture": tex, "texture_valid": np.ones(20, bool)})
        back = read_embeddings(path)
        np.testing.assert_array_equal(back["id"], ids)
        np.testing.assert_array_equal(back["app"], app)
        np.testing.assert_array_equal(back["texture"], tex)
        assert back["texture_valid"].all()
        with pytest.raises(ValueError, match="exists already"):
            add_columns(path, {"texture": tex})


def _texture_checkpoint(path, use_nnopcs: bool, reid_colour: bool = False):
    from nsd.core.atomic import atomic_save_torch
    from tests.netepu.texture.test_texture import K_BIPED, TINY_GEOMETRY_DATA, TINY_TEXTURE, _models
    from tests.netepu_world import TINY_MODEL

    tex, geo = _models(use_nnopcs=use_nnopcs, reid_colour=reid_colour)
    g = torch.Generator().manual_seed(1)  # a whitening the embeddings must carry
    d = tex.cfg.reid_dims
    tex.set_reid_whitening(torch.randn(d, generator=g), torch.randn(d, d, generator=g))
    atomic_save_torch({
        "format": "nsd-netepu-checkpoint-v1",
        "modules": {"geometry": geo.state_dict(), "texture": tex.state_dict()},
        "config": {"netepu": {"model": TINY_MODEL,
                              "data": {**TINY_GEOMETRY_DATA, "n_keypoints": K_BIPED},
                              "texture": {"model": {**TINY_TEXTURE, "use_nnopcs": use_nnopcs,
                                                    "reid_colour": reid_colour}}}},
    }, path)  # fmt: skip
    return tex, geo


def _fake_export(folder):
    """An export folder with crops of held-out frames (training-rig cameras) and a table.

    The table's rows are in the reverse order of the crops, and one crop has no keypoints.
    """
    from netepu.texture.data import _rig
    from nsd.cameras.calibration_io import write_toml
    from nsd.io.crops import CropWriter
    from nsd.io.embeddings import EmbeddingWriter
    from nsd.ops.boxes import mask_boxes_xyxy
    from tests.netepu.texture.test_texture import TINY_GEOMETRY_DATA, _tiny_data

    data = _tiny_data()
    h = data.heldout
    rig = _rig(TINY_GEOMETRY_DATA["rig"], tuple(TINY_GEOMETRY_DATA["image_size"]))
    write_toml(rig, folder / "calibration.toml")
    rows = [r for r in range(len(h["psnr_view"])) if h["camera"][h["psnr_view"][r]] < len(rig)]
    assert len(rows) >= 2
    writer = CropWriter(folder / "crops", 24)
    ids, kps = [], []
    for n, r in enumerate(rows):
        v = int(h["psnr_view"][r])
        mask = h["mask"][r]
        b = mask_boxes_xyxy(torch.from_numpy(mask)).tolist()
        writer.add(
            n + 1,
            1,
            rig.names[int(h["camera"][v])],
            0,
            h["colour"][r, 0],
            mask,
            [b[0], b[1], b[2] - b[0], b[3] - b[1]],
            0.1,
        )
        ids.append(n + 1)
        kps.append(h["keypoints"][v])
    writer.close()
    np.savez(folder / "keypoints.npz", id=np.array(ids[:-1]), keypoints=np.stack(kps[:-1]))
    w = EmbeddingWriter(folder / "embeddings")
    order = np.array(ids[::-1], np.int64)
    w.write({"id": order, "app": np.zeros((len(order), 3), np.float32)})
    w.close()
    return rig, ids, kps


@pytest.mark.parametrize(("use_nnopcs", "reid_colour"), [(True, True), (False, False)])
def test_netepu_embed_appends_texture_columns(tmp_path, use_nnopcs, reid_colour):
    from netepu.pipeline.embed import embed_export
    from netepu.texture.encoding import texture_codes
    from nsd.core.errors import ConfigError
    from nsd.io.crops import read_crop_index, read_crops
    from nsd.io.embeddings import read_embeddings

    tex, geo = _texture_checkpoint(tmp_path / "tex.pt", use_nnopcs, reid_colour)
    rig, ids, kps = _fake_export(tmp_path)
    kw = {"keypoints": tmp_path / "keypoints.npz", "calibration": tmp_path} if use_nnopcs else {}
    out = embed_export(tmp_path, tmp_path / "tex.pt", **kw)
    table = read_embeddings(tmp_path)
    assert out["rows"] == len(ids)
    assert set(table) == {"id", "app", "texture", "texture_valid", "texture_reid"}
    index = {r["id"]: r for r in read_crop_index(tmp_path / "crops")}
    enc = ids[:-1] if use_nnopcs else ids  # the last crop has no keypoints
    assert out["encoded"] == len(enc)
    images, masks = read_crops(tmp_path / "crops", enc)
    window = torch.tensor([[index[i]["crop_x"], index[i]["crop_y"], index[i]["crop_side"]]
                           for i in enc], dtype=torch.float64)  # fmt: skip
    cams = rig.stacked(torch.float32)
    ci = torch.tensor([rig.index(index[i]["camera"]) for i in enc])
    mu, rgb, inside, _ = texture_codes(
        tex,
        geo,
        torch.from_numpy(images),
        torch.from_numpy(masks > 0),
        torch.from_numpy(np.stack(kps[: len(enc)])),
        cams[ci],
        window=window,
        return_crops=True,
    )
    expected, reid = mu.numpy(), tex.reid_embedding(mu, rgb, inside).numpy()
    assert reid.shape[1] == tex.cfg.latent + (6 if reid_colour else 0)
    for k, i in enumerate(table["id"]):
        if i in enc:
            np.testing.assert_allclose(table["texture"][k], expected[enc.index(i)], rtol=1e-5,
                                       atol=1e-6)  # fmt: skip
            assert table["texture_valid"][k]
            np.testing.assert_allclose(table["texture_reid"][k], reid[enc.index(i)], rtol=1e-5,
                                       atol=1e-5)  # fmt: skip
        else:
            assert np.isnan(table["texture"][k]).all() and not table["texture_valid"][k]
            assert np.isnan(table["texture_reid"][k]).all()
    with pytest.raises(ValueError, match="exists already"):
        embed_export(tmp_path, tmp_path / "tex.pt", **kw)
    if use_nnopcs:
        with pytest.raises(ConfigError, match="keypoints"):
            embed_export(tmp_path, tmp_path / "tex.pt", column="t2")


def test_nearest_candidates_matches_a_loop_and_respects_the_candidates():
    rng = np.random.default_rng(3)
    emb = rng.normal(size=(23, 5))
    cand = rng.random((23, 23)) < 0.3
    cand[4] = False  # a row without candidates
    got = nearest_candidates(emb, cand, chunk=7)
    d = pairwise_distances(emb, emb)
    for i in range(23):
        js = np.nonzero(cand[i])[0]
        assert got[i] == (js[np.argmin(d[i, js])] if len(js) else -1)
    assert got[4] == -1
    # same-camera exclusion gives reid_metrics' rank-1 (every identity in every camera)
    emb = rng.normal(size=(24, 5))
    ids, cams = np.arange(24) % 4, (np.arange(24) // 4) % 3
    nn = nearest_candidates(emb, cams[:, None] != cams[None])
    assert (nn >= 0).all()
    assert np.isclose((ids[nn] == ids).mean(), reid_metrics(emb, ids, cams)["rank1"])
    with pytest.raises(ValueError, match="candidates must be"):
        nearest_candidates(emb, cand[:5])


# ----------------------------------------------------------------------------- whitening
def test_within_class_whitening_known_values():
    """1-D codes: two identities {-1, 1} and {9, 11}: within-class variance 1, mean 5."""
    x = np.array([[-1.0], [1.0], [9.0], [11.0]])
    y = np.array([0, 0, 1, 1])
    m, p = within_class_whitening(x, y, shrinkage=0.0)
    assert m.tolist() == [5.0] and p.shape == (1, 1) and abs(abs(p[0, 0]) - 1) < 1e-12
    _, p = within_class_whitening(x, y, shrinkage=1.0)  # lambda' = 1 x the mean variance
    assert abs(abs(p[0, 0]) - 1 / np.sqrt(2)) < 1e-12


@pytest.mark.parametrize("shrinkage", [0.0, 0.01, 0.5])
def test_within_class_whitening_whitens_the_within_class_scatter(shrinkage):
    rng = np.random.default_rng(0)
    D, C, n = 6, 4, 200
    mix = rng.normal(size=(D, D)) * np.array([5, 2, 1, 0.5, 0.2, 0.1])  # anisotropic spread
    centres = 10 * rng.normal(size=(C, D))
    y = np.repeat(np.arange(C), n)
    x = centres[y] + rng.normal(size=(C * n, D)) @ mix.T
    m, p = within_class_whitening(x, y, shrinkage)
    np.testing.assert_allclose(m, x.mean(0), atol=1e-12)
    e = (x - m) @ p
    means = np.stack([e[y == c].mean(0) for c in range(C)])
    within = (e - means[y]).T @ (e - means[y]) / len(e)
    scatter = np.cov((x - np.stack([x[y == c].mean(0) for c in range(C)])[y]).T, bias=True)
    lam = shrinkage * np.trace(scatter) / D
    np.testing.assert_allclose(p.T @ (scatter + lam * np.eye(D)) @ p, np.eye(D), atol=1e-9)
    if shrinkage == 0:  # the embedding's within-class scatter is exactly the identity
        np.testing.assert_allclose(within, np.eye(D), atol=1e-9)
    else:  # shrunk: every direction's within-class variance is below 1
        assert np.linalg.eigvalsh(within).max() < 1


def test_within_class_whitening_does_not_depend_on_numpy_blas_threads():
    """The fit is rounded by torch, not by NumPy's BLAS: one or two BLAS threads give the same
    bits (a shipped model's file is reproduced by its recipe on the same torch build)."""
    from threadpoolctl import threadpool_limits

    rng = np.random.default_rng(0)
    x, y = 3 * rng.normal(size=(4096, 134)), rng.integers(0, 16, 4096)
    fits = []
    for threads in (1, 2):
        with threadpool_limits(threads, user_api="blas"):
            fits.append(within_class_whitening(x, y, 0.01))
    assert all(np.array_equal(a, b) for a, b in zip(*fits, strict=True))


def test_within_class_whitening_rejects_bad_input():
    x = np.random.default_rng(0).normal(size=(10, 3))
    with pytest.raises(ValueError, match="2 identities"):
        within_class_whitening(x, np.zeros(10))
    with pytest.raises(ValueError, match="shrinkage"):
        within_class_whitening(x, np.arange(10) % 2, shrinkage=-1)
    bad = x.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        within_class_whitening(bad, np.arange(10) % 2)
    wide = np.random.default_rng(1).normal(size=(4, 8))  # 4 codes cannot span 8 dimensions
    with pytest.raises(ValueError, match="singular"):
        within_class_whitening(wide, np.array([0, 0, 1, 1]), shrinkage=0.0)
    within_class_whitening(wide, np.array([0, 0, 1, 1]), shrinkage=0.01)  # shrinkage fixes it


def test_reid_embedding_is_the_code_until_a_whitening_is_set_and_old_checkpoints_load():
    from tests.netepu.texture.test_texture import _models

    tex, _ = _models()
    mu = torch.randn(5, tex.cfg.latent)
    assert torch.equal(tex.reid_embedding(mu), mu)
    old = {k: v for k, v in tex.state_dict().items() if not k.startswith("reid_")}
    m, p = torch.randn(tex.cfg.latent), torch.randn(tex.cfg.latent, tex.cfg.latent)
    tex.set_reid_whitening(m, p)
    torch.testing.assert_close(tex.reid_embedding(mu), (mu - m) @ p)
    fresh, _ = _models()
    fresh.load_state_dict(tex.state_dict())
    torch.testing.assert_close(fresh.reid_embedding(mu), (mu - m) @ p)
    fresh.load_state_dict(old)  # a checkpoint from before the whitening: the identity again
    assert torch.equal(fresh.reid_embedding(mu), mu)
    with pytest.raises(ValueError, match="shapes"):
        tex.set_reid_whitening(m[:3], p)


def test_colour_statistics_known_values_and_the_mask():
    from netepu.texture.embedding import colour_statistics

    rgb = torch.rand(3, 8, 8, 3, dtype=torch.float64)  # noise outside the masks
    inside = torch.zeros(3, 8, 8, dtype=torch.bool)
    inside[0, :4] = True  # crop 0: a constant colour inside
    rgb[0, :4] = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    inside[1, :, :2] = True  # crop 1: half 0.1, half 0.5 in every channel
    rgb[1, :4, :2], rgb[1, 4:, :2] = 0.1, 0.5
    out = colour_statistics(rgb, inside)  # crop 2: an empty mask
    eps = 1 / 255
    torch.testing.assert_close(out[0, :3], torch.log(torch.tensor([0.2, 0.4, 0.6]) + eps).double())
    torch.testing.assert_close(out[0, 3:], torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(out[1, :3], torch.full((3,), np.log(0.3 + eps), dtype=torch.float64))
    torch.testing.assert_close(out[1, 3:], torch.full((3,), 0.2, dtype=torch.float64))
    torch.testing.assert_close(out[2], torch.tensor([np.log(eps)] * 3 + [0.0] * 3).double())
    # a grey shading factor s moves the log mean by log s (up to eps) and scales the spread
    scaled = colour_statistics(rgb * 0.5, inside)
    torch.testing.assert_close(scaled[1, :3], torch.full((3,), np.log(0.15 + eps)).double())
    torch.testing.assert_close(scaled[1, 3:], out[1, 3:] * 0.5)


def test_select_shrinkage_finds_the_weak_identity_direction_and_breaks_ties_upwards():
    from netepu.texture.embedding import select_shrinkage

    rng = np.random.default_rng(0)
    n = 400
    ids = np.arange(n) % 4
    cams = (np.arange(n) // 4) % 5
    folds = np.arange(n) // 10  # groups of 10 codes; the first 20 groups are fold 0
    # one weak but clean identity direction and three loud directions of pure nuisance
    weak = 0.05 * ids + rng.normal(0, 0.002, n)
    codes = np.column_stack([weak, rng.normal(0, 1, (n, 3))])
    best, scores = select_shrinkage(codes, ids, cams, folds)
    assert best == 1e-4, scores  # less shrinkage lets the weak direction count more
    assert scores[1e-4] > scores[1e-3] > scores[1e-2] > scores[0.1]
    assert scores[1e-4] > 0.8 and scores[0.1] < 0.5
    # every shrinkage separates well-apart identities: the largest wins the tie
    apart = 10.0 * np.eye(4)[ids] + rng.normal(0, 0.1, (n, 4))
    best, scores = select_shrinkage(apart, ids, cams, folds)
    assert best == 0.1 and len(set(scores.values())) == 1
    with pytest.raises(ValueError, match="grid"):
        select_shrinkage(codes, ids, cams, folds, grid=())


def test_reid_colour_reads_the_crop_and_keeps_old_checkpoints():
    from netepu.texture.embedding import colour_statistics
    from tests.netepu.texture.test_texture import _models

    tex, _ = _models(reid_colour=True)
    d = tex.cfg.latent
    assert tex.cfg.reid_dims == d + 6 and tex.reid_projection.shape == (d + 6, d + 6)
    mu = torch.randn(2, d)
    rgb, inside = torch.rand(2, 16, 16, 3), torch.rand(2, 16, 16) > 0.5
    u = tex.reid_embedding(mu, rgb, inside)  # no whitening yet: [mu, statistics]
    torch.testing.assert_close(u, torch.cat([mu, colour_statistics(rgb, inside)], -1))
    x = tex.encoder_input(rgb * inside[..., None], inside, torch.rand(2, 16, 16, 3))
    r2, i2 = tex.crop_colours(x)  # what the stage reads back from an encoder input
    torch.testing.assert_close(tex.reid_input(mu, r2, i2), u)
    with pytest.raises(ValueError, match="colour statistics"):
        tex.reid_embedding(mu)
    plain, _ = _models()  # models without the setting: the code, of d_z numbers
    assert plain.cfg.reid_dims == d and torch.equal(plain.reid_embedding(mu, rgb, inside), mu)
