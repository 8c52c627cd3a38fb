"""User files as text: UTF-8 (a spreadsheet's byte-order mark accepted), decoded as JSON or
TOML, every failure one line naming the file. The one place where afmctl turns a user's file
into data (model, drift-parameter, configuration, simulator settings and scanner files)."""
from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

from .base import ModelError


def read_text_file(path: str | Path, what: str, error: type[Exception] = ModelError) -> str:
    """The text of a UTF-8 file (a leading byte-order mark, as spreadsheets write, is dropped).
    Unreadable, UTF-16 or binary files raise ``error`` with one line naming the file: the one
    place where afmctl turns a user's file into text (model, drift-parameter, configuration and
    simulator settings files)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as err:
        raise error(f"{p}: cannot read {what} ({err.strerror or err})") from None
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise error(f"{p}: {what} is UTF-16 text; save it as UTF-8")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise error(f"{p}: {what} is not UTF-8 text (byte 0x{raw[err.start]:02x} at offset {err.start}); "
                    "is it a binary file?") from None
    if "\x00" in text:
        raise error(f"{p}: {what} contains NUL bytes; is it a binary file?")
    return text


def decode_text(text: str, fmt: str, where: str, error: type[Exception] = ModelError) -> Any:
    """``text`` decoded as ``fmt`` (``"JSON"`` or ``"TOML"``); bad syntax, integers of more
    than 4300 digits and nesting too deep to decode raise ``error`` with one line naming
    ``where`` (the file)."""
    loads = {"JSON": json.loads, "TOML": tomllib.loads}[fmt]
    try:
        return loads(text)
    except RecursionError:
        raise error(f"{where}: nested too deeply to decode as {fmt}") from None
    except ValueError as err:          # JSONDecodeError and TOMLDecodeError are ValueErrors too
        if isinstance(err, json.JSONDecodeError):
            raise error(f"{where}: not valid JSON (line {err.lineno}: {err.msg})") from None
        if isinstance(err, tomllib.TOMLDecodeError):
            raise error(f"{where}: not valid TOML ({err})") from None
        raise error(f"{where}: a number in it is too long (at most 4300 digits)") from None


def read_json_file(path: str | Path, what: str = "model file") -> Any:
    """Decode a JSON file; :class:`ModelError` naming the file for I/O, encoding and syntax
    errors (:func:`read_text_file`, :func:`decode_text`)."""
    return decode_text(read_text_file(path, what), "JSON", str(path))
