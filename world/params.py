"""Physical parameters of the simulated world, grouped in the scene file's tables.

Every default comes from the seed dissertation where it gives one (section cited in
the field's ``source``), otherwise it is a realistic value with a note. The scene's
``[drift]`` and ``[noise]`` tables have fixed keys (both required when the table is
given); every other table and key is optional. The world's truth is not the planner's
model: objects get a seeded per-object scatter in friction, adhesion, pivot and path
(``scatter`` keys), a scene may make its drift change (``[drift_change]``: settling and
jumps; off by default), and faults are off (probability 0) unless a scene turns them on.

``WorldParams.from_tables`` reads the tables of a scene, ``to_tables`` writes back only
what differs from the defaults, and :func:`params_markdown` renders the reference.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from nanoasm.errors import InputError
from nanoasm.instrument import InstrumentConfig
from nanoasm.instrument.protocol import MAX_SCANNER_SPEED
from nanoasm.param import ParamError, param, validate
from nanoasm.schema import Table

from .limits import (
    MAX_DRIFT_ACCELERATION,
    MAX_DRIFT_JUMP,
    MAX_DRIFT_RANDOM_WALK,
    MAX_DRIFT_SPEED,
    MAX_HEIGHT_NOISE,
    MAX_LEVER_GAIN,
    MAX_LEVER_LENGTH,
    MAX_OVERLAPPING_JUMPS,
    MAX_PAUSE,
    MAX_ROUGHNESS,
    MAX_ROUGHNESS_LENGTH,
    MAX_SAMPLE_TIME,
    MAX_SCAN_LINE_TIME,
    MAX_SCENE_TIP_RADIUS,
    MAX_STOP_TIME,
    MAX_VDW_AMPLITUDE,
    MAX_VDW_RANGE,
    MIN_JUMP_EVERY,
    MIN_LEVER_GAIN,
    MIN_LEVER_LENGTH,
    MIN_PUSH_SPEED,
    MIN_ROUGHNESS_LENGTH,
    MIN_SAMPLE_TIME,
    MIN_SCAN_LINE_TIME,
    MIN_STOP_TIME,
    MIN_TIP_RADIUS,
)
from .param_spec import from_table, markdown_rows, to_table


@dataclass(frozen=True)
class TipParams:
    """The tip apex."""

    radius: float = param(10.0, "nm", "apex radius", source="seed 3.4.1: apex diameter several nm "
                          "to tens of nm", positive=True, lo=MIN_TIP_RADIUS, hi=MAX_SCENE_TIP_RADIUS)
    half_angle: float = param(20.0, "deg", "open half angle γ of the apex; θ = θx + γ (eq. 4.1)",
                              source="not given in the seed; sharpened Si3N4 tips are 15-35°",
                              positive=True, hi=80.0)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class CantileverParams:
    """The lever, the photodiode and its spurious signals (ch. 3)."""

    k: float = param(0.12, "N/m", "normal spring constant", source="seed 3.4.2", positive=True)
    K_n: float = param(89.0, "nm/V", "normal signal gain δz = K_n S_n", source="seed 3.4.2, eq. 3.13",
                       positive=True, lo=MIN_LEVER_GAIN, hi=MAX_LEVER_GAIN)
    C1: float = param(1.3, "nm/V", "lateral tip displacement per volt of S̄l, δy = C1 S̄l",
                      source="seed 3.6.3; K_n h/l = 1.34", nonnegative=True)
    C2: float = param(23.0, "nm/V", "tip displacement along the lever per volt of S̄n, δx = C2 S̄n",
                      source="seed 3.6.4", nonnegative=True)
    lateral_gain: float = param(37.8, "nN/V", "k_l K_l / h, lateral force per volt of S_l",
                                source="seed 3.4.3", positive=True)
    alpha: float = param(0.18, "-", "normal-to-lateral cross-talk α, eq. 3.28", source="seed 3.5, "
                         "Fig. 3.17", lo=-1.0, hi=1.0)
    length: float = param(200000.0, "nm", "lever length l", source="seed 3.4.2: 200 µm", positive=True,
                          lo=MIN_LEVER_LENGTH, hi=MAX_LEVER_LENGTH)
    tip_height: float = param(3000.0, "nm", "tip height h, lever thickness included",
                              source="seed 3.4.2: 3 µm", positive=True)
    signal_limit: float = param(10.0, "V", "photodiode output saturates at ±signal_limit",
                                source="seed 3.6.4", positive=True)
    reflection_n: float = param(0.8, "V", "substrate-reflection offset of S_n near the surface, "
                                "A(i, j) of eq. 3.28", source="seed Fig. 3.14: -2.0 V to -1.2 V")
    reflection_l: float = param(0.12, "V", "offset of S_l near the surface, B(i, j) of eq. 3.28",
                                source="seed Fig. 3.14: 0 V to 0.12 V")
    signal_rms: float = param(0.005, "V", "photodiode noise per sample",
                              source="not given in the seed; a quiet quad detector", nonnegative=True)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class FrictionParams:
    """Friction coefficients (ch. 3.4.3, eq. 4.5) and their per-object scatter."""

    mu_ts: float = param(0.086, "-", "tip-substrate friction coefficient μ", source="seed 3.4.3",
                         nonnegative=True)
    mu_os: float = param(0.2, "-", "object-substrate sliding friction μos, eq. 4.5",
                         source="not given in the seed; Fig. 4.3 plots a range", nonnegative=True)
    nu: float = param(0.2, "-", "shear coefficient ν on the object-substrate adhesion, eq. 4.5",
                      source="seed Fig. 4.14-4.15", nonnegative=True)
    scatter: float = param(0.2, "-", "relative standard deviation of μos and ν per object",
                           source="the truth is not the model; 20 %", nonnegative=True, hi=1.0)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class AdhesionParams:
    """Adhesion forces (ch. 4.2.1): measured tip-substrate, others scaled by contact area."""

    tip_substrate: float = param(10.0, "nN", "tip-substrate adhesion F_ts^a, as a force curve measures it",
                                 source="not given in the seed; Si3N4 tips in air, 5-20 nN",
                                 nonnegative=True)
    object_ratio: float = param(20.0, "-", "object-substrate over tip-substrate adhesion, "
                                "F_os^a / F_ts^a; scales with contact area", source="seed Fig. 4.14",
                                nonnegative=True)
    pull_off_fraction: float = param(0.75, "-", "pull-off force over adhesion force, JKR",
                                     source="seed 4.2.1", positive=True, hi=1.0)
    scatter: float = param(0.3, "-", "relative standard deviation of adhesion per object",
                           source="the truth is not the model; 30 %", nonnegative=True, hi=1.0)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class PushParams:
    """How far the true motion of a pushed object departs from the model (ch. 4.3.2)."""

    pivot_scatter: float = param(0.03, "-", "standard deviation of a rod's pivot position, fraction "
                                 "of its length, about eq. 4.10", source="not in the seed; 3 %",
                                 nonnegative=True, hi=0.5)
    path_scatter: float = param(2.0, "deg", "standard deviation of a particle's direction of motion "
                                "about the push direction", source="not in the seed; 2°",
                                nonnegative=True, hi=45.0)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class VdwParams:
    """Random lateral error of objects that end close to others (seed 3.6.1)."""

    range: float = param(20.0, "nm", "gap to another object below which the error acts",
                         source="seed 3.6.1 gives no number; 20 nm", nonnegative=True, hi=MAX_VDW_RANGE)
    amplitude: float = param(5.0, "nm", "standard deviation of the error per axis",
                             source="seed 3.6.1 'a small position error'; 5 nm", nonnegative=True,
                             hi=MAX_VDW_AMPLITUDE)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class TimingParams:
    """How long the instrument takes for each activity (instrument time, not wall time)."""

    full_scan_line: float = param(1.0, "s", "one full-scan line, trace and retrace (1 Hz)",
                                  source="seed 9.2: several minutes per image (512 lines: 8.5 min)",
                                  positive=True, lo=MIN_SCAN_LINE_TIME, hi=MAX_SCAN_LINE_TIME)
    scan_line_sample: float = param(0.001, "s", "one sample of a local scan line (tapping mode)",
                                    source="same tip speed as a 1 Hz, 512-pixel full scan",
                                    positive=True, lo=MIN_SAMPLE_TIME, hi=MAX_SAMPLE_TIME)
    scan_line_overhead: float = param(0.2, "s", "settling before each local scan line",
                                      source="not in the seed", nonnegative=True, hi=MAX_PAUSE)
    mode_switch: float = param(2.0, "s", "switch between tapping (scan) and contact (push) mode, "
                               "approach or retract", source="seed 5.4 describes the switch; 2 s",
                               nonnegative=True, hi=MAX_PAUSE)
    push_speed: float = param(200.0, "nm/s", "tip speed while pushing: a dry-run pushes at it",
                              source="seed 4.2.2: >100 particles in half an hour", lo=MIN_PUSH_SPEED,
                              hi=MAX_SCANNER_SPEED)
    travel_speed: float = param(2000.0, "nm/s", "not read from a scene (refused there): a lifted tip "
                                "travels at the scanner's slew limit, `[scanner] max_speed`, on the "
                                "simulated instrument as on a real one", source="not in the seed",
                                positive=True)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class DriftParams:
    """Thermal drift of scanner versus sample: the scene's fixed `[drift]` table."""

    velocity: tuple[float, float] = param(
        (0.06, -0.04), "nm/s", "steady drift velocity: 260 nm per hour",
        source="seed 3.6.1: several hundred nm", required=True, lo=-MAX_DRIFT_SPEED, hi=MAX_DRIFT_SPEED)
    random_walk: float = param(
        0.1, "nm/√s", "random walk of the drift about its steady course (white noise on the "
        "velocity): Var x(t) = q² t per axis, 6 nm rms after 1 h", source="seed 3.6.1",
        required=True, nonnegative=True, hi=MAX_DRIFT_RANDOM_WALK)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class DriftChangeParams:
    """How the thermal drift departs from a steady velocity: settling and sudden jumps."""

    acceleration: tuple[float, float] = param(
        (0.0, 0.0), "nm/s²", "steady change of the drift velocity (thermal settling): the steady "
        "offset becomes v t + a t²/2", source="not in the seed; a drifting stage settles over hours",
        lo=-MAX_DRIFT_ACCELERATION, hi=MAX_DRIFT_ACCELERATION)
    jump: float = param(0.0, "nm", "size of a sudden offset jump (a knock, a thermal shock); 0: none",
                        source="not in the seed", nonnegative=True, hi=MAX_DRIFT_JUMP)
    jump_at: float = param(600.0, "s", "time of the first jump after the drift's zero (the simulated "
                           "instrument's start)", nonnegative=True)
    jump_every: float = param(0.0, "s", "period of repeated jumps (steps may overlap); 0: only once",
                              nonnegative=True)
    jump_duration: float = param(1.0, "s", "a jump is a smooth (C1) step over this time", positive=True,
                                 hi=MAX_PAUSE)

    def __post_init__(self) -> None:
        validate(self)
        if 0 < self.jump_every < MIN_JUMP_EVERY:
            raise ParamError("jump_every", f"must be 0 (one jump) or at least {MIN_JUMP_EVERY:g} s, "
                                           f"got {self.jump_every!r}")
        if self.jump_every > 0 and self.jump_duration > MAX_OVERLAPPING_JUMPS * self.jump_every:
            raise ParamError("jump_duration", f"must be at most {MAX_OVERLAPPING_JUMPS} x jump_every "
                                              f"({MAX_OVERLAPPING_JUMPS * self.jump_every:g} s: at most "
                                              f"{MAX_OVERLAPPING_JUMPS} jumps under way at once), "
                                              f"got {self.jump_duration:g}")


