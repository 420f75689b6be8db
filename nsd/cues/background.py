"""A camera's background from its footage when subjects linger: two stable colours per pixel.

The temporal median of a pixel is its background when the pixel shows the background in
most frames. A subject that stays in place for most of the recording (an animal asleep
in a corner, a person at a bench) turns that around: the median holds the subject, and
the background shows only in the frames before it came or after it left. Such a pixel
has **two stable colours** over time, in a telling order: its most frequent colour (the
densest cluster of its frames' colours) holds for one stretch of the recording, and
another colour holds most of the frames outside the stretch. Subjects walking past give
no such pattern: the colours they leave on a pixel are short and scattered.

Which of the two is the background is decided per region of such pixels by **continuity
with its surroundings**: the background continues the background around the region,
while a subject ends at its silhouette. Each colour of the region is extrapolated a few
pixels outwards (a normalised convolution over the region) and compared, along the
region's border, with the background extrapolated inwards from outside; where the second
colour continues the surroundings clearly better, the first is a subject's. The region's
background is then the median of its pixels (and of those within ``BORDER`` of it) over
the frames in which the subject was away (the frames most of the region's pixels do not
show their first colour): rather than each pixel's own second colour, which at the
region's edge, where a swaying subject shows only part of the time and the floor is the
first colour, would be the subject's.

Reported as uncertain (the scene check and the background report,
:mod:`nsd.io.background_report`, tell a user per camera, with the advice to give a
background plate): the pixels where the second colour was taken, the clear cases where
it was not (a stretch from the start or to the end of the recording, the other colour
holding ``STEP_PURITY`` of the rest), and those where no colour holds half of the frames.
A subject that never moves in the whole recording leaves a single stable colour, its own:
nothing label-free finds it, and only a plate helps.
"""

from __future__ import annotations

import warnings
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
BORDER = 3  # pixels on each side of a region's border where continuity is compared
MIN_REGION = 1e-4  # smallest region, a share of the image (smaller ones keep the median)
MAX_PIXELS = 512 * 512  # larger frames are analysed at about this size (then upsampled)
SWITCH_MARGIN = 0.8  # the second colour must continue the surroundings this much better


@dataclass
class BackgroundEstimate:
    """One camera's background and what is known of it.

    Attributes:
        image: the background, (H, W, 3) uint8 RGB.
        uncertain: (H, W) bool, the reported pixels: the second colour taken, a clear stay
            kept, or no colour in half of the frames (see the module docstring).
        replaced: (H, W) bool, where the second colour was taken instead of the first.
        samples: how many frames the estimate read.
    """

    image: np.ndarray
    uncertain: np.ndarray
    replaced: np.ndarray
    samples: int

    @property
    def uncertain_share(self) -> float:
        """The share of the image with two stable colours."""
        return float(self.uncertain.mean()) if self.uncertain.size else 0.0


def _densest(samples: np.ndarray, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The densest colour of each pixel among its allowed frames.

    Args:
        samples: (N, K, 3) int16 colours of K pixels; allowed: (N, K) bool.

    Returns:
        colour (K, 3) float (the median of its members, NaN without any), support (K,)
        and members (N, K) bool: the frames within ``MODE_TOLERANCE`` of the frame that
        has the most allowed frames within it.
    """
    close = np.abs(samples[:, None] - samples[None]).max(-1) <= MODE_TOLERANCE  # (N, N, K)
    close &= allowed[:, None] & allowed[None]
    density = close.sum(1)  # (N, K)
    best = density.argmax(0)
    k = np.arange(samples.shape[1])
    members = close[best, :, k].T  # (N, K)
    with warnings.catch_warnings():  # pixels without allowed frames: NaN, never used
        warnings.simplefilter("ignore", RuntimeWarning)
        colour = np.nanmedian(np.where(members[..., None], samples, np.nan), axis=0)
    return colour, members.sum(0), members


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
    need = max(2, int(np.ceil(MIN_SECOND_SHARE * N)))
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


def _spread(image: np.ndarray, region: np.ndarray, sigma: float) -> np.ndarray:
    """``image`` over ``region`` extrapolated a few pixels beyond it (normalised
    convolution): (H, W, 3) float, undefined (0) far from the region."""
    w = region.astype(np.float32)
    num = cv2.GaussianBlur(image.astype(np.float32) * w[..., None], (0, 0), sigma)
    den = cv2.GaussianBlur(w, (0, 0), sigma)
    return num / np.maximum(den, 1e-6)[..., None]


def _continuity_choice(first: np.ndarray, second: np.ndarray, two: np.ndarray) -> np.ndarray:
    """Where the second colour continues the surroundings better than the first: (H, W) bool
    over the regions of ``two`` (pixels with two stable colours)."""
    H, W = two.shape
    n, labels = cv2.connectedComponents(two.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(two)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * BORDER + 1, 2 * BORDER + 1))
    outside = ~two
    band = (cv2.dilate(two.astype(np.uint8), kernel) > 0) & (cv2.erode(
        two.astype(np.uint8), kernel) == 0)
    sigma = BORDER / 1.5
    around = _spread(first, outside, sigma)  # the surroundings, carried inwards
    cost = []
    for colour in (first, second):
        inner = _spread(colour, two, sigma)  # the region's colour, carried outwards
        cost.append(np.abs(inner - around).mean(-1))
    # each band pixel counts for the region it touches (labels spread over the band)
    near = cv2.dilate(labels.astype(np.float32), kernel).astype(np.int64)
    near[~band] = 0
    sums = [np.bincount(near.ravel(), weights=c.ravel(), minlength=n) for c in cost]
    counts = np.bincount(near.ravel(), minlength=n)
    areas = np.bincount(labels.ravel(), minlength=n)
    switch = (sums[1] < SWITCH_MARGIN * sums[0]) & (counts > 0) & (areas >= MIN_REGION * H * W)
    switch[0] = False
    return switch[labels]


def _vacated(stack: np.ndarray, first: np.ndarray, shows_first: np.ndarray,
             switched: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The background of each region whose first colour was found to be a subject: the
    median of the region's pixels (and of those within ``BORDER`` of it) over the frames
    the subject was away.

    The subject's presence is the region's vote: the frames in which most of its pixels
    show their first colour. Taking the free frames' median, rather than each pixel's
    second colour, also gets right the pixels at the region's edge (where the floor is
    the first colour and the subject, swaying, the second) and those with no majority.

    Returns:
        the background (H, W, 3) uint8 and the replaced pixels (H, W) bool: the regions and
        the pixels around them whose colour changed.
    """
    N = stack.shape[0]
    need = max(2, int(np.ceil(MIN_SECOND_SHARE * N)))
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
        image[reach] = np.median(stack[:, reach][free], axis=0).round().astype(np.uint8)
        regions |= region
        reached |= reach
    changed = np.abs(image.astype(np.int16) - first).max(-1) > MODE_TOLERANCE
    return image, regions | (reached & changed)


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
        return BackgroundEstimate(image, up(low.uncertain), up(low.replaced), int(N))
    first, second, step, stay, no_majority, shows_first = _two_colours(stack, median)
    replaced = np.zeros_like(step)
    image = median
    if method == "modes":
        image = first  # the most frequent colour where the median is none of the frames'
        if step.any():
            replaced = _continuity_choice(first, second, step)
            image, replaced = _vacated(stack, first, shows_first, replaced)
    return BackgroundEstimate(image, stay | replaced | no_majority, replaced, int(N))
