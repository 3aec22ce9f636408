"""Relocalisation by image registration: where a small new scan lies in the full scan.

When no reference object is left, a small scan of a distinctive window (an electrode's
corner, a cluster of particles that will not be pushed) registered on the same window
of the first full scan measures the drift in both coordinates at once (Yang et al.,
IEEE T-NANO 2008: image registration by phase correlation).

This module holds :func:`register`, which measures the shift of a new scan against the
full scan (:class:`Registration`); the windows are chosen by
:func:`~nanoasm.executor.windows.choose_windows`. Lengths in nm; images are
:class:`~nanoasm.instrument.HeightImage` (row 0 at the bottom, ``origin`` the lower-left
corner of pixel (0, 0)) of one pixel size.

The whole-pixel shift is the peak of the masked normalised cross-correlation of the new
scan over the full scan's window grown by ``max_shift`` on every side (Padfield's
masked correlation, the algorithm of skimage's masked ``phase_cross_correlation``,
here over whole overlaps only and keeping the whole surface, whose second peak tells
an ambiguous match). Phase correlation of two windows of one size wraps round at half
their side and loses the overlap as the shift grows (40 % of the side in both axes
leaves 36 % of the window); growing the reference's window instead keeps the new scan
wholly inside it, so nothing wraps and any shift up to ``max_shift`` is found.

The sub-pixel shift is a least-squares fit (Gauss-Newton through a cubic spline of the
reference, offset and tilt free), which takes masks as they come and gives its own
covariance. Measured on rendered scans (10 nm pixels, 0.3 nm noise, 48-pixel windows on
electrode corners and a particle cluster, 320 shifts up to 40 % of the side), from the
same whole-pixel step: the fit erred by 0.35 nm rms (0.17 median); a parabola through
the correlation's peak (what skimage's masked mode would leave) 0.47 (0.29);
``skimage.registration.phase_cross_correlation`` upsampled 20 times on the two
Hann-windowed windows 1.23 (0.35) without normalisation and 2.58 (0.94) with the phase
normalisation, which whitens the aliased high frequencies of steps and particles a
pixel or two wide and pulls the peak to whole pixels. So skimage's function is not
used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.signal import correlate

from nanoasm.instrument import HeightImage
from nanoasm.param import number

#: A registration scoring below this normalised cross-correlation is refused: the scans
#: do not show the same content (bare substrate scores 0.2-0.4: only its roughness
#: correlates under the noise).
MIN_SCORE = 0.7
#: A second correlation peak this close to the best (ratio) makes the match ambiguous.
AMBIGUITY = 0.9
#: A new scan whose slopes vary less than this fraction in their weakest direction than
#: in their strongest (eigenvalues of their covariance) holds one straight edge alone:
#: 0.001 for an edge with the corner just out of view, 0.16-0.4 with it in view.
MIN_CONDITION = 0.01
#: The shift's 1-sigma (pixels): the fit's own times STD_FACTOR, a floor for the
#: pixel phase of sampled steps, and BACK_FACTOR times the disagreement of the fit with
#: the fit the other way round (reference on new scan), which shows how much the
#: interpolation of content sampled too coarsely (particles a few pixels wide) errs.
#: Measured: see :func:`register`.
STD_FACTOR = 1.0
STD_FLOOR = 0.03
BACK_FACTOR = 1.5


@dataclass(frozen=True, eq=False)
class Registration:
    """Where the content of a new scan lies relative to the reference.

    Attributes
    ----------
    shift : (2,) array
        Content seen at ``p`` in the reference lies at ``p + shift`` in the new scan's
        frame (nm, x and y).
    std : float
        1-sigma of each component of ``shift`` (nm).
    score : float
        Normalised cross-correlation of the two scans after the shift, on their overlap.
    ok : bool
    reason : str
        ``"ok"``, or why the match is not trusted.
    """

    shift: np.ndarray
    std: float
    score: float
    ok: bool
    reason: str


def register(reference: HeightImage, moving: HeightImage, *, reference_mask=None, moving_mask=None,
             max_shift: float | None = None) -> Registration:
    """Where the content of a new small scan lies relative to the same content in the
    full scan.

    ``moving.origin`` is where the caller believes the new scan lies in the reference's
    frame (e.g. the scanner region minus the drift estimate); the shift says how far its
    content actually lies from there. The reference is cropped to the new scan's
    region grown by ``max_shift`` (masked where that leaves the image), both are
    levelled (:func:`_level`), the whole-pixel shift is the peak of their masked
    normalised cross-correlation and the sub-pixel shift a least-squares fit
    (:func:`_fit_shift`); see the module docstring.

    The match is refused (``ok`` False) when the score is below :data:`MIN_SCORE`; when
    a second peak of the correlation (a local maximum over 5 x 5 pixels) reaches
    :data:`AMBIGUITY` of the best (a periodic pattern); when the content varies along one
    direction only (the new scan's slopes, :func:`_condition`, below
    :data:`MIN_CONDITION`: a straight edge alone); or when the best peak
    lies on the search's limit (the shift may be larger).

    ``std`` (nm, each axis) holds the fit's 1-sigma in its weakest direction (from its
    residuals, so noise and any mismatch of the two scans count), a floor of
    :data:`STD_FLOOR` pixel for the pixel phase of sampled steps, and
    :data:`BACK_FACTOR` times the disagreement with the fit the other way round (how
    much interpolating content sampled too coarsely errs). Calibrated on rendered scans
    (10 nm pixels, 0.3 nm noise, 0.2 nm roughness, 48-pixel windows, 200 shifts each,
    uniform up to 40 % of the side in each axis, all registered ok):

    ==========================  =========  =====  ===========  ============
    window centred on           rms error  std    within 1 std within 2 std
    ==========================  =========  =====  ===========  ============
    electrode corner (square)   0.23 nm    0.32   86-92 %      100 %
    electrode corner (oblique)  0.05 nm    0.32   100 %        100 %
    cluster of 20 nm particles  0.50 nm    0.85   74-79 %      98-99.5 %
    ==========================  =========  =====  ===========  ============

    (per axis within 1 std; both axes within 2 std). It took 12-17 ms a call on a
    256 x 256 reference.

    Parameters
    ----------
    reference : HeightImage
        The full scan (or any scan the content is known in).
    moving : HeightImage
        The new scan, of the same pixel size, at least 8 x 8 pixels.
    reference_mask, moving_mask : bool array, optional
        True on pixels to use, shaped as each image (e.g. False on objects pushed since).
    max_shift : float, optional
        Largest shift searched in each axis (nm); 45 % of the new scan's shorter side by
        default. (Phase correlation of two windows of one size would wrap round at half
        the side.)

    Returns
    -------
    Registration
    """
    ps = _check_pair(reference, moving)
    ref_ok = _mask("reference_mask", reference_mask, reference.shape)
    mov_ok = _mask("moving_mask", moving_mask, moving.shape)
    mh, mw = moving.shape
    m = (int(0.45 * min(mh, mw)) if max_shift is None
         else int(math.ceil(number("max_shift", max_shift, nonnegative=True) / ps)))
    f = (np.asarray(moving.origin, float) - np.asarray(reference.origin, float)) / ps
    j0, i0 = (int(v) for v in np.round(f))
    big, big_ok = _crop(reference.height, ref_ok, i0 - m, j0 - m, mh + 2 * m, mw + 2 * m)
    if mov_ok.sum() < 0.25 * mov_ok.size or big_ok.sum() < 0.25 * mov_ok.size:
        return _refused("too little unmasked content to register")
    big, mov = _level(big, big_ok), _level(moving.height, mov_ok)
    ncc = _masked_ncc(big, big_ok, mov, mov_ok)
    if not np.isfinite(ncc).any():
        return _refused("no overlap of the unmasked content")
    peak = np.array(np.unravel_index(np.nanargmax(ncc), ncc.shape))
    fit = _fit_shift(big, big_ok, mov, mov_ok, peak)
    if fit is None:
        return _refused("the sub-pixel fit did not converge")
    at, cov, score = fit
    shift = ps * np.array([f[0] - j0 + m - at[1], f[1] - i0 + m - at[0]])
    back = _fit_back(big, big_ok, mov, mov_ok, peak)
    spread = math.inf if back is None else float(np.abs(back - at).max())
    std = ps * math.sqrt((STD_FACTOR ** 2) * np.linalg.eigvalsh(cov)[-1] + STD_FLOOR ** 2
                         + (BACK_FACTOR * spread) ** 2)
    second = _second_peak(ncc, peak)
    reason = "ok"
    if not score >= MIN_SCORE:
        reason = f"poor match: score {score:.2f} below {MIN_SCORE}"
    elif second >= AMBIGUITY * ncc[tuple(peak)]:
        reason = f"ambiguous: a second peak reaches {second / ncc[tuple(peak)]:.2f} of the best"
    elif _condition(mov, mov_ok) < MIN_CONDITION:
        reason = "ambiguous: the content varies along one direction only"
    elif np.any(peak == 0) or np.any(peak == np.array(ncc.shape) - 1):
        reason = f"shift at the search limit of {m * ps:g} nm"
    elif back is None:
        reason = "the fit the other way round did not converge"
    return Registration(shift, float(std), float(score), reason == "ok", reason)


def _refused(reason: str) -> Registration:
    return Registration(np.full(2, np.nan), math.inf, 0.0, False, reason)


def _check_pair(reference, moving) -> float:
    for name, im in (("reference", reference), ("moving", moving)):
        if not isinstance(im, HeightImage):
            raise ValueError(f"{name} must be a HeightImage, got {type(im).__name__}")
        if not np.all(np.isfinite(im.height)):
            raise ValueError(f"{name} must hold finite heights (mask bad pixels instead)")
    ps = reference.pixel_size
    if abs(moving.pixel_size - ps) > 1e-6 * ps:
        raise ValueError(f"moving must have the reference's pixel size {ps:g} nm, "
                         f"got {moving.pixel_size:g}")
    if min(moving.shape) < 8:
        raise ValueError(f"moving must be at least 8 x 8 pixels, got {moving.shape}")
    return ps


def _mask(name: str, mask, shape) -> np.ndarray:
    if mask is None:
        return np.ones(shape, bool)
    m = np.asarray(mask)
    if m.shape != shape:
        raise ValueError(f"{name} must have the image's shape {shape}, got {m.shape}")
    return m.astype(bool)


def _crop(a: np.ndarray, ok: np.ndarray, i: int, j: int, h: int, w: int):
    """``a[i:i+h, j:j+w]`` and its mask, False where the window leaves ``a``."""
    out, out_ok = np.zeros((h, w)), np.zeros((h, w), bool)
    r0, c0 = max(i, 0), max(j, 0)
    r1, c1 = min(i + h, a.shape[0]), min(j + w, a.shape[1])
    if r1 > r0 and c1 > c0:
        out[r0 - i:r1 - i, c0 - j:c1 - j] = a[r0:r1, c0:c1]
        out_ok[r0 - i:r1 - i, c0 - j:c1 - j] = ok[r0:r1, c0:c1]
    return out, out_ok


def _level(z: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``z`` less its tilt, 0 off ``ok``.

    The tilt is the mean slope between neighbouring ``ok`` pixels in each direction,
    over the pairs within 3 robust sigmas of the median slope: flat ground and flat tops
    share the tilt, while steps and the flanks of objects are outliers, so it holds for
    any mix of levels (a plane fitted to the heights leans towards an electrode that
    covers half the window). What remains of a tilt the sub-pixel fit takes out."""
    slopes = []
    for axis in (0, 1):
        d = np.diff(z, axis=axis)
        pair = ok[1:, :] & ok[:-1, :] if axis == 0 else ok[:, 1:] & ok[:, :-1]
        d = d[pair]
        if d.size < 3:
            slopes.append(0.0)
            continue
        med = np.median(d)
        sigma = 1.4826 * np.median(np.abs(d - med))
        slopes.append(float(np.mean(d[np.abs(d - med) <= max(3 * sigma, 1e-12)])))
    rows, cols = np.indices(z.shape)
    flat = z - slopes[0] * rows - slopes[1] * cols
    return np.where(ok, flat - np.median(flat[ok]), 0.0)


