"""Registration of a layout to a scan by its alignment marks, and the layout in the scan's frame.

A layout's ``[[mark]]``\\ s are features that exist on the sample (electrodes, markers),
drawn in the layout's own (CAD) frame; identification finds them among the obstacles,
in the scan's frame. :func:`register` finds the transform between the two:

1. corners of the marks and of the obstacles' outlines (:mod:`.corners`), obstacle
   corners near the scan's border left out (an outline cut by the border has corners
   there that are not the sample's), and in a run each moved by the drift of the time
   its row was scanned;
2. putative correspondences: every mark corner with every obstacle corner that turns
   the same way by about as much;
3. RANSAC over them (``skimage.measure.ransac``, two correspondences a sample, with
   ``EuclideanTransform``, or ``SimilarityTransform`` when the scale is free), rotations
   beyond ``MAX_ROTATION`` and scales beyond ``MAX_SCALE`` refused;
4. a least-squares refinement (``scipy.optimize.least_squares``) over the
   correspondences within ``gate`` of the model, mark corners matched one to one, with
   one more unknown: how much the obstacles' outlines are grown (the tip's broadening
   of a step, some 10-30 nm, moves every corner along its miter), re-matched until the
   matches hold.

It fails, in one line naming the layout and ``mark``, when fewer than ``MIN_CORNERS``
mark corners are matched (too few marks found), when the residual is above the
layout's position tolerance, or when the match is ambiguous: a distinct transform
(one moving some mark corner by more than the gate) matching at least
``AMBIGUOUS_SHARE`` as many corners within the tolerance (symmetric or repeated marks).
That failure is an :class:`AmbiguousMatch`, which keeps the rival registrations (a scan
torn by a jump of the drift shows the marks' early corners at one place and their late
ones at another: :mod:`nanoasm.executor.keepout_frame` reads it so).

:func:`in_scan_frame` is what ``plan``, ``dry-run`` and ``run`` call: the layout
registered when it has marks (and registration is not switched off), mapped into the
scan's frame, and its slots checked to lie in the scanned area (:mod:`.frames`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from nanoasm.cad.frame import Similarity, rounded
from nanoasm.cad.layout import Layout
from nanoasm.errors import InputError
from nanoasm.schema import Point
from nanoasm.world.environment import Environment

from .corners import Corner, corners
from .frames import check_in_area
from .options import ALIGNS

#: Largest rotation (degrees) between a layout and the scan: a sample is mounted within
#: it of the layout's orientation. It also tells apart the 90° turns of square marks.
MAX_ROTATION = 45.0
#: Largest scale error with the scale free (a scanner calibrated within 20 %).
MAX_SCALE = 1.2
#: Least mark corners matched for a registration.
MIN_CORNERS = 3
#: A distinct transform matching at least this share of the corners makes the match ambiguous.
AMBIGUOUS_SHARE = 0.75
#: Two corners are taken to be the same kind when their turns differ by at most this (degrees).
TURN_MATCH = 20.0
#: Pixel size (nm) assumed when the scan's is not known (an environment file).
RESOLUTION = 10.0
#: RANSAC: samples drawn at most, and the probability of a clean sample at which it stops.
MAX_TRIALS, STOP_PROBABILITY = 20_000, 0.999


@dataclass(frozen=True)
class Alignment:
    """A registration: the transform (layout frame -> scan frame, with its RMS residual),
    the mark corners it matched, the marks with a matched corner out of all, and how far
    the obstacles' outlines are grown beyond the marks (nm, the tip's broadening)."""

    transform: Similarity
    corners: int
    marks: int
    of: int
    grown: float
    #: the matched corners: each mark corner (layout frame, moved out by ``grown`` along
    #: its miter) with the obstacle corner it matched (as found, ``moved``)
    pairs: tuple[tuple[Point, Point], ...] = ()

    def line(self) -> str:
        return (f"registered the layout to the scan: {self.transform.line()}; {self.marks} of {self.of} "
                f"mark(s) found ({self.corners} corners; outlines grown {self.grown:.0f} nm)")

    def to_doc(self) -> dict:
        """For the run's subscribers (the CLI prints it)."""
        return {"text": self.line(), **self.transform.to_dict()}


