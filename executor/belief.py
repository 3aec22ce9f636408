"""What the executor believes about the sample: poses in the layout frame, and when and how
well each object was last seen."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from nanoasm.world.environment import EnvObject, Environment

from .json_parts import PartCache, Parts, PartsDict


@dataclass
class Seen:
    """Last sighting of an object: time (s), and the covariance (nm²) of its belief."""

    t: float
    cov: np.ndarray


class Objects(dict):
    """The believed objects by id, with an index of their positions (:meth:`near`) kept up
    to date as they are replaced: an object put back under its id takes its row; one
    added or removed has the index made anew when next asked."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._index: tuple[list[str], dict[str, int], np.ndarray, list[float]] | None = None

    def __setitem__(self, key: str, value: EnvObject) -> None:
        index = self._index
        if index is not None and key in index[1]:
            k = index[1][key]
            index[2][k] = value.at
            index[3][0] = max(index[3][0], value.length or value.diameter)
        else:
            self._index = None
        super().__setitem__(key, value)

    def __delitem__(self, key: str) -> None:
        self._index = None
        super().__delitem__(key)

    def pop(self, *args):
        self._index = None
        return super().pop(*args)

    def popitem(self):
        self._index = None
        return super().popitem()

    def clear(self) -> None:
        self._index = None
        super().clear()

    def update(self, *args, **kwargs) -> None:
        for k, v in dict(*args, **kwargs).items():
            self[k] = v

    def setdefault(self, key, default=None):
        if key not in self:
            self[key] = default
        return self[key]

    def __ior__(self, other):
        self.update(other)
        return self

    def __copy__(self) -> Objects:
        return Objects(self)                       # an index of its own

    def near(self, at, reach: float) -> list[str]:
        """Ids (in order) of the objects whose centre may lie within ``reach`` nm of ``at``
        plus the largest extent (length or diameter) of any: a superset of those within
        ``reach`` of ``at`` at their nearest, for a caller to test one by one."""
        if self._index is None:
            ids = list(self)
            xy = np.array([o.at for o in self.values()], float).reshape(-1, 2)
            self._index = (ids, {oid: k for k, oid in enumerate(ids)}, xy,
                           [max((o.length or o.diameter for o in self.values()), default=0.0)])
        ids, _, xy, extent = self._index
        x, y = float(at[0]), float(at[1])
        inside = np.hypot(xy[:, 0] - x, xy[:, 1] - y) <= reach + extent[0] + 1e-6 * (1.0 + reach)
        return [ids[k] for k in np.flatnonzero(inside)]