def _masked_ncc(big: np.ndarray, big_ok: np.ndarray, mov: np.ndarray, mov_ok: np.ndarray
                ) -> np.ndarray:
    """Normalised cross-correlation of ``mov`` placed at every whole-pixel offset inside
    ``big`` ((2m + 1, 2m + 1) array), each over the pixels valid in both (Padfield
    2012); NaN where they share fewer than half of ``mov``'s valid pixels."""
    b, bb, a, aa = big_ok.astype(float), big * big_ok, mov_ok.astype(float), mov * mov_ok

    def corr(x, t):
        return correlate(x, t, mode="valid", method="fft")

    n = np.round(corr(b, a))
    sa, sb = corr(b, aa), corr(bb, a)
    saa, sbb, sab = corr(b, aa * aa), corr(bb * bb, a), corr(bb, aa)
    with np.errstate(invalid="ignore", divide="ignore"):
        num = sab - sa * sb / n
        den = np.sqrt(np.maximum(saa - sa * sa / n, 0.0) * np.maximum(sbb - sb * sb / n, 0.0))
        ncc = num / den
    tiny = 1e-9 * max(float(np.abs(saa).max()), float(np.abs(sbb).max()), 1e-300)
    ncc[(n < 0.5 * a.sum()) | (den <= tiny)] = np.nan
    return np.clip(ncc, -1.0, 1.0)


