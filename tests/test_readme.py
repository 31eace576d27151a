"""The README and docs/: short, current, every link resolving, and the quick start running as written."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
HISTORY_PAGE = ROOT / "docs" / "decisions.md"  # the one page where dated, per-stop history belongs
MAX_README_LINES = 300

LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^()\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^(```|~~~)")
DATED = re.compile(r"\b(?:19|20)\d\d-[01]\d-[0-3]\d\b|\bstops? \d+\b", re.IGNORECASE)
# History told outside docs/decisions.md: a rename note ("`search` (was `fit.py`)", "`engine`, was `render.py`"), a
# comparison with an older version ("the earlier rule", "the code before", "before: 8.77 s", "today's 382 s"), what
# changed ("no longer", "previously"). Words that are plain prose elsewhere ("before", "was", "earlier", "previous")
# count only in those phrases.
HISTORY = re.compile(
    r"\((?:was|formerly|previously|renamed from)\b"
    r"|[,;]\s*(?:was|formerly|previously|renamed from)\s+`"
    r"|\b(?:no\s+longer|formerly|previously|until\s+now|renamed\s+from|today's)\b|\bbefore:"
    r"|\b(?:the|its)\s+(?:code|rule|count|default|version|behaviou?r)\s+before\b"
    r"|\b(?:earlier|older|previous|old)\s+(?:rules?|code|versions?|defaults?|behaviou?rs?|measurements?)\b"
    r"|\bbefore\s+(?:this|the|that)\s+change\b",
    re.IGNORECASE,
)


def prose(text: str) -> str:
    """Returns the Markdown text with its fenced code blocks blanked (line numbers kept)."""
    lines, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            lines.append("")
        else:
            lines.append("" if fenced else line)
    return "\n".join(lines)


def slug(heading: str) -> str:
    """Returns GitHub's anchor for a heading: its rendered text lower-cased, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text stays, its target goes
    text = re.sub(r"<[^>]+>", "", text).strip().lower()
    kept = (c for c in text if c in " -_" or unicodedata.category(c)[0] in "LNM")
    return "".join(kept).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Returns every heading anchor of a Markdown file, repeated headings numbered as GitHub numbers them."""
    seen: dict[str, int] = {}
    result = set()
    for line in prose(path.read_text()).splitlines():
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not match:
            continue
        base = slug(match.group(1))
        count = seen.get(base, 0)
        seen[base] = count + 1
        result.add(base if count == 0 else f"{base}-{count}")
    return result


def broken_links(path: Path) -> list[str]:
    """Returns the relative links and #anchors of a Markdown file that lead nowhere."""
    broken = []
    for target in LINK.findall(prose(path.read_text())):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # http:, mailto: ...
            continue
        file_part, _, anchor = target.partition("#")
        destination = (path.parent / file_part).resolve() if file_part else path
        if not destination.exists():
            broken.append(f"{path.name}: {target} (no such file)")
        elif anchor and destination.suffix == ".md" and anchor not in anchors(destination):
            broken.append(f"{path.name}: {target} (no heading #{anchor})")
    return broken


def test_slug_follows_githubs_rules():
    assert slug("The edit-and-see loop: `matfit serve`") == "the-edit-and-see-loop-matfit-serve"
    assert slug("1b. matfit's default (lbfgsb, 2 corrections)") == "1b-matfits-default-lbfgsb-2-corrections"
    assert slug("Fitting_options & [more](x.md)") == "fitting_options--more"


