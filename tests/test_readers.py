"""Height image files: every format to nm with row 0 at the bottom, one-line errors."""

from __future__ import annotations

import os

import numpy as np
import pytest

from nanoasm.errors import InputError
from nanoasm.instrument import HeightImage
from nanoasm.world.readers import read_height_image, save_height_image

RNG = np.random.default_rng(0)


def _one_line(exc: pytest.ExceptionInfo, *words: str) -> None:
    text = str(exc.value)
    assert "\n" not in text and "Traceback" not in text
    for w in words:
        assert w in text, text


def test_npz_round_trip_is_exact_and_atomic(tmp_path):
    h = RNG.normal(size=(7, 9))
    img = HeightImage(h, 2.5, (10.0, -4.0), "simulated")
    path = tmp_path / "scan.npz"
    save_height_image(img, path)
    back = read_height_image(path)
    assert np.array_equal(back.height, h) and back.pixel_size == 2.5 and back.origin == (10.0, -4.0)
    assert sorted(os.listdir(tmp_path)) == ["scan.npz"]
    with pytest.raises(InputError) as e:
        save_height_image(img, tmp_path / "scan.bin")
    _one_line(e, ".npz")
    with pytest.raises(InputError) as e:
        save_height_image(img, tmp_path / "nowhere" / "scan.npz")
    _one_line(e, "does not exist")


def test_npz_with_missing_or_bad_arrays_is_refused(tmp_path):
    p = tmp_path / "a.npz"
    np.savez(p, height=np.ones((3, 3)), origin=np.zeros(2))
    with pytest.raises(InputError) as e:
        read_height_image(p)
    _one_line(e, "pixel_size", "missing")
    np.savez(p, height=np.ones((3, 3)), pixel_size=np.array([1.0, 2.0]), origin=np.zeros(2))
    with pytest.raises(InputError) as e:
        read_height_image(p)
    _one_line(e, "pixel_size")
    np.savez(p, height=np.ones(5), pixel_size=1.0, origin=np.zeros(2))
    with pytest.raises(InputError) as e:
        read_height_image(p)
    _one_line(e, "2-D")
    np.savez(p, height=np.full((3, 3), np.nan), pixel_size=1.0, origin=np.zeros(2))
    with pytest.raises(InputError) as e:
        read_height_image(p)
    _one_line(e, "no finite height")
    p.write_bytes(p.read_bytes()[:60])
    with pytest.raises(InputError) as e:
        read_height_image(p)
    _one_line(e, str(p))


def test_npy_needs_a_pixel_size_and_is_flipped_to_row_zero_at_the_bottom(tmp_path):
    h = np.arange(12.0).reshape(3, 4)
    p = tmp_path / "a.npy"
    np.save(p, h)
    with pytest.raises(InputError) as e:
        read_height_image(p)
    _one_line(e, "pixel_size", "--pixel-size")
    img = read_height_image(p, pixel_size=0.5)
    assert np.array_equal(img.height, h[::-1]) and img.pixel_size == 0.5
    with pytest.raises(InputError) as e:
        read_height_image(p, pixel_size=-1.0)
    _one_line(e, "pixel_size", "positive")
    np.save(p, np.array(["a", "b"]))
    with pytest.raises(InputError) as e:
        read_height_image(p, pixel_size=1.0)
    _one_line(e, "not numeric")


def test_ascii_matrix_with_a_gwyddion_header(tmp_path):
    p = tmp_path / "m.txt"
    p.write_text("# Channel: Height\n# Width: 4.000 µm\n# Height: 2.000 µm\n# Value units: m\n"
                 "1e-9 2e-9 3e-9 4e-9\n5e-9\t6e-9\t7e-9\t8e-9\n", encoding="utf-8")
    img = read_height_image(p)
    assert img.pixel_size == pytest.approx(1000.0)
    assert np.allclose(img.height, [[5, 6, 7, 8], [1, 2, 3, 4]])       # first line is the top


