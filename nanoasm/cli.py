"""The ``nanoasm`` command line.

Every user error (bad file, bad option) ends in one line on stderr and a non-zero exit:
1 for a bad input file or value, 2 for a bad command line. No traceback, no partial
output file, and no output written over one of the command's inputs (:func:`_outputs_apart`).
SIGTERM ends a command as Ctrl-C does, in one line, with exit 143.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path
from typing import Annotated, NoReturn, Optional

import typer

try:  # typer >= 0.22 carries its own copy of click
    from typer._click import exceptions as cx
except ImportError:  # pragma: no cover - older typer on click
    from click import exceptions as cx

from . import __version__
from .errors import InputError, NanoasmError
from .listing import first

app = typer.Typer(
    name="nanoasm",
    help="Automated AFM nanoassembly: layouts, scenes, identification, planning, execution.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)
layout_app = typer.Typer(help="Check and convert target layouts (nanoasm.layout/1).",
                         no_args_is_help=True)
scene_app = typer.Typer(help="Check and generate simulated scenes (nanoasm.scene/1).",
                        no_args_is_help=True)
app.add_typer(layout_app, name="layout")
app.add_typer(scene_app, name="scene")

NATIVE = (".toml", ".json")


def _same_file(a: Path, b: Path) -> bool:
    """Whether paths ``a`` and ``b`` name one file: ``os.path.samefile`` when both exist
    (links, ``..``, another spelling), else their resolved paths."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    try:
        return a.resolve() == b.resolve()
    except (OSError, RuntimeError):
        return a.absolute() == b.absolute()


def _outputs_apart(outputs: list[tuple[str, Path | None]], inputs: list[tuple[str, Path | None]]) -> None:
    """Refuse, before anything is read or written, an output that is one of the inputs, or
    whose folder is missing or not writable: ``outputs`` and ``inputs`` pair the option
    (or argument) naming a file with it (None: not given). The one line names the output,
    its option and the input it would overwrite or the folder."""
    for option, out in outputs:
        for source, given in inputs:
            if out is not None and given is not None and _same_file(out, given):
                raise InputError(str(out), option, f"is also an input ({source}); an output never "
                                                   "overwrites an input")
    for option, out in outputs:                 # and where it goes can take it, before the work
        if out is None:
            continue
        parent = out.parent if str(out.parent) else Path(".")
        if not parent.is_dir():
            raise InputError(str(out), option, f"output folder {str(parent)!r} does not exist")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise InputError(str(out), option, f"output folder {str(parent)!r} is not writable")


def _version(value: bool) -> None:
    if value:
        print(f"nanoasm {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
) -> None:
    """Automated AFM nanoassembly."""


# -- layouts ------------------------------------------------------------------------

Scale = Annotated[Optional[float], typer.Option(help="nm per drawing unit (SVG, DXF without units).")]
Cell = Annotated[Optional[str], typer.Option(help="GDSII cell to read (default: the top cell).")]
RodDiameter = Annotated[Optional[float], typer.Option(help="Diameter in nm of rods drawn as DXF LINEs.")]
Area = Annotated[Optional[tuple[float, float]], typer.Option(metavar="W H",
                 help="Working area in nm when the drawing has none (GDSII, DXF).")]
Layer = Optional[str]


def _layer_option(kind: str, default: str) -> object:
    return typer.Option(metavar="L/D", help=f"GDSII layer/datatype of {kind} (default {default}).")


def _parse_layer(text: str | None, option: str) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        layer, _, datatype = text.partition("/")
        value = (int(layer), int(datatype or 0))
    except ValueError:
        raise InputError(None, option, f"must be LAYER/DATATYPE such as 1/0, got {text!r}") from None
    if min(value) < 0:
        raise InputError(None, option, f"layer and datatype must not be negative, got {text!r}")
    return value


def _read_layout(path: Path, options: dict):
    from nanoasm.cad.layout import layout_from_dict, load_layout

    given = {k: v for k, v in options.items() if v is not None}
    if path.suffix.lower() in NATIVE or not path.suffix:
        if given:
            raise InputError(str(path), None,
                             f"option(s) {', '.join('--' + k.replace('_', '-') for k in given)} "
                             "apply only to SVG, GDSII and DXF files")
        return load_layout(path)
    from nanoasm.cad.importers import import_layout

    notes: list[str] = []
    layout = layout_from_dict(import_layout(path, warnings=notes, **given), str(path))
    for note in notes:
        print(f"nanoasm: note: {note}", file=sys.stderr)
    return layout


MarksLayer = Annotated[Optional[str], typer.Option(metavar="LAYER", help="Alignment marks ([[mark]]): an SVG "
                       "class or group name, a GDSII LAYER/DATATYPE, a DXF layer (default: none).")]


def _importer_options(scale, cell, rod_diameter, area, particle_layer, rod_layer, keepout_layer,
                      area_layer, keepout_class, marks_layer=None) -> dict:
    return dict(
        scale=scale, cell=cell, rod_diameter=rod_diameter, area=area,
        particle_layer=_parse_layer(particle_layer, "--particle-layer"),
        rod_layer=_parse_layer(rod_layer, "--rod-layer"),
        keepout_layer=_parse_layer(keepout_layer, "--keepout-layer"),
        area_layer=_parse_layer(area_layer, "--area-layer"),
        keepout_class=keepout_class, marks_layer=marks_layer,
    )


@layout_app.command("check")
def layout_check(
    file: Annotated[Path, typer.Argument(help="Layout: TOML or JSON, or SVG, GDSII, DXF.")],
    scale: Scale = None, cell: Cell = None, rod_diameter: RodDiameter = None, area: Area = None,
    particle_layer: Annotated[Layer, _layer_option("particle slots", "1/0")] = None,
    rod_layer: Annotated[Layer, _layer_option("rod slots", "2/0")] = None,
    keepout_layer: Annotated[Layer, _layer_option("keep-outs", "3/0")] = None,
    area_layer: Annotated[Layer, _layer_option("the working area", "0/0")] = None,
    keepout_class: Annotated[Optional[str], typer.Option(help="SVG class of keep-outs (default keepout).")] = None,
    marks_layer: MarksLayer = None,
) -> None:
    """Validate a layout and print a summary."""
    opts = _importer_options(scale, cell, rod_diameter, area, particle_layer, rod_layer,
                             keepout_layer, area_layer, keepout_class, marks_layer)
    layout = _read_layout(file, opts)
    print(f"{file}: ok: {layout.summary()}")


