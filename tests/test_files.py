"""File-level rejections: every broken file gets one line and nothing is written."""

from __future__ import annotations

import pytest

from nanoasm.cad.layout import load_layout
from nanoasm.errors import InputError
from nanoasm.examples import path as example
from nanoasm.fileio import dumps_toml, write_atomic
from nanoasm.world.scene import load_scene

GOOD = example("bowtie.toml").read_text()


def problem(tmp_path, name: str, content: bytes | str, loader=load_layout) -> str:
    p = tmp_path / name
    p.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(InputError) as info:
        loader(p)
    line = str(info.value)
    assert line.startswith(str(p)) and "\n" not in line
    return line


@pytest.mark.parametrize("name,content,expect", [
    ("e.toml", b"", "file is empty"),
    ("e.toml", b"  \n\t\n", "file is empty"),
    ("b.toml", b"format = \x00\x01\x02", "binary file"),
    ("g.toml", b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "binary file"),
    ("u.toml", b'format = "nanoasm.layout/1"\nname = "\xff\xfe"\n', "not UTF-8"),
    ("t.toml", GOOD[: len(GOOD) // 2].rsplit("=", 1)[0] + "= [12", "not valid TOML"),
    ("t.json", '{"format": "nanoasm.layout/1", "area": [5000, ', "truncated JSON"),
    ("n.json", '{"format": "nanoasm.layout/1", "area": [NaN, 5]}', "NaN is not allowed"),
    ("i.json", '{"format": "nanoasm.layout/1", "area": [Infinity, 5]}', "Infinity is not allowed"),
    ("d.json", '{"format": "nanoasm.layout/1", "format": "x"}', "duplicate key 'format'"),
    ("l.json", '[1, 2]', "top level must be a table"),
    ("x.toml", 'format = "nanoasm.layout/1"\narea = [nan, 5]\n', "area: width must be finite"),
    ("s.txt", '{"format": "nanoasm.layout/1", "area": [5, 5], "target": []}', "at least one"),
    ("dup.toml", 'format = "nanoasm.layout/1"\nformat = "x"\n', "not valid TOML"),
])
def test_broken_files(tmp_path, name, content, expect):
    assert expect in problem(tmp_path, name, content)


def test_truncated_toml_at_every_cut(tmp_path):
    """Any prefix of a valid layout is either still valid or rejected with one line."""
    for cut in range(0, len(GOOD), 37):
        p = tmp_path / "cut.toml"
        p.write_text(GOOD[:cut])
        try:
            load_layout(p)
        except InputError as exc:
            assert "\n" not in str(exc)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load_layout(tmp_path / "nope.toml")
    with pytest.raises(InputError, match="is a directory"):
        load_scene(tmp_path)


def test_write_atomic_leaves_nothing_on_failure(tmp_path):
    class Boom(Exception):
        pass

    class Bad(str):
        def encode(self, *a, **k):
            raise Boom

    with pytest.raises(Boom):
        write_atomic(tmp_path / "out.toml", Bad("x"))
    assert list(tmp_path.iterdir()) == []
    write_atomic(tmp_path / "out.toml", "a = 1\n")
    assert [p.name for p in tmp_path.iterdir()] == ["out.toml"]
    with pytest.raises(InputError, match="does not exist"):
        write_atomic(tmp_path / "no" / "out.toml", "a = 1\n")


def test_dumps_toml_escapes_strings():
    import tomllib

    doc = {"name": 'a "quoted" \\ name\u00e9\x7f', "x": 1.5e-300, "n": [1, 2.5], "t": [{"k": True}]}
    assert tomllib.loads(dumps_toml(doc)) == doc
