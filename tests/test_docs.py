"""The documentation site (mkdocs.yml, docs/): it builds with `--strict`, so a broken link, a missing
anchor, a page left out of the nav or a nav entry without its page fails the build (mkdocs.yml's
`validation` makes each a warning and `--strict` every warning an error); every command and every
option of every command appears on the site, in the options table docs/hooks.py generates from the
command itself; and a build that should fail does."""

from __future__ import annotations

import html
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def build(root: Path, out: Path) -> subprocess.CompletedProcess:
    """`mkdocs build --strict` of the site at `root` into `out` (run from `root`, as `make docs` runs). Not
    `-q`: it silences the warnings before `--strict` counts them, and a broken site would build."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(root / "mkdocs.yml"),
                           "-d", str(out)], cwd=root, env=env, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    result = build(ROOT, out)
    assert result.returncode == 0, result.stdout + result.stderr
    return out


def text_of(page: Path) -> str:
    """A built page's text: tags dropped, entities decoded, whitespace collapsed."""
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", page.read_text())).split())


def leaf_commands() -> dict[tuple[str, ...], object]:
    """Every command of `illm` that runs (not a group), by its path, from the click command tree."""
    import typer.main

    from cli.main import app

    found = {}

    def walk(command, path):
        children = getattr(command, "commands", None)
        if children is None:
            found[path] = command
        for name, sub in (children or {}).items():
            walk(sub, path + (name,))

    walk(typer.main.get_command(app), ())
    return found


def test_the_site_builds_strict(site):
    assert (site / "index.html").is_file() and (site / "commands" / "train" / "index.html").is_file()
    assert (site / "results" / "oracle" / "quality.png").is_file()


def test_every_command_and_each_of_its_options_is_on_its_page(site):
    commands = leaf_commands()
    assert len(commands) >= 17
    everywhere = " ".join(text_of(p) for p in site.rglob("*.html"))
    for path, command in commands.items():
        name = "illm " + " ".join(path)
        assert name in everywhere, f"`{name}` appears nowhere on the site"
        page = text_of(site / "commands" / path[0] / "index.html")
        start = page.find(f"Options of {name} ")
        assert start >= 0, f"no generated options table for `{name}` on commands/{path[0]}"
        table = page[start:]
        for param in command.params:
            flags = [*param.opts, *param.secondary_opts]
            if getattr(param, "param_type_name", "") == "argument":
                flags = [param.name.upper()]
            for flag in flags:
                assert re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", table), f"{name}: {flag} missing"


def test_the_options_tables_say_what_help_says(site):
    """A field's docstring is its option's help and its default the table's default (no drift)."""
    page = text_of(site / "commands" / "train" / "index.html")
    from illm_tools.rl.config import TrainConfig

    assert f"--num-envs int {TrainConfig().num_envs} " in page
    assert "--frames , --total-steps int 200000" in page


def broken_copy(tmp_path: Path) -> Path:
    """A copy of the site's sources to break on purpose."""
    root = tmp_path / "repo"
    shutil.copytree(ROOT / "docs", root / "docs")
    shutil.copy(ROOT / "mkdocs.yml", root / "mkdocs.yml")
    return root


@pytest.mark.slow  # a strict build per damage, 2-3 s each
@pytest.mark.parametrize("damage, said", [
    ("link", "no-such-page.md"),
    ("orphan", "orphan.md"),
    ("marker", "names no command"),
    ("anchor", "#no-such-heading"),
    ("table", "no page shows the options of `illm eval`"),
], ids=["broken-link", "page-not-in-nav", "unknown-command-marker", "missing-anchor", "command-without-table"])
def test_a_broken_site_fails_the_strict_build(tmp_path, damage, said):
    root = broken_copy(tmp_path)
    docs = root / "docs"
    if damage == "link":
        (docs / "measured.md").write_text((docs / "measured.md").read_text() + "\nSee [this](no-such-page.md).\n")
    elif damage == "orphan":
        (docs / "orphan.md").write_text("# A page no nav entry names\n")
    elif damage == "marker":
        (docs / "measured.md").write_text((docs / "measured.md").read_text() + "\n<!-- options: trian -->\n")
    elif damage == "anchor":
        (docs / "measured.md").write_text((docs / "measured.md").read_text()
                                          + "\nSee [it](troubleshooting.md#no-such-heading).\n")
    else:
        page = docs / "commands" / "eval.md"
        page.write_text(page.read_text().replace("<!-- options: eval -->", ""))
    result = build(root, tmp_path / "site")
    assert result.returncode != 0 and said in result.stdout + result.stderr, result.stdout + result.stderr
