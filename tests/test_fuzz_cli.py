"""Hostile and mutated files through the commands that read them (issue 15).

For every kind of file nanoasm reads (layouts in TOML and JSON, scenes, environments,
plans, instrument files, SVG, GDSII, DXF, ``.npy``/``.npz`` height arrays, run logs for
``review`` and ``dry-run --resume``), hypothesis mutates a small valid seed (byte flips,
truncation, inserted or overwritten bytes, numbers made huge, tiny, non-finite or of a
wrong type, deep nesting; :mod:`fuzzkit`). The command either accepts the file or refuses
it in one line naming it, exit 1, no traceback, no output written, within 10 s of CPU time
(and 30 s by the clock, however loaded the machine) and 1 GiB of address space.
The kept corpus (``fuzz_corpus/KIND/``) and the issue's generated hostile files must be
refused.

Files go through one worker process (``fuzzkit.py``) that runs ``nanoasm`` many times
without importing it again, under the same memory limit, counting what C code writes to
its stderr; a crash or a hang of it fails the case. A handful of hostile files also go
through the real ``nanoasm`` in a process of its own (about 1 s each, for the import).
"""

from __future__ import annotations

import functools
import os
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from fuzzkit import (HOSTILE, KINDS, MEMORY, SECONDS, Kind, Worker, check_outcome, check_refused, corpus, mutate,
                     run_cli)

#: Mutated files per kind; each is a command run in the worker (about 0.05-0.5 s). The
#: suite's run is derandomised (the same files each time); NANOASM_FUZZ_EXAMPLES=N draws N
#: new files per kind, to hunt (add what breaks to fuzz_corpus/).
EXAMPLES = int(os.environ.get("NANOASM_FUZZ_EXAMPLES", "12"))


@pytest.fixture(scope="module")
def worker():
    w = Worker()
    yield w
    w.close()


@functools.cache
def _seed(kind: str) -> bytes:
    return KINDS[kind].seed()


def _outputs(out: Path) -> list[Path]:
    return [out, out.with_name(out.name + ".json"), out.with_name(out.name + ".sim")]


def _beside(kind, path: Path) -> None:
    for suffix, data in (kind.beside() if kind.beside else {}).items():
        path.with_name(path.name + suffix).write_bytes(data)


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_the_seed_is_accepted(worker, kind, tmp_path):
    """The seed a kind's mutations start from is valid: what refuses a mutant is the mutation."""
    k = KINDS[kind]
    path, out = tmp_path / f"seed{k.suffix}", tmp_path / f"out{k.out_suffix}"
    path.write_bytes(_seed(kind))
    _beside(k, path)
    result = worker.run(k.args(path, out))
    if kind == "mcap-resume":
        # the seed log is of a finished run: there is nothing to resume
        assert "the run finished" in check_refused(result, path, _outputs(out))
    else:
        assert not check_outcome(result, path, _outputs(out)), result.err


#: Kinds whose command takes a second or more on an accepted file (a review drawing its
#: plot, a resume going on with the run): fewer mutants, a third as many.
SLOW = ("mcap-review", "mcap-resume")


