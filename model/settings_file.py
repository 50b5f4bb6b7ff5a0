"""Reading a settings file (a model file, a rig file): the checks made before its content is parsed.

Each refusal is one line naming the file: a folder or a missing file, a file larger than any settings
file is (a few kB), text that is not UTF-8, YAML/JSON that does not parse, or nests deeper or holds more
values than a settings file does (a YAML alias bomb, a pathological nesting that would exhaust the
stack or the memory long before a schema could say no).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml

from model.errors import UserInputError

MAX_SETTINGS_BYTES = 1_000_000  # the presets are ~5 kB; a megabyte is no settings file
MAX_DEPTH = 32  # sections → fields → lists: a settings file nests 4 deep
MAX_VALUES = 100_000  # scalars and containers, aliases counted each time they are used


def read_settings(path: Path, what: str, error: type[UserInputError]) -> Any:
    """The parsed content of a YAML (or `.json`) settings file; `error` (one line) when it cannot be."""
    if path.is_dir():
        raise error(f"{path}: is a folder, not a {what} file")
    try:
        size = path.stat().st_size
        if size > MAX_SETTINGS_BYTES:
            raise error(f"{path}: {size} bytes is too large for a {what} file (at most {MAX_SETTINGS_BYTES})")
        raw = path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start})") from None
    kind = "JSON" if path.suffix.lower() == ".json" else "YAML"
    try:
        data = json.loads(text) if kind == "JSON" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark is not None else ""
        raise error(f"{path}: not valid {kind}{at}: {detail}") from None
    except RecursionError:
        raise error(f"{path}: nested deeper than a {what} file is (at most {MAX_DEPTH} levels)") from None
    _check_shape(data, path, what, error)
    return data


def _check_shape(data: Any, path: Path, what: str, error: type[UserInputError]) -> None:
    """Depth and size by an explicit stack: a deep or aliased document must not exhaust ours."""
    stack: list[tuple[Any, int]] = [(data, 1)]
    count = 0
    while stack:
        node, depth = stack.pop()
        count += 1
        if depth > MAX_DEPTH:
            raise error(f"{path}: nested deeper than a {what} file is (at most {MAX_DEPTH} levels)")
        if count > MAX_VALUES:
            raise error(f"{path}: more than {MAX_VALUES} values (YAML aliases included): not a {what} file")
        if isinstance(node, dict):
            stack.extend((value, depth + 1) for value in node.values())
        elif isinstance(node, list):
            stack.extend((value, depth + 1) for value in node)
