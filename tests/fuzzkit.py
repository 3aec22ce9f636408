"""The fuzz corpus of issue 15: a small valid seed file per kind of file nanoasm reads,
the mutations that make hostile files of them, the command that reads each kind, and a
worker process that runs ``nanoasm`` on many files under a memory limit.

The corpus grows in two ways: ``tests/fuzz_corpus/KIND/`` holds tiny files that once
broke a command (add one there whenever a fuzz test or a user finds another), and
:data:`HOSTILE` generates the issue's hostile files that are too large to keep. Every
file of both must be refused by its command: exit 1, one line naming the file.

Run as a script (``python fuzzkit.py``), this module is the worker: it reads one JSON
argument list a line and answers each with the exit code, stderr, seconds and peak memory
of ``nanoasm ARGS`` run in its own process.
"""

from __future__ import annotations

import functools
import io
import json
import os
import random
import re
import resource
import select
import subprocess
import sys
import tempfile
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CORPUS = HERE / "fuzz_corpus"
EXAMPLES = REPO / "examples"
GOLDEN = HERE / "golden"

MEMORY = 1 << 30          # bytes of address space a command may map
SECONDS = 10.0            # the most CPU time a command may take on a hostile file
#: The longest a command may take by the clock before it counts as hung: CPU time is
#: what the command costs, the clock also what else loads the machine (tests share it).
HUNG = 3 * SECONDS


def limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY, MEMORY))


def cli_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "NANOASM_DEBUG"}
    env.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return env


# == seeds: one small valid file per kind ==============================================

def _npy(array) -> bytes:
    import numpy as np

    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return buf.getvalue()


def _heights():
    """Three particles on a flat, slightly noisy substrate (nm), 128 x 128 pixels."""
    from test_hostile_inputs import _particles

    return _particles()


def seed_npy() -> bytes:
    return _npy(_heights())


def seed_npz() -> bytes:
    import numpy as np

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("height.npy", _npy(_heights()))
        zf.writestr("pixel_size.npy", _npy(np.float64(10.0)))
        zf.writestr("origin.npy", _npy(np.zeros(2)))
    return buf.getvalue()


def _toml_to_json(text: str) -> bytes:
    import tomllib

    return json.dumps(tomllib.loads(text), indent=1).encode()


def seed_scene_json() -> bytes:
    return _toml_to_json((EXAMPLES / "particles_scene.toml").read_text())


SVG_HEAD = ('<svg xmlns="http://www.w3.org/2000/svg" xmlns:xlink="http://www.w3.org/1999/xlink" '
            'viewBox="0 0 1000 1000">\n')


def seed_svg() -> bytes:
    body = ('<defs><g id="cell"><circle cx="0" cy="0" r="10"/>'
            '<line x1="20" y1="0" x2="60" y2="0" stroke-width="8"/></g></defs>'
            '<use href="#cell" x="100" y="100"/><use xlink:href="#cell" x="300" y="500"/>'
            '<rect class="keepout" x="700" y="700" width="100" height="50"/>')
    return (SVG_HEAD + body + "</svg>\n").encode()


def seed_gds() -> bytes:
    from test_hostile_cad import gds_aref, gds_circle, gds_library, gds_polygon, gds_sref

    return gds_library([("P", [gds_circle(100, 100)]),
                        ("TOP", [gds_polygon(3, [(2000, 0), (3000, 0), (3000, 500)]),
                                 gds_aref("P", 3, 2, pitch=400), gds_sref("P")])])


def seed_dxf() -> bytes:
    from test_hostile_cad import dxf_doc

    doc = dxf_doc()
    doc.blocks.new("P").add_circle((0, 0), 10)
    msp = doc.modelspace()
    msp.add_blockref("P", (100, 100)).grid(size=(2, 2), spacing=(200, 100))
    msp.add_line((500, 500), (900, 500), dxfattribs={"lineweight": 50})
    buf = io.StringIO()
    doc.write(buf)
    return buf.getvalue().encode()


TINY_SCENE = """format = "nanoasm.scene/1"
area = [1500, 1500]
seed = 2
[[object]]
kind = "particle"
at = [400, 500]
diameter = 85
[[object]]
kind = "particle"
at = [1100, 1000]
diameter = 90
[drift]
velocity = [0.1, 0.05]
random_walk = 0.05
"""
TINY_LAYOUT = """format = "nanoasm.layout/1"
area = [1500, 1500]
[[target]]
kind = "particle"
at = [750, 750]
diameter = 90
"""


