"""Hostile input files (issue 15): each ends in one line naming the file and the problem,
exit 1, in bounded time and memory; never a crash, a hang or a traceback.

Every hostile file is generated here, small. A file that could blow memory or hang is
read by a subprocess under a 1 GiB address-space limit and a timeout.
"""

from __future__ import annotations

import io
import json
import os
import resource
import subprocess
import sys
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema

from nanoasm.cli import main
from nanoasm.errors import InputError
from nanoasm.executor import logread
from nanoasm.examples import path as example
from nanoasm.world.limits import MAX_PIXELS

MEMORY = 1 << 30          # bytes a subprocess may map
SECONDS = 10.0            # the most a hostile file may take


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY, MEMORY))


def _run(*args: str | Path, cwd: Path) -> tuple[int, str, float]:
    """``nanoasm ARGS`` in a subprocess under the memory limit: (exit code, stderr, seconds)."""
    env = {k: v for k, v in os.environ.items() if k != "NANOASM_DEBUG"}
    env.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    start = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "nanoasm.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, env=env, timeout=4 * SECONDS, preexec_fn=_limit_memory)
    return proc.returncode, proc.stderr, time.monotonic() - start


def _cli(capsys, *args: str | Path) -> tuple[int, str, float]:
    """``nanoasm ARGS`` in this process: (exit code, stderr, seconds)."""
    start = time.monotonic()
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err, time.monotonic() - start


def _refused(result: tuple[int, str, float], path: Path | str, *words: str) -> str:
    """Exit 1, one line on stderr naming ``path`` (and ``words``), no traceback, in time."""
    code, err, seconds = result
    lines = err.strip().splitlines()
    assert code == 1, err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"nanoasm: error: {path}: "), err
    assert "Traceback" not in err and "internal error" not in err
    for w in words:
        assert w in lines[0], lines[0]
    assert seconds < SECONDS, f"took {seconds:.1f} s"
    return lines[0]


# -- MCAP run logs ------------------------------------------------------------------------

MCAP_MAGIC = b"\x89MCAP0\r\n"


def _chunk_records() -> bytes:
    rb = RecordBuilder()
    Schema(id=1, name="nanoasm.Stop", encoding="jsonschema", data=b"{}").write(rb)
    Channel(id=1, schema_id=1, topic="/stop", message_encoding="json", metadata={}).write(rb)
    Message(channel_id=1, sequence=0, log_time=10**9, publish_time=10**9,
            data=json.dumps({"state": "done", "reason": "ok"}).encode()).write(rb)
    return rb.end()


def _write_mcap(path: Path, chunks: list[tuple[str, bytes, int, int]]) -> Path:
    """An MCAP file of ``chunks`` (compression, data, stated uncompressed size, CRC) and
    nanoasm's metadata, built record by record."""
    rb = RecordBuilder()
    Header(profile="nanoasm.runlog/1", library="test").write(rb)
    for compression, data, size, crc in chunks:
        Chunk(compression=compression, data=data, message_start_time=10**9, message_end_time=10**9,
              uncompressed_size=size, uncompressed_crc=crc).write(rb)
    Metadata(name="nanoasm", metadata={"kind": "dry-run"}).write(rb)
    DataEnd(data_section_crc=0).write(rb)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(rb)
    path.write_bytes(MCAP_MAGIC + rb.end() + MCAP_MAGIC)
    return path


def _zstd(data: bytes) -> bytes:
    # no content size in the frame: a decompressor must trust the chunk's stated size
    return zstandard.ZstdCompressor(write_content_size=False).compress(data)


def test_a_well_formed_hand_built_log_is_read(tmp_path):
    records = _chunk_records()
    for compression, data in (("zstd", _zstd(records)), ("", records)):
        log = logread.read_log(_write_mcap(tmp_path / "ok.mcap", [(compression, data, len(records),
                                                                   zlib.crc32(records))]))
        assert log.complete and log.problem is None
        assert [m.data for m in log.topic("/stop")] == [{"state": "done", "reason": "ok"}]


