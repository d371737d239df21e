"""mkdocs hooks: every command page's options table, generated at build time from the command itself.

A page writes a marker where the table goes, `<!-- options: train -->` (a sub-command by its path:
`<!-- options: cache verify -->`). `on_page_markdown` replaces each marker with a markdown table built
from the Typer app's click command (`typer.main.get_command(cli.main.app)`): for every parameter its
flags, type, default and help, so the page shows exactly what `illm COMMAND --help` shows and cannot
drift from it (the options themselves are generated from the stage configs, `cli/options.py`).

A marker naming no command stops the build; a command that no page's marker names is a warning,
an error under `mkdocs build --strict` (`make docs`, tests/test_docs.py)."""

from __future__ import annotations

import logging
import re

log = logging.getLogger("mkdocs.hooks.options")

MARKER = re.compile(r"<!--\s*options:\s*([a-z][a-z -]*?)\s*-->")
_placed: set[tuple[str, ...]] = set()


def command_tree() -> dict[tuple[str, ...], object]:
    """Every command of `illm` by its path (("train",), ("cache", "verify")); groups included."""
    import typer.main

    from cli.main import app

    tree: dict[tuple[str, ...], object] = {}

    def walk(command, path: tuple[str, ...]) -> None:
        tree[path] = command
        for name, sub in getattr(command, "commands", {}).items():
            walk(sub, path + (name,))

    walk(typer.main.get_command(app), ())
    return tree


def _cell(text: str) -> str:
    """Text safe inside a markdown table cell: one line, pipes escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _flags(param) -> str:
    if getattr(param, "param_type_name", "") == "argument":
        return f"`{param.name.upper()}` (argument)"
    flags = [*param.opts, *param.secondary_opts]
    return ", ".join(f"`{flag}`" for flag in flags)


def _type(param) -> str:
    if getattr(param, "is_flag", False):
        return "flag"
    bare = param.bare_type()
    return f"{bare}, repeatable" if getattr(param, "multiple", False) else bare


def _default(param) -> str:
    if param.required:
        return "required"
    default = param.default
    if callable(default) or default is None or default == [] or default == ():
        return ""
    if getattr(param, "is_flag", False) and param.secondary_opts:
        return f"`{param.opts[0] if default else param.secondary_opts[0]}`"
    if isinstance(default, bool):
        return "on" if default else "off"
    return f"`{_cell(default)}`"


def options_table(path: tuple[str, ...]) -> str:
    """The markdown table of one command's parameters (arguments first, as the command reads them)."""
    command = command_tree()[path]
    params = [p for p in command.params if not getattr(p, "hidden", False)]
    params.sort(key=lambda p: getattr(p, "param_type_name", "") != "argument")
    lines = [f"Options of `illm {' '.join(path)}` (generated from the command at build time; "
             f"`illm {' '.join(path)} --help` shows the same):", "",
             "| option | type | default | what it sets |", "|---|---|---|---|"]
    for p in params:
        lines.append(f"| {_flags(p)} | {_cell(_type(p))} | {_default(p)} | {_cell(p.help or '')} |")
    lines.append("| `--help` | flag | | Show the command's help and exit. |")
    return "\n".join(lines)


def on_pre_build(config, **kwargs) -> None:
    _placed.clear()


def on_page_markdown(markdown: str, page, config, files, **kwargs) -> str:
    tree = command_tree()

    def replace(match: re.Match) -> str:
        path = tuple(match.group(1).split())
        if path not in tree or not path or hasattr(tree[path], "commands"):
            from mkdocs.exceptions import PluginError

            known = ", ".join(" ".join(p) for p, c in tree.items() if p and not hasattr(c, "commands"))
            raise PluginError(f"{page.file.src_path}: `<!-- options: {match.group(1)} -->` names no command; "
                              f"commands: {known}")
        _placed.add(path)
        return options_table(path)

    return MARKER.sub(replace, markdown)


def on_post_build(config, **kwargs) -> None:
    for path, command in command_tree().items():
        if path and not hasattr(command, "commands") and path not in _placed:
            log.warning("no page shows the options of `illm %s`: add `<!-- options: %s -->` to its page",
                        " ".join(path), " ".join(path))
