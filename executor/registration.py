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

The whole-pixel shift is found by ``skimage.registration.phase_cross_correlation`` in
its masked mode (Padfield's masked normalised cross-correlation) of the new scan over
the full scan's window grown by ``max_shift`` on every side; the correlation surface,
whose second peak tells an ambiguous match, comes from skimage's own
``cross_correlate_masked`` (private in skimage 0.26, scikit-image issue 6326). Phase
correlation of two windows of one size wraps round at half their side and loses the
overlap as the shift grows (40 % of the side in both axes leaves 36 % of the window);
growing the reference's window instead keeps the new scan wholly inside it, so nothing
wraps and any shift up to ``max_shift`` is found. Beyond it the masked correlation
still sees the content on the part of the new scan that overlaps the grown window (at
least :data:`MIN_OVERLAP`), so a larger shift is refused as such.

The sub-pixel shift is a least-squares fit from that whole-pixel shift (Gauss-Newton
through a cubic spline of the reference, offset and tilt free), which takes masks as
they come and gives its own covariance. Measured on rendered scans (10 nm pixels, 0.3 nm
noise, 48-pixel windows on three electrode corners and a particle cluster, 280 shifts up
to 40 % of the side), from the same whole-pixel step: the fit erred by 0.31 nm rms (0.08
median); a parabola through the correlation's peak 0.90 (0.48); skimage's sub-pixel
step (``upsample_factor`` 20, which it offers without masks only) on the two
Hann-windowed windows 1.43 (0.40) without normalisation and 3.44 (1.02) with the phase
normalisation, which whitens the aliased high frequencies of steps and particles a
pixel or two wide and pulls the peak to whole pixels. So the sub-pixel step is the fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage.registration import phase_cross_correlation
from skimage.registration._masked_phase_cross_correlation import cross_correlate_masked

from nanoasm.instrument import HeightImage
from nanoasm.param import number

#: A registration scoring below this normalised cross-correlation is refused: the scans
#: do not show the same content (bare substrate scores 0.2-0.4: only its roughness
#: correlates under the noise).
MIN_SCORE = 0.7
#: A second correlation peak this close to the best (ratio) makes the match ambiguous.
AMBIGUITY = 0.9
#: Offsets at which the unmasked pixels of the two scans overlap less than this fraction
#: of their largest overlap are not searched (``overlap_ratio`` of skimage's masked
#: correlation): a small overlap matches by chance.
MIN_OVERLAP = 0.5
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
    levelled (:func:`_level`), the whole-pixel shift is the peak of skimage's masked
    ``phase_cross_correlation`` and the sub-pixel shift a least-squares fit from there
    (:func:`_fit_shift`); see the module docstring.

    The match is refused (``ok`` False) when the score is below :data:`MIN_SCORE`; when
    a second peak of the correlation (a local maximum over 5 x 5 pixels) reaches
    :data:`AMBIGUITY` of the best (a periodic pattern); when the content varies along one
    direction only (the new scan's slopes, :func:`_condition`, below
    :data:`MIN_CONDITION`: a straight edge alone); or when the best peak lies on or
    beyond the search's limit (the shift may be larger).

    ``std`` (nm, each axis) holds the fit's 1-sigma in its weakest direction (from its
    residuals, so noise and any mismatch of the two scans count), a floor of
    :data:`STD_FLOOR` pixel for the pixel phase of sampled steps, and
    :data:`BACK_FACTOR` times the disagreement with the fit the other way round (how
    much interpolating content sampled too coarsely errs). Calibrated on rendered scans
    (10 nm pixels, 0.3 nm noise, 0.2 nm roughness, 48-pixel windows, 200 shifts each,
    uniform up to 40 % of the side in each axis, all registered ok):

    ==========================  ============  =====  ============  ============
    window centred on           rms error     std    within 1 std  within 2 std
    ==========================  ============  =====  ============  ============
    electrode corner (square)   0.22-0.23 nm  0.32   83-92 %       100 %
    electrode corner (oblique)  0.06 nm       0.33   100 %         100 %
    cluster of 20 nm particles  0.52-0.55 nm  1.05   72-82 %       97-99.5 %
    ==========================  ============  =====  ============  ============

    (three seeds; per axis within 1 std; both axes within 2 std). It took 20 ms a call
    (processor time, median) on a 256 x 256 reference, 7.5 ms of it the whole-pixel
    step: skimage's masked correlation works on the full 137 x 137 surface of a 48-pixel
    scan and a 21-pixel search, and ``phase_cross_correlation`` does not return the
    surface, so it is computed twice.

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
    found, _, _ = phase_cross_correlation(big, mov, reference_mask=big_ok, moving_mask=mov_ok,
                                          overlap_ratio=MIN_OVERLAP)
    peak = np.round(found).astype(int) + m           # mov's pixel (0, 0) in big
    ncc = cross_correlate_masked(big, mov, big_ok, mov_ok, mode="full", axes=(0, 1),
                                 overlap_ratio=MIN_OVERLAP)
    zero = np.array(mov.shape) - 1                   # ncc's index of peak (0, 0)
    best = ncc[tuple(peak + zero)]
    if not best > 0:
        return _refused("the unmasked content does not correlate anywhere")
    start = np.clip(peak, 0, 2 * m)
    limit = (f"shift at or beyond the search limit of {m * ps:g} nm"
             if np.any(peak <= 0) or np.any(peak >= 2 * m) else "")
    fit = _fit_shift(big, big_ok, mov, mov_ok, start)
    if fit is None:                                  # the whole-pixel correlation tells why
        return _refused(f"poor match: score {best:.2f} below {MIN_SCORE}" if best < MIN_SCORE
                        else limit or "the sub-pixel fit did not converge")
    at, cov, score = fit
    shift = ps * np.array([f[0] - j0 + m - at[1], f[1] - i0 + m - at[0]])
    back = _fit_back(big, big_ok, mov, mov_ok, start)
    spread = math.inf if back is None else float(np.abs(back - at).max())
    std = ps * math.sqrt((STD_FACTOR ** 2) * np.linalg.eigvalsh(cov)[-1] + STD_FLOOR ** 2
                         + (BACK_FACTOR * spread) ** 2)
    searched = (slice(zero[0], zero[0] + 2 * m + 1), slice(zero[1], zero[1] + 2 * m + 1))
    second = _second_peak(ncc, peak + zero, searched)
    reason = "ok"
    if not score >= MIN_SCORE:
        reason = f"poor match: score {score:.2f} below {MIN_SCORE}"
    elif second >= AMBIGUITY * best:
        reason = f"ambiguous: a second peak reaches {second / best:.2f} of the best"
    elif _condition(mov, mov_ok) < MIN_CONDITION:
        reason = "ambiguous: the content varies along one direction only"
    elif limit:
        reason = limit
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


def _second_peak(ncc: np.ndarray, peak: np.ndarray, searched: tuple[slice, slice]) -> float:
    """The highest local maximum (over 5 x 5) of ``ncc`` within ``searched``, other than
    the one at index ``peak``."""
    local = ncc == ndimage.maximum_filter(ncc, size=5, mode="constant", cval=-np.inf)
    local[max(peak[0] - 2, 0):peak[0] + 3, max(peak[1] - 2, 0):peak[1] + 3] = False
    values = ncc[searched][local[searched]]
    return float(values.max()) if values.size else -1.0


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