def test_repeated_headings_are_numbered(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# A\n## Measured\n```sh\n# not a heading\n```\n## Measured\n")
    assert anchors(page) == {"a", "measured", "measured-1"}


def test_broken_links_are_found(tmp_path):
    (tmp_path / "other.md").write_text("## Here\n")
    page = tmp_path / "page.md"
    page.write_text("[a](other.md#here) [b](other.md#there) [c](missing.md) [d](#top) [e](https://x.org/#y)\n# Top\n")
    assert broken_links(page) == ["page.md: other.md#there (no heading #there)", "page.md: missing.md (no such file)"]


def test_readme_is_short():
    lines = len(README.read_text().splitlines())
    assert lines <= MAX_README_LINES, f"README.md has {lines} lines; the manual goes to docs/"


def test_every_docs_page_is_linked_from_the_readme():
    linked = {(ROOT / target.partition("#")[0]).resolve() for target in LINK.findall(README.read_text())}
    assert DOCS, "docs/ holds no page"
    assert [page.name for page in DOCS if page.resolve() not in linked] == []


def history(text: str) -> list[str]:
    """Returns the dates, stop numbers and history notes of a text (`DATED`, `HISTORY`): docs/decisions.md's alone."""
    return [match.group(0) for pattern in (DATED, HISTORY) for match in pattern.finditer(text)]


def test_history_is_found_and_prose_is_not():
    planted = [
        "`search` (was `fit.py`) holds the objective",
        "`engine`, was `render.py`, renders",
        "about twice the renders of the earlier rule",
        "Against the code before the render children: 8.77 s",
        "81% with three, the\ncount before",
        "cold fit before: 6.13 s",
        "a failed fit no longer restarts Mitsuba",
        "previously a traceback",
        "today's 382 s",
        "measured on 2024-05-01",
        "as stop 12 found",
    ]
    assert [text for text in planted if not history(text)] == []
    prose = [
        "every output path checked before any work",
        "whose distance at least halved since the round before keeps its move",
        "the earlier rounds' points are steps on the way",
        "the previous frame's optimum joins the candidates",
        "a matfit command without `worker` (an older matfit) runs each fit as a process of its own",
        "how each constant was measured: `export.py`",
        "the watched file ... was deleted while it was fitted",
        "image i is the same whatever was rendered before it",
        "renamed into place together, only once every one of them was written",
    ]
    assert [text for text in prose if history(text)] == []


@pytest.mark.parametrize("page", [README, *[page for page in DOCS if page != HISTORY_PAGE]], ids=lambda page: page.name)
def test_nothing_dated_outside_the_decisions(page):
    found = history(page.read_text())
    assert found == [], (
        f"{page.name}: dated, per-stop or history text (a rename, a past version) goes to docs/decisions.md"
    )


@pytest.mark.parametrize("page", [README, *DOCS], ids=lambda page: page.name)
def test_every_relative_link_and_anchor_resolves(page):
    assert broken_links(page) == []


def test_the_docs_sections_the_code_points_to_exist():
    cited = re.compile(r"docs/([a-z-]+\.md)(?:#([a-z0-9_-]+))?")
    missing = []
    for source in sorted((ROOT / "matfit").rglob("*.py")):
        for name, anchor in cited.findall(source.read_text()):
            page = ROOT / "docs" / name
            if not page.exists() or (anchor and anchor not in anchors(page)):
                missing.append(f"{source.relative_to(ROOT)}: docs/{name}{'#' + anchor if anchor else ''}")
    assert missing == []


def quick_start_commands() -> list[list[str]]:
    """Returns the `matfit fit` and `matfit render` command lines of the README's quick start, as written."""
    text = README.read_text()
    section = text.split("\n## Quick start\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```sh\n(.*?)```", section, re.DOTALL)
    lines = [line.split(" #", 1)[0].strip() for block in blocks for line in block.splitlines()]
    return [shlex.split(line) for line in lines if line.startswith(("matfit fit ", "matfit render "))]


def tiny(command: list[str]) -> list[str]:
    """Returns the command with its renders at 16 px and 4 spp and the package's example paths made absolute."""
    small = {"--size": "16", "--spp": "4"}
    result = []
    for i, word in enumerate(command):
        if i > 0 and command[i - 1] in small:
            word = small[command[i - 1]]
        elif word.startswith("matfit/data/"):
            word = str(ROOT / word)
        result.append(word)
    renders = command[1] == "render" or "--render" in command
    return result + [f"{option}={value}" for option, value in small.items() if renders and option not in command]


@pytest.fixture(scope="module")
def quick_start(tmp_path_factory) -> tuple[Path, list[tuple[list[str], subprocess.CompletedProcess]]]:
    """Returns (the folder, [(command, its run)]) of the README's quick start run as written, each command a `matfit`
    process in that folder (renders made tiny). Two tests read it: a default fit costs seconds."""
    folder = tmp_path_factory.mktemp("quick-start")
    runs = []
    for command in quick_start_commands():
        runs.append(
            (
                command,
                subprocess.run(
                    [sys.executable, "-m", "matfit", *tiny(command)[1:]], cwd=folder, capture_output=True, text=True
                ),
            )
        )
    return folder, runs


@pytest.mark.slow
def test_the_quick_start_runs_as_written(quick_start):
    folder, runs = quick_start
    assert [command[:2] for command, _ in runs] == [["matfit", "fit"], ["matfit", "render"]]
    for command, run in runs:
        assert run.returncode == 0, f"{shlex.join(command)}\n{run.stderr}"
        outputs = [command[i + 1] for i, word in enumerate(command) if word in ("-o", "--report", "--render")]
        assert outputs and all((folder / output).stat().st_size > 0 for output in outputs)
    fitted = json.loads((folder / "params.json").read_text())
    assert len(fitted["params"]) == 19
    assert 0 < fitted["mitsuba_rmse"] < 6  # the recoloured example's render lands about 3 from its target


@pytest.mark.slow
def test_a_second_fit_of_the_quick_start_picture_writes_the_same_params_json_but_for_the_timings(
    quick_start, tmp_path, monkeypatch
):
    # The quick start's default fit of a shipped example with the shipped model (gradient stage, two rounds of
    # correction, which carry a render's last bits into the answer, verification's renders in a render process),
    # made again by another process, this one, in another folder: the same params.json but for its timings.
    from typer.testing import CliRunner

    from matfit.app.cli import app

    folder, runs = quick_start
    command = next(command for command, _ in runs if command[1] == "fit")
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, tiny(command)[1:])
    assert result.exit_code == 0, result.output
    document = json.loads((tmp_path / "params.json").read_text())
    assert document["verification"]["corrections"] == 2 and document["verification"]["seconds"] > 0
    timings = ('"fit_seconds": ', '"wall_time_s": ', '"seconds": ')
    texts = [
        [line for line in (where / "params.json").read_text().splitlines() if not line.strip().startswith(timings)]
        for where in (folder, tmp_path)
    ]
    assert texts[0] == texts[1]