@dataclass(frozen=True)
class CreepParams:
    """Logarithmic piezo creep after large moves: γ s log10(1 + t / τ) along the step s."""

    amplitude: float = param(0.01, "1/decade", "creep γ, fraction of the step per decade of time",
                             source="typical open-loop piezo tubes 0.01-0.03; seed 3.7 defers to its "
                             "ref. [50]", nonnegative=True, hi=0.5)
    tau: float = param(0.1, "s", "time constant τ", source="typical t0 = 0.1 s", positive=True)
    min_step: float = param(500.0, "nm", "smaller moves add no creep term (carried into the next); a "
                            "motion creeps in pieces this long (at least 100 nm) as it goes",
                            source="model economy", nonnegative=True)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class NoiseParams:
    """Measurement noise: the scene's fixed `[noise]` table."""

    height_rms: float = param(0.3, "nm", "height noise per sample", required=True,
                              source="typical tapping-mode noise floor in air", nonnegative=True,
                              hi=MAX_HEIGHT_NOISE)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class FaultParams:
    """Rare failures, per push unless stated; all off by default."""

    stuck_object: float = param(0.0, "-", "probability that a pushed object does not move",
                                nonnegative=True, hi=1.0)
    tip_slip: float = param(0.0, "-", "probability that the tip slips over the object mid-push",
                            nonnegative=True, hi=1.0)
    lost_object: float = param(0.0, "-", "probability that a pushed object leaves the surface",
                               nonnegative=True, hi=1.0)
    tip_blunting: float = param(0.0, "-", "probability that the tip apex blunts", nonnegative=True,
                                hi=1.0)
    blunting_step: float = param(5.0, "nm", "apex radius gained per blunting", nonnegative=True)
    slip_after_min: float = param(0.5, "contact radii", "a tip_slip fault strikes after a push "
                                  "distance drawn between slip_after_min and slip_after_max", positive=True)
    slip_after_max: float = param(4.0, "contact radii", "see slip_after_min", positive=True)
    lost_min: float = param(2000.0, "nm", "a lost object jumps a distance drawn between lost_min "
                            "and lost_max, in a random direction", nonnegative=True)
    lost_max: float = param(10000.0, "nm", "see lost_min", nonnegative=True)

    def __post_init__(self) -> None:
        validate(self)
        if self.slip_after_max < self.slip_after_min or self.lost_max < self.lost_min:
            raise ParamError("slip_after_max" if self.slip_after_max < self.slip_after_min else "lost_max",
                             "must not be below its minimum")