@layout_app.command("convert")
def layout_convert(
    file: Annotated[Path, typer.Argument(help="SVG, GDSII (.gds), DXF, TOML or JSON layout.")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Output .toml or .json file.")],
    scale: Scale = None, cell: Cell = None, rod_diameter: RodDiameter = None, area: Area = None,
    particle_layer: Annotated[Layer, _layer_option("particle slots", "1/0")] = None,
    rod_layer: Annotated[Layer, _layer_option("rod slots", "2/0")] = None,
    keepout_layer: Annotated[Layer, _layer_option("keep-outs", "3/0")] = None,
    area_layer: Annotated[Layer, _layer_option("the working area", "0/0")] = None,
    keepout_class: Annotated[Optional[str], typer.Option(help="SVG class of keep-outs (default keepout).")] = None,
    marks_layer: MarksLayer = None,
) -> None:
    """Convert a CAD drawing (or a TOML/JSON layout) into a validated layout file."""
    if output.suffix.lower() not in NATIVE:
        raise InputError(str(output), None, "output must end in .toml or .json")
    _outputs_apart([("-o", output)], [("FILE", file)])
    opts = _importer_options(scale, cell, rod_diameter, area, particle_layer, rod_layer,
                             keepout_layer, area_layer, keepout_class, marks_layer)
    layout = _read_layout(file, opts)
    layout.save(output)
    print(f"{output}: written: {layout.summary()}")


# -- scenes -------------------------------------------------------------------------

Range = Optional[tuple[float, float]]


@scene_app.command("check")
def scene_check(file: Annotated[Path, typer.Argument(help="Scene: TOML or JSON.")]) -> None:
    """Validate a scene and print a summary."""
    from nanoasm.world.scene import load_scene

    scene = load_scene(file)
    print(f"{file}: ok: {scene.summary()}")


@scene_app.command("random")
def scene_random(
    output: Annotated[Path, typer.Option("-o", "--output", help="Output .toml or .json file.")],
    particles: Annotated[int, typer.Option(help="Number of particles.")] = 20,
    rods: Annotated[int, typer.Option(help="Number of rods.")] = 0,
    obstacles: Annotated[int, typer.Option(help="Number of rectangular obstacles.")] = 0,
    seed: Annotated[int, typer.Option(help="Random seed; the same seed gives the same scene.")] = 0,
    area: Annotated[tuple[float, float], typer.Option(metavar="W H", help="Area in nm.")] = (10000.0, 10000.0),
    particle_diameter: Annotated[tuple[float, float], typer.Option(metavar="MIN MAX")] = (60.0, 120.0),
    rod_length: Annotated[tuple[float, float], typer.Option(metavar="MIN MAX")] = (500.0, 1300.0),
    rod_diameter: Annotated[tuple[float, float], typer.Option(metavar="MIN MAX")] = (60.0, 100.0),
    obstacle_size: Annotated[tuple[float, float], typer.Option(metavar="MIN MAX")] = (300.0, 1500.0),
    obstacle_height: Annotated[tuple[float, float], typer.Option(metavar="MIN MAX")] = (20.0, 60.0),
    gap: Annotated[float, typer.Option(help="Least clearance between footprints, nm.")] = 50.0,
    drift: Annotated[Optional[tuple[float, float]], typer.Option(metavar="VX VY",
                     help="Steady drift velocity, nm/s (default: the world's own).")] = None,
    random_walk: Annotated[float, typer.Option(help="Random walk of the drift about its course, nm/sqrt(s).")] = 0.1,
    height_noise: Annotated[Optional[float], typer.Option(help="Height noise, nm RMS.")] = None,
    lever_spread: Annotated[float, typer.Option(help="Draw the lever's k, K_n, C1, C2, lateral gain and alpha "
                                                     "within this fraction of the seed's lever (0: nominal).")] = 0.2,
    layout: Annotated[Optional[Path], typer.Option("--layout", help="Also write a layout (.toml or .json) of "
                                                   "--slots slots that this scene can fill.")] = None,
    slots: Annotated[Optional[int], typer.Option(help="Slots of --layout: the sizes of the scene's particles "
                                                      "(then rods of L/d below 15) nearest its centre, "
                                                      "clustered about it on free ground.")] = None,
) -> None:
    """Generate a valid random scene (never an overlap), and with --layout a layout it can fill."""
    from nanoasm.world.random_scene import SceneSpec, random_scene
    from nanoasm.world.params import DriftParams, NoiseParams

    if output.suffix.lower() not in NATIVE:
        raise InputError(str(output), None, "output must end in .toml or .json")
    _outputs_apart([("-o", output)], [])
    if layout is not None:
        if layout.suffix.lower() not in NATIVE:
            raise InputError(str(layout), "--layout", "must end in .toml or .json")
        if slots is None:
            raise InputError(None, "--slots", "is required with --layout: how many slots the layout has")
        _outputs_apart([("--layout", layout)], [("-o", output)])
    elif slots is not None:
        raise InputError(None, "--slots", "goes with --layout OUT.toml (the layout to write)")
    if seed < 0:
        raise InputError(None, "--seed", f"must not be negative, got {seed}")
    drift_params = None if drift is None else _options(DriftParams, {"velocity": "--drift"},
                                                       velocity=drift, random_walk=random_walk)
    noise = None if height_noise is None else _options(NoiseParams, {"height_rms": "--height-noise"},
                                                       height_rms=height_noise)
    spec = SceneSpec(
        area=area, particles=particles, rods=rods, obstacles=obstacles,
        particle_diameter=particle_diameter, rod_length=rod_length, rod_diameter=rod_diameter,
        obstacle_size=obstacle_size, obstacle_height=obstacle_height, gap=gap, drift=drift_params, noise=noise,
        lever_spread=lever_spread,
    )
    scene = random_scene(spec, seed)
    matching = None
    if layout is not None:
        from nanoasm.cad.layout import layout_from_dict
        from nanoasm.world.random_layout import matching_layout

        matching = layout_from_dict(matching_layout(scene, slots, gap=gap, name=f"random-{seed}"),
                                    "generated layout")
    scene.save(output)
    print(f"{output}: written: {scene.summary()}")
    if matching is not None:
        matching.save(layout)
        print(f"{layout}: written: {matching.summary()}")


def _number(option: str, value: float, **limits) -> None:
    """A number option checked by the project's one check of a number; a bad one is the
    usual one-line error naming the option."""
    from nanoasm.param import check_number

    def fail(problem: str) -> NoReturn:
        raise InputError(None, option, problem)

    check_number(value, fail, **limits)


def _options(cls, names: dict[str, str] | None = None, **values):
    """``cls(**values)``: an option class checked by its own declaration (``param()``); a
    bad field is the usual one-line error naming its option (``names``, else ``--field-name``)."""
    from nanoasm.param import ParamError

    try:
        return cls(**values)
    except ParamError as err:
        option = (names or {}).get(err.key) or "--" + str(err.key).replace("_", "-")
        raise InputError(None, option, err.problem) from None


# -- identification -----------------------------------------------------------------

def _read_scan(scan: Path, pixel_size: float | None):
    """The height image of SCAN (``--pixel-size`` checked against the limits first), its
    warnings printed, one line each."""
    from nanoasm.world.readers import check_pixel_size, image_warnings, read_height_image

    if pixel_size is not None:
        check_pixel_size(pixel_size, None, "--pixel-size")
    image = read_height_image(scan, pixel_size=pixel_size)
    for line in image_warnings(image):
        print(f"nanoasm: warning: {line}", file=sys.stderr)
    return image


@app.command("identify")
def identify_cmd(
    scan: Annotated[Path, typer.Argument(help="Height image: .gwy .stp .jpk .spm .ibw .txt/.asc/.csv "
                                              ".xyz .npy .npz")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Output environment .json.")],
    cut: Annotated[Optional[float], typer.Option(help="Cut plane, nm above the levelled substrate "
                                                      "(default: from the height histogram).")] = None,
    min_area: Annotated[Optional[float], typer.Option(help="Smallest object area, nm^2.")] = None,
    pixel_size: Annotated[Optional[float], typer.Option(help="Pixel size, nm (.npy, bare ASCII).")] = None,
    tip_radius: Annotated[float, typer.Option(help="AFM tip radius, nm (first guess).")] = 10.0,
    plot: Annotated[Optional[Path], typer.Option(metavar="FILE", help="Also draw the levelled scan with what "
                                                 "was found here (.png, .svg or .pdf).")] = None,
) -> None:
    """Identify particles, rods, wires and obstacles in an AFM image (environment v1)."""
    from nanoasm import previews
    from nanoasm.world.identify import identify
    from nanoasm.world.limits import MAX_TIP_RADIUS

    if output.suffix.lower() != ".json":
        raise InputError(str(output), None, "output must end in .json")
    previews.check_plot_path(plot)
    _outputs_apart([("-o", output), ("--plot", plot)], [("SCAN", scan)])
    for option, value in (("--cut", cut), ("--min-area", min_area)):
        if value is not None:
            _number(option, value, positive=True)
    _number("--tip-radius", tip_radius, positive=True, hi=MAX_TIP_RADIUS)
    image = _read_scan(scan, pixel_size)
    env = identify(image, cut=cut, min_area=min_area, tip_radius=tip_radius)
    env.save(output)
    kinds = {k: sum(o.kind == k for o in env.objects) for k in ("particle", "rod", "wire")}
    edge = sum(o.edge for o in env.objects)
    print(f"{output}: written: {kinds['particle']} particle(s), {kinds['rod']} rod(s), "
          f"{kinds['wire']} wire(s), {len(env.obstacles)} obstacle(s); {edge} cut by the border")
    if plot is not None:
        previews.write_figure(previews.identify_figure(image, env, scan.name), plot)
        print(f"{plot}: written")


# -- planning -------------------------------------------------------------------------

NoAlign = Annotated[bool, typer.Option("--no-align", help="Do not register a layout with [[mark]]s to the scan: "
                                                         "take the layout's frame for the scan's.")]
AlignScale = Annotated[bool, typer.Option("--align-scale", help="Register a layout with [[mark]]s with the scale "
                                                               "free too (by default rotation and translation).")]


def _align(no_align: bool, align_scale: bool) -> str:
    """``PlanOptions.align`` from ``--no-align`` and ``--align-scale``."""
    if no_align and align_scale:
        raise InputError(None, "--align-scale", "does not go with --no-align")
    return "none" if no_align else "similarity" if align_scale else "rigid"


@app.command("plan")
def plan_cmd(
    layout_file: Annotated[Path, typer.Argument(metavar="LAYOUT", help="Layout (TOML/JSON).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Output plan .json.")],
    env_file: Annotated[Optional[Path], typer.Option("--env", help="Environment from identify.")] = None,
    scan: Annotated[Optional[Path], typer.Option("--scan", help="AFM image to identify first.")] = None,
    pixel_size: Annotated[Optional[float], typer.Option(help="Pixel size of --scan, nm.")] = None,
    planner: Annotated[str, typer.Option(help="OMPL planner for detours: rrtconnect, rrt, rrtstar, "
                                              "informedrrtstar, bitstar, prm, prmstar, fmt, kpiece, "
                                              "bkpiece, lbkpiece.")] = "rrtconnect",
    budget: Annotated[float, typer.Option(help="Planning effort per path, in work (about 1 s a unit here; a plan does not depend on the machine's load).")] = 1.0,
    tip_radius: Annotated[float, typer.Option(help="Tip radius, nm.")] = 10.0,
    margin: Annotated[float, typer.Option(help="Clearance beyond footprints and tip, nm.")] = 20.0,
    seed: Annotated[int, typer.Option(help="Seed of the planners' sampling.")] = 0,
    no_align: NoAlign = False,
    align_scale: AlignScale = False,
    plot: Annotated[Optional[Path], typer.Option(metavar="FILE", help="Also draw the plan here (.png, .svg or "
                                                 ".pdf): slots, objects, assignments, pushes, over the scan.")] = None,
) -> None:
    """Assign objects to slots and plan the pushes (plan v1)."""
    from nanoasm import previews
    from nanoasm.cad.layout import load_layout
    from nanoasm.planner.core import plan_assembly
    from nanoasm.planner.options import PlanOptions
    from nanoasm.world.environment import load_environment

    if output.suffix.lower() != ".json":
        raise InputError(str(output), None, "output must end in .json")
    if (env_file is None) == (scan is None):
        raise InputError(None, "--env/--scan", "give exactly one of --env ENV.json or --scan SCAN")
    previews.check_plot_path(plot)
    _outputs_apart([("-o", output), ("--plot", plot)], [("LAYOUT", layout_file), ("--env", env_file),
                                                         ("--scan", scan)])
    _check_planner(planner)
    options = _options(PlanOptions, tip_radius=tip_radius, margin=margin, planner=planner, budget=budget,
                       seed=seed, align=_align(no_align, align_scale))
    layout = load_layout(layout_file)
    resolution = image = None
    if env_file is not None:
        env = load_environment(env_file)
    else:
        from nanoasm.world.identify import identify

        image = _read_scan(scan, pixel_size)
        env, resolution = identify(image, tip_radius=tip_radius), image.pixel_size
    layout = _in_scan_frame(layout, env, options.align, resolution, str(layout_file))
    plan, stats = _with_progress("planning", lambda progress: plan_assembly(layout, env, options, progress))
    plan.save(output)
    print(f"{output}: written: {len(plan.assignment)} of {len(layout.targets)} slot(s) assigned, "
          f"{len(plan.operations)} push(es), {stats.parked} object(s) parked, "
          f"{len(plan.unfilled)} unfilled; {stats.wall_time:.2f} s")
    if stats.particle_turns:
        print(f"  particle paths: {stats.path_ratio:.3f} x straight length, "
              f"{sum(stats.particle_turns) / len(stats.particle_turns):.2f} turns per object")
    if stats.rod_pushes:
        print(f"  rods: {sum(stats.rod_pushes) / len(stats.rod_pushes):.1f} pushes per rod")
    shown, more = first(plan.unfilled)
    for u in shown:
        print(f"  unfilled {u.target}: {u.reason}")
    if more:
        print(f"  … and {more} more unfilled (see {output})")
    if plot is not None:
        previews.write_figure(previews.plan_figure(layout, env, plan, image), plot)
        print(f"{plot}: written")




def _in_scan_frame(layout, env, align: str, resolution: float | None, source: str):
    """The layout in the scan's frame (registered by its marks, the registration said on
    stderr), its slots checked to lie in the scanned area (:mod:`nanoasm.planner.alignment`)."""
    from nanoasm.planner.alignment import RESOLUTION, in_scan_frame

    layout, alignment = in_scan_frame(layout, env, align, resolution=resolution or RESOLUTION, source=source)
    if alignment is not None:
        print(f"nanoasm: {alignment.line()}", file=sys.stderr)
    return layout


def _with_progress(label: str, work):
    """Run ``work(progress)`` with a rich progress bar on a terminal (silent otherwise)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    if not sys.stderr.isatty():
        return work(None)
    with Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  transient=True) as bar:
        task = bar.add_task(label, total=None)

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        return work(progress)


# -- dry-run and run ------------------------------------------------------------------

LogFile = Annotated[Optional[Path], typer.Option("--log", help="Write the run log here (MCAP with Foxglove "
                                                 "schemas; nanoasm review reads it, Foxglove opens it).")]
Live = Annotated[bool, typer.Option("--live", help="Stream the run live over Foxglove's WebSocket "
                                    "protocol on 127.0.0.1 (open it in Foxglove).")]
LivePort = Annotated[int, typer.Option("--live-port", help="Port of the --live stream.")]
StrategyName = Annotated[str, typer.Option("--strategy", help="open-loop, local-scan, kalman, full or anchor.")]
#: Strategies whose final check scans know where the slots are (they estimate the drift
#: against the full scan): the ones a run on an instrument may use.
VERIFIED = ("full", "kalman")
ReportFile = Annotated[Optional[Path], typer.Option("--report", help="Write the report (JSON) here.")]
Resume = Annotated[Optional[Path], typer.Option("--resume", help="Go on with the stopped run of this log from "
                                                              "its last checkpoint (writes LOG-resumed.mcap "
                                                              "unless --log says otherwise).")]
Force = Annotated[bool, typer.Option("--force", help="Overwrite an existing --log file (and, for a dry-run, "
                                                     "the world kept beside it, LOG.sim).")]
PlanFile = Annotated[Optional[Path], typer.Option("--plan", help="Execute this reviewed plan (plan.json of nanoasm "
                                                  "plan) after the full scan instead of planning afresh; refused, "
                                                  "nothing pushed, when the scene changed since it was made.")]
Region = Annotated[Optional[tuple[float, float, float, float]], typer.Option(
    "--region", metavar="X0 Y0 X1 Y1", help="What the full scan covers, scanner nm (default: the layout's area "
                                            "centred in the scanner's range); its lower-left corner is the "
                                            "layout's origin.")]
Pixels = Annotated[Optional[int], typer.Option("--pixels", help="Pixels a side of the full scan, 16-4096 "
                                                                "(default: 10 nm a pixel).")]
ContactBatch = Annotated[Optional[int], typer.Option("--contact-batch", help="Pushes of particles that cannot "
                                                     "touch one another made in one contact phase, 1-64 (default 4; "
                                                     "1: each push scanned after before the next). A resumed run "
                                                     "keeps its log's.")]


def _check_fresh(resume: Path | None, plan: Path | None, region, pixels: int | None,
                 contact_batch: int | None = None) -> None:
    """``--plan``, ``--region``, ``--pixels`` and ``--contact-batch`` shape how a run
    starts: refused with ``--resume``; ``--contact-batch`` checked against its limits."""
    if contact_batch is not None:
        from nanoasm.executor.strategy import ExecOptions

        _options(ExecOptions, contact_batch=contact_batch)
    for option, value in (("--plan", plan), ("--region", region), ("--pixels", pixels),
                          ("--contact-batch", contact_batch)):
        if resume is not None and value is not None:
            raise InputError(None, option, "shapes how a run starts; a resumed run goes on from its log's "
                                           "checkpoint (not with --resume)")


def _check_log(log: Path | None, force: bool, kept: Path | None = None) -> None:
    """Refuse an existing ``--log`` file, or the world a dry-run keeps beside it (``kept``),
    unless ``--force``: checked before anything runs."""
    if log is None or force:
        return
    if os.path.lexists(log) and not log.is_dir():
        raise InputError(str(log), "--log", "exists; give --force to overwrite it")
    if kept is not None and os.path.lexists(kept) and not kept.is_dir():
        raise InputError(str(kept), "--log", "the world kept by a dry-run logged there exists; give --force "
                                             "to overwrite it")


def _check_run_options(strategy: str, report: Path | None) -> None:
    """The options dry-run and run share: a known strategy, a report that is JSON."""
    from nanoasm.executor.strategy import STRATEGIES

    if strategy not in STRATEGIES:
        raise InputError(None, "--strategy", f"unknown strategy {strategy!r}; one of {', '.join(STRATEGIES)}")
    if report is not None and report.suffix.lower() != ".json":
        raise InputError(str(report), None, "report must end in .json")


def _check_planner(planner: str) -> None:
    from nanoasm.planner.options import PLANNERS

    if planner not in PLANNERS:
        raise InputError(None, "--planner", f"unknown planner {planner!r}; one of {', '.join(PLANNERS)}")


def _run_progress(label: str, log_level: str | None = None):
    """Engine subscribers showing how far the run is (:func:`nanoasm.progress.run_progress`):
    timestamped log lines on stdout when it is not a terminal or ``--log-level`` is given, a
    progress bar on a terminal; the level is checked here, before the run."""
    from nanoasm.progress import run_progress

    return run_progress(label, log_level)


LogLevel = Annotated[Optional[str], typer.Option("--log-level", metavar="LEVEL", help="Say how the run goes "
                     "in timestamped log lines on stdout (debug, info, warning or error and above; info when "
                     "stdout is not a terminal) instead of the progress bar.")]


@app.command("dry-run")
def dry_run_cmd(
    scene_file: Annotated[Optional[Path], typer.Argument(metavar="SCENE", help="Scene (default: the "
                                                         "bundled bowtie example).")] = None,
    layout_file: Annotated[Optional[Path], typer.Argument(metavar="LAYOUT", help="Layout (default: "
                                                          "the bundled bowtie).")] = None,
    seed: Annotated[Optional[int], typer.Option(help="Seed of the simulated world (default: the "
                                                     "scene's).")] = None,
    strategy: StrategyName = "full",
    report: ReportFile = None,
    planner: Annotated[str, typer.Option(help="OMPL planner for detours.")] = "rrtconnect",
    budget: Annotated[float, typer.Option(help="Planning effort per path, in work (about 1 s a unit here; a plan does not depend on the machine's load).")] = 1.0,
    log: LogFile = None,
    live: Live = False,
    live_port: LivePort = 8765,
    resume: Resume = None,
    force: Force = False,
    no_align: NoAlign = False,
    align_scale: AlignScale = False,
    log_level: LogLevel = None,
    plan: PlanFile = None,
    region: Region = None,
    pixels: Pixels = None,
    contact_batch: ContactBatch = None,
) -> None:
    """Assemble LAYOUT in a simulated world holding SCENE, exactly as a real run would."""
    from nanoasm.dryrun import dry_run_files, resume_dry_run
    from nanoasm.examples import path as example
    from nanoasm.harness import LogTo
    from nanoasm.planner.options import PlanOptions
    from nanoasm.simkeep import sim_state_path

    _check_run_options(strategy, report)
    progress = _run_progress("dry-run", log_level)
    if resume is None and scene_file is None and layout_file is None:
        scene_file, layout_file = example("bowtie_scene.toml"), example("bowtie.toml")
    kept = None if log is None else sim_state_path(log)
    _check_fresh(resume, plan, region, pixels, contact_batch)
    _outputs_apart([("--log", log), ("--log", kept), ("--report", report)],
                   [("SCENE", scene_file), ("LAYOUT", layout_file), ("--resume", resume), ("--plan", plan),
                    ("the world kept for --resume", None if resume is None else sim_state_path(resume))])
    _check_log(log, force, kept)
    log_to = LogTo(log, live, live_port)
    if resume is not None:
        if scene_file is not None or layout_file is not None:
            raise InputError(None, "--resume", "takes the scene and the layout from the log; give neither")
        _check_planner(planner)
        plan_options = _options(PlanOptions, planner=planner, budget=budget)
        outcome, layout = resume_dry_run(resume, plan_options=plan_options, log=log_to, report=report,
                                         progress=progress)
        _print_summary(layout, outcome)
        return
    if (scene_file is None) != (layout_file is None):
        raise InputError(None, "SCENE LAYOUT", "give both a scene and a layout, or neither for the example")
    _check_planner(planner)
    plan_options = _options(PlanOptions, planner=planner, budget=budget, seed=seed or 0,
                            align=_align(no_align, align_scale))
    outcome, layout = dry_run_files(scene_file, layout_file, seed=seed, strategy=strategy,
                                    plan_options=plan_options, log=log_to, report=report,
                                    progress=progress, plan=plan, region=region, pixels=pixels,
                                    contact_batch=contact_batch)
    _print_summary(layout, outcome)
    if report is not None:
        print(f"{report}: written")


@app.command("run")
def run_cmd(
    layout_file: Annotated[Optional[Path], typer.Argument(metavar="LAYOUT", help="Layout (TOML/JSON); "
                                                          "not with --resume.")] = None,
    instrument: Annotated[Optional[Path], typer.Option(help="Instrument file (nanoasm.instrument/1); "
                                                           "required. Its backend: nidaq (NI-DAQmx, the "
                                                           "default) or nanonis (Nanonis TCP).")] = None,
    strategy: StrategyName = "full",
    report: ReportFile = None,
    log: LogFile = None,
    live: Live = False,
    live_port: LivePort = 8765,
    resume: Resume = None,
    force: Force = False,
    no_align: NoAlign = False,
    align_scale: AlignScale = False,
    log_level: LogLevel = None,
    plan: PlanFile = None,
    region: Region = None,
    pixels: Pixels = None,
    contact_batch: ContactBatch = None,
) -> None:
    """Assemble LAYOUT unattended on the instrument described by --instrument: an NI-DAQmx
    card (backend = "nidaq") or a Nanonis controller (backend = "nanonis")."""
    from nanoasm.harness import LogTo
    from nanoasm.planner.options import PlanOptions
    from nanoasm.run import run_files

    if instrument is None:
        raise InputError(None, "--instrument", "is required: the instrument file (nanoasm.instrument/1)")
    _check_run_options(strategy, report)
    if strategy not in VERIFIED:
        # without a drift estimate a check scan cannot tell a drifted object from a placed one:
        # its verdict would be as blind as its pushes (dry-runs compare it with the truth)
        raise InputError(None, "--strategy", f"{strategy} measures no drift, so its report could not say truly "
                                             f"which slots are filled; on an instrument use {' or '.join(VERIFIED)} "
                                             f"(the others are for dry-runs)")
    if resume is not None and layout_file is not None:
        raise InputError(None, "--resume", "takes the layout from the log; give no LAYOUT")
    if resume is None and layout_file is None:
        raise InputError(None, "LAYOUT", "is required (or --resume LOG)")
    _check_fresh(resume, plan, region, pixels, contact_batch)
    _outputs_apart([("--log", log), ("--report", report)],
                   [("LAYOUT", layout_file), ("--instrument", instrument), ("--resume", resume), ("--plan", plan)])
    _check_log(log, force)
    rep = run_files(instrument, layout_file, strategy=strategy, resume_from=resume,
                    log=LogTo(log, live, live_port), report=report, progress=_run_progress("run", log_level),
                    plan_options=PlanOptions(align=_align(no_align, align_scale)), plan=plan, region=region,
                    pixels=pixels, contact_batch=contact_batch)
    states = {s: sum(v.state == s for v in rep.slots) for s in ("filled", "missed", "unfilled")}
    print(f"run: {states['filled']} of {len(rep.targets)} slot(s) filled by the check scans "
          f"({states['missed']} missed, {states['unfilled']} unfilled), "
          f"{rep.counts.pushes} push(es), {rep.counts.failed_pushes} failed; "
          f"{rep.instrument_time.total / 60:.1f} min")
    if rep.plan is not None:
        print(f"  executed the reviewed plan {rep.plan}")
    shown, more = first(v for v in rep.slots if v.state != "filled")
    for v in shown:
        print(f"  {v.state} {v.target}" + ("" if v.error is None else f": {v.error:.1f} nm off"))
    if more:
        print(f"  … and {more} more not filled (the report lists every slot)")


def _print_summary(layout, outcome) -> None:
    """The dry-run's summary: the run's own verdict on every slot (its check scans), the
    simulated truth beside it, and a warning wherever the two differ."""
    from rich.console import Console
    from rich.table import Table as RichTable

    rep = outcome.report
    n = len(layout.targets)
    t = rep.instrument_time
    mine = outcome.verdict_filled
    table = RichTable(title=f"dry-run of {layout.name or 'layout'}: {len(mine)} of {n} slot(s) filled "
                            f"(the run's check scans)", show_header=False)
    error = (f"RMS error of the assigned slots filled {outcome.rms_error:.1f} nm" if outcome.filled
             else "no assigned slot filled: no error to measure")
    table.add_row("simulated truth", f"{len(outcome.truly_filled)} of {n} filled; {error}")
    found = outcome.summary.env
    kinds = ", ".join(f"{sum(o.kind == k for o in found.objects)} {k}(s)" for k in ("particle", "rod", "wire"))
    table.add_row("identified", f"{kinds}, {len(found.obstacles)} obstacle(s) in the full scan")
    if rep.plan is not None:
        table.add_row("plan", f"the reviewed plan {rep.plan}")
    if outcome.disagreements:
        table.add_row("[bold red]warning[/]", "the run's verdict differs from the truth on "
                      + ", ".join(outcome.disagreements))
    table.add_row("pushes (failed)", f"{rep.counts.pushes} ({rep.counts.failed_pushes})")
    table.add_row("local scans / replans", f"{rep.counts.local_scans} / {rep.counts.replans}")
    table.add_row("instrument time", f"{t.total / 60:.1f} min (full scan {t.full_scan / 60:.1f}, local scans "
                                     f"{t.local_scan / 60:.1f}, pushing {t.push / 60:.1f}, travel {t.travel / 60:.1f}, "
                                     f"mode switches {t.mode_switch / 60:.1f})")
    w = rep.wall_time
    table.add_row("wall time", f"{w.total:.1f} s (identify {w.identify:.1f}, plan {w.plan:.1f}, execute {w.execute:.1f})")
    reasons = {u.target: u.reason for u in rep.unfilled}
    shown, more = first(v for v in rep.slots if v.state != "filled")
    for v in shown:
        seen = "nothing found there" if v.error is None else f"{v.error:.1f} nm off"
        why = reasons.get(v.target, f"{v.object}: {seen}" if v.object else seen)
        table.add_row(f"{v.state} {v.target}", why)
    if more:
        table.add_row("…", f"and {more} more not filled (the report lists every slot)")
    Console().print(table)


# -- calibration ----------------------------------------------------------------------

@app.command("calibrate")
def calibrate_cmd(
    output: Annotated[Path, typer.Option("-o", "--output", help="Write the [cantilever], [friction] and "
                                         "[baseline] tables here (.toml, to paste into the instrument file).")],
    instrument: Annotated[Optional[Path], typer.Option(help="Calibrate the lever of this instrument file's "
                          "hardware, at the places its [calibration] table names.")] = None,
    dry_run: Annotated[Optional[Path], typer.Option("--dry-run", metavar="SCENE", help="Calibrate the "
                       "simulated AFM of this scene instead (its lever, over a calibration specimen).")] = None,
    seed: Annotated[Optional[int], typer.Option(help="Seed of the simulated instrument (--dry-run; default: "
                                                     "the scene's).")] = None,
    spring_constant: Annotated[Optional[float], typer.Option(help="The lever's k in N/m (default: the "
                               "instrument file's [cantilever] k).")] = None,
    plot: Annotated[Optional[Path], typer.Option(metavar="DIR", help="Also write a plot of each step into "
                                                                     "this folder (PNG).")] = None,
) -> None:
    """Measure the lever's constants through the instrument (seed 3.4-3.6): force curve, baselines,
    friction loops on the substrate and on a slope, a step edge."""
    from nanoasm.calibrate import calibrate_files

    if (instrument is None) == (dry_run is None):
        raise InputError(None, "--instrument/--dry-run", "give exactly one of --instrument FILE or --dry-run SCENE")
    if output.suffix.lower() != ".toml":
        raise InputError(str(output), None, "output must end in .toml")
    if spring_constant is not None:
        _number("--spring-constant", spring_constant, positive=True)
    if seed is not None and seed < 0:
        raise InputError(None, "--seed", f"must not be negative, got {seed}")
    _outputs_apart([("-o", output)], [("--instrument", instrument), ("--dry-run", dry_run)])
    cal = calibrate_files(output, instrument=instrument, scene=dry_run, seed=seed,
                          spring_constant=spring_constant, plot=plot)
    v = cal.values
    print(f"{output}: written: K_n = {v['K_n'].value:.2f} nm/V, C2 = {v['C2'].value:.2f} nm/V, k_l K_l / h = "
          f"{v['lateral_gain'].value:.2f} nN/V, alpha = {v['alpha'].value:.3f}, mu_ts = {v['mu_ts'].value:.3f}")
    if plot is not None:
        print(f"{plot}: 5 plot(s) written")


# -- sweeps ---------------------------------------------------------------------------

@app.command("sweep")
def sweep_cmd(
    families: Annotated[str, typer.Option(help="Scene families, comma-separated: tiny, sparse, dense, rods, "
                                               "mixed, device, allpushed, rodgap, wide, or all; "
                                               "scaleN: N particles at a constant density.")] = "sparse,dense,rods,mixed",
    seeds: Annotated[str, typer.Option(help="Seeds: numbers and ranges, e.g. 1-5 or 1,4,9.")] = "1-3",
    strategies: Annotated[str, typer.Option(help="open-loop, local-scan, kalman, full, anchor "
                                                 "(comma-separated), or all.")] = "full",
    drift: Annotated[str, typer.Option(help="Steady drift speeds, nm/s, comma-separated.")] = "0.3",
    knob: Annotated[Optional[list[str]], typer.Option(metavar="NAME=V1,V2", help="Also run each value of "
                    "one knob (an ExecOptions or PlanOptions field), the others at their defaults; "
                    "repeatable.")] = None,
    workers: Annotated[Optional[int], typer.Option(help="Local worker processes (default: the CPU "
                                                        "count).")] = None,
    scheduler: Annotated[Optional[str], typer.Option(metavar="ADDRESS", help="dask.distributed "
                         "scheduler, e.g. tcp://10.0.0.5:8786: run there instead.")] = None,
    output: Annotated[Optional[Path], typer.Option("-o", "--output", help="Write every run's row "
                                                   "here (.csv or .json).")] = None,
) -> None:
    """Dry-run generated scene families over seeds, strategies and knobs in parallel; one table."""
    from nanoasm import sweep as sw
    from nanoasm.executor.strategy import STRATEGIES

    def parsed(option: str, fn, *args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except ValueError as exc:
            raise cx.BadParameter(str(exc), param_hint=f"'{option}'") from None

    fams = parsed("--families", sw.parse_families, families)
    strats = parsed("--strategies", sw.parse_names, strategies, STRATEGIES, "strategy")
    seed_list = parsed("--seeds", sw.parse_seeds, seeds)
    drifts = parsed("--drift", sw.parse_numbers, drift, "drift speeds")
    knobs = dict(parsed("--knob", sw.parse_knob, k) for k in knob or ())
    cases = parsed("--knob", sw.grid, fams, seed_list, strats, drifts=drifts, knobs=knobs)
    if workers is not None and workers < 1:
        raise cx.BadParameter(f"must be at least 1, got {workers}", param_hint="'--workers'")
    if output is not None:
        if output.suffix.lower() not in (".csv", ".json"):
            raise cx.BadParameter("must end in .csv or .json", param_hint="'-o'")
        _outputs_apart([("-o", output)], [])
    try:
        rows = _with_progress(f"sweep: {len(cases)} dry-run(s)", lambda progress: sw.sweep(
            cases, workers=workers, scheduler=scheduler, progress=progress))
    except sw.Interrupted as stop:
        if output is not None and stop.rows:
            sw.write_table(stop.rows, output)
        kept = f"; their rows written to {output}" if output is not None and stop.rows else ""
        # typer turns KeyboardInterrupt into a silent exit 0 here: say it and exit 130
        interrupted = cx.ClickException(f"interrupted after {len(stop.rows)} of {stop.total} dry-run(s){kept}")
        interrupted.exit_code = 130
        raise interrupted from None
    if output is not None:
        sw.write_table(rows, output)
    _print_sweep(rows, sw.medians(rows))
    failed = [r for r in rows if r["error"]]
    for r in failed[:5]:
        print(f"sweep: {r['case']}: {r['error']}", file=sys.stderr)
    if output is not None:
        print(f"{output}: written: {len(rows)} row(s), {len(failed)} failed")


def _print_sweep(rows, groups) -> None:
    from rich.console import Console
    from rich.table import Table as RichTable

    table = RichTable(title=f"sweep: {len(rows)} dry-run(s), medians over seeds")
    cols = ("family", "drift", "strategy", "knob", "runs", "fill_rate", "rms_error_nm",
            "per_filled_slot_s", "bound_s", "ratio_after_scan", "ratio_after_scan_switch")
    heads = ("family", "drift nm/s", "strategy", "knob", "runs", "fill", "RMS nm (filled)",
             "s per filled slot", "bound s", "(T - scan) / bound", "/ (bound + mode switches)")
    for h in heads:
        table.add_column(h)
    for g in groups:
        table.add_row(*("-" if g[c] is None else f"{g[c]:.3g}" if isinstance(g[c], float) else str(g[c])
                        for c in cols))
    Console(width=None if sys.stdout.isatty() else 160).print(table)


# -- review ---------------------------------------------------------------------------

@app.command("review")
def review_cmd(
    log_file: Annotated[Path, typer.Argument(metavar="LOG", help="Run log (.mcap) of a dry-run or run.")],
    plot: Annotated[Optional[Path], typer.Option(help="Also plot the run here (.png, .svg or .pdf): "
                                                      "before/after scene, push paths, drift.")] = None,
) -> None:
    """Summarise a run log: slots filled, errors, pushes, failures, instrument time, drift."""
    from nanoasm.harness import warn
    from nanoasm.review import plot_review, print_review, review

    if plot is not None and plot.suffix.lower() not in (".png", ".svg", ".pdf"):
        raise InputError(str(plot), None, "plot must end in .png, .svg or .pdf")
    _outputs_apart([("--plot", plot)], [("LOG", log_file)])
    rev = review(log_file)
    warn(f"{log_file}: {line}" for line in rev.damage)
    print_review(rev)
    if plot is not None:
        plot_review(rev, plot)
        print(f"{plot}: written")


# -- entry point --------------------------------------------------------------------

class _Terminated(BaseException):
    """SIGTERM outside a run; within one the run engine raises its own ``Terminated``
    (after stopping the run and closing its log)."""

    stop_reason = "terminated (SIGTERM)"    # what a run log opened before its run says (harness.run_logs)


def _raise_terminated(signum, frame) -> NoReturn:
    raise _Terminated()


def _is_terminated(exc: BaseException) -> bool:
    engine = sys.modules.get("nanoasm.executor.engine")     # imported only by the commands that run
    return isinstance(exc, _Terminated) or (engine is not None and isinstance(exc, engine.Terminated))


def _ignore_further_stops() -> None:
    """Once a command ends on Ctrl-C or SIGTERM, another one is ignored: it would cut
    the line that says so, or end the process with a traceback and exit -2."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


def main(argv: list[str] | None = None, *, restore_signals: bool = True) -> int:
    """Run the CLI; returns (and, as a script, exits with) the exit code.

    SIGTERM ends the command as Ctrl-C does (a run stopped, its log closed, no output
    half-written), with the line ``nanoasm: terminated`` and exit 143 (128 + SIGTERM).
    The handlers of SIGINT and SIGTERM are as before on return, unless not
    ``restore_signals`` (the script, whose process ends then: a further Ctrl-C after an
    interrupted command stays ignored until it has)."""
    on_main_thread = threading.current_thread() is threading.main_thread()
    previous_int = signal.getsignal(signal.SIGINT) if on_main_thread else None
    previous = signal.signal(signal.SIGTERM, _raise_terminated) if on_main_thread else None
    try:
        return _main(argv)
    except BaseException as exc:
        if not _is_terminated(exc):
            raise
        _ignore_further_stops()
        print("nanoasm: terminated", file=sys.stderr)
        return 143
    finally:
        if on_main_thread and restore_signals:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
            signal.signal(signal.SIGINT, previous_int if previous_int is not None else signal.SIG_DFL)


def _main(argv: list[str] | None) -> int:
    command = typer.main.get_command(app)
    args = sys.argv[1:] if argv is None else argv
    try:
        rv = command.main(args=args, prog_name="nanoasm", standalone_mode=False)
        if rv == 130:           # typer turns Ctrl-C into this return value
            _ignore_further_stops()
            print("nanoasm: interrupted", file=sys.stderr)
            return 130
    except InputError as exc:
        print(f"nanoasm: error: {exc.line()}", file=sys.stderr)
        return 1
    except NanoasmError as exc:
        print(f"nanoasm: error: {exc}", file=sys.stderr)
        return 1
    except cx.NoArgsIsHelpError as exc:
        # typer/click print the help for a bare group; that is not an error for the user
        print(exc.ctx.get_help() if exc.ctx else "", file=sys.stdout)
        return 0
    except cx.UsageError as exc:
        where = exc.ctx.command_path if exc.ctx else "nanoasm"
        print(f"nanoasm: error: {exc.format_message()} (see '{where} --help')", file=sys.stderr)
        return 2
    except typer.Exit as exc:
        return exc.exit_code
    except (typer.Abort, KeyboardInterrupt):
        _ignore_further_stops()
        print("nanoasm: interrupted", file=sys.stderr)
        return 130
    except cx.ClickException as exc:
        print(f"nanoasm: error: {exc.format_message()}", file=sys.stderr)
        return exc.exit_code or 1
    except Exception as exc:  # a bug of ours: one line, the traceback on request
        if os.environ.get("NANOASM_DEBUG"):
            raise
        print(f"nanoasm: internal error: {type(exc).__name__}: {exc} "
              "(run with NANOASM_DEBUG=1 for the traceback, and please report it)", file=sys.stderr)
        return 3
    return 0


def script() -> None:
    from nanoasm.executor.stopping import ignore_after_stop, interrupt_outside_imports

    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        # Ctrl-C inside an extension module's import aborts the process (OMPL's, seen)
        signal.signal(signal.SIGINT, interrupt_outside_imports)
    ignore_after_stop()         # the process ends once a run is stopped: a further Ctrl-C cannot cut its last lines
    sys.exit(main(restore_signals=False))


if __name__ == "__main__":
    script()