class AmbiguousMatch(InputError):
    """The marks fit the scan as well at distinct transforms; ``fits`` holds each of them
    as an :class:`Alignment`, the best first (the message is the user's, as any
    :class:`~nanoasm.errors.InputError`'s)."""

    def __init__(self, source: str | None, key: str | None, problem: str, fits: tuple[Alignment, ...]):
        super().__init__(source, key, problem)
        self.fits = fits


@dataclass(frozen=True)
class _Fit:
    transform: Similarity
    grown: float
    pairs: tuple[tuple[int, int], ...]      # (mark corner, obstacle corner)
    residual: float


def _mark_corners(layout: Layout, min_edge: float, gap: float) -> list[Corner]:
    out: list[Corner] = []
    for k, m in enumerate(layout.marks):
        out += corners(m.polygon, min_edge=min_edge, max_gap=gap, outline=k)
    return out


def _obstacle_corners(env: Environment, min_edge: float, gap: float, border: float,
                      moved: Callable[[Point], Point] | None, tolerance: float) -> list[Corner]:
    w, h = env.area
    out: list[Corner] = []
    for k, ob in enumerate(env.obstacles):
        for c in corners(ob.polygon, min_edge=min_edge, max_gap=gap, tolerance=tolerance, outline=k):
            x, y = c.at
            if border <= x <= w - border and border <= y <= h - border:
                out.append(c if moved is None else replace(c, at=moved(c.at)))
    return out


def _predict(params: np.ndarray, scale: bool, src: np.ndarray, miter: np.ndarray) -> np.ndarray:
    theta, tx, ty, grown = params[:4]
    s = math.exp(params[4]) if scale else 1.0
    c, sn = math.cos(theta), math.sin(theta)
    p = src + grown * miter
    return s * np.column_stack([c * p[:, 0] - sn * p[:, 1], sn * p[:, 0] + c * p[:, 1]]) + (tx, ty)