class Belief:
    """Poses of the objects (layout frame), their last sightings, and which are lost.

    ``touched`` holds objects pushed (on purpose) since they were last seen: their
    position is known only through the push model until the next scan.
    """

    def __init__(self, env: Environment, t0: float, cov0: float = 4.0):
        self.area = env.area
        self.obstacles = env.obstacles
        self.objects = Objects((o.id, o) for o in env.objects)
        self.seen: dict[str, Seen] = {o.id: Seen(t0, np.eye(2) * cov0) for o in env.objects}
        self.touched: set[str] = set()
        self.lost: set[str] = set()
        self._object_parts, self._seen_parts = PartCache(), PartCache()   # state_dict's (json_parts)

    def __getitem__(self, object_id: str) -> EnvObject:
        return self.objects[object_id]

    def observe(self, object_id: str, at, t: float, cov: np.ndarray, *, angle: float | None = None) -> None:
        o = self.objects[object_id]
        new_angle = o.angle if angle is None or not o.elongated else float(angle)
        self.objects[object_id] = replace(o, at=(float(at[0]), float(at[1])), angle=new_angle)
        self.seen[object_id] = Seen(t, np.asarray(cov, float))
        self.touched.discard(object_id)

    def reframe(self, object_id: str, shift) -> None:
        """The drift estimate its position was put into the layout frame by has moved by
        ``shift`` (nm, new less old offset): the same sighting, put there by the new one."""
        o = self.objects[object_id]
        at = np.asarray(o.at, float) - shift
        self.objects[object_id] = replace(o, at=(float(at[0]), float(at[1])))

    def expect(self, object_id: str, at, angle: float | None) -> None:
        """The object was pushed: its pose is now the push model's prediction."""
        o = self.objects[object_id]
        new_angle = o.angle if angle is None or not o.elongated else float(angle)
        self.objects[object_id] = replace(o, at=(float(at[0]), float(at[1])), angle=new_angle)
        self.touched.add(object_id)

    def add_new(self, kind: str, at, height: float, like: EnvObject, t: float, cov: np.ndarray) -> str:
        """An object seen where no believed object can be: added as ``new<k>`` (a particle
        ``height`` nm across; a rod takes the length and angle of ``like``, the object
        looked for). Returns its id."""
        k = 1 + sum(oid.startswith("new") for oid in self.objects)
        while f"new{k}" in self.objects:
            k += 1
        oid = f"new{k}"
        rod = kind != "particle" and like.elongated
        self.objects[oid] = EnvObject(oid, kind if rod else "particle", (float(at[0]), float(at[1])),
                                      float(height), like.angle if rod else None,
                                      max(like.length, float(height)) if rod else None, confidence=0.5)
        self.seen[oid] = Seen(t, np.asarray(cov, float))
        return oid

    def lose(self, object_id: str) -> None:
        self.lost.add(object_id)

    def taken(self, object_id: str, at) -> bool:
        """Whether another believed particle (not lost) overlaps particle ``object_id``
        placed at ``at`` by more than half the smaller's diameter: two objects cannot be
        there."""
        me = self.objects[object_id]
        if me.kind != "particle":
            return False
        return any(math.dist(o.at, at) < me.radius + o.radius - 0.5 * min(me.diameter, o.diameter)
                   for other, o in self.objects.items()
                   if other != object_id and other not in self.lost and o.kind == "particle")

    def forget(self, object_id: str) -> None:
        """``object_id`` was never an object of its own (another imaged twice): gone."""
        self.objects.pop(object_id, None)
        self.seen.pop(object_id, None)
        self.touched.discard(object_id)
        self.lost.discard(object_id)

    def to_dict(self) -> dict:
        return {"objects": [o.to_dict() for o in self.objects.values()],
                "lost": sorted(self.lost), "touched": sorted(self.touched)}

    def state_dict(self) -> dict:
        """Everything, for resuming a run: :meth:`to_dict` plus the sightings, area and
        obstacles (JSON types). Each object's and each sighting's part is the same
        (:func:`~.json_parts.kept`) from one checkpoint to the next while it stands."""
        objects = Parts(self._object_parts.parts(self.objects.items(), lambda o: o.to_dict()))
        sights = []
        for k, v in self.seen.items():
            cov = np.asarray(v.cov, float)
            sights.append((k, (v.t, cov.shape, cov.tobytes())))
        seen = PartsDict(zip(self.seen, self._seen_parts.parts(
            sights, lambda s: {"t": s[0], "cov": np.frombuffer(s[2]).reshape(s[1]).tolist()})))
        return PartsDict(objects=objects, lost=sorted(self.lost), touched=sorted(self.touched),
                         area=list(self.area), obstacles=[ob.to_dict() for ob in self.obstacles], seen=seen)

    @classmethod
    def from_state(cls, state: dict) -> Belief:
        """The belief :meth:`state_dict` wrote."""
        from nanoasm.world.environment import FORMAT as ENV_FORMAT, environment_from_dict

        env = environment_from_dict({"format": ENV_FORMAT, "area": state["area"],
                                     "objects": state["objects"], "obstacles": state["obstacles"]},
                                    "checkpoint")
        b = cls(env, 0.0)
        b.seen = {k: Seen(float(v["t"]), np.asarray(v["cov"], float)) for k, v in state["seen"].items()}
        b.lost, b.touched = set(state["lost"]), set(state["touched"])
        return b
