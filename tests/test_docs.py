"""
The documentation keeps its promises: its relative links resolve, the README stays short, and the README's Python
examples run as written (scaled down to a tiny planner and a few hundred steps).

A Python block that cannot run here (it needs a GPU, say) is skipped when one of its lines is the comment
``# docs-test: skip``; keep those rare.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import gymnasium.envs.registration
import pytest
from conftest import TINY

import sb3_poplin
import sb3_poplin.poplin
import sb3_poplin.tasks
from sb3_poplin import POPLIN

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
# the documentation beside README.md and docs/
OTHER_PAGES = ("CHANGELOG.md", "benchmarks/README.md")
MAX_README_LINES = 300
SKIP_COMMENT = "# docs-test: skip"
# env steps per env that a README example may train for
LEARN_STEPS_PER_ENV = 400

FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
HTML_ANCHOR = re.compile(r"""<a\s+(?:name|id)=["']([^"']+)["']""")
CODE_SPAN = re.compile(r"(`+)(.+?)\1")
INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+\"[^\"]*\")?\s*$")
EXTERNAL = re.compile(r"^[a-z][a-z0-9+.-]*:", re.IGNORECASE)


# ---------------------------------------------------------------------------------------- Markdown reading
def prose_lines(path: Path) -> Iterator[tuple[int, str]]:
    """The lines of a Markdown file outside fenced code blocks, with their numbers (from 1)."""
    fence: str | None = None
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        match = FENCE.match(line)
        if match:
            if fence is None:
                fence = match.group(1)
            elif match.group(1) == fence:
                fence = None
            continue
        if fence is None:
            yield number, line


def github_slug(heading: str) -> str:
    """
    The anchor GitHub gives a heading: its text (link targets and code marks dropped) in lower case, without
    punctuation other than ``-`` and ``_``, spaces turned into ``-``.
    """
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = re.sub(r"[^\w\- ]", "", text.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor of a Markdown file: its headings' slugs (repeats numbered as GitHub does) and HTML anchors."""
    seen: Counter[str] = Counter()
    found: set[str] = set()
    for _, line in prose_lines(path):
        match = HEADING.match(line)
        if match:
            slug = github_slug(match.group(2))
            found.add(slug if seen[slug] == 0 else f"{slug}-{seen[slug]}")
            seen[slug] += 1
        found.update(HTML_ANCHOR.findall(line))
    return found


def links(path: Path) -> Iterator[tuple[int, str]]:
    """The link and image targets of a Markdown file's prose (inline and reference definitions), with line numbers."""
    for number, line in prose_lines(path):
        text = CODE_SPAN.sub("code", line)
        for match in INLINE_LINK.finditer(text):
            yield number, match.group(1)
        match = REFERENCE_LINK.match(text)
        if match:
            yield number, match.group(1)


def documentation_files() -> list[Path]:
    """README.md, docs/*.md, the changelog and the benchmarks' index."""
    return [README, *sorted((ROOT / "docs").glob("*.md")), *(ROOT / name for name in OTHER_PAGES)]


def broken_links(path: Path, root: Path = ROOT) -> list[str]:
    """The relative links of one Markdown file whose file or ``#anchor`` does not exist, as messages."""
    problems = []
    for number, target in links(path):
        if EXTERNAL.match(target):
            continue
        file_part, _, anchor = target.partition("#")
        destination = (path.parent / file_part).resolve() if file_part else path.resolve()
        where = f"{path.relative_to(root)}:{number}: {target}"
        if not destination.exists():
            problems.append(f"{where}: {file_part} does not exist")
            continue
        if anchor and destination.suffix == ".md" and anchor not in anchors(destination):
            problems.append(f"{where}: no heading with anchor #{anchor} in {destination.relative_to(root.resolve())}")
    return problems


def python_blocks(path: Path) -> list[tuple[int, str]]:
    """The ```python blocks of a Markdown file, in order, with the line number of their opening fence."""
    blocks: list[tuple[int, str]] = []
    lines = path.read_text(encoding="utf-8").splitlines()
    start: int | None = None
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if start is None and re.fullmatch(r"```\s*python", stripped):
            start = number
        elif start is not None and stripped == "```":
            blocks.append((start, "\n".join(lines[start : number - 1]) + "\n"))
            start = None
    assert start is None, f"{path.name}: the python block opened on line {start} is never closed"
    return blocks


# ---------------------------------------------------------------------------------------- the reading itself
def test_github_slug() -> None:
    assert github_slug("How to replicate") == "how-to-replicate"
    assert github_slug("The paper's Cheetah (`sb3_poplin/PETSCheetah-v0`), issue 18") == (
        "the-papers-cheetah-sb3_poplinpetscheetah-v0-issue-18"
    )
    assert github_slug("CPU suite (`benchmarks/compare.py --budget cpu`)") == "cpu-suite-benchmarkscomparepy---budget-cpu"
    assert github_slug("See [the docs](docs/index.md) \u00b7 2 \u00d7 3") == "see-the-docs--2--3"


