"""README's first screen and the docs pages it links: every relative link reaches a file and
heading that exist (the long sections moved out of README, and a moved heading must not leave
a dead link), and the tour's `quakescan` commands are ones the parser accepts."""
import re
import shlex
from pathlib import Path

import pytest

from quakescan.cli import build_parser

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def _without_code_blocks(text: str) -> str:
    """The text with fenced code removed: a `# comment` in a shell block is no heading, and
    `[x](y)` in code is no link."""
    return re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)


def _anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation other than - and _ dropped,
    spaces turned into hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(path: Path):
    seen: dict = {}
    for heading in re.findall(r"^#{1,6} (.+)$", _without_code_blocks(path.read_text()), flags=re.M):
        base = _anchor(heading)
        n = seen.get(base, 0)
        seen[base] = n + 1
        yield base if n == 0 else f"{base}-{n}"


def _links(path: Path) -> list:
    text = re.sub(r"`[^`\n]*`", "", _without_code_blocks(path.read_text()))
    return [t for t in re.findall(r"\]\(([^)\s]+)\)", text) if not re.match(r"[a-z]+:", t)]


def test_anchors_follow_githubs_rule():
    assert _anchor("Building result (`classify`)") == "building-result-classify"
    assert _anchor("Roof and facade details (`--details typical`)") == "roof-and-facade-details---details-typical"
    assert _anchor("The paper's experiment, simulated") == "the-papers-experiment-simulated"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_relative_link_reaches_a_file_and_heading(page):
    dead = []
    for link in _links(page):
        target, _, anchor = link.partition("#")
        path = (page.parent / target).resolve() if target else page
        if not path.exists():
            dead.append(f"{link}: no file {path.relative_to(REPO)}")
        elif anchor and path.suffix == ".md" and anchor not in set(_anchors(path)):
            dead.append(f"{link}: no heading #{anchor} in {path.relative_to(REPO)}")
    assert not dead, "\n".join(dead)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_code_block_is_closed(page):
    """An unclosed fence turns the rest of the page into code (and hides its links from the
    check above)."""
    fences = re.findall(r"^```", page.read_text(), flags=re.M)
    assert len(fences) % 2 == 0, f"{page.name}: {len(fences)} fence lines"


def test_the_readme_links_every_docs_page():
    readme = (REPO / "README.md").read_text()
    unlinked = [p.name for p in PAGES[1:] if f"](docs/{p.name}" not in readme]
    assert not unlinked, f"docs pages the README does not link: {unlinked}"


def test_the_tours_quakescan_commands_parse():
    readme = (REPO / "README.md").read_text()
    tour = readme[readme.index("## A tour in ten lines\n"):]
    tour = tour[:tour.index("\n## ")]
    commands = [c for c in re.findall(r"`(quakescan [^`]+)`", tour) if not c.endswith(" -h")]
    assert len(commands) >= 7, commands
    parser = build_parser()
    for command in commands:
        try:
            parser.parse_args(shlex.split(command)[1:])
        except SystemExit:
            pytest.fail(f"the tour's command does not parse: {command}")