@functools.cache
def _logged_run() -> tuple[bytes, bytes]:
    """The run log (300 kB) and kept world of a dry-run filling one slot (about 3 s, once)."""
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "scene.toml").write_text(TINY_SCENE)
        (d / "layout.toml").write_text(TINY_LAYOUT)
        result = run_cli(["dry-run", "scene.toml", "layout.toml", "--log", "run.mcap"], d)
        assert result.code == 0, result.err
        return (d / "run.mcap").read_bytes(), (d / "run.mcap.sim").read_bytes()


def seed_mcap() -> bytes:
    return _logged_run()[0]


def kept_world() -> dict[str, bytes]:
    """What a dry-run's log keeps beside it: ``LOG.sim``, the world a resume goes on with."""
    return {".sim": _logged_run()[1]}


# == the command that reads each kind ==================================================

#: The layout a command reading another kind of file is given.
LAYOUT = GOLDEN / "layout_input.toml"


@dataclass(frozen=True)
class Kind:
    """One kind of file: its suffix, its seed, and ``nanoasm ARGS`` reading ``path`` and
    writing (at most) ``out``."""

    name: str
    suffix: str
    seed: Callable[[], bytes]
    args: Callable[[Path, Path], list[str]]
    out_suffix: str = ".json"
    text: bool = True           # mutate numbers and values as text too
    beside: Callable[[], dict[str, bytes]] | None = None    # files kept beside it, by suffix


def _convert(path: Path, out: Path) -> list[str]:
    return ["layout", "convert", str(path), "-o", str(out)]


def _identify(path: Path, out: Path) -> list[str]:
    size = ["--pixel-size", "10"] if path.suffix == ".npy" else []
    return ["identify", str(path), "-o", str(out), *size]


KINDS: dict[str, Kind] = {k.name: k for k in (
    Kind("layout-toml", ".toml", lambda: LAYOUT.read_bytes(), _convert, ".toml"),
    Kind("layout-json", ".json", lambda: _toml_to_json(LAYOUT.read_text()), _convert, ".toml"),
    Kind("scene", ".toml", lambda: (EXAMPLES / "particles_scene.toml").read_bytes(),
         lambda p, o: ["scene", "check", str(p)]),
    Kind("scene-json", ".json", seed_scene_json, lambda p, o: ["scene", "check", str(p)]),
    Kind("env", ".json", lambda: (GOLDEN / "env.json").read_bytes(),
         lambda p, o: ["plan", str(LAYOUT), "--env", str(p), "-o", str(o), "--budget", "0.05"]),
    # no command reads a plan: ``plan-check`` is the worker's own (load_plan, errors as the CLI's)
    Kind("plan", ".json", lambda: (GOLDEN / "plan.json").read_bytes(), lambda p, o: ["plan-check", str(p)]),
    Kind("instrument", ".toml", lambda: (EXAMPLES / "instrument_ni.toml").read_bytes(),
         lambda p, o: ["run", str(LAYOUT), "--instrument", str(p), "--report", str(o)]),
    Kind("svg", ".svg", seed_svg, _convert, ".toml"),
    Kind("gds", ".gds", seed_gds, lambda p, o: [*_convert(p, o), "--area", "3000", "3000"], ".toml",
         text=False),
    Kind("dxf", ".dxf", seed_dxf, lambda p, o: [*_convert(p, o), "--area", "2000", "1000", "--rod-diameter", "20"], ".toml"),
    Kind("npy", ".npy", seed_npy, _identify, text=False),
    Kind("npz", ".npz", seed_npz, _identify, text=False),
    Kind("mcap-review", ".mcap", seed_mcap, lambda p, o: ["review", str(p), "--plot", str(o)], ".svg",
         text=False),
    Kind("mcap-resume", ".mcap", seed_mcap,
         lambda p, o: ["dry-run", "--resume", str(p), "--log", str(o), "--report", str(o) + ".json"], ".mcap",
         text=False, beside=kept_world),
)}

#: Lines an accepted file may leave on stderr (warnings), and the one a run on a valid
#: instrument file ends with on a machine without NI-DAQmx.
ACCEPTED_STDERR = re.compile(r"nanoasm: (?:warning|note): |nanoasm: error: NI-DAQmx driver not found")


# == hostile files too large to keep in the corpus ======================================

def _deep_svg() -> bytes:
    n = 100_000
    return (SVG_HEAD + "<g>" * n + '<circle cx="5" cy="5" r="1"/>' + "</g>" * n + "</svg>\n").encode()


def _npz_bomb() -> bytes:
    """A 6.7 GB height array in a few kB: a deflated member declaring 30000 x 30000."""
    import numpy as np

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("height.npy", "w", force_zip64=True) as fh:
            np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False,
                                                      "shape": (30000, 30000)})
            for _ in range(8):
                fh.write(bytes(1 << 20))
        zf.writestr("pixel_size.npy", _npy(np.float64(10.0)))
        zf.writestr("origin.npy", _npy(np.zeros(2)))
    return buf.getvalue()