def test_broken_link_is_found(tmp_path: Path) -> None:
    (tmp_path / "other.md").write_text("# Some title\n\n## Repeated\n\n## Repeated\n")
    page = tmp_path / "page.md"
    page.write_text(
        "[ok](other.md#some-title) [ok](other.md#repeated-1) [ok](#here) [ok](https://example.org/x.md#nothing)\n"
        "## Here\n```bash\n[not a link](missing.md)\n```\n"
        "[bad](missing.md) [bad](other.md#nowhere) ![bad](img.png) `[code](missing.md)`\n[ref]: gone.md\n"
    )
    problems = broken_links(page, root=tmp_path)
    assert [problem.split(": ")[1] for problem in problems] == ["missing.md", "other.md#nowhere", "img.png", "gone.md"]
    (tmp_path / "CHANGELOG.md").write_text("# Changelog\n")
    page.write_text("[ok](CHANGELOG.md#changelog) [bad](CHANGELOG.md#nowhere)\n")
    assert [problem.split(": ")[1] for problem in broken_links(page, root=tmp_path)] == ["CHANGELOG.md#nowhere"]


# ---------------------------------------------------------------------------------------- the documentation
@pytest.mark.parametrize("path", documentation_files(), ids=lambda path: str(path.relative_to(ROOT)))
def test_relative_links_resolve(path: Path) -> None:
    problems = broken_links(path)
    assert not problems, "broken links:\n" + "\n".join(problems)


def test_docs_folder_has_its_pages() -> None:
    for page in ("index", "tasks", "variants", "design", "analyses", "replication", "results"):
        assert (ROOT / "docs" / f"{page}.md").is_file(), f"docs/{page}.md is missing"


def test_readme_is_short() -> None:
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines; at most {MAX_README_LINES}"


# ---------------------------------------------------------------------------------------- the README's examples
class TinyPOPLIN(POPLIN):
    """POPLIN with the test suite's tiny planner and model, whatever the example asks for, and short ``learn`` calls."""

    def __init__(self, policy: Any = "pets", env: Any = None, **kwargs: Any) -> None:
        if kwargs.get("_init_setup_model", True):  # a new agent, not one being loaded
            kwargs = {**kwargs, **TINY}
        super().__init__(policy, env, **kwargs)

    def learn(self, total_timesteps: int, *args: Any, **kwargs: Any) -> TinyPOPLIN:  # type: ignore[override]
        return super().learn(min(total_timesteps, LEARN_STEPS_PER_ENV * self.n_envs), *args, **kwargs)


def run_blocks(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> int:
    """Execute a Markdown file's python blocks in order in one namespace; return how many ran."""
    blocks = python_blocks(path)
    assert blocks, f"{path.name} has no python block"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sb3_poplin, "POPLIN", TinyPOPLIN)
    monkeypatch.setattr(sb3_poplin.poplin, "POPLIN", TinyPOPLIN)
    # what a page registers (its own env and task) ends with the test: later tests see the built-in registries
    monkeypatch.setattr(sb3_poplin.tasks, "_REGISTRY", dict(sb3_poplin.tasks._REGISTRY))
    monkeypatch.setattr(gymnasium.envs.registration, "registry", dict(gymnasium.envs.registration.registry))
    namespace: dict[str, Any] = {"__name__": "__docs__"}
    ran = 0
    for line, source in blocks:
        if any(code_line.strip() == SKIP_COMMENT for code_line in source.splitlines()):
            continue
        code = compile(source, f"{path.name}, python block at line {line}", "exec")
        try:
            exec(code, namespace)
        except Exception as error:
            pytest.fail(f"{path.name}: the python block at line {line} fails: {type(error).__name__}: {error}")
        ran += 1
    return ran


def test_readme_python_blocks_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert run_blocks(README, tmp_path, monkeypatch) >= 2  # the callbacks example runs in docs/usage.md


def test_runner_catches_a_broken_block(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    page = tmp_path / "page.md"
    page.write_text(
        "```python\nfrom sb3_poplin import POPLIN\nmodel = POPLIN('pets', 'Pendulum-v1', horizon=30)\n```\n"
        "```python\nassert model.settings.horizon == 5 and model.settings.population_size == 20  # the tiny settings won\n"
        "model.learn(100_000)\nassert model.num_timesteps <= 400\n```\n"
        f"```python\n{SKIP_COMMENT}\nraise RuntimeError('skipped')\n```\n"
    )
    assert run_blocks(page, tmp_path, monkeypatch) == 2
    page.write_text("```python\nfrom sb3_poplin import POPLIN\nPOPLIN('pets', 'Pendulum-v1').lern(100)\n```\n")
    with pytest.raises(pytest.fail.Exception, match="AttributeError"):
        run_blocks(page, tmp_path, monkeypatch)


@pytest.mark.parametrize(
    "path",
    [path for path in sorted((ROOT / "docs").glob("*.md")) if python_blocks(path)],
    ids=lambda path: str(path.relative_to(ROOT)),
)
def test_docs_python_blocks_run(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert run_blocks(path, tmp_path, monkeypatch) >= 1