def test_ascii_matrix_without_size_needs_the_option(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("1,2,3\n4,5,6\n7,8,9\n")
    with pytest.raises(InputError) as e:
        read_height_image(p)
    _one_line(e, "--pixel-size")
    img = read_height_image(p, pixel_size=2.0)
    assert img.shape == (3, 3) and img.height[0, 0] == 7.0 and img.pixel_size == 2.0
    p.write_text("1 2 3\n4 5\n")
    with pytest.raises(InputError) as e:
        read_height_image(p, pixel_size=2.0)
    _one_line(e, "different numbers")
    p.write_text("1 2 3\n4 x 6\n")
    with pytest.raises(InputError) as e:
        read_height_image(p, pixel_size=2.0)
    _one_line(e, "line 2")
    p.write_text("nan nan\nnan nan\n")
    with pytest.raises(InputError) as e:
        read_height_image(p, pixel_size=2.0)
    _one_line(e, "no finite")
    p.write_bytes(b"1 2\x00\x01 3\n")
    with pytest.raises(InputError) as e:
        read_height_image(p, pixel_size=2.0)
    _one_line(e, "binary")


def test_xyz_on_a_regular_grid(tmp_path):
    xs, ys = np.meshgrid(np.arange(4) * 5.0 + 100.0, np.arange(3) * 5.0 + 50.0)
    z = xs / 10 + ys
    rows = np.column_stack([xs.ravel(), ys.ravel(), z.ravel()])
    RNG.shuffle(rows)
    p = tmp_path / "s.xyz"
    np.savetxt(p, rows)
    img = read_height_image(p)
    assert img.pixel_size == pytest.approx(5.0)
    assert img.origin == pytest.approx((97.5, 47.5))
    assert np.allclose(img.height, z)                                  # row 0 is the lowest y
    np.savetxt(p, rows * np.array([1e-9, 1e-9, 1e-9]))                  # metres
    img = read_height_image(p)
    assert img.pixel_size == pytest.approx(5.0) and np.allclose(img.height, z)
    np.savetxt(p, rows[:-1])
    with pytest.raises(InputError) as e:
        read_height_image(p)
    _one_line(e, "regular")
    bad = rows.copy()
    bad[:, 0] = np.where(bad[:, 0] == 115.0, 118.0, bad[:, 0])
    np.savetxt(p, bad)
    with pytest.raises(InputError) as e:
        read_height_image(p)
    _one_line(e, "regular grid")


def test_gwyddion_file_written_by_gwyfile(tmp_path):
    from gwyfile.objects import GwyContainer, GwyDataField, GwySIUnit

    data = np.arange(12.0).reshape(3, 4) * 1e-9
    field = GwyDataField(data, xreal=4e-8, yreal=3e-8, si_unit_xy=GwySIUnit(unitstr="m"),
                         si_unit_z=GwySIUnit(unitstr="m"))
    phase = GwyDataField(np.zeros((3, 4)), xreal=4e-8, yreal=3e-8, si_unit_xy=GwySIUnit(unitstr="m"),
                         si_unit_z=GwySIUnit(unitstr="deg"))
    c = GwyContainer()
    c["/0/data"], c["/0/data/title"] = phase, "Phase"
    c["/1/data"], c["/1/data/title"] = field, "Topography"
    p = tmp_path / "t.gwy"
    c.tofile(str(p))
    img = read_height_image(p)
    assert img.meta["channel"] == "Topography"
    assert img.pixel_size == pytest.approx(10.0)
    assert np.allclose(img.height, np.arange(12.0).reshape(3, 4)[::-1])
    with pytest.raises(InputError) as e:
        read_height_image(p, channel="Phase")
    _one_line(e, "not a length")
    with pytest.raises(InputError) as e:
        read_height_image(p, channel="Amplitude")
    _one_line(e, "channel", "Topography")


@pytest.mark.parametrize("name", ["bad.gwy", "bad.stp", "bad.jpk-qi-image", "bad.spm", "bad.ibw",
                                  "bad.npz", "bad.npy"])
def test_corrupt_instrument_files_give_one_line(tmp_path, name):
    p = tmp_path / name
    p.write_bytes(RNG.integers(0, 256, 3000, dtype=np.uint8).tobytes())
    with pytest.raises(InputError) as e:
        read_height_image(p, pixel_size=1.0 if name.endswith(".npy") else None)
    _one_line(e, str(p))


def test_spm_without_header_end_does_not_hang(tmp_path):
    p = tmp_path / "x.spm"
    p.write_bytes(b"\\*File list\r\n\\Version: 0x09300201\r\n")
    with pytest.raises(InputError) as e:
        read_height_image(p)
    _one_line(e, "header")


def test_files_that_are_not_images(tmp_path):
    with pytest.raises(InputError) as e:
        read_height_image(tmp_path / "missing.gwy")
    _one_line(e, "no such file")
    with pytest.raises(InputError) as e:
        read_height_image(tmp_path)
    _one_line(e, "directory")
    empty = tmp_path / "e.gwy"
    empty.write_bytes(b"")
    with pytest.raises(InputError) as e:
        read_height_image(empty)
    _one_line(e, "empty")
    other = tmp_path / "notes.md"
    other.write_text("hello")
    with pytest.raises(InputError) as e:
        read_height_image(other)
    _one_line(e, "unknown file type", ".md")


# Real AFM files (third-party test data in ../shared/data/afm; skipped when absent).
REAL = [
    ("sample_g.gwy", {}, (256, 256), 11.71875),
    ("sample_1_um_scale.stp", {}, (512, 512), 3.90625),
    ("file.stp", {}, (512, 512), 0.9765625),
    ("file.jpk-qi-image", {}, (100, 100), 5.0),
    ("minicircle_cropped_flattened.npy", {"pixel_size": 0.4940029296875}, (256, 256), 0.4940029296875),
    ("example_catenanes.npy", {"pixel_size": 0.488}, (400, 400), 0.488),
]


@pytest.mark.parametrize("name,kw,shape,pixel", REAL)
def test_real_files_load(shared_afm, name, kw, shape, pixel):
    img = read_height_image(shared_afm / name, **kw)
    assert img.shape == shape
    assert img.pixel_size == pytest.approx(pixel, rel=1e-6)
    assert np.isfinite(img.height).all()
    assert 0.5 < np.ptp(img.height) < 2000.0                           # nm, not metres


def test_real_gwy_is_flipped_to_row_zero_at_the_bottom(shared_afm):
    import gwyfile

    raw = gwyfile.load(str(shared_afm / "sample_g.gwy"))["/0/data"].data * 1e9
    img = read_height_image(shared_afm / "sample_g.gwy")
    assert np.allclose(img.height, raw[::-1])
