"""Reading TOML/JSON documents and writing outputs atomically.

Every problem with a file becomes an :class:`~nanoasm.errors.InputError` whose one
line names the file and what is wrong with it: missing, a directory, empty, binary,
not UTF-8, truncated or otherwise not valid TOML/JSON, duplicate JSON keys, NaN or
infinity in JSON, an integer of more than :data:`MAX_INT_DIGITS` digits, a top level that
is not a table.
"""

from __future__ import annotations

import json
import os
import re
import sys
import tempfile
import tomllib
from pathlib import Path
from typing import Any

from .errors import InputError
from .param import type_name

#: Largest document we read; layouts and scenes are far smaller.
MAX_BYTES = 64 * 1024 * 1024
#: Most digits of an integer in a TOML or JSON document: Python's limit on turning text
#: into an int (``sys.get_int_max_str_digits()``, 4300 unless PYTHONINTMAXSTRDIGITS says
#: otherwise), which bounds the quadratic time of the conversion. A longer integer is
#: refused in one line; no value of nanoasm's needs more than 20 digits.
MAX_INT_DIGITS = sys.get_int_max_str_digits()


def read_bytes(path: str | os.PathLike) -> bytes:
    """The bytes of ``path``; missing, unreadable, oversized and empty files are refused."""
    p, src = Path(path), str(path)
    if not p.exists():
        raise InputError(src, None, "no such file")
    if p.is_dir():
        raise InputError(src, None, "is a directory, not a file")
    try:
        size = p.stat().st_size
        if size > MAX_BYTES:
            raise InputError(src, None, f"file is too large ({size} bytes; at most {MAX_BYTES})")
        raw = p.read_bytes()
    except OSError as exc:
        raise InputError(src, None, f"cannot read: {exc.strerror or exc}") from None
    if not raw.strip():
        raise InputError(src, None, "file is empty")
    return raw


def read_text(path: str | os.PathLike) -> str:
    """Return the text of ``path``, refusing missing, empty, binary or non-UTF-8 files."""
    return decode_text(read_bytes(path), str(path))


def decode_text(raw: bytes, src: str) -> str:
    if not raw.strip():
        raise InputError(src, None, "file is empty")
    if b"\x00" in raw[:8192] or raw.count(b"\x00") > 0:
        raise InputError(src, None, "binary file, expected TOML or JSON text")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            src, None, f"not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start})"
        ) from None


def _json_constant(name: str) -> Any:
    raise ValueError(f"non-finite number {name} is not allowed")


def _json_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"duplicate key {k!r}")
        out[k] = v
    return out


def _too_many_digits(text: str, what: str) -> str:
    """The problem of a document holding an integer longer than Python converts (the
    ValueError of ``int(text)``), with the line of the first such integer when found."""
    limit = sys.get_int_max_str_digits() or MAX_INT_DIGITS
    found = re.search(r"(?<![0-9_])[0-9][0-9_]{%d,}" % limit, text)    # each run tried once
    if found is None:
        return f"not valid {what}: an integer has more than {limit} digits"
    digits = sum(c.isdigit() for c in found.group())
    line = text.count("\n", 0, found.start()) + 1
    return f"not valid {what}: an integer of {digits} digits on line {line}; at most {limit} are read"


def _int_limit(exc: ValueError) -> bool:
    return "integer string conversion" in str(exc)


def parse_json(text: str, src: str) -> Any:
    try:
        return json.loads(text, parse_constant=_json_constant, object_pairs_hook=_json_pairs)
    except json.JSONDecodeError as exc:
        at_end = exc.pos >= len(text.rstrip())
        what = "truncated JSON" if at_end else "not valid JSON"
        raise InputError(src, None, f"{what}: {exc.msg} (line {exc.lineno}, column {exc.colno})") from None
    except ValueError as exc:  # from the hooks above, or an integer too long to convert
        problem = _too_many_digits(text, "JSON") if _int_limit(exc) else f"not valid JSON: {exc}"
        raise InputError(src, None, problem) from None
    except RecursionError:
        raise InputError(src, None, "not valid JSON: nested too deeply") from None


def parse_toml(text: str, src: str) -> dict[str, Any]:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(src, None, f"not valid TOML: {exc}") from None
    except ValueError as exc:  # int() of an integer longer than MAX_INT_DIGITS
        problem = _too_many_digits(text, "TOML") if _int_limit(exc) else f"not valid TOML: {exc}"
        raise InputError(src, None, problem) from None
    except RecursionError:
        raise InputError(src, None, "not valid TOML: nested too deeply") from None


def is_json(path: str | os.PathLike, text: str) -> bool:
    suffix = Path(path).suffix.lower()
    if suffix == ".json":
        return True
    if suffix == ".toml":
        return False
    return text.lstrip().startswith(("{", "["))