@dataclass(frozen=True)
class SimParams:
    """How the simulated instrument and sample behave beyond the seed's equations."""

    roughness_rms: float = param(0.2, "nm", "substrate roughness", source="a smooth glass slide",
                                 nonnegative=True, hi=MAX_ROUGHNESS)
    roughness_length: float = param(50.0, "nm", "correlation length of the roughness", positive=True,
                                    lo=MIN_ROUGHNESS_LENGTH, hi=MAX_ROUGHNESS_LENGTH)
    line_offset_prob: float = param(0.02, "-", "probability of a whole-line height offset in a full scan",
                                    nonnegative=True, hi=1.0)
    line_offset_rms: float = param(0.5, "nm", "rms of such a line offset", nonnegative=True)
    piezo_tau: float = param(0.003, "s", "time constant of the piezo amplifier's low-pass between "
                             "DAC and scanner", positive=True)
    stop_time: float = param(0.05, "s", "XY at rest this long ends a move (creep counts moves)",
                             positive=True, lo=MIN_STOP_TIME, hi=MAX_STOP_TIME)
    capture_angle: float = param(45.0, "deg", "half-angle of the cone about the tip's motion within "
                                 "which a particle is carried", positive=True, hi=90.0)
    heading_length: float = param(30.0, "nm", "length of tip path over which its direction of "
                                  "motion is taken", positive=True)
    release: float = param(2.0, "nm", "clearance beyond contact within which a push continues",
                           nonnegative=True)
    bifurcation_band: float = param(0.02, "-", "half-width, as a fraction of L, of the band about a "
                                    "rod's middle where either end can become the pivot (eq. 4.10)",
                                    nonnegative=True, hi=0.5)
    uncertain_gain: float = param(3.0, "-", "scatter multiplier of pivot and path for rods with "
                                  "15 <= L/d <= 25 (seed 4.3.1: uncertain)", positive=True)
    reflection_decay: float = param(1000.0, "nm", "height over which the substrate-reflection "
                                    "baseline fades as the tip lifts", positive=True)
    wire_affect_fraction: float = param(0.25, "-", "radius of a wire's bending region as a fraction "
                                        "of its length (seed ch. 6 is empirical)", positive=True, hi=1.0)
    wire_affect_min: float = param(4.0, "diameters", "least radius of that region", positive=True)

    def __post_init__(self) -> None:
        validate(self)