def _second_peak(ncc: np.ndarray, peak: np.ndarray) -> float:
    """The highest local maximum (over 5 x 5) of ``ncc`` other than ``peak``'s."""
    filled = np.where(np.isfinite(ncc), ncc, -np.inf)
    local = (filled == ndimage.maximum_filter(filled, size=5, mode="constant", cval=-np.inf))
    local &= np.isfinite(filled)
    local[max(peak[0] - 2, 0):peak[0] + 3, max(peak[1] - 2, 0):peak[1] + 3] = False
    return float(filled[local].max()) if local.any() else -1.0


def _condition(z: np.ndarray, ok: np.ndarray) -> float:
    """Smaller over larger eigenvalue of the covariance of the slopes of ``z`` (Gaussian
    derivatives over a pixel) on its ``ok`` pixels: 0 for content that varies along one
    direction only."""
    g = np.stack([ndimage.gaussian_filter(z, 1.0, order=o)[ok] for o in ((1, 0), (0, 1))])
    lam = np.linalg.eigvalsh(np.cov(g))
    return float(lam[0] / lam[1]) if lam[1] > 0 else 0.0


def _fit_back(big: np.ndarray, big_ok: np.ndarray, mov: np.ndarray, mov_ok: np.ndarray,
              peak: np.ndarray) -> np.ndarray | None:
    """The position of :func:`_fit_shift` found the other way round: the reference's
    window at ``peak`` (less a one-pixel rim) fitted in the new scan."""
    h, w = mov.shape
    inner = (slice(peak[0] + 1, peak[0] + h - 1), slice(peak[1] + 1, peak[1] + w - 1))
    fit = _fit_shift(mov, mov_ok, big[inner], big_ok[inner], np.ones(2, int))
    return None if fit is None else peak + 1 - fit[0]


