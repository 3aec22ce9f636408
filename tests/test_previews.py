"""``identify --plot`` and ``plan --plot``: the pictures are written whole, show what was
found and planned (checked in the SVG: one outline per object, slot and push, the ids as
text, slots in the scan's frame), and a bad picture path is one line and exit 1."""

from __future__ import annotations

import contextlib
import io
import json
import re
import tomllib
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from nanoasm.cli import main
from nanoasm.examples import path as example
from nanoasm.planner.plan import load_plan
from nanoasm.previews import EDGE, identify_figure
from nanoasm.world.environment import Environment, EnvObject, EnvObstacle, load_environment

SHIFT = (-150.0, 100.0)           # the chip's frame against the scan's


def run(capsys, *args) -> tuple[int, list[str], str]:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out.splitlines(), err


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """A simulated full scan of the bundled mixed scene (22 objects, two electrode pads
    reaching the border, a particle cut by it)."""
    from nanoasm.world.readers import save_height_image
    from nanoasm.world.render import make_surface, render_scan
    from nanoasm.world.scene import load_scene

    scene = load_scene(example("mixed_scene.toml"))
    rng = np.random.default_rng(1)
    path = tmp_path_factory.mktemp("scan") / "mixed.npz"
    save_height_image(render_scan(make_surface(scene.objects, scene.obstacles, scene.area, rng=rng), 10.0,
                                  rng=rng), path)
    return path


@pytest.fixture(scope="module")
def identified(scan):
    """``identify SCAN -o env.json --plot found.svg``, once: its folder and stdout lines."""
    folder = scan.parent / "identified"
    folder.mkdir()
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["identify", str(scan), "-o", str(folder / "env.json"), "--plot", str(folder / "found.svg")])
    assert code == 0, err.getvalue()
    return folder, out.getvalue().splitlines()


def svg_of(path) -> ET.Element:
    return ET.fromstring(path.read_text())      # well-formed XML, or this fails


def gids(root: ET.Element, prefix: str) -> list[str]:
    return [g.get("id")[len(prefix) + 1:] for g in root.iter("{http://www.w3.org/2000/svg}g")
            if (g.get("id") or "").startswith(prefix + "-")]


def texts(root: ET.Element) -> list[str]:
    return [t.text for t in root.iter("{http://www.w3.org/2000/svg}text") if t.text]


def centre(root: ET.Element, gid: str) -> np.ndarray:
    """The middle of the bounding box of the outline with id ``gid``, in SVG units."""
    group = next(g for g in root.iter("{http://www.w3.org/2000/svg}g") if g.get("id") == gid)
    d = next(group.iter("{http://www.w3.org/2000/svg}path")).get("d")
    xy = np.array([float(v) for v in re.findall(r"-?\d+(?:\.\d+)?(?:e-?\d+)?", d)]).reshape(-1, 2)
    return (xy.min(axis=0) + xy.max(axis=0)) / 2


def only_files(folder, *names) -> None:
    """Nothing else in ``folder``: no temporary file left behind."""
    assert sorted(p.name for p in folder.iterdir()) == sorted(names)


def test_identify_svg_outlines_and_labels_every_object(identified):
    folder, out = identified
    env_file, plot = folder / "env.json", folder / "found.svg"
    assert out[0].startswith(f"{env_file}: written: 20 particle(s), 2 rod(s)") and out[1] == f"{plot}: written"
    env = load_environment(env_file)
    root = svg_of(plot)
    drawn = gids(root, "object")
    assert sorted(drawn) == sorted(o.id for o in env.objects) and len(drawn) == len(env.objects) == 22
    assert len(gids(root, "obstacle")) == len(env.obstacles) == 2
    labels = texts(root)
    edge = {o.id for o in env.objects if o.edge}
    assert edge and {o.id + EDGE for o in env.objects if o.edge} <= set(labels)
    assert {o.id for o in env.objects if not o.edge} <= set(labels)
    assert not {o.id for o in env.objects if o.edge} & set(labels)     # an edge object's label says so
    assert "height above the levelled substrate, nm" in labels and "x, nm" in labels
    only_files(folder, "env.json", "found.svg")