class _Matcher:
    """Mark corners, obstacle corners and the compatible pairs between them."""

    def __init__(self, marks: list[Corner], found: list[Corner], scale: bool, gate: float, tight: float):
        self.marks, self.found, self.scale, self.gate, self.tight = marks, found, scale, gate, tight
        self.src = np.array([c.at for c in marks], float).reshape(-1, 2)
        self.miter = np.array([c.miter for c in marks], float).reshape(-1, 2)
        self.dst = np.array([c.at for c in found], float).reshape(-1, 2)
        self.ok = np.array([[(m.turn > 0) == (f.turn > 0) and abs(m.turn - f.turn) <= TURN_MATCH
                             for f in found] for m in marks], bool).reshape(len(marks), len(found))
        self.pairs = np.argwhere(self.ok)

    def ransac(self, exclude: np.ndarray, rng: np.random.Generator):
        """The RANSAC model over the pairs not excluded, or None."""
        from skimage.measure import ransac
        from skimage.transform import EuclideanTransform, SimilarityTransform

        pairs = self.pairs[~exclude]
        if len(pairs) < 2:
            return None
        src, dst = self.src[pairs[:, 0]], self.dst[pairs[:, 1]]
        gate, lo, hi = self.gate, 1 / MAX_SCALE if self.scale else 1.0, MAX_SCALE if self.scale else 1.0

        def data_ok(s, d) -> bool:          # two distinct corners each side, as far apart (within the scale)
            ls, ld = math.dist(s[0], s[1]), math.dist(d[0], d[1])
            return ls > gate and lo * ls - 2 * gate <= ld <= hi * ls + 2 * gate

        def model_ok(model, *_) -> bool:
            scale = getattr(model, "scale", 1.0)
            return abs(math.degrees(model.rotation)) <= MAX_ROTATION and lo - 1e-9 <= scale <= hi + 1e-9

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model, inliers = ransac((src, dst), SimilarityTransform if self.scale else EuclideanTransform, 2, gate,
                                    is_data_valid=data_ok, is_model_valid=model_ok, max_trials=MAX_TRIALS,
                                    stop_probability=STOP_PROBABILITY, rng=rng)
        if model is None or inliers is None or inliers.sum() < 2:
            return None
        return model

    def near(self, predicted: np.ndarray, gate: float) -> list[tuple[int, int]]:
        """Mark corner -> its nearest compatible obstacle corner within ``gate`` of where
        it is predicted, one to one (the closest pairs first)."""
        if not len(self.dst):
            return []
        d = np.hypot(predicted[:, None, 0] - self.dst[None, :, 0], predicted[:, None, 1] - self.dst[None, :, 1])
        d = np.where(self.ok, d, np.inf)
        cand = sorted((d[i, j], i, j) for i, j in zip(*np.nonzero(d <= gate)))
        used_i, used_j, out = set(), set(), []
        for _, i, j in cand:
            if i not in used_i and j not in used_j:
                used_i.add(i)
                used_j.add(j)
                out.append((int(i), int(j)))
        return sorted(out)

    def refine(self, model) -> _Fit | None:
        """The least-squares fit from a RANSAC model, re-matched until its matches hold."""
        params = np.array([model.rotation, *model.translation, 0.0]
                          + ([math.log(model.scale)] if self.scale else []))
        gate, pairs = self.gate, []
        for _ in range(6):
            new = self.near(_predict(params, self.scale, self.src, self.miter), gate)
            if len(new) < 2:
                return None
            if new == pairs:
                break
            pairs = new
            i, j = np.array(pairs).T

            def resid(p, i=i, j=j):
                return (_predict(p, self.scale, self.src[i], self.miter[i]) - self.dst[j]).ravel()

            params = least_squares(resid, params, method="lm" if 2 * len(pairs) >= len(params) else "trf").x
            gate = self.tight
        i, j = np.array(pairs).T
        err = np.hypot(*(_predict(params, self.scale, self.src[i], self.miter[i]) - self.dst[j]).T)
        theta, tx, ty, grown = params[:4]
        s = math.exp(params[4]) if self.scale else 1.0
        rotation = math.degrees(math.remainder(theta, 2 * math.pi))
        residual = float(math.sqrt(np.mean(err ** 2)))
        return _Fit(Similarity(rotation, (float(tx), float(ty)), s, residual), float(grown), tuple(pairs), residual)

    def excluded_by(self, model, exclude: np.ndarray) -> np.ndarray:
        """``exclude`` with every pair ``model`` explains (within the gate) added."""
        pred = model(self.src[self.pairs[:, 0]])
        return exclude | (np.hypot(*(pred - self.dst[self.pairs[:, 1]]).T) < self.gate)