def read_document(path: str | os.PathLike) -> dict[str, Any]:
    """Parse a TOML or JSON file (by suffix, else by its first character) into a dict."""
    src = str(path)
    text = read_text(path)
    data = parse_json(text, src) if is_json(path, text) else parse_toml(text, src)
    if not isinstance(data, dict):
        raise InputError(src, None, f"top level must be a table/object, got {type_name(data)}")
    return data


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_atomic(path: str | os.PathLike, data: str | bytes, mode: int | None = None) -> None:
    """Write ``data`` to ``path`` so that the file is either complete or absent.

    ``mode``: the file's permissions (default: as ``open()`` would create it, under the
    process's umask).

    The bytes go to a temporary file in the same folder, are flushed to disk and then
    renamed over ``path``; a crash half-way leaves no partial output. A folder that is
    missing or cannot be written, or a full disk, is an :class:`InputError` (one line).
    """
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(str(path), None, f"output folder {str(parent)!r} does not exist")
    payload = data.encode("utf-8") if isinstance(data, str) else data
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=parent)
    except OSError as exc:
        raise InputError(str(path), None, f"cannot write in {str(parent)!r}: {exc.strerror or exc}") from None
    try:
        # mkstemp makes the file private; an output gets the mode open() would give it
        os.chmod(tmp, mode if mode is not None else 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, OSError):          # a full disk, a folder gone read-only: one line
            raise InputError(str(path), None, f"cannot write: {exc.strerror or exc}") from None
        raise


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if v.is_integer() and abs(v) < 1e15:
            return str(int(v))
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _toml_key(k: str) -> str:
    return k if k and all(c.isalnum() or c in "_-" for c in k) and k.isascii() else json.dumps(k)


def dumps_toml(doc: dict[str, Any]) -> str:
    """Write a document of scalars, inline arrays, tables and arrays of tables as TOML.

    Arrays stay on one line (``at = [1200, 2500]``); integral floats are written
    without a fraction, which reads back as the same number.
    """
    lines: list[str] = []
    _toml_table(doc, "", lines)
    return "\n".join(lines).lstrip("\n") + "\n"


def _is_table_array(v: Any) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _toml_table(d: dict[str, Any], prefix: str, lines: list[str]) -> None:
    nested = []
    for k, v in d.items():
        if v is None:
            continue
        if isinstance(v, dict) or _is_table_array(v):
            nested.append((k, v))
        else:
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    for k, v in nested:
        name = f"{prefix}{_toml_key(k)}"
        if isinstance(v, dict):
            lines += ["", f"[{name}]"]
            _toml_table(v, name + ".", lines)
        else:
            for item in v:
                lines += ["", f"[[{name}]]"]
                _toml_table(item, name + ".", lines)


def _flat(v: Any) -> bool:
    """Scalars, and arrays of scalars or of arrays of scalars (points, paths) stay on one line."""
    if isinstance(v, (list, tuple)):
        return all(not isinstance(x, (dict, list, tuple)) or
                   (isinstance(x, (list, tuple)) and all(not isinstance(y, (dict, list, tuple)) for y in x))
                   for x in v)
    return not isinstance(v, dict)


def dumps_json(doc: Any, _indent: int = 0) -> str:
    """Indented JSON with points and paths kept on one line; NaN and infinity refused."""
    pad, inner = " " * _indent, " " * (_indent + 2)
    if isinstance(doc, dict):
        if not doc:
            return "{}"
        items = [f"{inner}{json.dumps(str(k))}: {dumps_json(v, _indent + 2)}" for k, v in doc.items()]
        return "{\n" + ",\n".join(items) + f"\n{pad}}}" + ("\n" if _indent == 0 else "")
    if isinstance(doc, (list, tuple)) and not _flat(doc):
        items = [f"{inner}{dumps_json(v, _indent + 2)}" for v in doc]
        return "[\n" + ",\n".join(items) + f"\n{pad}]"
    return json.dumps(doc, allow_nan=False, ensure_ascii=False)


class Document:
    """Mixin for value types written as TOML or JSON: subclasses provide ``to_dict``."""

    def to_dict(self) -> dict:  # pragma: no cover - every subclass defines it
        raise NotImplementedError

    def dumps_toml(self) -> str:
        return dumps_toml(self.to_dict())

    def dumps_json(self) -> str:
        return dumps_json(self.to_dict())

    def save(self, path: str | os.PathLike) -> None:
        """Write as JSON when ``path`` ends in ``.json``, else as TOML; atomically."""
        text = self.dumps_json() if str(path).lower().endswith(".json") else self.dumps_toml()
        write_atomic(path, text)