def _fit_shift(big: np.ndarray, big_ok: np.ndarray, mov: np.ndarray, mov_ok: np.ndarray,
               start: np.ndarray):
    """Sub-pixel position (row, col) of ``mov`` in ``big`` by least squares (Gauss-Newton).

    ``mov`` is matched to ``big`` read at the shifted pixel positions through a cubic
    spline, with an offset and a tilt as free nuisances, over the pixels whose spline
    support is valid in ``big`` and valid in ``mov``. The Jacobian is the gradient of
    ``big`` smoothed over a pixel (the noise then hardly feeds the information in a
    direction the content does not vary in). Returns ``(position (2,), covariance
    (2, 2) in pixels^2, normalised cross-correlation on the overlap)``, or None when the
    fit runs off by more than three pixels or keeps too few pixels.
    """
    coef = ndimage.spline_filter(big, order=3)
    bad = ndimage.binary_dilation(~big_ok, iterations=3).astype(float)
    g_row = ndimage.gaussian_filter(big, 1.0, order=(1, 0))
    g_col = ndimage.gaussian_filter(big, 1.0, order=(0, 1))
    rows, cols = np.indices(mov.shape, dtype=float)
    at = start.astype(float)
    for _ in range(12):
        where = [rows + at[0], cols + at[1]]
        use = mov_ok & (ndimage.map_coordinates(bad, where, order=1) < 1e-9)
        if use.sum() < 0.25 * mov.size:
            return None
        f = ndimage.map_coordinates(coef, where, order=3, prefilter=False)
        a = np.column_stack([ndimage.map_coordinates(g, where, order=1)[use] for g in (g_row, g_col)]
                            + [np.ones(use.sum()), rows[use] / mov.shape[0], cols[use] / mov.shape[1]])
        step, *_ = np.linalg.lstsq(a, mov[use] - f[use], rcond=None)
        at = at + step[:2]
        if np.abs(at - start).max() > 3.0:
            return None
        if np.abs(step[:2]).max() < 1e-3:
            break
    r = mov[use] - f[use] - a @ step
    sigma2 = float(r @ r) / max(r.size - a.shape[1], 1)
    cov = sigma2 * np.linalg.inv(a.T @ a)[:2, :2]
    score = float(np.corrcoef(mov[use], f[use])[0, 1]) if np.std(f[use]) > 0 else 0.0
    return at, cov, (score if math.isfinite(score) else 0.0)