def register(layout: Layout, env: Environment, *, scale: bool = False, resolution: float = RESOLUTION,
             source: str | None = None, seed: int = 0, moved: Callable[[Point], Point] | None = None) -> Alignment:
    """Register ``layout`` (in its own frame, with marks) to the obstacles of ``env``.

    ``resolution`` is the scan's pixel size (nm): edges shorter than 6 pixels are not
    used, obstacle corners within 4 pixels (and twice the position tolerance) of the
    scan's border are left out. ``moved``: where a point of the scan truly is (a run
    takes out the drift of the row it was scanned in), applied to the obstacles' corners
    once they are found. Raises
    InputError naming ``source`` and ``mark`` when too few marks are found, the match is
    ambiguous or its residual is above ``layout.tolerance.position``.
    """
    tol = layout.tolerance.position
    min_edge, gap = max(6 * resolution, 40.0), max(10 * resolution, 100.0)
    gate, tight = max(100.0, 3 * tol, 10 * resolution), max(2 * tol, 4 * resolution)
    marks = _mark_corners(layout, min_edge, gap)
    found = _obstacle_corners(env, min_edge, gap, max(4 * resolution, 2 * tol), moved, resolution)
    n_marks = len(layout.marks)

    def fail(problem: str) -> InputError:
        return InputError(source, "mark", problem)

    if len(marks) < MIN_CORNERS:
        raise fail(f"the layout's {n_marks} mark(s) have {len(marks)} corner(s) with edges of {min_edge:g} nm or "
                   f"more; registration needs {MIN_CORNERS}")
    m = _Matcher(marks, found, scale, gate, tight)
    rng = np.random.default_rng(seed)
    exclude = np.zeros(len(m.pairs), bool)
    fits: list[_Fit] = []
    for _ in range(4):                          # the best fit, then rivals among what it leaves
        model = m.ransac(exclude, rng)
        if model is None:
            break
        exclude = m.excluded_by(model, exclude)
        fit = m.refine(model)
        if fit is not None and len(fit.pairs) >= MIN_CORNERS:
            fits.append(fit)
        if not fits:
            break
    if not fits:
        raise fail(f"too few marks found: fewer than {MIN_CORNERS} of the {len(marks)} corners of the layout's "
                   f"{n_marks} mark(s) match corners of the {len(env.obstacles)} obstacle(s) identified in the scan "
                   f"({len(found)} corners away from its border); are the marks in the scanned area? (--no-align "
                   "takes the layout's frame for the scan's)")
    best = max(fits, key=lambda f: (len(f.pairs), -f.residual))
    n = len(best.pairs)
    if best.residual > tol:
        raise fail(f"registration residual {best.residual:.1f} nm is above the layout's position tolerance "
                   f"{tol:g} nm ({n} mark corners matched; {best.transform.line()})")
    rivals = [other for other in fits if other is not best and other.residual <= tol
              and len(other.pairs) >= AMBIGUOUS_SHARE * n
              and np.hypot(*(best.transform.apply(m.src) - other.transform.apply(m.src)).T).max() > tight]
    if rivals:
        other = rivals[0]
        raise AmbiguousMatch(source, "mark", f"ambiguous match: the marks fit the scan as well at "
                             f"{best.transform.line()} ({n} corners) as at {other.transform.line()} "
                             f"({len(other.pairs)} corners); add a mark that tells them apart, or give --no-align",
                             tuple(_alignment(f, m, marks, n_marks) for f in (best, *rivals)))
    return _alignment(best, m, marks, n_marks)


def _alignment(fit: _Fit, m: _Matcher, marks: list[Corner], n_marks: int) -> Alignment:
    pairs = tuple(((float(m.src[i, 0] + fit.grown * m.miter[i, 0]), float(m.src[i, 1] + fit.grown * m.miter[i, 1])),
                   (float(m.dst[j, 0]), float(m.dst[j, 1]))) for i, j in fit.pairs)
    return Alignment(rounded(fit.transform), len(fit.pairs), len({marks[i].outline for i, _ in fit.pairs}),
                     n_marks, fit.grown, pairs)


def in_scan_frame(layout: Layout, env: Environment, align: str = "rigid", *, resolution: float = RESOLUTION,
                  source: str | None = None, seed: int = 0, moved: Callable[[Point], Point] | None = None
                  ) -> tuple[Layout, Alignment | None]:
    """``layout`` in the frame of the scan ``env`` was identified in, and its registration
    (None when it has no marks or ``align`` is ``none``: the layout frame is the scan's;
    ``moved``: see :func:`register`). Raises InputError (naming ``source``) when
    registration fails or a slot lies outside the scanned area."""
    if align not in ALIGNS:
        raise ValueError(f"align must be one of {ALIGNS}, got {align!r}")
    alignment = None
    if layout.marks and align != "none":
        alignment = register(layout, env, scale=align == "similarity", resolution=resolution, source=source,
                             seed=seed, moved=moved)
        layout = layout.mapped(alignment.transform, env.area)
    check_in_area(layout, env.area, source)
    return layout, alignment