def test_lz4_chunks_are_read_too(tmp_path):
    import lz4.frame

    records = _chunk_records()
    log = logread.read_log(_write_mcap(tmp_path / "lz4.mcap", [("lz4", lz4.frame.compress(records), len(records),
                                                                  zlib.crc32(records))]))
    assert log.complete and len(log.topic("/stop")) == 1


def test_review_of_a_zstd_chunk_claiming_6_gb_is_one_line(tmp_path):
    records = _chunk_records()
    path = _write_mcap(tmp_path / "bomb.mcap", [("zstd", _zstd(records), 6 * 10**9, 0)])
    line = _refused(_run("review", path, cwd=tmp_path), path, "6000000000", "MAX_CHUNK_BYTES")
    assert f"at most {logread.MAX_CHUNK_BYTES}" in line


def test_read_log_refuses_chunks_beyond_the_total(tmp_path, monkeypatch):
    records = _chunk_records()
    chunk = ("zstd", _zstd(records), len(records), zlib.crc32(records))
    path = _write_mcap(tmp_path / "many.mcap", [chunk] * 5)
    assert logread.read_log(path).complete
    monkeypatch.setattr(logread, "MAX_LOG_BYTES", 3 * len(records))
    with pytest.raises(InputError) as e:
        logread.read_log(path)
    assert str(e.value).startswith(f"{path}: ") and "MAX_LOG_BYTES" in str(e.value)


def test_a_chunk_holding_more_than_it_states_is_read_no_further(tmp_path):
    """The stated size is a ceiling: 64 MiB of zeros behind a chunk stating 100 bytes is
    damage, found after 101 bytes, and ends the readable prefix."""
    records = _chunk_records()
    cobj = zstandard.ZstdCompressor().compressobj()
    data = cobj.compress(records) + b"".join(cobj.compress(bytes(1 << 20)) for _ in range(64)) + cobj.flush()
    assert len(data) < 64 * 1024
    path = _write_mcap(tmp_path / "liar.mcap", [("zstd", data, len(records), 0)])
    start = time.monotonic()
    log = logread.read_log(path)
    assert time.monotonic() - start < SECONDS
    assert not log.complete and "decompresses to more bytes" in log.problem


def test_a_chunk_of_zeros_is_damage_not_millions_of_records(tmp_path):
    zeros = bytes(32 << 20)
    path = _write_mcap(tmp_path / "zeros.mcap", [("zstd", _zstd(zeros), len(zeros), 0)])
    start = time.monotonic()
    log = logread.read_log(path)
    assert time.monotonic() - start < SECONDS
    assert not log.complete and "opcode 0x00" in log.problem


# -- AFM images -----------------------------------------------------------------------------

def _npy_header(shape: tuple[int, ...], descr: str = "<f8") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def _npy(array) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(array))
    return buf.getvalue()


def _particles(n: int = 128) -> np.ndarray:
    """Heights (nm) of three particles on a flat, slightly noisy substrate, first row on top."""
    rng = np.random.default_rng(1)
    z = rng.normal(0.0, 0.3, (n, n))
    yy, xx = np.mgrid[:n, :n]
    for cx, cy in ((30, 30), (90, 40), (60, 100)):
        r2 = (xx - cx) ** 2 + (yy - cy) ** 2
        z += np.where(r2 < 64, 2 * np.sqrt(np.clip(64 - r2, 0, None)), 0.0)
    return z


