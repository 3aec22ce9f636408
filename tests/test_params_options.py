"""The option classes are declared with nanoasm.param and checked by it alone."""

from __future__ import annotations

import ast
import dataclasses
import enum
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

import nanoasm.param as param_module
from nanoasm.drift import CreepModelParams, DriftFilterParams
from nanoasm.executor.dac_frames import LinearDrift
from nanoasm.executor.scan_lines import ScanOptions
from nanoasm.executor.strategy import ExecOptions, Strategy
from nanoasm.param import ParamError, check_number, is_param, number, param, validate
from nanoasm.planner.options import PlanOptions

OPTION_CLASSES = (ExecOptions, PlanOptions, DriftFilterParams, CreepModelParams, ScanOptions)
#: Fields an option class checks itself (a nested parameter group).
NOT_PARAMS = {(DriftFilterParams, "creep")}


@pytest.mark.parametrize("cls", OPTION_CLASSES, ids=lambda c: c.__name__)
def test_defaults_are_accepted_and_every_field_is_declared(cls):
    obj = cls()
    for f in dataclasses.fields(cls):
        if (cls, f.name) in NOT_PARAMS:
            assert not is_param(f)
            continue
        assert is_param(f), f.name
        assert f.metadata["doc"], f.name
        assert getattr(obj, f.name) == f.default
    assert dataclasses.replace(obj) == obj


BAD = [
    (ExecOptions, "pixel_size", math.nan),
    (ExecOptions, "r_max", -1.0),
    (ExecOptions, "line_factor", 0.0),
    (ExecOptions, "scan_spacing", math.inf),
    (ExecOptions, "push_speed", -200.0),
    (ExecOptions, "drift_q", -1e-6),
    (ExecOptions, "drift_q_offset", math.nan),
    (ExecOptions, "max_corrections", -1),
    (ExecOptions, "max_corrections", 2.0),
    (ExecOptions, "max_failures", 0),
    (ExecOptions, "chunk", 15),
    (ExecOptions, "force_limit", "300"),
    (ExecOptions, "strategy", "fast"),
    (PlanOptions, "tip_radius", 0.0),
    (PlanOptions, "margin", -1.0),
    (PlanOptions, "lead", math.nan),
    (PlanOptions, "planner", "astar"),
    (PlanOptions, "planner", 3),
    (PlanOptions, "budget", -1.0),
    (PlanOptions, "min_confidence", 1.5),
    (PlanOptions, "min_confidence", -0.1),          # a limit lo=0.0 holds (0.0 == False)
    (PlanOptions, "seed", -1),
    (PlanOptions, "seed", 1.5),
    (PlanOptions, "rod_swing", 61.0),
    (PlanOptions, "rod_swing", 0.0),
    (PlanOptions, "rod_push_point", 0.31),
    (PlanOptions, "rod_push_point", -0.01),
    (DriftFilterParams, "q_offset", -0.1),
    (DriftFilterParams, "gate_probability", 0.0),
    (DriftFilterParams, "gate_probability", 1.0),
    (DriftFilterParams, "time_tolerance", math.inf),
    (CreepModelParams, "amplitude_std", -0.01),
    (CreepModelParams, "max_moves", 1.0),
    (CreepModelParams, "tau", math.nan),
    (ScanOptions, "spacing", 0.0),
    (ScanOptions, "margin", -1.0),
    (ScanOptions, "fraction", 0.0),
    (ScanOptions, "fraction", 1.0),
    (ScanOptions, "height", math.nan),
    (ScanOptions, "noise_rms", -0.1),
    (ScanOptions, "max_lines", 1),
    (ScanOptions, "length_tolerance", 0.0),
    (ScanOptions, "taller", 0.9),
    (ScanOptions, "rod_height", -0.1),
]


@pytest.mark.parametrize("cls, name, value", BAD, ids=lambda v: getattr(v, "__name__", repr(v)))
def test_a_bad_value_is_a_value_error_naming_the_field(cls, name, value):
    with pytest.raises(ParamError) as e:
        cls(**{name: value})
    assert isinstance(e.value, ValueError)
    assert e.value.key == name and str(e.value).startswith(f"{name}: ")


def test_values_are_normalised():
    ex = ExecOptions(strategy="kalman", pixel_size=np.float32(5), scan_spacing=None, push_speed=None,
                     chunk=np.int64(64))
    assert ex.strategy is Strategy.KALMAN
    assert type(ex.pixel_size) is float and ex.pixel_size == 5.0
    assert ex.scan_spacing is None and ex.push_speed is None
    assert type(ex.chunk) is int and ex.chunk == 64
    assert PlanOptions(margin=0, lead=0, rod_push_point=0.3, rod_swing=60).clearance == 10.0
    assert DriftFilterParams(q=0).q == 0.0 and type(DriftFilterParams(q=0).q) is float


