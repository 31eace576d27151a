"""Output files: the checks made before any work, and the temporaries a killed process leaves."""

import os
import subprocess
import sys

import pytest

from matfit import files
from matfit.errors import OutputError


def test_output_folders_that_are_files_are_refused(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match=r"frames out .*file is a file: give a folder"):
        files.check_folder(str(tmp_path / "file"), field="frames_out")
    with pytest.raises(OutputError, match=r"cannot be created: .*file is a file"):
        files.check_folder(str(tmp_path / "file" / "sub"))


def test_a_read_only_output_folder_is_refused_however_deep():
    with pytest.raises(OutputError, match=r"out /proc/a/b cannot be written: /proc is read-only"):
        files.check_folder("/proc/a/b")


def test_two_outputs_that_are_one_file_are_refused(tmp_path):
    a = str(tmp_path / "r.png")
    with pytest.raises(OutputError, match=r"^report .*r.png and render .*r.png are the same file") as caught:
        files.check_outputs({"output": str(tmp_path / "p.json"), "report": a, "render": a})
    assert caught.value.field == "report"
    (tmp_path / "sub").mkdir()
    with pytest.raises(OutputError, match="are the same file"):  # the same new file, written two ways
        files.check_outputs({"report": a, "render": str(tmp_path / "sub" / ".." / "r.png")})
    files.check_outputs({"report": a, "render": str(tmp_path / "r2.png")})  # distinct: accepted


def test_an_output_that_is_an_input_is_refused_through_links(tmp_path):
    picture = tmp_path / "edited.png"
    picture.write_bytes(b"the user's picture")
    (tmp_path / "link.png").symlink_to(picture)
    os.link(picture, tmp_path / "hard.png")
    (tmp_path / "dir").symlink_to(tmp_path)
    for output in ("edited.png", "link.png", "hard.png", "dir/edited.png"):
        with pytest.raises(OutputError, match=f"^report .*{output} is the target .*edited.png: writing it would"):
            files.check_outputs({"report": str(tmp_path / output)}, {"target": str(picture), "mask": None})
    files.check_outputs({"report": str(tmp_path / "other.png")}, {"target": str(picture)})
    assert picture.read_bytes() == b"the user's picture"


def test_no_output_lies_in_the_model_s_folder_or_is_one_of_its_files_by_a_link(tmp_path):
    from matfit import shipped

    model = tmp_path / "model"
    model.mkdir()
    (model / "decoder.json").write_text("the decoder")
    os.link(model / "decoder.json", tmp_path / "hard.json")
    (tmp_path / "soft.json").symlink_to(model / "decoder.json")
    (tmp_path / "folder").symlink_to(model)
    for output in ("model/decoder.json", "model/evaluation.json", "hard.json", "soft.json", "folder/new.json"):
        with pytest.raises(OutputError, match=f"^output {tmp_path / output} is a file of the model {model}: writing"):
            files.check_outputs({"output": str(tmp_path / output)}, model=str(model))
    files.check_outputs({"output": str(tmp_path / "p.json")}, model=str(model))
    for output in (shipped.MODEL / "decoder.json", shipped.MODEL / "new.png"):  # the shipped one's, always
        with pytest.raises(OutputError, match=f"is a file of the model {shipped.MODEL}: writing it would change"):
            files.check_outputs({"output": str(output)})
    with pytest.raises(OutputError, match=r"choose another out folder$"):
        files.check_folder(str(model), [("summary", str(model / "summary.md"))], model=str(model))
    assert (model / "decoder.json").read_text() == "the decoder"


def test_a_name_too_long_for_the_folder_is_refused_before_any_work(tmp_path):
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    with pytest.raises(OutputError, match=f"its name is 300 bytes, longer than the {limit} its folder takes"):
        files.check_outputs({"output": str(tmp_path / ("p" * 295 + ".json"))})
    # the name fits, but the temporary written beside it (.matfit-<pid>@<host>-XXXXXXXX<extension>) would not
    extension = "." + "x" * (limit - 10)
    with pytest.raises(OutputError, match="the temporary file written beside it would have a name of"):
        files.check_outputs({"output": str(tmp_path / ("p" + extension))})
    files.check_outputs({"output": str(tmp_path / ("p" * (limit - 5) + ".json"))})  # the longest that fits


def dead_pid() -> int:
    """Returns the pid of a process of this host that has ended."""
    process = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(process.stdout)


def test_temporaries_name_their_owner_and_a_dead_owners_are_removed(tmp_path):
    host = files.owner().partition("@")[2]
    stale = tmp_path / f".matfit-{dead_pid()}@{host}-abcd1234.png"
    alive = tmp_path / f".matfit-{os.getppid()}@{host}-efgh5678.png"  # pytest's parent: running
    elsewhere = tmp_path / f".matfit-{dead_pid()}@another-host-ijkl9012.png"
    anonymous = tmp_path / ".matfit-mnop3456.png"
    for path in (stale, alive, elsewhere, anonymous):
        path.write_bytes(b"half")
    files.write_text(str(tmp_path / "p.json"), "{}\n")
    assert sorted(os.listdir(tmp_path)) == sorted([alive.name, elsewhere.name, anonymous.name, "p.json"])
    temporary = files.temporary_beside(str(tmp_path / "r.png"))
    assert os.path.basename(temporary).startswith(f".matfit-{os.getpid()}@{host}-")
    files.remove(temporary)


KILLED_WHILE_WRITING = """
import os, sys
from matfit import files
temporary = files.temporary_beside(sys.argv[1])
print(temporary, flush=True)
os.kill(os.getpid(), 9)
"""


def test_a_temporary_left_by_kill_9_is_removed_by_the_next_write(tmp_path):
    target = str(tmp_path / "params.json")
    killed = subprocess.run([sys.executable, "-c", KILLED_WHILE_WRITING, target], capture_output=True, text=True)
    assert killed.returncode == -9
    left = killed.stdout.strip()
    assert os.path.exists(left) and os.path.basename(left).startswith(".matfit-")
    files.write_text(target, "{}\n")
    assert os.listdir(tmp_path) == ["params.json"]
