"""JSON documents: the one reader of every JSON file or request matfit takes, and the one writer of what it gives.

Reading: a text that is not JSON, or nested deeper than Python's parser recurses (`'[' * 100000`
raised RecursionError), is one MatfitError naming the file and the fix, never a traceback. A file is
read only if it is a regular file (`files.read_input`: `mkfifo f.json` or `/dev/zero` is refused
before a byte is read) of at most MAX_BYTES (a params.json is under 2 KB, a model's card under 4 KB),
and a document of any source is at most MAX_BYTES too, so that no input costs more than one bounded
parse. A leading UTF-8 byte order mark (what some Windows editors write) is accepted from every source.
Writing: JSON has no NaN or Infinity (`"neural_rmse": NaN` is refused by strict readers), so a
figure that is not finite is written as `null`, "no figure"; parameter values are never written
non-finite (`params.to_mapping` refuses them before a document is made).
"""

from __future__ import annotations

import json
import math
from typing import Any

from matfit import files
from matfit.errors import MatfitError, printable

MAX_BYTES = 2**20  # the largest JSON document matfit reads: 1 MB, hundreds of times the largest it writes
MAX_DIGITS = 40  # the longest whole number a document may hold: a seed or a count has at most 20 digits
BOM = "\ufeff"


def parse(text: str | bytes, source: str, fix: str, error: type[MatfitError] = MatfitError, **options: Any) -> Any:
    """Returns the JSON value of `text` (read from `source`); `error` naming `source` and `fix` if it is not JSON.

    `options` go to `json.loads` (`object_pairs_hook`, `parse_int`); a MatfitError that a hook raises is
    re-raised as `error`, prefixed with `source`. Whole numbers are read by `whole_number` unless `parse_int` says
    otherwise: one of 5000 digits is refused for what it is, not with Python's advice to raise its digit limit.
    """
    options.setdefault("parse_int", whole_number)
    source = printable(source)
    if len(text) > MAX_BYTES:
        raise error(f"{source} is more than {MAX_BYTES / 2**20:g} MB, the most a JSON document may be: {fix}")
    if isinstance(text, str):
        text = text.removeprefix(BOM)  # bytes are decoded by json.loads, which takes the mark itself
    try:
        return json.loads(text, **options)
    except json.JSONDecodeError as problem:
        where = f"{problem.msg} at line {problem.lineno}, column {problem.colno}"
        raise error(f"{source} is not valid JSON ({where}): {fix}") from None
    except RecursionError:
        raise error(f"{source} is not valid JSON (nested too deeply to read): {fix}") from None
    except MatfitError as problem:
        raise error(f"{source}: {problem}") from None
    except (ValueError, UnicodeDecodeError) as problem:  # bytes that are not UTF-8, an integer of 5000 digits
        raise error(f"{source} is not valid JSON ({str(problem).splitlines()[0]}): {fix}") from None


def whole_number(text: str) -> int:
    """Returns the JSON whole number `text` as an int; MatfitError if it has more than MAX_DIGITS digits (no value
    matfit takes is that long)."""
    digits = len(text.lstrip("-"))
    if digits > MAX_DIGITS:
        raise MatfitError(
            f"the whole number {text[:12]}... has {digits} digits, more than any value matfit takes: "
            "give one in the field's range"
        )
    return int(text)


def read(path: str, fix: str, error: type[MatfitError] = MatfitError, **options: Any) -> Any:
    """Returns the JSON value of the file `path`; `error` naming the file and `fix` if it cannot be read (it is not a
    regular file, or is larger than MAX_BYTES) or parsed."""
    try:
        text = files.read_input(path, MAX_BYTES)
    except OSError as problem:
        raise error(f"cannot read {printable(path)}: {problem.strerror or problem}: {fix}") from None
    return parse(text, path, fix, error, **options)


def finite(value: Any) -> Any:
    """Returns `value` (JSON data: dicts, lists, tuples, numbers, text) with every NaN or infinite float as None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [finite(item) for item in value]
    return value


def dumps(document: Any, indent: int | None = 2) -> str:
    """Returns a document as strict JSON text (a non-finite figure as null), ending with a newline when indented."""
    text = json.dumps(finite(document), indent=indent, allow_nan=False)
    return text + "\n" if indent is not None else text