def test_plan_svg_draws_slots_in_the_scan_frame(scan, identified, tmp_path, capsys):
    """The chip's frame is shifted against the scan; registered by its marks (the pads),
    the slots are drawn where they lie in the scan, not where the chip file says."""
    doc = tomllib.loads(example("mixed.toml").read_text())
    for t in doc["target"]:
        t["at"] = [t["at"][0] + SHIFT[0], t["at"][1] + SHIFT[1]]
    doc["mark"] = [{"polygon": [[max(0.0, x + SHIFT[0]), y + SHIFT[1]] for x, y in k["polygon"]]}
                   for k in doc.pop("keepout")]
    chip, plan_file, plot = tmp_path / "chip.json", tmp_path / "plan.json", tmp_path / "plan.svg"
    chip.write_text(json.dumps(doc))
    code, out, err = run(capsys, "plan", chip, "--scan", scan, "-o", plan_file, "--budget", "0.05", "--plot", plot)
    assert code == 0, err
    assert "registered the layout to the scan" in err and out[-1] == f"{plot}: written"
    plan = load_plan(plan_file)
    root = svg_of(plot)
    slots = [t["id"] for t in doc["target"]]
    assert sorted(gids(root, "slot")) == sorted(slots) and set(slots) <= set(texts(root))
    assert sorted(gids(root, "push"), key=int) == [str(op.id) for op in plan.operations]
    assert sorted(gids(root, "assign")) == sorted(a.target for a in plan.assignment)
    objects = gids(root, "object")
    assert len(objects) == 22 and set(objects) <= {t.removesuffix(EDGE) for t in texts(root)}
    assert any(t.startswith("layout registered by its marks: ") for t in texts(root))

    # SVG units back to nm, from two objects' outlines (identify finds them at the scene's
    # places within a few nm), then each slot's outline against its place in the scan
    env = load_environment(identified[0] / "env.json")         # as plan --scan identifies it
    a, b = env.object("o1"), env.object("o22")
    ca, cb = centre(root, "object-o1"), centre(root, "object-o22")
    scale = (cb - ca) / (np.array(b.at) - np.array(a.at))

    def to_nm(p):
        return np.array(a.at) + (p - ca) / scale

    reg = plan.registration
    for t in doc["target"]:
        drawn = to_nm(centre(root, f"slot-{t['id']}"))
        assert np.hypot(*(drawn - reg.point(t["at"]))) < 3, t["id"]
        assert np.hypot(*(drawn - np.array(t["at"]))) > 150, t["id"]


def test_plan_png_from_an_environment(identified, tmp_path, capsys):
    from matplotlib.image import imread

    plot = tmp_path / "plan.png"
    code, out, err = run(capsys, "plan", example("mixed.toml"), "--env", identified[0] / "env.json",
                         "-o", tmp_path / "plan.json", "--budget", "0.05", "--plot", plot)
    assert code == 0 and out[0].startswith(f"{tmp_path / 'plan.json'}: written: 5 of 5 slot(s) assigned")
    assert out[-1] == f"{plot}: written", err
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    pixels = imread(plot)                   # decodes whole
    assert pixels.shape[0] > 500 and pixels.shape[1] > 500 and pixels.std() > 0.05
    only_files(tmp_path, "plan.json", "plan.png")


@pytest.mark.parametrize("command", ["identify", "plan"])
@pytest.mark.parametrize("name", ["out.jpg", "out", "out.svg.json"])
def test_a_plot_of_no_known_format_is_one_line(scan, tmp_path, capsys, command, name):
    args = ([example("mixed.toml"), "--scan"] if command == "plan" else []) + [scan]
    code, out, err = run(capsys, command, *args, "-o", tmp_path / "o.json", "--plot", tmp_path / name)
    assert code == 1 and not out
    assert err.splitlines() == [f"nanoasm: error: {tmp_path / name}: plot must end in .png, .svg or .pdf"]
    only_files(tmp_path)                # refused before any work: nothing written