def test_the_messages_say_what_is_wrong():
    with pytest.raises(ValueError, match=r"^line_factor: must be positive, got -1.0$"):
        ExecOptions(line_factor=-1.0)
    with pytest.raises(ValueError, match=r"^strategy: must be one of 'open-loop', .*'anchor', got 'fast'$"):
        ExecOptions(strategy="fast")
    with pytest.raises(ValueError, match=r"^rod_push_point: must be at most 0.3, got 0.5$"):
        PlanOptions(rod_push_point=0.5)
    with pytest.raises(ValueError, match=r"^max_moves: must be an integer, got 1.0$"):
        CreepModelParams(max_moves=1.0)
    with pytest.raises(ValueError, match=r"^fraction: must be below 1, got 1.0$"):
        ScanOptions(fraction=1.0)


# -- the mechanism --------------------------------------------------------------------------------

class Colour(enum.Enum):
    RED = "red"
    BLUE = "blue"


@dataclass(frozen=True)
class Knobs:
    size: float = param(1.0, "nm", "a size", positive=True)
    count: int = param(3, "-", "a count", lo=1, hi=5)
    step: float | None = param(None, "nm", "a step or None", optional=True, nonnegative=True)
    name: str = param("a", "", "a name", choices=("a", "b"))
    label: str = param("x", "", "any string")
    colour: Colour = param(Colour.RED, "", "a colour")
    pair: tuple = param((0.0, 1.0), "nm", "two numbers", nonnegative=True)
    extra: list = field(default_factory=list)          # not a param: left to the class

    def __post_init__(self) -> None:
        validate(self)


def test_param_kinds():
    k = Knobs(size=2, step=0, name="b", label="anything", colour="blue", pair=[1, 2], extra=["kept"])
    assert (k.size, k.step, k.name, k.label, k.colour, k.pair, k.extra) == \
        (2.0, 0.0, "b", "anything", Colour.BLUE, (1.0, 2.0), ["kept"])
    for kwargs, message in [
        ({"size": 0.0}, "size: must be positive, got 0.0"),
        ({"count": 6}, "count: must be at most 5, got 6"),
        ({"count": True}, "count: must be an integer, got a boolean True"),
        ({"step": -1.0}, "step: must not be negative, got -1.0"),
        ({"name": "c"}, "name: must be one of 'a', 'b', got 'c'"),
        ({"label": 1}, "label: must be a string, got an integer 1"),
        ({"colour": "green"}, "colour: must be one of 'red', 'blue', got 'green'"),
        ({"pair": (1.0, -1.0)}, "pair: y must not be negative, got -1.0"),
        ({"pair": (1.0,)}, "pair: must be 2 numbers, got (1.0,)"),
        ({"size": None}, "size: must be a number, got null None"),
    ]:
        with pytest.raises(ParamError) as e:
            Knobs(**kwargs)
        assert str(e.value) == message


def test_param_refuses_what_it_cannot_check():
    with pytest.raises(TypeError, match="boolean"):
        param(True, "", "a flag")
    with pytest.raises(TypeError, match="optional"):
        param(None, "nm", "a size")


def test_number_and_check_number():
    assert number("x", np.float32(0.5)) == 0.5 and type(number("x", np.float64(2))) is float
    assert number("n", np.int64(7), integer=True) == 7 and type(number("n", np.int64(7), integer=True)) is int
    for value in (True, np.bool_(True), "1", None, [1.0], complex(1, 0)):
        with pytest.raises(ParamError, match=r"^x: must be a number"):
            number("x", value)
    with pytest.raises(ParamError, match=r"^x: must be finite, got nan$"):
        number("x", np.float64("nan"))
    problems = []

    def fail(problem):
        problems.append(problem)
        raise ValueError(problem)

    with pytest.raises(ValueError):
        check_number(2**1100, fail)
    assert problems == [f"must be finite, got a number too large for a float ({str(2**1100)[:12]}...)"]


def test_value_types_name_the_bad_number():
    with pytest.raises(ValueError, match=r"^offset\[1\]: must be finite, got nan$"):
        LinearDrift(offset=(0.0, math.nan))
    with pytest.raises(ValueError, match=r"^t_ref: must be a number"):
        LinearDrift(t_ref="0")


def test_the_param_module_imports_only_the_standard_library():
    """drift may import nanoasm.param, and drift imports nothing else of the project."""
    tree = ast.parse(Path(param_module.__file__).read_text())
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, "no relative imports"
            roots.add(node.module.split(".")[0])
    assert roots and roots <= set(sys.stdlib_module_names) | {"__future__"}, roots
