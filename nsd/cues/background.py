"""A camera's background from its footage when subjects linger: two stable colours per pixel.

The temporal median of a pixel is its background when the pixel shows the background in
most frames. A subject that stays in place for most of the recording (an animal asleep
in a corner, a person at a bench) turns that around: the median holds the subject, and
the background shows only in the frames after it left (or before it came). Such a pixel
has **two stable colours** over time: the median, and a second mode that the frames
away from the median agree on. Subjects walking past give no second mode: the colours
they leave on a pixel scatter.

Which of the two is the background is decided per region of such pixels by **continuity
with its surroundings**: the background continues the background around the region,
while a subject ends at its silhouette. Each colour of the region is extrapolated a few
pixels outwards (a normalised convolution over the region) and compared, along the
region's border, with the median background extrapolated inwards from outside; the
second mode replaces the median where it continues the surroundings clearly better.

Every pixel with two stable colours is reported as uncertain (whichever colour was
kept): the share of such pixels per camera is what the scene check and the background
report (:mod:`nsd.io.background_report`) tell a user, with the advice to give a
background plate. A subject that never moves in the whole recording leaves a single
stable colour, its own: nothing label-free finds it, and only a plate helps.
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
MIN_SECOND_SHARE = 0.15  # each colour of a step spans at least this share of the frames
STEP_PURITY = 0.7  # and shows its colour in at least this share of its part
BORDER = 3  # pixels on each side of a region's border where continuity is compared
MIN_REGION = 1e-4  # smallest region, a share of the image (smaller ones keep the median)
SWITCH_MARGIN = 0.8  # the second colour must continue the surroundings this much better


@dataclass
class BackgroundEstimate:
    """One camera's background and what is known of it.

    Attributes:
        image: the background, (H, W, 3) uint8 RGB.
        uncertain: (H, W) bool, pixels with two stable colours over the samples.
        replaced: (H, W) bool, where the second colour was taken instead of the median.
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


def _step(members: np.ndarray, need: int) -> tuple[np.ndarray, np.ndarray]:
    """Where a pixel's most frequent colour holds for one part of the recording and not
    the other: a subject that stayed, then left (or came, then stayed).

    Args:
        members: (N, K) bool, the frames (in time order) showing the pixel's first colour.
        need: frames each part must span.

    Returns:
        (K,) bool, a step was found (each part at least ``STEP_PURITY`` pure), and (N, K)
        bool, the frames of the other part that do not show the first colour.
    """
    N, K = members.shape
    inside = np.cumsum(members, 0)  # first-colour frames among the first tau + 1
    total = inside[-1]
    tau = np.arange(need, N - need + 1)  # the split: frames [0, tau) and [tau, N)
    if not len(tau):
        return np.zeros(K, bool), np.zeros_like(members)
    before = inside[tau - 1]  # (S, K)
    after = total[None] - before
    n_before, n_after = tau[:, None], (N - tau)[:, None]
    first_then_other = np.minimum(before / n_before, 1 - after / n_after)  # purity of both
    other_then_first = np.minimum(1 - before / n_before, after / n_after)
    purity = np.maximum(first_then_other, other_then_first)
    best = purity.argmax(0)
    found = purity[best, np.arange(K)] >= STEP_PURITY
    split = tau[best]
    late = first_then_other[best, np.arange(K)] >= other_then_first[best, np.arange(K)]
    t = np.arange(N)[:, None]
    part = np.where(late[None], t >= split[None], t < split[None])  # the other colour's part
    return found, part & ~members & found[None]


def _two_colours(stack: np.ndarray, median: np.ndarray) -> tuple[np.ndarray, ...]:
    """Each pixel's most frequent colour and, where the recording steps from one stable
    colour to another (a subject stayed, then left), the other one.

    Returns:
        first, second: (H, W, 3) uint8 colours (the median where there is none);
        step: (H, W) bool, the pixels with a step between two stable colours;
        no_majority: (H, W) bool, no colour holds half of the frames.
    """
    N = stack.shape[0]
    need = max(2, int(np.ceil(MIN_SECOND_SHARE * N)))
    first, second = median.copy(), median.copy()
    step = np.zeros(median.shape[:2], bool)
    no_majority = np.zeros(median.shape[:2], bool)
    off = np.abs(stack.astype(np.int16) - median.astype(np.int16)).max(-1) > MODE_TOLERANCE
    ys, xs = np.nonzero(off.sum(0) >= need)  # elsewhere the median is the one colour
    chunk = max(1, 2_000_000 // (N * N))  # bounds the (N, N, K) neighbour table
    for s in range(0, len(ys), chunk):
        y, x = ys[s : s + chunk], xs[s : s + chunk]
        samples = stack[:, y, x].astype(np.int16)  # (N, K, 3)
        c1, n1, m1 = _densest(samples, np.ones(samples.shape[:2], bool))
        has1 = n1 >= need
        first[y[has1], x[has1]] = np.round(c1[has1]).astype(np.uint8)
        no_majority[y, x] = n1 < N / 2
        found, part = _step(m1, need)
        c2, n2, _ = _densest(samples, part)  # the other part's stable colour
        ok = found & has1 & (n2 >= STEP_PURITY * part.sum(0).clip(min=1)) & (n2 >= need)
        second[y[ok], x[ok]] = np.round(c2[ok]).astype(np.uint8)
        step[y[ok], x[ok]] = True
    return first, second, step, no_majority


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


def estimate_background(stack: np.ndarray, method: str = "modes") -> BackgroundEstimate:
    """A camera's background from frames spread over its recording.

    Args:
        stack: (N, H, W, 3) uint8 frames.
        method: ``median`` (the temporal median; pixels with two stable colours are still
            reported) or ``modes`` (the second colour replaces the median where it
            continues the surroundings, see the module docstring).

    Returns:
        :class:`BackgroundEstimate`.

    Example:
        >>> frames = np.zeros((5, 4, 4, 3), np.uint8)
        >>> estimate_background(frames).uncertain.any()
        np.False_
    """
    if method not in BACKGROUND_METHODS:
        raise ValueError(f"background method must be one of {BACKGROUND_METHODS}, got {method!r}")
    median = np.median(stack, axis=0).round().astype(np.uint8)
    first, second, bimodal, no_majority = _two_colours(stack, median)
    replaced = np.zeros_like(bimodal)
    image = median
    if method == "modes":
        image = first  # the most frequent colour where the median is none of the frames'
        if bimodal.any():
            replaced = _continuity_choice(first, second, bimodal)
            image = np.where(replaced[..., None], second, first)
    return BackgroundEstimate(image, bimodal | no_majority, replaced, int(stack.shape[0]))
