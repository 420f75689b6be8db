"""A camera's background from its footage when subjects linger: two stable colours per pixel.

The temporal median of a pixel is its background when the pixel shows the background in
most frames. A subject that stays in place for most of the recording (an animal asleep
in a corner, a person at a bench) turns that around: the median holds the subject, and
the background shows only in the frames before it came or after it left. Such a pixel
has **two stable colours** over time, in a telling order: its most frequent colour (the
densest cluster of its frames' colours) holds for one stretch of the recording, and
another colour holds most of the frames outside the stretch. Subjects walking past give
no such pattern: the colours they leave on a pixel are short and scattered.

Which of the two is the background is decided by **what subjects look like**. The
recording itself shows it: wherever a pixel does not show its usual colour, a subject is
passing (the lingering one too, when it walks). The *subject-likeness* of a colour is
log p(colour | a subject passing) - log p(colour | the background), two colour histograms
of the camera (``BINS`` bins a channel) over its steady pixels (those showing their usual
colour in all but ``MIN_SECOND_SHARE`` of the frames): one of the colours of the frames
that differ from the usual one, one of the usual colours. A region of pixels with two
stable colours (8-connected) holds a subject in its first colour when, summed over its
pixels, the first colour is more subject-like than the second.
(Deciding by continuity with the surroundings, the background continuing the floor
around the region, was the earlier rule: a subject whose clothes resemble the floor
breaks into many small regions, and each small region's border is too short to tell.)

The region's background is then, at each of its pixels and those within ``BORDER`` of
it, the densest colour of the frames in which the subject was away (the frames most of
the region's pixels do not show their first colour), or the second densest where that is
more background-like by ``MARGIN``: rather than each pixel's own second
colour, which at the region's edge, where a swaying subject shows only part of the time
and the floor is the first colour, would be the subject's; a pixel keeps its first colour
where that is the more background-like by ``MARGIN``.

Last, **pixel by pixel**: where a pixel's colour is still subject-like (likeness above 0)
and another stable colour holds ``MIN_SECOND_SHARE`` of its frames without forming a
stretch (a subject that sways or is lit in changing shades while it stays, so that no
colour holds ``STEP_PURITY`` of the stretch), the pixel takes that colour when it is
background-like (likeness below 0) by ``MARGIN`` more than its own. (A share as low as
6 % recovered more of a subject that stays 85 % of the time, but painted passing
subjects' colours into scenes where nobody lingers.)

Reported as uncertain (the scene check and the background report,
:mod:`nsd.io.background_report`, tell a user per camera, with the advice to give a
background plate): the pixels whose colour was changed, those left with a subject-like
colour beside another stable one, the clear cases of a stretch kept (from the start or to
the end of the recording, the other colour holding ``STEP_PURITY`` of the rest), and
those where no colour holds half of the frames.
A subject that never moves in the whole recording leaves a single stable colour, its own:
nothing label-free finds it, and only a plate helps.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "BACKGROUND_METHODS",
    "BackgroundEstimate",
    "estimate_background",
]

BACKGROUND_METHODS = ("median", "modes")  # the `data.background` values
MODE_TOLERANCE = 24  # grey levels (largest over the channels): a sample belongs to a colour
MIN_SECOND_SHARE = 0.15  # the stretch and the rest each span at least this share of frames
STEP_PURITY = 0.7  # the stretch shows the first colour in this share of its frames at least
MIN_OTHER = 0.4  # the second colour holds this share of the other part's frames at least
BORDER = 3  # pixels around a replaced region that take the subject-free frames' colour
MAX_PIXELS = 512 * 512  # larger frames are analysed at about this size (then upsampled)
BINS = 16  # colour histogram bins a channel of the subject-likeness
MARGIN = 1.0  # nats of subject-likeness a pixel's colour change must gain
EPS = 1e-4  # added to the histograms' probabilities


@dataclass
class BackgroundEstimate:
    """One camera's background and what is known of it.

    Attributes:
        image: the background, (H, W, 3) uint8 RGB.
        uncertain: (H, W) bool, the reported pixels: the colour changed, a subject-like
            colour or a clear stay kept, or no colour in half of the frames (see the
            module docstring).
        replaced: (H, W) bool, where another colour was taken instead of the first.
        samples: how many frames the estimate read.
        stayed: (H, W) bool, where something stayed for a stretch of the recording and the
            estimate may hold it or replaced it: the pixels replaced, and the clear stays
            kept (a stretch from the start or to the end, another colour in the rest) whose
            kept colour is subject-like (``modes``; with ``median`` every clear stay). The
            other uncertain pixels (no colour in half of the frames; a subject-like colour
            beside another that forms no stretch; the floor kept beside a subject that stood
            at the start or the end) are where subjects pass or stood: there the estimate
            was right on the synthetic scenes measured (docs/benchmarks/background.md).
    """

    image: np.ndarray
    uncertain: np.ndarray
    replaced: np.ndarray
    samples: int
    stayed: np.ndarray

    @property
    def uncertain_share(self) -> float:
        """The share of the image with two stable colours."""
        return float(self.uncertain.mean()) if self.uncertain.size else 0.0

    @property
    def stayed_share(self) -> float:
        """The share of the image where something stayed for a stretch (``stayed``)."""
        return float(self.stayed.mean()) if self.stayed.size else 0.0


def _need(n_frames: int) -> int:
    """Frames a stable colour must hold: ``MIN_SECOND_SHARE`` of them, at least 2."""
    return max(2, int(np.ceil(MIN_SECOND_SHARE * n_frames)))


def _as_colour(colour: np.ndarray) -> np.ndarray:
    """A :func:`_densest` colour (float, NaN without members) as uint8."""
    return np.clip(np.nan_to_num(colour), 0, 255).round().astype(np.uint8)


def _densest(samples: np.ndarray, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The densest colour of each pixel among its allowed frames.

    Args:
        samples: (N, K, 3) int16 colours of K pixels; allowed: (N, K) bool.

    Returns:
        colour (K, 3) float (the median of its members, NaN without any), support (K,)
        and members (N, K) bool: the frames within ``MODE_TOLERANCE`` of the frame that
        has the most allowed frames within it.
    """
    close = allowed[:, None] & allowed[None]  # (N, N, K)
    # a channel at a time into two reused buffers: 30-40x faster than the largest absolute
    # difference over the channels of an (N, N, K, 3) table (which gives the same)
    diff, near = np.empty(close.shape, np.int16), np.empty(close.shape, bool)
    for channel in np.moveaxis(samples.astype(np.int16, copy=False), -1, 0):
        channel = np.ascontiguousarray(channel)
        np.subtract(channel[:, None], channel[None], out=diff)
        np.less_equal(np.abs(diff, out=diff), MODE_TOLERANCE, out=near)
        close &= near
    density = close.sum(1)  # (N, K)
    best = density.argmax(0)
    k = np.arange(samples.shape[1])
    members = close[best, :, k].T  # (N, K)
    support = members.sum(0)
    # the median of the members: non-members sorted last, the middle one or two averaged
    ordered = np.sort(np.where(members[..., None], samples, np.inf), axis=0)  # (N, K, 3)
    lo = np.clip((support - 1) // 2, 0, None)[None, :, None]
    hi = np.clip(support // 2, 0, len(samples) - 1)[None, :, None]
    colour = (np.take_along_axis(ordered, lo, 0)[0] + np.take_along_axis(ordered, hi, 0)[0]) / 2
    colour[support == 0] = np.nan  # pixels without allowed frames: never used
    return colour, support, members


def _step(
    members: np.ndarray, need: int, ends_only: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Where a pixel's most frequent colour holds for one stretch of the recording and not
    outside it: a subject that came, stayed and left (the stretch may start or end the
    recording).

    Args:
        members: (N, K) bool, the frames (in time order) showing the pixel's first colour.
        need: frames the stretch and the rest must each span.
        ends_only: the stretch starts or ends the recording (a subject that was there
            from the start, or stayed to the end).

    Returns:
        (K,) bool, a stretch was found (it and the rest each at least ``STEP_PURITY`` pure),
        and (N, K) bool, the frames outside it that do not show the first colour.
    """
    N, K = members.shape
    cums = np.concatenate([np.zeros((1, K), np.int64), np.cumsum(members, 0)])  # (N + 1, K)
    a, b = np.triu_indices(N + 1, 1)  # the stretch [a, b)
    keep = ((b - a) >= need) & ((N - (b - a)) >= need)
    if ends_only:
        keep &= (a == 0) | (b == N)
    a, b = a[keep], b[keep]
    if not len(a):
        return np.zeros(K, bool), np.zeros_like(members)
    inside = cums[b] - cums[a]  # (S, K) first-colour frames in the stretch
    length = (b - a)[:, None]
    outside_other = (N - length) - (cums[-1][None] - inside)
    purity = np.minimum(inside / length, outside_other / (N - length))
    best = purity.argmax(0)
    k = np.arange(K)
    found = purity[best, k] >= STEP_PURITY
    t = np.arange(N)[:, None]
    outside = (t < a[best][None]) | (t >= b[best][None])
    return found, outside & ~members & found[None]


def _two_colours(stack: np.ndarray, median: np.ndarray) -> tuple[np.ndarray, ...]:
    """Each pixel's most frequent colour and, where it holds for one stretch of the
    recording and another stable colour for most of the rest (a subject came, stayed,
    left), the other one.

    Returns:
        first, second: (H, W, 3) uint8 colours (the median where there is none);
        step: (H, W) bool, the pixels with such a second colour (candidates);
        stay: (H, W) bool, the clear cases that are reported: the stretch starts or ends
            the recording and the other colour holds ``STEP_PURITY`` of the rest;
        no_majority: (H, W) bool, no colour holds half of the frames;
        shows_first: (N, H, W) bool, the frames showing each pixel's first colour (all
            frames where the median is the one colour).
    """
    N = stack.shape[0]
    need = _need(N)
    first, second = median.copy(), median.copy()
    step = np.zeros(median.shape[:2], bool)
    stay = np.zeros(median.shape[:2], bool)
    no_majority = np.zeros(median.shape[:2], bool)
    off = np.abs(stack.astype(np.int16) - median.astype(np.int16)).max(-1) > MODE_TOLERANCE
    shows_first = ~off
    ys, xs = np.nonzero(off.sum(0) >= need)  # elsewhere the median is the one colour
    chunk = max(1, 2_000_000 // (N * N))  # bounds the (N, N, K) neighbour table
    for s in range(0, len(ys), chunk):
        y, x = ys[s : s + chunk], xs[s : s + chunk]
        samples = stack[:, y, x].astype(np.int16)  # (N, K, 3)
        c1, n1, m1 = _densest(samples, np.ones(samples.shape[:2], bool))
        has1 = n1 >= need
        shows_first[:, y, x] = m1
        first[y[has1], x[has1]] = np.round(c1[has1]).astype(np.uint8)
        no_majority[y, x] = n1 < N / 2
        found, part = _step(m1, need)
        c2, n2, _ = _densest(samples, part)  # the other part's stable colour
        # the other colour: most of the rest (a subject walking off passes there too)
        ok = found & has1 & (n2 >= np.maximum(3, MIN_OTHER * part.sum(0)))
        second[y[ok], x[ok]] = np.round(c2[ok]).astype(np.uint8)
        # reported: a stay from the start or to the end, the other colour holding the rest
        found, part = _step(m1, need, ends_only=True)
        _, n2, _ = _densest(samples, part)
        sure = found & has1 & (n2 >= np.maximum(need, STEP_PURITY * part.sum(0)))
        step[y[ok], x[ok]] = True
        stay[y[sure], x[sure]] = True
    return first, second, step, stay, no_majority, shows_first


def _bins(colours: np.ndarray) -> np.ndarray:
    """Histogram bin of each colour: (..., 3) uint8 -> (...) int."""
    q = colours.astype(np.int64) * BINS // 256
    return (q[..., 0] * BINS + q[..., 1]) * BINS + q[..., 2]


def _histogram(colours: np.ndarray) -> np.ndarray:
    """(M, 3) uint8 colours -> (BINS**3,) probabilities (zeros without colours)."""
    counts = np.bincount(_bins(colours).ravel(), minlength=BINS**3).astype(np.float64)
    return counts / max(counts.sum(), 1.0)


def _subject_likeness(stack: np.ndarray, first: np.ndarray,
                      shows_first: np.ndarray) -> np.ndarray:
    """The subject-likeness of each histogram bin (see the module docstring).

    Args:
        stack: (N, H, W, 3) uint8 frames; first: (H, W, 3) each pixel's usual colour;
        shows_first: (N, H, W) bool, the frames showing it. Only the steady pixels count
        (another colour in fewer than ``MIN_SECOND_SHARE`` of the frames).

    Returns:
        (BINS**3,) float: log p(bin | a subject passing) - log p(bin | the background).
    """
    need = _need(stack.shape[0])
    steady = (~shows_first).sum(0) < need
    passing = ~shows_first & steady[None]
    return (np.log(_histogram(stack[passing]) + EPS)
            - np.log(_histogram(first[steady]) + EPS))


def _likeness(colours: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Subject-likeness of colours: (..., 3) uint8 -> (...) float."""
    return table[_bins(colours)]


def _appearance_choice(first: np.ndarray, second: np.ndarray, two: np.ndarray,
                       table: np.ndarray) -> np.ndarray:
    """The regions of ``two`` (pixels with two stable colours, 8-connected) whose first
    colour is, summed over the region, more subject-like than the second: (H, W) bool."""
    n, labels = cv2.connectedComponents(two.astype(np.uint8), connectivity=8)
    score = _likeness(first, table) - _likeness(second, table)
    switch = np.bincount(labels.ravel(), weights=score.ravel(), minlength=n) > 0
    switch[0] = False
    return switch[labels]


def _vacated(stack: np.ndarray, first: np.ndarray, shows_first: np.ndarray,
             switched: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The background of each region whose first colour was found to be a subject: at
    each of its pixels (and of those within ``BORDER`` of it) the densest colour of the
    frames the subject was away, or their second densest (seen in two frames at least)
    where that is more background-like by ``MARGIN`` (the subject walking off, or swaying,
    still covers the pixel in many of those frames), unless the pixel's first colour is
    more background-like by ``MARGIN``.

    The subject's presence is the region's vote: the frames in which most of its pixels
    show their first colour. Taking the free frames' colour, rather than each pixel's
    second colour, also gets right the pixels at the region's edge (where the floor is
    the first colour and the subject, swaying, the second) and those with no majority.

    Returns:
        the background (H, W, 3) uint8 and the replaced pixels (H, W) bool: the regions and
        the pixels around them whose colour changed.
    """
    N = stack.shape[0]
    need = _need(N)
    image = first.copy()
    regions, reached = np.zeros(first.shape[:2], bool), np.zeros(first.shape[:2], bool)
    n, labels = cv2.connectedComponents(switched.astype(np.uint8), connectivity=8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * BORDER + 1, 2 * BORDER + 1))
    for r in range(1, n):
        region = labels == r
        present = shows_first[:, region].mean(1) > 0.5  # (N,) the subject is there
        free = np.flatnonzero(~present)
        if len(free) < need:
            continue
        reach = cv2.dilate(region.astype(np.uint8), kernel) > 0
        samples = stack[:, reach].astype(np.int16)  # (N, K, 3)
        allowed = np.zeros(samples.shape[:2], bool)
        allowed[free] = True
        colour, _, members = _densest(samples, allowed)
        other, support, _ = _densest(samples, allowed & ~members)  # the free frames' second
        colour, other = _as_colour(colour), _as_colour(other)
        better = (support >= 2) & (_likeness(other, table) < _likeness(colour, table) - MARGIN)
        image[reach] = np.where(better[:, None], other, colour)
        regions |= region
        reached |= reach
    keep = _likeness(first, table) < _likeness(image, table) - MARGIN  # the first is floor
    image[keep] = first[keep]
    changed = np.abs(image.astype(np.int16) - first).max(-1) > MODE_TOLERANCE
    return image, (regions | (reached & changed)) & ~keep


def _pixel_by_pixel(stack: np.ndarray, image: np.ndarray, fixed: np.ndarray,
                    table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels whose colour is still subject-like take a stable background-like colour of
    their own (see the module docstring).

    Args:
        stack: (N, H, W, 3) uint8; image: (H, W, 3) uint8, the background so far;
        fixed: (H, W) bool, pixels left alone (the replaced regions); table: the
        subject-likeness.

    Returns:
        the background (H, W, 3) uint8 (``image`` where nothing changed) and (H, W) bool,
        the pixels with a subject-like colour and another stable one (changed or not).
    """
    N = stack.shape[0]
    need = _need(N)
    own = _likeness(image, table)
    off = np.abs(stack.astype(np.int16) - image.astype(np.int16)).max(-1) > MODE_TOLERANCE
    ys, xs = np.nonzero((off.sum(0) >= need) & ~fixed & (own > 0))
    out, doubtful = image.copy(), np.zeros(image.shape[:2], bool)
    chunk = max(1, 2_000_000 // (N * N))  # bounds the (N, N, K) neighbour table
    for s in range(0, len(ys), chunk):
        y, x = ys[s : s + chunk], xs[s : s + chunk]
        samples = stack[:, y, x].astype(np.int16)  # (N, K, 3)
        allowed = off[:, y, x]
        best, best_like = image[y, x].copy(), own[y, x]
        for _ in range(2):  # the two densest other colours
            colour, support, members = _densest(samples, allowed)
            colour = _as_colour(colour)  # (K, 3) uint8
            like = _likeness(colour, table)
            doubtful[y, x] |= support >= need
            better = (support >= need) & (like < 0) & (like < best_like - MARGIN)
            best[better], best_like[better] = colour[better], like[better]
            allowed &= ~members
        out[y, x] = best
    return out, doubtful


def estimate_background(
    stack: np.ndarray, method: str = "modes", max_pixels: int = MAX_PIXELS
) -> BackgroundEstimate:
    """A camera's background from frames spread over its recording.

    Args:
        stack: (N, H, W, 3) uint8 frames.
        method: ``median`` (the temporal median; pixels with two stable colours are still
            reported) or ``modes`` (the second colour replaces the median where it
            continues the surroundings, see the module docstring).
        max_pixels: frames larger than this are analysed at a size of about this many
            pixels (area-averaged); the background is the native median except where
            the analysis changed it, there its colour upsampled, and the masks upsampled.

    Returns:
        :class:`BackgroundEstimate`.

    Example:
        >>> frames = np.zeros((5, 4, 4, 3), np.uint8)
        >>> estimate_background(frames).uncertain.any()
        np.False_
    """
    if method not in BACKGROUND_METHODS:
        raise ValueError(f"background method must be one of {BACKGROUND_METHODS}, got {method!r}")
    N, H, W = stack.shape[:3]
    median = np.median(stack, axis=0).round().astype(np.uint8)
    if H * W > max_pixels:  # HD footage: the analysis at a working size, then upsampled
        f = (H * W / max_pixels) ** 0.5
        size = (max(1, round(W / f)), max(1, round(H / f)))
        small = np.stack([cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in stack])
        # at the working size, whatever its rounding (a size rounded up past max_pixels
        # would otherwise be analysed smaller again, without end)
        low = estimate_background(small, method, max_pixels=size[0] * size[1])
        low_median = np.median(small, axis=0).round().astype(np.uint8)
        changed = np.abs(low.image.astype(np.int16) - low_median).max(-1) > MODE_TOLERANCE

        def up(mask: np.ndarray) -> np.ndarray:
            return cv2.resize(mask.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0

        colour = cv2.resize(low.image, (W, H), interpolation=cv2.INTER_LINEAR)
        image = np.where(up(changed)[..., None], colour, median)
        return BackgroundEstimate(image, up(low.uncertain), up(low.replaced), int(N),
                                  up(low.stayed))
    first, second, step, stay, no_majority, shows_first = _two_colours(stack, median)
    replaced = np.zeros_like(step)
    image = median
    clear = stay  # the clear stays, before the pixel-by-pixel doubts join the reported ones
    if method == "modes":
        image = first  # the most frequent colour where the median is none of the frames'
        table = _subject_likeness(stack, first, shows_first)
        if step.any():
            switched = _appearance_choice(first, second, step, table)
            image, replaced = _vacated(stack, first, shows_first, switched, table)
        image_before = image
        image, doubtful = _pixel_by_pixel(stack, image, replaced, table)
        replaced = replaced | (np.abs(image.astype(np.int16) - image_before).max(-1)
                               > MODE_TOLERANCE)
        stay = stay | doubtful
        # a clear stay kept in a background-like colour is the floor kept beside a subject
        # that stood there at the start or the end: the estimate holds no subject there
        clear = clear & (_likeness(image, table) > 0)
    return BackgroundEstimate(image, stay | replaced | no_majority, replaced, int(N),
                              clear | replaced)