def test_a_plot_over_an_input_is_refused(tmp_path, capsys):
    chip = tmp_path / "chip.svg"
    chip.write_text("<svg/>")
    (tmp_path / "sub").mkdir()
    plot = tmp_path / "sub" / ".." / "chip.svg"           # the same file by another path
    code, out, err = run(capsys, "plan", chip, "--env", tmp_path / "env.json", "-o", tmp_path / "p.json",
                         "--plot", plot)
    assert code == 1 and err.splitlines() == [f"nanoasm: error: {plot}: --plot: is also an input (LAYOUT); "
                                              "an output never overwrites an input"]
    assert chip.read_text() == "<svg/>" and not (tmp_path / "p.json").exists()


def test_kinds_and_the_border_are_drawn_apart(tmp_path):
    """Particles, rods, wires and obstacles each in their own style; what the border cuts
    dashed; written as a whole PDF."""
    from nanoasm.instrument import HeightImage
    from nanoasm.previews import COLOURS, OBSTACLE, write_figure

    env = Environment((1000.0, 1000.0), (
        EnvObject("p", "particle", (200.0, 200.0), 80.0),
        EnvObject("r", "rod", (500.0, 500.0), 60.0, 30.0, 400.0),
        EnvObject("w", "wire", (500.0, 800.0), 20.0, 0.0, 600.0),
        EnvObject("e", "particle", (20.0, 600.0), 80.0, edge=True)),
        (EnvObstacle(((700.0, 100.0), (900.0, 100.0), (900.0, 300.0)), 30.0),
         EnvObstacle(((0.0, 0.0), (100.0, 0.0), (0.0, 100.0)), 30.0, edge=True)))
    image = HeightImage(np.random.default_rng(0).normal(0.0, 0.3, (100, 100)), 10.0)
    fig = identify_figure(image, env)
    patches = {p.get_gid(): p for p in fig.axes[0].patches}
    colour = {gid: tuple(p.get_edgecolor()[:3]) for gid, p in patches.items()}
    assert len({colour["object-p"], colour["object-r"], colour["object-w"], colour["obstacle-1"]}) == 4
    from matplotlib.colors import to_rgb

    assert colour["object-w"] == to_rgb(COLOURS["wire"]) and colour["obstacle-1"] == to_rgb(OBSTACLE)
    dashed = {gid for gid, p in patches.items() if p.get_linestyle() in ("--", "dashed")}
    assert dashed == {"object-e", "obstacle-2"}
    assert {t.get_text() for t in fig.axes[0].texts} == {"p", "r", "w", "e" + EDGE}
    write_figure(fig, tmp_path / "kinds.pdf")
    data = (tmp_path / "kinds.pdf").read_bytes()
    assert data.startswith(b"%PDF-") and data.rstrip().endswith(b"%%EOF")
    only_files(tmp_path, "kinds.pdf")


def test_a_large_scan_is_drawn_thinned_without_losing_a_peak():
    from nanoasm.instrument import HeightImage
    from nanoasm.previews import SHOWN_PIXELS

    z = np.random.default_rng(1).normal(0.0, 0.3, (SHOWN_PIXELS + 77, SHOWN_PIXELS + 5))
    z[901, 333] = 50.0                                  # one pixel: a block's highest
    image = HeightImage(z, 2.0)
    fig = identify_figure(image, Environment(image.extent))
    (shown,) = fig.axes[0].images
    pixels = shown.get_array()
    assert max(pixels.shape) <= SHOWN_PIXELS and pixels.max() == pytest.approx(50.0, abs=1.0)
    x0, x1, y0, y1 = shown.get_extent()
    assert (x0, y0) == (0, 0) and x1 >= image.extent[0] and y1 >= image.extent[1]
    assert fig.axes[0].get_xlim() == (0, image.extent[0]) and fig.axes[0].get_ylim() == (0, image.extent[1])