def _mutants(examples: int):
    return settings(max_examples=examples, deadline=None,
                    derandomize="NANOASM_FUZZ_EXAMPLES" not in os.environ,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.mark.parametrize("kind", sorted(set(KINDS) - set(SLOW)))
@_mutants(EXAMPLES)
@given(rnd=st.randoms(use_true_random=False), rounds=st.integers(1, 3))
def test_a_mutated_file_is_accepted_or_refused_in_one_line(worker, kind, rnd, rounds):
    _mutant(worker, kind, rnd, rounds)


@pytest.mark.parametrize("kind", SLOW)
@_mutants(max(EXAMPLES // 3, 1))
@given(rnd=st.randoms(use_true_random=False), rounds=st.integers(1, 3))
def test_a_mutated_run_log_is_accepted_or_refused_in_one_line(worker, kind, rnd, rounds):
    _mutant(worker, kind, rnd, rounds)


def _mutant(worker: Worker, kind: str, rnd, rounds: int) -> None:
    k = KINDS[kind]
    data = _seed(kind)
    for _ in range(rounds):
        data = mutate(data, k, rnd) or b"\0"
    with tempfile.TemporaryDirectory() as tmp:
        path, out = Path(tmp) / f"mutant{k.suffix}", Path(tmp) / f"out{k.out_suffix}"
        path.write_bytes(data)
        _beside(k, path)
        check_outcome(worker.run(k.args(path, out)), path, _outputs(out))


def _corpus_cases():
    return [pytest.param(kind, path, id=f"{kind}/{path.name}") for kind, path in corpus()]


def _hostile(kind: str, file: Path | str, tmp_path: Path) -> tuple[Kind, Path, Path]:
    """The hostile ``file`` (kept, or the name of a generated one) written to ``tmp_path``
    with what is kept beside its kind; returns the kind, the file and the output path."""
    k = KINDS[kind]
    path = tmp_path / (file if isinstance(file, str) else file.name)
    path.write_bytes(dict((n, make) for _, n, make in HOSTILE)[file]() if isinstance(file, str)
                     else file.read_bytes())
    _beside(k, path)
    return k, path, tmp_path / f"out{k.out_suffix}"


@pytest.mark.parametrize("kind, file", _corpus_cases())
def test_a_hostile_file_is_refused(worker, kind, file, tmp_path):
    """Each file of the corpus: exit 1, one line, nothing written, in time and memory (the
    worker runs under the memory limit too)."""
    k, path, out = _hostile(kind, file, tmp_path)
    check_refused(worker.run(k.args(path, out)), path, _outputs(out))


#: Kinds whose hostile file also goes through the real command: the generated ones (the
#: largest), GDSII (whose library printed from C and segfaulted) and run logs (decompression).
REAL = ("gds", "mcap-review")


def _real_cases():
    first = {kind: path for kind, path in reversed(corpus()) if kind in REAL}
    first.update((kind, name) for kind, name, _ in HOSTILE)
    return [pytest.param(kind, file, id=kind) for kind, file in sorted(first.items())]


@pytest.mark.parametrize("kind, file", _real_cases())
def test_the_real_command_refuses_a_hostile_file(kind, file, tmp_path):
    """A handful of hostile files through ``python -m nanoasm.cli`` in a process of its
    own (its import, its stderr whatever writes to it, its peak memory from wait4)."""
    k, path, out = _hostile(kind, file, tmp_path)
    result = run_cli(k.args(path, out), tmp_path)
    check_refused(result, path, _outputs(out))
    assert result.maxrss < MEMORY and result.cpu < SECONDS


def test_the_corpus_covers_every_kind_of_file():
    kinds = {kind for kind, _ in corpus()} | {kind for kind, _, _ in HOSTILE}
    # no command reads a plan, and scenes in JSON share the TOML scenes' checks
    assert kinds >= set(KINDS) - {"plan", "scene-json"}, set(KINDS) - kinds


def test_a_repaired_dxf_prints_no_library_lines(worker, tmp_path):
    """ezdxf logged each repair of a damaged DXF as a warning, which Python printed beside
    nanoasm's own line (found by the mutations above)."""
    lines = _seed("dxf").decode().split("\n")
    code = next(i for i in range(0, len(lines) - 1, 2) if lines[i].strip() == "70")
    lines[code + 1] += "x"                          # an integer ezdxf recovers
    path, out = tmp_path / "repaired.dxf", tmp_path / "out.toml"
    path.write_text("\n".join(lines))
    result = worker.run(KINDS["dxf"].args(path, out))
    assert result.code == 0 and result.err.splitlines() == [
        f"nanoasm: note: {path}: ezdxf repaired 1 problem(s) in the file"], result.err


def test_gdstk_lines_become_notes(tmp_path):
    """gdstk printed ``[GDSTK] Record type ELKEY (0x27) is not supported.`` from its C code
    and warned in Python of the same record (found by the mutations above): both are now
    one note each, and the real command prints nothing else."""
    from test_hostile_cad import _ints, _record

    data = _seed("gds")
    at = data.index(_record(0x08, 0)) + 4               # inside the first BOUNDARY
    path, out = tmp_path / "elkey.gds", tmp_path / "out.toml"
    path.write_bytes(data[:at] + _record(0x27, 2, _ints("h", 0)) + data[at:])
    result = run_cli(KINDS["gds"].args(path, out), tmp_path)
    assert result.code == 0 and out.exists(), result.err
    assert result.err.splitlines() == [
        f"nanoasm: note: {path}: gdstk: Record type ELKEY (0x27) is not supported (1 time(s))",
        f"nanoasm: note: {path}: gdstk: Unsupported record in file (1 time(s))"]
