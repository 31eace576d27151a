import json
import math
import os
import time

import numpy as np
import pytest

from matfit import documents
from matfit.errors import MatfitError, SequenceError


def test_a_figure_that_is_not_finite_is_written_as_null_and_the_text_is_strict_json():
    document = {"neural_rmse": math.nan, "start_rmse": 2.5, "history": [1.0, math.inf, -math.inf], "nested": {"x": ()}}
    text = documents.dumps(document)
    assert text.endswith("}\n") and "NaN" not in text and "Infinity" not in text

    def strict(constant):
        raise AssertionError(f"{constant} is not JSON")

    assert json.loads(text, parse_constant=strict) == {
        "neural_rmse": None,
        "start_rmse": 2.5,
        "history": [1.0, None, None],
        "nested": {"x": []},
    }
    assert documents.dumps({"a": 1}, indent=None) == '{"a": 1}'
    with pytest.raises(TypeError):  # a NumPy scalar is not JSON data: callers convert, nothing is written silently
        documents.dumps({"a": np.float32(1.0)})


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("[" * 100000, "nested too deeply to read"),  # was a RecursionError
        ('{"a": ' * 100000, "nested too deeply to read"),
        ("{oops", "Expecting property name enclosed in double quotes at line 1, column 2"),
        (b'{"a": "\xff"}', "'utf-8' codec can't decode byte 0xff in position 7"),
        ("", "Expecting value at line 1, column 1"),
    ],
)
def test_text_that_is_not_json_is_one_line_naming_the_source_and_the_fix(text, reason):
    with pytest.raises(SequenceError) as error:
        documents.parse(text, "frame_1.json", "delete it", SequenceError)
    message = str(error.value)
    assert message.startswith("frame_1.json is not valid JSON (") and reason in message
    assert message.endswith("): delete it") and "\n" not in message


def test_a_file_that_cannot_be_read_is_one_line(tmp_path):
    with pytest.raises(
        MatfitError, match=rf"^cannot read {tmp_path}/none\.json: No such file or directory: check the path$"
    ):
        documents.read(str(tmp_path / "none.json"), "check the path")
    (tmp_path / "ok.json").write_text('{"a": [1, 2]}')
    assert documents.read(str(tmp_path / "ok.json"), "check the path") == {"a": [1, 2]}


def test_only_a_regular_file_is_read_and_at_most_its_cap(tmp_path):
    # `mkfifo f.json; matfit render f.json` hung opening it; `--init /dev/zero` read without end.
    os.mkfifo(tmp_path / "f.json")
    started = time.perf_counter()
    with pytest.raises(MatfitError, match=r"f\.json: it is a FIFO \(named pipe\), not a regular file: give a file$"):
        documents.read(str(tmp_path / "f.json"), "give a file")
    with pytest.raises(MatfitError, match=r"^cannot read /dev/zero: it is a character device, not a regular file"):
        documents.read("/dev/zero", "give a file")
    with pytest.raises(MatfitError, match=rf"^cannot read {tmp_path}: it is a folder, not a regular file"):
        documents.read(str(tmp_path), "give a file")
    assert time.perf_counter() - started < 5
    (tmp_path / "large.json").write_text(" " * documents.MAX_BYTES + "{}")
    with pytest.raises(MatfitError, match=r"large\.json is more than 1 MB, the most a JSON document may be: give a f"):
        documents.read(str(tmp_path / "large.json"), "give a file")
    with pytest.raises(MatfitError, match=r"^the request is more than 1 MB"):
        documents.parse(b" " * documents.MAX_BYTES + b"{}", "the request", "send less")
    (tmp_path / "large.json").write_text(" " * (documents.MAX_BYTES - 2) + "{}")
    assert documents.read(str(tmp_path / "large.json"), "give a file") == {}


def test_a_byte_order_mark_is_accepted_from_every_source(tmp_path):
    (tmp_path / "bom.json").write_bytes(b'\xef\xbb\xbf{"a": 1}')
    assert documents.read(str(tmp_path / "bom.json"), "fix") == {"a": 1}
    assert documents.parse(b'\xef\xbb\xbf{"a": 1}', "upload", "fix") == {"a": 1}
    assert documents.parse('\ufeff{"a": 1}', "the init field", "fix") == {"a": 1}


def test_a_whole_number_too_long_for_any_value_is_refused_for_what_it_is(tmp_path):
    # 5000 digits were refused with Python's advice to call sys.set_int_max_str_digits().
    path = tmp_path / "meta.json"
    path.write_text('{"count": ' + "1" * 5000 + "}")
    with pytest.raises(SequenceError) as raised:
        documents.read(str(path), "write it again", SequenceError)
    assert str(raised.value) == (
        f"{path}: the whole number 111111111111... has 5000 digits, more than any value matfit takes: "
        "give one in the field's range"
    )
    assert documents.parse('{"seed": 18446744073709551615}', "x", "fix") == {"seed": 2**64 - 1}
