"""The README and docs/ stay short, linked and true to the code they describe."""

import contextlib
import io
import re
from pathlib import Path

import pytest

from lodserver.api.settings import Settings
from lodserver.cli import main

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]

# [text](target) and [text]: target, with the target's #fragment dropped.
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)|^\[[^\]]+\]:\s*(\S+)", re.MULTILINE)
DATE = re.compile(r"20\d\d-\d\d-\d\d")


def _relative_links(page: Path):
    text = page.read_text(encoding="utf-8")
    for match in LINK.finditer(text):
        target = match.group(1) or match.group(2)
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue                              # a URL (http:, mailto:) or an anchor on the page
        yield target.split("#", 1)[0]


def test_the_readme_is_at_most_200_lines():
    assert len(README.read_text(encoding="utf-8").splitlines()) <= 200


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.name)
def test_every_relative_link_resolves_to_a_file(page):
    missing = [target for target in _relative_links(page)
               if not (page.parent / target).exists()]
    assert not missing, f"{page.name} links to files that do not exist: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.name)
def test_no_page_carries_a_date(page):
    """Dated figures live in bench/README.md, beside the commit they measured."""
    found = DATE.findall(page.read_text(encoding="utf-8"))
    assert not found, f"{page.name} names dates {found}: move dated figures to bench/README.md"


def test_every_server_setting_is_documented_in_server_md():
    prefix = Settings.model_config["env_prefix"]
    names = [prefix + field.upper() for field in Settings.model_fields]
    assert names, "the Settings model has no fields"
    text = (ROOT / "docs" / "server.md").read_text(encoding="utf-8")
    missing = [name for name in names if not re.search(rf"`{name}`", text)]
    assert not missing, f"docs/server.md does not document {missing}"


def _cli_help(command: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        main([command, "--help"])
    return out.getvalue()


def test_every_flag_the_readme_shows_is_one_its_command_takes():
    lines, fence = [], None
    for line in README.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fence = None if fence is not None else line[3:].strip()
        elif fence in ("sh", "bash", "console", ""):
            lines.append(line.split("#", 1)[0])      # a shell block, its comment cut
    shown = {}
    for line in lines:
        for call in re.finditer(r"lodserver ([a-z]+)([^&|;]*)", line):
            shown.setdefault(call.group(1), set()).update(re.findall(r"--[a-z][a-z-]*",
                                                                     call.group(2)))
    assert shown, "the README shows no lodserver command"
    for command, flags in shown.items():
        helped = set(re.findall(r"--[a-z][a-z-]*", _cli_help(command)))
        assert flags <= helped, f"lodserver {command} takes no {sorted(flags - helped)}"
