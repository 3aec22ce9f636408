"""Fixed features of the obstacles (electrodes, pads, debris) as drift references that
never run out, and the windows of the full scan that relocalise the estimate.

The first full scan shows the obstacles; :func:`~nanoasm.executor.fixed_features.find_features`
turns their straight edges and sharp corners into *features*, each a few *sites* where a
short scan line crosses an edge (an edge: two sites on it, measuring the coordinate
normal to it; a corner: one site on each of its two edges, measuring both). A site's
reference is where the full scan saw the edge's half-height crossing, at the time its
row was scanned; like an object's, it is taken out of that row's drift with the
estimated velocity when it is measured. :class:`Landmarks` keeps them with how often
each was missed, and the relocalisation windows
(:func:`~nanoasm.executor.registration.choose_windows`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import shapely

from .feature_types import Feature, feature_from_dict, feature_to_dict
from .fixed_features import find_features
from .reference_choice import Candidate, travel_cost
from .windows import Window, choose_windows

#: Extra reach of an edge line beyond 3σ of the edge's position, nm, plus the step's
#: height: room for the tip's broadening of the step and for flat levels on both sides.
EDGE_MARGIN = 50.0
#: Sample spacing of an edge line, nm.
EDGE_SPACING = 1.0
#: 1σ (nm) of a local line's crossing, assumed when choosing (measured 0.1-0.5 nm).
LINE_STD = 0.5
#: Variance (nm²) added to every site's measurement: what the full scan's pixels and
#: the identification of the step leave unexplained.
SITE_VAR = 1.0
#: A feature missed (not found, or found out of place) this many times in a row is retired.
RETIRE_AFTER = 3
#: An object this close (nm, beyond its radius and its position's 3σ) to a feature's
#: line spoils it: that feature is not chosen while the object is there.
CLEAR_OF_OBJECTS = 20.0


@dataclass
class Landmarks:
    """The run's fixed features (``features``: id -> Feature), when the full scan saw each
    site (``seen``: id -> instrument times), how many times in a row each was missed,
    the features retired, and the relocalisation windows (layout frame, best first)."""

    features: dict[str, Feature] = field(default_factory=dict)
    seen: dict[str, tuple[float, ...]] = field(default_factory=dict)
    misses: dict[str, int] = field(default_factory=dict)
    retired: set[str] = field(default_factory=set)
    windows: tuple[Window, ...] = ()
    rows: tuple[float, float] | None = None     # the full scan's first row time and line time, s

    @classmethod
    def of_scan(cls, image, obstacles, rows: tuple[float, float]) -> Landmarks:
        """The features of the first full scan (``image``, layout frame) and its
        identified ``obstacles``; ``rows``: the instrument time its first row started and
        the time of one line (row ``i`` was scanned at ``rows[0] + (i + 0.5) rows[1]``)."""
        feats = find_features(image, obstacles)
        t0, line = (float(v) for v in rows)
        seen = {f.id: tuple(t0 + (s.row + 0.5) * line for s in f.sites) for f in feats}
        return cls({f.id: f for f in feats}, seen, {}, set(), (), (t0, line))

    def choose_windows(self, image, side: float, avoid=None) -> None:
        """Relocalisation windows of side ``side`` (at most 0.8 of the image) in the full
        scan ``image``, away from ``avoid`` (a shapely geometry: what the plan moves)."""
        side = min(side, 0.8 * min(image.extent))
        self.windows = tuple(choose_windows(image, side, avoid=avoid)) if side > 20 * image.pixel_size else ()

    # -- where a feature is ---------------------------------------------------------------
    def sites(self, est, fid: str) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
        """Each site of ``fid`` as ``(layout point, normal, height, tau)``: the point
        taken out of its row's drift by the estimator ``est``; ``tau`` its row's time
        after the epoch."""
        out = []
        for s, t_seen in zip(self.features[fid].sites, self.seen[fid]):
            tau = t_seen - est.epoch
            out.append((est.unskew(np.asarray(s.point, float), tau), np.asarray(s.normal, float), s.height, tau))
        return out

    def measurement_cov(self, est, fid: str, line_stds=None) -> np.ndarray:
        """Covariance (nm²) of the components a scan of ``fid`` measures against the full
        scan: each line's own std (``line_stds``; None: a typical line, :data:`LINE_STD`,
        for choosing), its site's in the full scan and :data:`SITE_VAR` (the full scan's
        row drift is the filter's to know)."""
        feat = self.features[fid]
        line = np.full(len(feat.sites), LINE_STD) if line_stds is None else np.asarray(line_stds, float)
        return np.diag(line ** 2 + self.site_stds(fid) ** 2 + SITE_VAR)

    def taus(self, est, fid: str) -> list[float]:
        """When the full scan saw each site of ``fid``, s after the epoch."""
        return [ts - est.epoch for ts in self.seen[fid]]

    def site_stds(self, fid: str) -> np.ndarray:
        """The full scan's 1σ of each site of ``fid`` along its normal, nm."""
        return np.array([s.std for s in self.features[fid].sites])

    def check_stds(self, est, fid: str) -> np.ndarray:
        """Each site's 1σ along its normal with the velocity's share in taking its row's
        drift out: what two sites of one edge may disagree by, besides their lines."""
        return np.array([math.sqrt(s.std ** 2 + n @ est.skew_cov(tau) @ n)
                         for (_, n, _, tau), s in zip(self.sites(est, fid), self.features[fid].sites)])

    def reach(self, est, fid: str, t: float) -> float:
        """Half-length (nm) of the lines that scan ``fid`` at ``t``: 3σ of where each
        edge may be along its normal, plus the margin."""
        worst = 0.0
        for (_, n, h, _), s, C in zip(self.sites(est, fid), self.features[fid].sites, self.site_covs(est, fid, t)):
            var = n @ C @ n + s.std ** 2
            worst = max(worst, 3.0 * math.sqrt(max(var, 0.0)) + EDGE_MARGIN + h)
        return worst

    def site_covs(self, est, fid: str, t: float) -> list[np.ndarray]:
        """Covariance (nm²) of where each site of ``fid`` lies in the scanner frame at
        ``t``: the offset's and the row drift's taken out; before the velocity is known
        (the bootstrap), what that velocity's prior makes of the time since the row."""
        return [est.full_scan_cov(t, tau) for tau in self.taus(est, fid)]

    def within_room(self, est, fid: str, t: float) -> bool:
        """Whether every site of ``fid`` is known well enough along its edge at ``t``
        that its line crosses the same straight side (3σ within the site's ``room``)."""
        for (_, n, _, _), s, C in zip(self.sites(est, fid), self.features[fid].sites, self.site_covs(est, fid, t)):
            tangent = np.array([-n[1], n[0]])
            if 3.0 * math.sqrt(max(tangent @ C @ tangent, 0.0)) > s.room:
                return False
        return True

    # -- which to scan --------------------------------------------------------------------
    def candidates(self, ctx, est, t: float) -> list[Candidate]:
        """The features usable now, each with its cost and information: not retired, and
        no believed object near its lines."""
        if not self.features:
            return []
        objects = [(o, 3.0 * math.sqrt(max(float(np.linalg.eigvalsh(ctx.belief.seen[oid].cov)[-1]), 0.0)))
                   for oid, o in ctx.belief.objects.items() if oid not in ctx.belief.lost]
        tree = shapely.STRtree([o.geometry() for o, _ in objects]) if objects else None
        off = est.offset(t)
        out = []
        for fid, feat in self.features.items():
            if fid in self.retired or not self.within_room(est, fid, t):
                continue
            reach = self.reach(est, fid, t)
            sites = self.sites(est, fid)
            lines = [shapely.LineString([p - reach * n, p + reach * n]) for p, n, _, _ in sites]
            if tree is not None and self._spoilt(lines, tree, objects):
                continue
            R = self.measurement_cov(est, fid)
            H = feat.normals()
            gain = est.information(t, H, est.static_rows(H, self.taus(est, fid)), R)
            samples = len(sites) * int(2 * reach / EDGE_SPACING)
            seconds = (ctx.timing.seconds(len(sites), samples)
                       + travel_cost(ctx.here, sites[0][0] + off, ctx.config.max_speed))
            out.append(Candidate("feature", fid, H, R, seconds, gain))
        return out

    @staticmethod
    def _spoilt(lines, tree, objects) -> bool:
        for line in lines:
            for i in tree.query(line, predicate="dwithin", distance=500.0):
                o, r3 = objects[int(i)]
                if shapely.distance(line, o.geometry()) < o.radius + r3 + CLEAR_OF_OBJECTS:
                    return True
        return False

    # -- outcomes -------------------------------------------------------------------------
    def found(self, fid: str) -> None:
        self.misses.pop(fid, None)

    def missed(self, fid: str) -> bool:
        """``fid`` was not found, or not where it should be; True when that retires it."""
        self.misses[fid] = self.misses.get(fid, 0) + 1
        if self.misses[fid] >= RETIRE_AFTER:
            self.retired.add(fid)
            return True
        return False

    def forgive(self, labels) -> None:
        """The misses of ``labels`` were the drift's doing (it jumped), not the features'."""
        for fid in labels:
            self.misses.pop(fid, None)

    # -- checkpoints ----------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"features": [feature_to_dict(f) for f in self.features.values()],
                "seen": {k: list(v) for k, v in self.seen.items()}, "misses": dict(self.misses),
                "retired": sorted(self.retired),
                "windows": [[list(w.region), w.score] for w in self.windows],
                "rows": None if self.rows is None else list(self.rows)}

    @classmethod
    def from_state(cls, state: dict | None) -> Landmarks:
        if not state:
            return cls()
        feats = [feature_from_dict(d) for d in state["features"]]
        return cls({f.id: f for f in feats}, {k: tuple(float(x) for x in v) for k, v in state["seen"].items()},
                   {k: int(v) for k, v in state["misses"].items()}, set(state["retired"]),
                   tuple(Window(tuple(float(x) for x in r), float(s)) for r, s in state["windows"]),
                   None if state.get("rows") is None else tuple(float(v) for v in state["rows"]))


def moved_area(env, ops, layout, margin: float = 100.0):
    """What a plan may disturb (a shapely geometry): the objects it moves, their push
    paths and the slots, widened by ``margin`` nm; relocalisation windows keep away."""
    moving = {op.object for op in ops}
    parts = [o.geometry().buffer(o.radius + margin) for o in env.objects if o.id in moving]
    parts += [shapely.LineString(op.tip_path).buffer(margin) for op in ops if len(op.tip_path) > 1]
    parts += [t.geometry().buffer(t.radius + margin) for t in layout.targets]
    return shapely.union_all(parts) if parts else None
