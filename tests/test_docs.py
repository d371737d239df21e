"""The documentation site (mkdocs.yml, docs/): it builds with `--strict`, so a broken link, a missing
anchor, a page left out of the nav or a nav entry without its page fails the build (mkdocs.yml's
`validation` makes each a warning and `--strict` every warning an error); every command and every
option of every command appears on the site, in the options table docs/hooks.py generates from the
command itself; and a build that should fail does. The whole site is built once per test run (every
xdist worker reads that one build); the builds that must fail build a minimal tree of three pages with
the real mkdocs.yml's settings and hooks."""

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


def _build_the_site(out: Path) -> None:
    result = build(ROOT, out)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.fixture(scope="session")
def site(tmp_path_factory) -> Path:
    """The whole site, built strictly once per test run (read-only)."""
    from fakes import run_wide

    return run_wide(tmp_path_factory, "docs-site", _build_the_site)


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


def minimal_tree(tmp_path: Path) -> Path:
    """A site of three pages to break on purpose: the real mkdocs.yml but its nav, the real hooks, and
    one page holding every command's options marker (so the hooks have nothing to warn about)."""
    import yaml

    root, docs = tmp_path / "repo", tmp_path / "repo" / "docs"
    docs.mkdir(parents=True)
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    config["nav"] = [{"Home": "index.md"}, {"Commands": "commands.md"}, {"Measured": "measured.md"},
                     {"Troubleshooting": "troubleshooting.md"}]
    (root / "mkdocs.yml").write_text(yaml.safe_dump(config, sort_keys=False))
    shutil.copy(ROOT / "docs" / "hooks.py", docs / "hooks.py")
    (docs / "index.md").write_text("# illm\n\nSee [the commands](commands.md) and [what was measured](measured.md).\n")
    (docs / "measured.md").write_text("# Measured\n\nSee [troubleshooting](troubleshooting.md#options).\n")
    (docs / "troubleshooting.md").write_text("# Troubleshooting\n\n## Options\n\nOne line each.\n")
    markers = [f"## illm {' '.join(path)}\n\n<!-- options: {' '.join(path)} -->\n" for path in leaf_commands()]
    (docs / "commands.md").write_text("# Commands\n\n" + "\n".join(markers))
    return root


def test_the_minimal_tree_builds_strict(tmp_path):
    """The control of the broken builds below: untouched, it builds."""
    result = build(minimal_tree(tmp_path), tmp_path / "site")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Options of illm eval" in text_of(tmp_path / "site" / "commands" / "index.html")


@pytest.mark.parametrize("damage, said", [
    ("link", "no-such-page.md"),
    ("orphan", "orphan.md"),
    ("marker", "names no command"),
    ("anchor", "#no-such-heading"),
    ("table", "no page shows the options of `illm eval`"),
], ids=["broken-link", "page-not-in-nav", "unknown-command-marker", "missing-anchor", "command-without-table"])
def test_a_broken_site_fails_the_strict_build(tmp_path, damage, said):
    root = minimal_tree(tmp_path)
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
        page = docs / "commands.md"
        page.write_text(page.read_text().replace("<!-- options: eval -->", ""))
    result = build(root, tmp_path / "site")
    assert result.returncode != 0 and said in result.stdout + result.stderr, result.stdout + result.stderr


def _command_lines(text: str) -> list[str]:
    """The `illm ...` command lines of a page's fenced shell blocks (continuations joined, comments cut)."""
    lines = []
    for block in re.findall(r"```(?:bash|sh|shell|console)?\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = re.sub(r"\s#\s.*$", "", line).strip()
            found = re.search(r"(?:^|[\s;&|(])(?:\S*/)?illm\s+(.*)$", line)
            if found and not line.startswith("#"):
                lines.append(found.group(1))
    return lines


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def test_every_command_in_the_docs_is_one_the_cli_takes():
    """Every `illm` command line of README.md and docs/: its command exists and each of its options is
    one of that command's (parsed by the CLI's own command tree; placeholders such as DATA are left
    as they are, and an option inside [brackets] is still checked)."""
    import shlex

    import typer.main

    from cli.main import app

    root = typer.main.get_command(app)
    wrong, seen = [], 0
    for page in _pages():
        for line in _command_lines(page.read_text()):
            try:
                words = shlex.split(line.replace("[", " ").replace("]", " "))
            except ValueError:
                words = line.split()
            command, path = root, []
            while words and getattr(command, "commands", None) and words[0] in command.commands:
                command = command.commands[words[0]]
                path.append(words.pop(0))
            if getattr(command, "commands", None) and words and not words[0].startswith("-"):
                wrong.append(f"{page.relative_to(ROOT)}: `illm {line}`: no command {words[0]!r}")
                continue
            known = {opt for p in command.params for opt in (*p.opts, *p.secondary_opts)} | {"--help"}
            for word in words:
                flag = word.split("=", 1)[0]
                if flag.startswith("--") and flag not in known:
                    wrong.append(f"{page.relative_to(ROOT)}: `illm {' '.join(path)}` has no option {flag}")
            seen += 1
    assert seen > 100, seen  # the pages' commands were found
    assert not wrong, "\n".join(wrong)
