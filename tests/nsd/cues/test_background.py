"""Backgrounds when subjects linger (nsd.cues.background), their cache, report and warning."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from nsd.core.errors import FootageError
from nsd.cues.background import (
    _densest,
    _likeness,
    _step,
    _subject_likeness,
    _two_colours,
    estimate_background,
)
from nsd.io.background_report import write_background_report
from nsd.io.footage import MultiViewFootage
from nsd.io.scene_check import check_scene

H = W = 64
N = 50
TOL = 24


def _floor(seed: int = 0) -> np.ndarray:
    """A checkered, noisy floor (H, W, 3) uint8."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:H, :W]
    floor = np.stack([100 + 30 * (((yy // 8) + (xx // 8)) % 2)] * 3, -1)
    return np.clip(floor + rng.integers(-5, 6, floor.shape), 0, 255).astype(np.uint8)


def _recording(stay: range | None, walkers: bool = True, seed: int = 0):
    """N frames of the floor with a red subject standing in a box during ``stay`` and
    walkers of random colours crossing; returns (stack, floor, subject mask)."""
    rng = np.random.default_rng(seed)
    floor = _floor(seed)
    yy, xx = np.mgrid[:H, :W]
    subject = (abs(yy - 30) < 10) & (abs(xx - 20) < 6)
    stack = np.repeat(floor[None], N, 0).copy()
    for t in stay or ():
        stack[t][subject] = (200, 60, 40)
    if walkers:
        for t in range(N):
            walk = (abs(yy - 50) < 6) & (abs(xx - int(t * W / N)) < 4)
            stack[t][walk] = rng.integers(0, 255, 3)
    stack = np.clip(stack.astype(int) + rng.integers(-3, 4, stack.shape), 0, 255)
    return stack.astype(np.uint8), floor, subject


def _wrong(image: np.ndarray, floor: np.ndarray) -> np.ndarray:
    return np.abs(image.astype(int) - floor).max(-1) > TOL


@pytest.mark.parametrize("stay", [range(0, 35), range(15, 50), range(8, 44)],
                         ids=["left", "came", "came and left"])
def test_a_subject_that_stayed_most_of_the_time_is_replaced_by_the_floor(stay):
    stack, floor, subject = _recording(stay)
    median = estimate_background(stack, "median")
    assert _wrong(median.image, floor).sum() == subject.sum()  # the median holds it
    assert not median.replaced.any()
    if stay.start == 0 or stay.stop == N:  # the clear cases are reported by either method
        assert (median.uncertain == subject).all()
    modes = estimate_background(stack, "modes")
    assert not _wrong(modes.image, floor).any()
    assert (modes.uncertain == subject).all() and (modes.replaced == subject).all()
    assert (modes.stayed == subject).all()
    assert modes.uncertain_share == modes.stayed_share == pytest.approx(subject.mean())


def test_a_swaying_subject_leaves_no_trace_at_its_edge():
    """The subject leans into the column next to it from frame 10 until it leaves (frame
    35), lit in two shades: there the floor is the most frequent colour (frames 0-9 and
    35-49) and one shade of the subject a second one. Each pixel's second colour would
    paint the subject there; the frames the subject was away give the floor everywhere."""
    stack, floor, subject = _recording(range(0, 35))
    yy, xx = np.mgrid[:H, :W]
    edge = (abs(yy - 30) < 10) & (xx == 26)
    for t in range(10, 35):
        stack[t][edge] = (200, 60, 40) if t % 2 else (140, 100, 70)
    est = estimate_background(stack, "modes")
    assert not _wrong(est.image, floor).any()
    assert est.replaced[subject].all() and not est.replaced[~(subject | edge)].any()


def test_subject_likeness_tells_passing_colours_from_the_floor():
    """Colours seen only where a pixel does not show its usual colour (the walkers) are
    subject-like (above 0), the floor's usual colours background-like (below 0)."""
    stack, floor, _ = _recording(None)
    median = np.median(stack, axis=0).round().astype(np.uint8)
    first, _, _, _, _, shows = _two_colours(stack, median)
    table = _subject_likeness(stack, first, shows)
    walkers = stack[~shows]
    floor_like = _likeness(floor.reshape(-1, 3), table)
    assert np.median(floor_like) < -5 and (floor_like < 0).mean() > 0.95
    passing = _likeness(walkers, table)
    far = np.abs(walkers.astype(int) - 115).max(-1) > 40  # colours unlike any floor's
    assert far.sum() > 100 and (passing[far] > 0).all()


def test_a_subject_lit_in_changing_shades_is_found_pixel_by_pixel():
    """It stays for frames 0-34 lit in two shades, one frame each, then walks off to the
    right: no colour holds 70 % of the stay, so there is no stretch, and the median is a
    shade of it. Its shades are seen as it walks, the floor's grey is the background's:
    pixel by pixel, the floor (15 frames, ``MIN_SECOND_SHARE``). A few pixels stay: the
    histograms' bins are 16 grey levels wide, and a floor grey on a bin's edge (95 where
    the floor is mostly 100 +- 5) is rare in the background's histogram, so not
    background-like by ``MARGIN``."""
    stack, floor, subject = _recording(range(0, 35))
    yy, xx = np.mgrid[:H, :W]
    for t in range(35):
        stack[t][subject] = (200, 60, 40) if t % 2 else (150, 40, 90)
    for t in range(35, 40):
        walk = (abs(yy - 30) < 10) & (abs(xx - (32 + 6 * (t - 35))) < 6)
        stack[t][walk] = (200, 60, 40) if t % 2 else (150, 40, 90)
    assert _wrong(estimate_background(stack, "median").image, floor)[subject].all()
    est = estimate_background(stack, "modes")
    wrong = _wrong(est.image, floor)
    assert wrong[subject].mean() < 0.02 and not wrong[~subject].any()
    assert (est.replaced == subject & ~wrong).all() and est.uncertain[subject].all()
    # a subject that never leaves keeps its shades: no floor colour to take
    stack, floor, subject = _recording(range(0, N))
    for t in range(N):
        stack[t][subject] = (200, 60, 40) if t % 2 else (150, 40, 90)
    assert _wrong(estimate_background(stack, "modes").image, floor)[subject].all()


def test_large_frames_are_analysed_smaller_and_upsampled():
    """A 64 x 64 recording analysed at 32 x 32: the same subject found and replaced by the
    floor (its colour from the working size), the floor elsewhere the native median."""
    stack, floor, subject = _recording(range(0, 35))
    est = estimate_background(stack, "modes", max_pixels=32 * 32)
    assert est.image.shape == floor.shape and est.uncertain.shape == subject.shape
    inner = cv2.erode(subject.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert est.replaced[inner].all() and not est.replaced[~cv2.dilate(
        subject.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)].any()
    assert _wrong(est.image, floor).mean() < 0.01  # the checker's edges blur a little
    median = estimate_background(stack, "median")
    assert np.array_equal(est.image[~est.replaced], median.image[~est.replaced])


def test_a_working_size_rounded_past_the_limit_is_analysed_once():
    """20 x 26 frames for 400 pixels: the working size rounds to 18 x 23 = 414 > 400 (a
    1080 x 1920 camera does the same at the default limit); it must not shrink again and
    again (it recursed until memory ran out)."""
    stack = np.random.default_rng(0).integers(0, 255, (5, 20, 26, 3)).astype(np.uint8)
    est = estimate_background(stack, "modes", max_pixels=400)
    assert est.image.shape == (20, 26, 3) and est.samples == 5


def test_walkers_alone_leave_nothing_uncertain():
    stack, floor, _ = _recording(None)
    est = estimate_background(stack, "modes")
    assert not est.uncertain.any() and not _wrong(est.image, floor).any()


def test_a_short_stay_is_reported_and_the_floor_kept():
    stack, floor, subject = _recording(range(0, 12))  # 24 % of the frames, then it left
    est = estimate_background(stack, "modes")
    assert not _wrong(est.image, floor).any()
    assert (est.uncertain == subject).all() and not est.replaced.any()
    assert not est.stayed.any()  # the floor kept beside a short stay: nothing to warn about
    median = estimate_background(stack, "median")
    assert (median.stayed == subject).all()  # the median cannot tell: every clear stay
    # a stay in the middle is no step: the floor before and after, nothing to report
    stack, floor, _ = _recording(range(20, 32))
    est = estimate_background(stack, "modes")
    assert not _wrong(est.image, floor).any() and not est.uncertain.any()


def test_a_pixel_occupied_in_every_frame_by_others_is_reported():
    """A crowded spot: someone different stands there in every frame (random colours), so
    no colour holds half of the frames: uncertain, whatever the estimate."""
    stack, _, subject = _recording(None, walkers=False)
    rng = np.random.default_rng(5)
    for t in range(N):
        stack[t][subject] = rng.integers(0, 255, 3)
    for method in ("median", "modes"):
        est = estimate_background(stack, method)
        assert (est.uncertain == subject).all()
        assert not est.stayed.any()  # nothing stayed there: no stretch of one colour


def test_a_subject_that_never_moves_cannot_be_found():
    """The limit, said in the docs: one stable colour, the subject's; only a plate helps."""
    stack, floor, subject = _recording(range(N))
    est = estimate_background(stack, "modes")
    assert _wrong(est.image, floor).sum() == subject.sum() and not est.uncertain.any()


def test_step_finds_the_split_and_the_other_part():
    members = np.array([[1] * 35 + [0, 1] + [0] * 13, [1, 0] * 25]).T.astype(bool)  # (N, 2)
    found, part = _step(members, 8)
    assert found.tolist() == [True, False]
    # the purest split is after frame 36 (36 of 37 before, 13 of 13 after)
    assert part[:, 0].nonzero()[0].tolist() == list(range(37, 50))
    assert not part[:, 1].any()


def test_unknown_method_is_refused():
    with pytest.raises(ValueError, match=r"background method must be one of \('median', 'modes'\)"):
        estimate_background(np.zeros((3, 2, 2, 3), np.uint8), "mean")


def _scene(tiny_scene, stay: range):
    """The tiny scene's two cameras (32 x 24) showing the lingering recording, N frames."""
    shutil.rmtree(tiny_scene / ".cache", ignore_errors=True)  # caches of the fixture's frames
    for cam in ("left", "right"):
        shutil.rmtree(tiny_scene / cam)
        (tiny_scene / cam).mkdir()
        stack, _, _ = _recording(stay, seed=1 if cam == "left" else 2)
        for t, frame in enumerate(stack):
            small = cv2.resize(frame, (32, 24), interpolation=cv2.INTER_NEAREST)
            cv2.imwrite(str(tiny_scene / cam / f"{t:06d}.png"), cv2.cvtColor(small,
                                                                             cv2.COLOR_RGB2BGR))
    return tiny_scene


def test_estimates_are_cached_with_their_masks(tiny_scene):
    scene = _scene(tiny_scene, range(0, 35))
    first = MultiViewFootage(scene, background="modes").background_estimate(0)
    again = MultiViewFootage(scene, background="modes").background_estimate(0)  # from disk
    assert len(list((scene / ".cache" / "background").glob("left.*.uncertain.png"))) == 1
    assert np.array_equal(first.image, again.image)
    assert np.array_equal(first.uncertain, again.uncertain) and first.uncertain.any()
    assert np.array_equal(first.replaced, again.replaced) and first.replaced.any()
    assert np.array_equal(first.stayed, again.stayed) and first.stayed.any()
    median = MultiViewFootage(scene, background="median").background_estimate(0)
    assert not median.replaced.any()  # another method, another cache entry


def test_the_cameras_estimated_side_by_side_are_those_estimated_one_by_one(tiny_scene):
    """background_estimates with two worker processes gives every camera what
    background_estimate gives it alone, and caches them; a frame that cannot be read stops it
    with the camera and the file named, as it does in this process."""
    scene = _scene(tiny_scene, range(0, 35))
    both = MultiViewFootage(scene, background="modes").background_estimates(workers=2)
    assert len(list((scene / ".cache" / "background").glob("*.uncertain.png"))) == 2
    shutil.rmtree(scene / ".cache")
    for v, est in enumerate(both):
        alone = MultiViewFootage(scene, background="modes").background_estimate(v)
        for part in ("image", "uncertain", "replaced", "stayed"):
            assert np.array_equal(getattr(est, part), getattr(alone, part)), (v, part)
    assert both[0].replaced.any() and both[1].replaced.any()
    shutil.rmtree(scene / ".cache")
    bad = sorted((scene / "right").glob("*.png"))[7]
    bad.write_bytes(b"not a png")
    with pytest.raises(FootageError, match=f"camera 'right'.*{bad.name}"):
        MultiViewFootage(scene, background="modes").background_estimates(workers=2)


def test_a_run_on_one_thread_estimates_the_cameras_in_its_own_process(tiny_scene,
                                                                      monkeypatch):
    """threads=1 (check_scene's workers) forks no process; workers=2 uses the pool."""
    import nsd.io.footage as footage_module

    made = []

    class Recorded(footage_module.BatchPool):
        def __init__(self, *args, **kwargs):
            made.append(args[1])
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(footage_module, "BatchPool", Recorded)
    scene = _scene(tiny_scene, range(0, 35))
    check_scene(scene, background="modes", workers=1)
    assert made == []
    shutil.rmtree(scene / ".cache")
    check_scene(scene, background="modes", workers=2)
    assert made == [2]


def test_scene_check_warns_by_camera_and_the_report_is_written(tiny_scene, tmp_path):
    scene = _scene(tiny_scene, range(0, 35))
    check = check_scene(scene, background="modes")
    lingering = [w for w in check.warnings if "stayed in place" in w]
    assert len(lingering) == 2 and "camera 'left'" in lingering[0]
    assert "background plate" in lingering[0] and str(scene / "background" / "left") in lingering[0]
    assert check.background["left"]["stayed"] > 0.03
    assert check.background["left"]["uncertain"] >= check.background["left"]["stayed"]
    report = write_background_report(check.estimates, check.plates, tmp_path / "bg", "modes")
    assert json.loads((tmp_path / "bg" / "report.json").read_text()) == report
    assert report["cameras"]["left"]["replaced"] == pytest.approx(
        report["cameras"]["left"]["uncertain"])
    img = cv2.imread(str(tmp_path / "bg" / "left.uncertain.png"))
    assert img.shape == (24, 32, 3)
    # a plate ends the warning for its camera
    (scene / "background").mkdir()
    cv2.imwrite(str(scene / "background" / "left.png"), cv2.cvtColor(
        cv2.resize(_floor(1), (32, 24), interpolation=cv2.INTER_NEAREST), cv2.COLOR_RGB2BGR))
    check = check_scene(scene, background="modes")
    lingering = [w for w in check.warnings if "stayed in place" in w]
    assert len(lingering) == 1 and lingering[0].startswith("camera 'right'")
    assert "left" not in check.background


def test_a_crowded_spot_is_reported_but_not_warned_about(tiny_scene, tmp_path):
    """Subjects passing a spot in every frame (no colour holds half of them) leave it
    uncertain in the report, but nothing stayed there: no warning (the built-in scene's
    interaction area, docs/benchmarks/background.md)."""
    scene = _scene(tiny_scene, range(0))
    for cam in ("left", "right"):
        rng = np.random.default_rng(3)
        for f in sorted((scene / cam).glob("*.png")):
            img = cv2.imread(str(f))
            img[8:16, 6:14] = rng.integers(0, 255, 3)  # someone else there in every frame
            cv2.imwrite(str(f), img)
    check = check_scene(scene, background="modes")
    assert check.background["left"]["uncertain"] > 0.05
    assert check.background["left"]["stayed"] == 0
    assert not [w for w in check.warnings if "background" in w], check.warnings
    report = write_background_report(check.estimates, check.plates, tmp_path / "bg", "modes")
    img = cv2.cvtColor(cv2.imread(str(tmp_path / "bg" / "left.uncertain.png")),
                       cv2.COLOR_BGR2RGB)
    assert (img[10, 10] == (60, 120, 255)).all() and report["cameras"]["left"]["stayed"] == 0


def _densest_slowly(samples: np.ndarray, allowed: np.ndarray):
    """_densest pixel by pixel, frame by frame: the allowed frame with the most allowed frames
    within the tolerance on every channel (the first on a tie), its members and their
    median."""
    N, K = allowed.shape
    colour, support, members = np.full((K, 3), np.nan), np.zeros(K, int), np.zeros((N, K), bool)
    for k in range(K):
        near = [[bool(allowed[i, k] and allowed[j, k]
                      and np.abs(samples[i, k] - samples[j, k]).max() <= TOL)
                 for j in range(N)] for i in range(N)]
        best = int(np.argmax([sum(row) for row in near]))
        members[:, k] = near[best]
        support[k] = sum(near[best])
        if support[k]:
            colour[k] = np.median(samples[members[:, k], k], axis=0)
    return colour, support, members


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_densest_colour_matches_a_slow_reference(seed):
    """The vectorised densest colour (a channel at a time, medians by sorting) gives what a
    loop over pixels and frame pairs gives: members, support and colour, also for pixels
    without allowed frames (NaN) and an even number of members (the middle two averaged)."""
    rng = np.random.default_rng(seed)
    n, k = 12 + seed, 40
    samples = rng.integers(0, 256, (n, k, 3))
    steady = rng.random(k) < 0.6  # a stable colour with noise around it
    samples[:, steady] = samples[:1, steady] + rng.integers(-30, 31, (n, int(steady.sum()), 3))
    samples = np.clip(samples, 0, 255).astype(np.int16)
    allowed = rng.random((n, k)) < 0.7
    allowed[:, 0] = False  # a pixel with no allowed frame
    colour, support, members = _densest(samples, allowed)
    ref_colour, ref_support, ref_members = _densest_slowly(samples, allowed)
    np.testing.assert_array_equal(members, ref_members)
    np.testing.assert_array_equal(support, ref_support)
    np.testing.assert_array_equal(colour, ref_colour)  # NaN where equal NaN
    assert np.isnan(colour[0]).all() and (support % 2 == 0).any() and (support > 2).any()