def _npz_bomb(path: Path, shape=(30000, 30000)) -> Path:
    """A 6.7 GB height array in a few kB: a deflated member whose header declares ``shape``,
    followed by 8 MiB of real zeros."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("height.npy", "w", force_zip64=True) as fh:
            fh.write(_npy_header(shape))
            for _ in range(8):
                fh.write(bytes(1 << 20))
        zf.writestr("pixel_size.npy", _npy(np.float64(10.0)))
        zf.writestr("origin.npy", _npy(np.zeros(2)))
    return path


@pytest.fixture
def layout() -> Path:
    return example("bowtie.toml")


def _commands(scan: Path, out: Path, layout: Path, *extra: str) -> list[list]:
    """``identify SCAN`` and ``plan LAYOUT --scan SCAN``, with ``extra`` options."""
    return [["identify", scan, "-o", out, *extra],
            ["plan", layout, "--scan", scan, "-o", out, *extra]]


def test_npz_zip_bomb_is_refused_from_its_header(tmp_path, layout):
    scan = _npz_bomb(tmp_path / "bomb.npz")
    assert scan.stat().st_size < 100_000
    for args in _commands(scan, tmp_path / "out.json", layout):
        _refused(_run(*args, cwd=tmp_path), scan, "height", "30000, 30000", "MAX_PIXELS")
        assert not (tmp_path / "out.json").exists()


def test_npz_small_arrays_declaring_a_huge_shape_are_refused(tmp_path):
    scan = tmp_path / "ps.npz"
    with zipfile.ZipFile(scan, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("height.npy", _npy(_particles()))
        zf.writestr("pixel_size.npy", _npy_header((10**9,)) + bytes(64))
        zf.writestr("origin.npy", _npy(np.zeros(2)))
    _refused(_run("identify", scan, "-o", tmp_path / "o.json", cwd=tmp_path), scan, "pixel_size", "at most 1")


def test_npy_declaring_a_huge_shape_is_refused(tmp_path):
    scan = tmp_path / "huge.npy"
    scan.write_bytes(_npy_header((100000, 100000)) + bytes(4096))
    _refused(_run("identify", scan, "-o", tmp_path / "o.json", "--pixel-size", "10", cwd=tmp_path), scan,
             "100000, 100000", str(MAX_PIXELS))


def test_npy_heights_near_the_float_limit_are_refused(tmp_path, capsys, layout):
    scan = tmp_path / "big.npy"
    np.save(scan, _particles() * 1e306)
    for args in _commands(scan, tmp_path / "o.json", layout, "--pixel-size", "10"):
        _refused(_cli(capsys, *args), scan, "heights reach", "nm")


@pytest.mark.parametrize("size", ["1e-300", "1e300", "0.001", "2e6"])
def test_an_implausible_pixel_size_is_refused(tmp_path, capsys, layout, size):
    scan = tmp_path / "ok.npy"
    np.save(scan, _particles())
    for args in _commands(scan, tmp_path / "o.json", layout, "--pixel-size", size):
        code, err, seconds = _cli(capsys, *args)
        assert code == 1 and err.strip().splitlines() == [err.strip()], err
        assert err.startswith("nanoasm: error: --pixel-size: ") and "0.01 to 1e+06 nm" in err, err
        assert "Warning" not in err and seconds < SECONDS


def test_a_tip_radius_that_overflows_the_tip_image_is_refused(tmp_path, capsys, layout):
    scan = tmp_path / "ok.npy"
    np.save(scan, _particles())
    identify_args, plan_args = _commands(scan, tmp_path / "o.json", layout, "--pixel-size", "10",
                                         "--tip-radius", "1e300")
    code, err, _ = _cli(capsys, *identify_args)
    assert code == 1 and err.strip() == "nanoasm: error: --tip-radius: must be at most 100000, got 1e+300", err
    _refused(_cli(capsys, *plan_args), scan, "tip_radius", "at most 100000")


def test_a_scan_file_with_an_implausible_pixel_size_is_refused(tmp_path, capsys):
    scan = tmp_path / "tiny.npz"
    np.savez(scan, height=_particles(), pixel_size=np.float64(1e-300), origin=np.zeros(2))
    _refused(_cli(capsys, "identify", scan, "-o", tmp_path / "o.json"), scan, "pixel_size", "0.01 to 1e+06 nm")


def test_shapely_warnings_do_not_leak_at_the_largest_pixel_size(tmp_path, capsys):
    scan = tmp_path / "ok.npy"
    np.save(scan, _particles())
    code, err, _ = _cli(capsys, "identify", scan, "-o", tmp_path / "o.json", "--pixel-size", "1e6")
    # the one line said is the question about units (a 128 mm image), no library warning
    assert code == 0 and len(err.splitlines()) == 1 and "more than 1 mm: are its units right" in err, err


def test_a_good_npy_still_finds_its_three_particles(tmp_path, capsys):
    scan = tmp_path / "ok.npy"
    np.save(scan, _particles())
    code, err, _ = _cli(capsys, "identify", scan, "-o", tmp_path / "o.json", "--pixel-size", "10")
    assert code == 0 and err == ""
    assert len(json.loads((tmp_path / "o.json").read_text())["objects"]) == 3


def test_half_the_rows_nan_warns_in_one_line(tmp_path, capsys):
    z = _particles()
    z[::2] = np.nan
    scan = tmp_path / "half.npy"
    np.save(scan, z)
    code, err, _ = _cli(capsys, "identify", scan, "-o", tmp_path / "o.json", "--pixel-size", "10")
    lines = err.strip().splitlines()
    assert code == 0 and len(lines) == 1, err
    assert lines[0].startswith(f"nanoasm: warning: {scan}: ") and "50%" in lines[0] and "no finite height" in lines[0]


def test_mostly_nan_is_refused(tmp_path, capsys):
    z = _particles()
    z[:100] = np.nan
    scan = tmp_path / "mostly.npy"
    np.save(scan, z)
    _refused(_cli(capsys, "identify", scan, "-o", tmp_path / "o.json", "--pixel-size", "10"), scan,
             "78%", "no finite height", "at most 50%")


@pytest.mark.parametrize("name,head", [("garbage.ibw", b""), ("v5.ibw", b"\x05\x00"), ("v2.ibw", b"\x02\x00"),
                                       ("garbage.spm", b"")])
def test_instrument_garbage_is_one_line(tmp_path, name, head):
    rng = np.random.default_rng(7)
    scan = tmp_path / name
    body = rng.integers(0, 256, 5000, dtype=np.uint8).tobytes()
    if name.endswith(".spm"):
        # a header end marker that is not a line of its own: pySPM would read for ever
        body = b"\\*File list\r\n" + body + b"\\*File list end\r\n" + body
    scan.write_bytes(head + body)
    line = _refused(_run("identify", scan, "-o", tmp_path / "o.json", cwd=tmp_path), scan)
    assert "local variable" not in line


def test_jpk_garbage_prints_no_library_lines(tmp_path):
    rng = np.random.default_rng(8)
    scan = tmp_path / "garbage.jpk"
    scan.write_bytes(b"II*\x00" + rng.integers(0, 256, 5000, dtype=np.uint8).tobytes())
    _refused(_run("identify", scan, "-o", tmp_path / "o.json", cwd=tmp_path), scan, "JPK")


# -- numbers in TOML and JSON ---------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_a_5000_digit_integer_is_one_line(tmp_path, capsys, suffix):
    path = tmp_path / f"layout{suffix}"
    if suffix == ".toml":
        path.write_text('format = "nanoasm.layout/1"\narea = [5000, ' + "9" * 5000 + "]\n")
    else:
        path.write_text('{"format": "nanoasm.layout/1", "area": [5000, ' + "9" * 5000 + "]}")
    line = _refused(_cli(capsys, "layout", "check", path), path, "5000 digits")
    assert "set_int_max_str_digits" not in line


def test_a_log_attachment_declaring_a_huge_scan_is_refused_before_it_is_read():
    """A resumed run reads the full scan back from its log: an attachment whose height
    array declares 30000 x 30000 values (a few bytes of header) is refused, never loaded."""
    import io
    import time
    import zipfile

    import numpy as np

    from nanoasm.executor.scan_attachment import full_scan_bytes, full_scan_image

    good = full_scan_bytes({"height": np.zeros((4, 4)), "pixel_size": 10.0, "origin": (0.0, 0.0)})
    assert full_scan_image(good).height.shape == (4, 4)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("height.npy", "w") as fh:
            np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False,
                                                      "shape": (30000, 30000)})
            fh.write(b"\0" * (1 << 20))
        for key, arr in (("pixel_size", np.float64(10.0)), ("origin", np.zeros(2))):
            with zf.open(key + ".npy", "w") as fh:
                np.lib.format.write_array(fh, np.asarray(arr))
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="declares 900000000 values"):
        full_scan_image(buf.getvalue())
    assert time.perf_counter() - t0 < 2.0
