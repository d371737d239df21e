"""Typer options generated from a config dataclass: one option per field, named as the field
(`num_envs` -> `--num-envs`), its default the field's default and its help the field's docstring,
so that every documented setting is settable and defaults live in one place.

Hand-written on Typer because tyro would replace the Typer app (and its one-line errors, help
layout and the other commands); Typer reads a command's `inspect.Signature`, so the generated
parameters are given to it as one. A field may carry a short alias kept from the documented
command line (`--frames` for `total_steps`); dict fields are repeatable `--x-option KEY=VALUE`
options; bool fields are `--x/--no-x` flags; `arguments` are positional (a list field: several).
A field whose type is itself a dataclass (a stage's `llm: LLMSpec`) is flattened: its fields are
options of their own (`--model`, `--dtype`), gathered back into it by `config_from_options`; `names`
gives such a field's parameter another name than its own (`{"llm.dtype": "model_dtype"}`), and
`exclude` leaves out a nested field by its dotted name (`"llm.device"`).
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
import types
import typing
from pathlib import Path
from typing import Any

import typer


def field_docs(cls: type) -> dict[str, str]:
    """Each field's docstring (the string literal after its annotation in the class body)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs = {}
    for node, after in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and \
                isinstance(after, ast.Expr) and isinstance(getattr(after, "value", None), ast.Constant) and \
                isinstance(after.value.value, str):
            docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _optional(hint: Any) -> tuple[Any, bool]:
    """(the type inside `X | None`, whether None is allowed)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return hint, False


def dataclass_parameters(cls: type, *, aliases: dict[str, str | tuple[str, ...]] | None = None,
                         dict_flags: dict[str, str] | None = None, exclude: set[str] = frozenset(),
                         defaults: dict[str, Any] | None = None, required: set[str] = frozenset(),
                         extra_help: dict[str, str] | None = None, arguments: set[str] = frozenset(),
                         names: dict[str, str] | None = None, _prefix: str = "") -> list[inspect.Parameter]:
    """One keyword parameter per field of `cls` (minus `exclude`) with a `typer.Option` default.

    aliases: field -> an extra flag kept from the documented CLI (a tuple: the only flags); dict_flags: dict field -> its
    repeatable KEY=VALUE flag; defaults: CLI defaults that differ from the field's (e.g. None for
    "take it from a preset"); required: fields the command needs; extra_help: appended to help;
    arguments: positional fields (required); names: a nested field's parameter name by its dotted
    name (the other arguments name it by its parameter name)."""
    aliases, dict_flags, defaults, extra_help = aliases or {}, dict_flags or {}, defaults or {}, extra_help or {}
    renamed = names or {}
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    params = []
    for f in dataclasses.fields(cls):
        dotted = _prefix + f.name
        if f.name in exclude or dotted in exclude:
            continue
        name = renamed.get(dotted, f.name)
        hint, nullable = _optional(hints[f.name])
        if dataclasses.is_dataclass(hint):  # a nested config: its fields are options of their own
            params += dataclass_parameters(hint, aliases=aliases, dict_flags=dict_flags, exclude=exclude,
                                           defaults=defaults, required=required, extra_help=extra_help,
                                           names=renamed, _prefix=dotted + ".")
            continue
        help_text = " ".join(filter(None, [docs.get(f.name, ""), extra_help.get(name, "")]))
        if name in arguments:
            params.append(inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                            annotation=list[Path] if typing.get_origin(hint) in (list, tuple) else hint,
                                            default=typer.Argument(..., help=help_text)))
            continue
        if name in dict_flags:
            decls, annotation, default = [dict_flags[name]], list[str], None
            help_text += " Repeatable KEY=VALUE."
        else:
            alias = aliases.get(name)
            # the documented one first; a tuple of flags replaces the field's own (its name means another thing)
            names = list(alias) if isinstance(alias, tuple) else ([alias] if alias else []) + [flag(name)]
            if hint is bool:
                decls = [f"{names[0]}/--no-{names[0][2:]}"] + names[1:]
            else:
                decls = names
            if typing.get_origin(hint) is list:  # a list: a repeatable option
                pass
            elif typing.get_origin(hint) is tuple:  # a tuple of names: one comma-separated option
                hint = str
                help_text += " Comma-separated."
            elif typing.get_origin(hint) in (typing.Union, types.UnionType):  # e.g. int | str: the config parses it
                hint = str
            annotation = hint if not nullable else typing.Optional[hint]  # noqa: UP007 - Typer reads Optional
            if hint is bool and nullable:
                annotation = typing.Optional[bool]  # noqa: UP007
            default = ... if name in required else defaults.get(
                name, f.default if f.default is not dataclasses.MISSING else None)
            if isinstance(default, Path):
                default = str(default)
            elif isinstance(default, tuple):
                default = ",".join(default)
        params.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=annotation,
                                        default=typer.Option(default, *decls, help=help_text,
                                                             show_default=default is not None)))
    return params


def config_from_options(cls: type, options: dict, dict_flags: dict[str, str] | None = None):
    """The config `cls` from a generated command's options (`dataclass_parameters`): repeatable
    KEY=VALUE options parsed into their dict fields, comma-separated ones into tuples; `cls`
    validates the rest in its `__post_init__` (a bad value: one line)."""
    from illm_tools.settings import parse_pairs

    dict_flags = dict_flags or {}
    hints = typing.get_type_hints(cls)
    fields = dict(options)
    for f in dataclasses.fields(cls):
        hint, _ = _optional(hints[f.name])
        if dataclasses.is_dataclass(hint) and f.name not in fields:  # a nested config from its own options
            names = {g.name for g in dataclasses.fields(hint)}
            fields[f.name] = config_from_options(hint, {k: fields.pop(k) for k in list(fields) if k in names},
                                                 dict_flags)
    for name, option in dict_flags.items():
        if name in hints:
            fields[name] = parse_pairs(fields.get(name), option)
    for name, value in list(fields.items()):
        hint, _ = _optional(hints.get(name))
        if typing.get_origin(hint) is tuple and isinstance(value, str):
            fields[name] = tuple(v.strip() for v in value.split(",") if v.strip())
        elif typing.get_origin(hint) is tuple and isinstance(value, list):  # a positional list
            fields[name] = tuple(value)
        elif typing.get_origin(hint) is list and value is None:  # a repeatable option not given: the field's default
            del fields[name]
    return cls(**fields)