def _npy_near_float_limit() -> bytes:
    return _npy(_heights() * 1e306)


def _many_targets() -> bytes:
    rows = "".join(f'[[target]]\nkind = "particle"\nat = [{10 + 20 * (k % 1000)}, {10 + 20 * (k // 1000)}]\n'
                   f"diameter = 5\n" for k in range(100_000))
    return ('format = "nanoasm.layout/1"\narea = [20000, 20000]\n' + rows).encode()


#: (kind, file name, bytes): the issue's hostile files that are generated, not kept.
HOSTILE: list[tuple[str, str, Callable[[], bytes]]] = [
    ("svg", "deep-groups.svg", _deep_svg),
    ("npz", "zip-bomb.npz", _npz_bomb),
    ("npy", "near-float-limit.npy", _npy_near_float_limit),
    ("layout-toml", "100k-targets.toml", _many_targets),
    ("layout-json", "nested-100000-deep.json",
     lambda: b'{"format": "nanoasm.layout/1", "area": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"),
]


def corpus() -> list[tuple[str, Path]]:
    """(kind, file) of every kept hostile file: ``fuzz_corpus/KIND/NAME``."""
    return sorted((d.name, f) for d in CORPUS.iterdir() if d.is_dir() for f in d.iterdir() if f.is_file())


# == mutations ==========================================================================

NUMBER = re.compile(rb"(?<![\w.])-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?(?![\w.])")
#: What a number is replaced with: huge, tiny, not finite, negative, wrong types, nesting.
REPLACEMENTS = [b"1e308", b"-1e308", b"1e-300", b"0", b"-1", b"9" * 400, b"nan", b"inf", b"-0.0",
                b"1e999", b'"x"', b"true", b"[]", b"{}", b"[" * 600 + b"]" * 600,
                b"[[[[1, 2]]]]", b'"' + b"\\u0000" * 8 + b'"', b"4294967296", b"1e-320"]


def mutate(data: bytes, kind: Kind, rnd: random.Random) -> bytes:
    """One random mutation of ``data``: byte flips, truncation, inserted or overwritten
    bytes, and for text a number replaced by a huge, tiny or non-finite one, a wrong type
    or deep nesting, or the document nested deep."""
    ops = ["flip", "truncate", "insert", "overwrite"] + (["number"] * 4 + ["nest"] if kind.text else [])
    op = rnd.choice(ops)
    buf = bytearray(data)
    if op == "flip":
        for _ in range(rnd.randint(1, 4)):
            buf[rnd.randrange(len(buf))] ^= 1 << rnd.randrange(8)
    elif op == "truncate":
        del buf[rnd.randrange(len(buf)):]
    elif op == "insert":
        at = rnd.randrange(len(buf) + 1)
        buf[at:at] = bytes(rnd.randrange(256) for _ in range(rnd.randint(1, 16)))
    elif op == "overwrite":
        # big-endian and little-endian extremes over counts, sizes, lengths and offsets
        at = rnd.randrange(len(buf))
        width = rnd.choice((2, 4, 8))
        buf[at:at + width] = rnd.choice((b"\xff", b"\x7f", b"\x00", b"\x80")) * width
    elif op == "number":
        numbers = list(NUMBER.finditer(data))
        if numbers:
            m = rnd.choice(numbers)
            buf[m.start():m.end()] = rnd.choice(REPLACEMENTS)
    else:   # nest: the whole value of one key wrapped a thousand times
        numbers = list(NUMBER.finditer(data))
        if numbers:
            m = rnd.choice(numbers)
            depth = rnd.choice((50, 1000, 100_000))
            buf[m.start():m.end()] = b"[" * depth + m.group() + b"]" * depth
    return bytes(buf)


# == the worker =========================================================================

@dataclass
class Result:
    code: int | None          # None: the process died (signal) or hung
    err: str
    out: str
    seconds: float            # by the clock
    maxrss: int               # bytes, the process's peak so far
    cpu: float = 0.0          # seconds of CPU time, user and system


def check_refused(result: Result, path: Path, outputs: list[Path]) -> str:
    """Exit 1, one line on stderr naming ``path``, no traceback, no output written, in
    time. Returns the line."""
    lines = result.err.strip().splitlines()
    assert result.code == 1, f"{path.name}: exit {result.code}: {result.err[-2000:]}"
    assert len(lines) == 1, f"{path.name}: {result.err[-2000:]}"
    assert lines[0].startswith(f"nanoasm: error: {path}: "), lines[0]
    assert "Traceback" not in result.err and "internal error" not in result.err, result.err
    assert result.cpu < SECONDS, f"{path.name}: took {result.cpu:.1f} s of CPU time"
    assert result.maxrss < MEMORY
    for out in outputs:
        assert not out.exists(), f"{path.name}: {out.name} written although refused"
    return lines[0]


def check_outcome(result: Result, path: Path, outputs: list[Path]) -> bool:
    """A mutated file is either refused (as :func:`check_refused` says) or accepted (exit
    0, or a run stopped for want of NI-DAQmx, and only warnings on stderr). Returns
    whether it was refused."""
    assert "Traceback" not in result.err and "internal error" not in result.err, \
        f"{path.name}: exit {result.code}: {result.err[-2000:]}"
    lines = result.err.strip().splitlines()
    if lines and all(ACCEPTED_STDERR.match(line) for line in lines) or result.code == 0:
        assert result.code in (0, 1) and all(ACCEPTED_STDERR.match(line) for line in lines), result.err
        assert result.cpu < SECONDS, f"{path.name}: took {result.cpu:.1f} s of CPU time"
        return False
    check_refused(result, path, outputs)
    return True


class Worker:
    """``python fuzzkit.py`` under the memory limit: ``nanoasm ARGS`` many times in one
    process (no second import), each answer awaited at most ``HUNG`` s; a worker that
    dies or hangs is replaced, and its case fails."""

    def __init__(self):
        self.proc: subprocess.Popen | None = None

    def _start(self) -> subprocess.Popen:
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__))], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=HERE,
                                     env=cli_env(), preexec_fn=limit_memory)
        return self.proc

    def run(self, args: list[str], timeout: float = HUNG) -> Result:
        proc = self.proc if self.proc is not None and self.proc.poll() is None else self._start()
        start = time.monotonic()
        proc.stdin.write(json.dumps(args) + "\n")
        proc.stdin.flush()
        ready, _, _ = select.select([proc.stdout], [], [], timeout)
        line = proc.stdout.readline() if ready else ""
        if not line:
            self.close()
            return Result(None, f"no answer ({'died' if ready else 'hung'}) within {timeout} s",
                          "", time.monotonic() - start, 0)
        return Result(**json.loads(line))

    def close(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None


def run_cli(args: list[str], cwd: Path) -> Result:
    """``nanoasm ARGS`` as a process of its own (the real CLI, with its import) under the
    memory limit; its peak memory from ``wait4``."""
    start = time.monotonic()
    with open(cwd / ".stdout", "w+") as out, open(cwd / ".stderr", "w+") as err:
        proc = subprocess.Popen([sys.executable, "-m", "nanoasm.cli", *args], stdout=out, stderr=err,
                                cwd=cwd, env=cli_env(), preexec_fn=limit_memory)
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.monotonic() - start > HUNG:
                proc.kill()
                pid, status, usage = os.wait4(proc.pid, 0)
                break
            time.sleep(0.01)
        proc.returncode = os.waitstatus_to_exitcode(status)     # reaped here, not by Popen
        out.seek(0)
        err.seek(0)
        code = proc.returncode if proc.returncode >= 0 else None
        return Result(code, err.read(), out.read()[-2000:], time.monotonic() - start, usage.ru_maxrss * 1024,
                      usage.ru_utime + usage.ru_stime)


def _plan_check(path: str) -> None:
    from nanoasm.planner.plan import load_plan

    plan = load_plan(path)
    print(f"{path}: ok: {len(plan.operations)} operation(s)")


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _serve() -> None:
    import contextlib

    from nanoasm import cli
    from nanoasm.errors import InputError

    real_out = sys.stdout
    for line in sys.stdin:
        args = json.loads(line)
        out, err = io.StringIO(), io.StringIO()
        start, used = time.monotonic(), _cpu()
        # what C code writes to file descriptor 2 counts too: a library's own lines leak so
        c_err = tempfile.TemporaryFile()
        saved = os.dup(2)
        os.dup2(c_err.fileno(), 2)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                if args[0] == "plan-check":
                    try:
                        _plan_check(args[1])
                        code = 0
                    except InputError as exc:
                        print(f"nanoasm: error: {exc.line()}", file=sys.stderr)
                        code = 1
                else:
                    code = cli.main(args)
            except BaseException as exc:    # noqa: BLE001 - reported, the case fails
                import traceback

                traceback.print_exc()
                code = 3 if not isinstance(exc, SystemExit) else exc.code
        os.dup2(saved, 2)
        os.close(saved)
        c_err.seek(0)
        err.write(c_err.read(1 << 16).decode("utf-8", "replace"))
        c_err.close()
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        real_out.write(json.dumps({"code": code, "err": err.getvalue(), "out": out.getvalue()[-2000:],
                                   "seconds": time.monotonic() - start, "maxrss": rss,
                                   "cpu": _cpu() - used}) + "\n")
        real_out.flush()


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    _serve()