_GROUPS: dict[str, type] = {
    "tip": TipParams, "cantilever": CantileverParams, "friction": FrictionParams,
    "adhesion": AdhesionParams, "push": PushParams, "vdw": VdwParams, "scanner": InstrumentConfig,
    "timing": TimingParams, "drift": DriftParams, "drift_change": DriftChangeParams, "creep": CreepParams,
    "noise": NoiseParams, "faults": FaultParams, "sim": SimParams,
}

#: The scene tables whose keys :class:`WorldParams` owns, in documentation order.
TABLES: tuple[str, ...] = tuple(_GROUPS)


@dataclass(frozen=True)
class WorldParams:
    """All physical parameters of a simulated world, one field per table."""

    tip: TipParams = field(default_factory=TipParams)
    cantilever: CantileverParams = field(default_factory=CantileverParams)
    friction: FrictionParams = field(default_factory=FrictionParams)
    adhesion: AdhesionParams = field(default_factory=AdhesionParams)
    push: PushParams = field(default_factory=PushParams)
    vdw: VdwParams = field(default_factory=VdwParams)
    scanner: InstrumentConfig = field(default_factory=InstrumentConfig)
    timing: TimingParams = field(default_factory=TimingParams)
    drift: DriftParams = field(default_factory=DriftParams)
    drift_change: DriftChangeParams = field(default_factory=DriftChangeParams)
    creep: CreepParams = field(default_factory=CreepParams)
    noise: NoiseParams = field(default_factory=NoiseParams)
    faults: FaultParams = field(default_factory=FaultParams)
    sim: SimParams = field(default_factory=SimParams)

    def __post_init__(self) -> None:
        for name, cls in _GROUPS.items():
            if not isinstance(getattr(self, name), cls):
                raise ParamError(name, f"must be a {cls.__name__}")

    @classmethod
    def from_tables(cls, tables: Mapping[str, Table]) -> WorldParams:
        """Read the given tables (any subset of :data:`TABLES`); absent ones keep defaults.

        A bad key or value raises :class:`~nanoasm.errors.InputError` naming the file
        and the key path, e.g. ``scene.toml: cantilever.Kn: unknown key (did you mean 'K_n'?)``.
        """
        kwargs = {}
        for name, t in tables.items():
            if name not in _GROUPS:
                raise InputError(t.source, t.path or name,
                                 f"unknown table (world tables: {', '.join(TABLES)})")
            if name == "timing" and "travel_speed" in t:
                t.fail("travel_speed", "has no effect: a lifted tip travels at the scanner's slew limit, "
                                       "so set [scanner] max_speed instead")
            kwargs[name] = from_table(_GROUPS[name], t)
        return cls(**kwargs)

    @classmethod
    def from_document(cls, doc: Table) -> WorldParams:
        """Read every world table present in a scene document (other keys are the caller's)."""
        return cls.from_tables({n: doc.table(n) for n in TABLES if n in doc})

    def to_tables(self) -> dict[str, dict]:
        """Non-default values only, per table; ``from_tables`` of the result is equal."""
        out = {}
        for name in TABLES:
            values = to_table(getattr(self, name))
            if values:
                out[name] = values
        return out


def params_markdown() -> str:
    """Reference of every world table, key, default, unit and meaning, as Markdown."""
    lines = []
    for name, cls in _GROUPS.items():
        doc = (cls.__doc__ or "").strip().splitlines()[0]
        lines += [f"### `[{name}]`", "", doc, "", "| key | default | unit | meaning | source |",
                  "| --- | --- | --- | --- | --- |", *markdown_rows(cls), ""]
    return "\n".join(lines).rstrip() + "\n"


__all__ = [
    "TABLES", "AdhesionParams", "CantileverParams", "CreepParams", "DriftChangeParams", "DriftParams",
    "FaultParams", "FrictionParams", "NoiseParams", "PushParams", "SimParams", "TimingParams", "TipParams",
    "VdwParams", "WorldParams", "params_markdown",
]

