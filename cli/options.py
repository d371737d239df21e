"""Typer options generated from a config dataclass: one option per field, named as the field
(`num_envs` -> `--num-envs`), its default the field's default and its help the field's docstring,
so that every documented setting is settable and defaults live in one place.

Hand-written on Typer because tyro would replace the Typer app (and its one-line errors, help
layout and the other commands); Typer reads a command's `inspect.Signature`, so the generated
parameters are given to it as one. A field declares its documented flag
where it is declared (`illm_tools.settings.setting(flag=...)`: `--frames` for `total_steps`, kept
beside the field's own; a tuple replaces it); dict fields are repeatable
`--x-option KEY=VALUE` options (their flag declared the same way); bool fields are `--x/--no-x`
flags; `arguments` are positional (a list field: several). A field whose type is itself a dataclass
(a stage's `llm: LLMSpec`, a run's `ppo: PPOConfig`) is flattened: its fields are options of their
own (`--model`, `--dtype`), gathered back into it by `config_from_options`, with the defaults of the
field's own default (a probe's `PromptConfig(history_len=0)`); `exclude` leaves out a nested field by
its dotted name (`"llm.offline"`).
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


def dataclass_parameters(cls: type, *, exclude: set[str] = frozenset(), defaults: dict[str, Any] | None = None,
                         required: set[str] = frozenset(), extra_help: dict[str, str] | None = None,
                         arguments: set[str] = frozenset(), names: dict[str, str] | None = None, _prefix: str = "",
                         _instance: Any = None) -> list[inspect.Parameter]:
    """One keyword parameter per field of `cls` (minus `exclude`) with a `typer.Option` default.

    defaults: CLI defaults that differ from the field's (e.g. None for "take it from a preset");
    required: fields the command needs; extra_help: appended to help; arguments: positional fields
    (required); a dict field is a repeatable KEY=VALUE option (its flag declared, `--x-option` by
    default: `pair_fields`); names: a nested field's parameter name by its dotted name
    where the command has another setting of its own name (a run's `llm.device` is `llm_device`,
    its flag `--llm-device`, beside the run's `--device`). All but `exclude` name a field by its
    parameter name."""
    defaults, extra_help, renamed = defaults or {}, extra_help or {}, names or {}
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    params = []
    for f in dataclasses.fields(cls):
        dotted = _prefix + f.name
        if f.name in exclude or dotted in exclude:
            continue
        name = renamed.get(dotted, f.name)
        hint, nullable = _optional(hints[f.name])
        own = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        if _instance is not None:
            own = getattr(_instance, f.name)
        if dataclasses.is_dataclass(hint):  # a nested config: its fields are options of their own
            # with the defaults its field gives (a probe's history 0), not what its class resolves them to
            given = own if f.default_factory not in (hint, dataclasses.MISSING) else None
            params += dataclass_parameters(hint, exclude=exclude, defaults=defaults, required=required,
                                           extra_help=extra_help, names=renamed,
                                           _prefix=dotted + ".", _instance=given)
            continue
        help_text = " ".join(filter(None, [docs.get(f.name, ""), extra_help.get(name, "")]))
        if name in arguments:
            params.append(inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                            annotation=list[Path] if typing.get_origin(hint) in (list, tuple) else hint,
                                            default=typer.Argument(..., help=help_text)))
            continue
        declared = f.metadata.get("flag")
        if _is_pairs(hint):
            decls, annotation, default = [declared or flag(name.removesuffix("s"))], list[str], None
            help_text += " Repeatable KEY=VALUE."
        else:
            # the documented one first; a tuple of flags replaces the field's own (its name means another thing)
            flags = list(declared) if isinstance(declared, tuple) else ([declared] if declared else []) + [flag(name)]
            flags = list(dict.fromkeys(flags))  # a declared flag that is the field's own: once
            decls = [f"{flags[0]}/--no-{flags[0][2:]}"] + flags[1:] if hint is bool else flags
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
            default = ... if name in required else defaults.get(name, own)
            if isinstance(default, Path):
                default = str(default)
            elif isinstance(default, tuple):
                default = ",".join(map(str, default))
        params.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=annotation,
                                        default=typer.Option(default, *decls, help=help_text,
                                                             show_default=default is not None)))
    return params


def _is_pairs(hint) -> bool:
    """Whether a field of this type is taken as repeatable KEY=VALUE options: a dict."""
    return hint is dict or typing.get_origin(hint) is dict


def pair_fields(cls: type) -> set[str]:
    """The names of `cls`'s dict fields, its nested configs' included: its repeatable KEY=VALUE options."""
    hints = typing.get_type_hints(cls)
    out = set()
    for f in dataclasses.fields(cls):
        hint, _ = _optional(hints[f.name])
        out |= pair_fields(hint) if dataclasses.is_dataclass(hint) else {f.name} if _is_pairs(hint) else set()
    return out


def config_from_options(cls: type, options: dict):
    """The config `cls` from a generated command's options (`dataclass_parameters`): repeatable
    KEY=VALUE options parsed into their dict fields, comma-separated ones into tuples, a nested
    config's options gathered into it; `cls` validates the rest in its `__post_init__` (a bad
    value: one line)."""
    from illm_tools.settings import parse_pairs

    hints = typing.get_type_hints(cls)
    fields = dict(options)
    out = {}
    for f in dataclasses.fields(cls):
        hint, _ = _optional(hints[f.name])
        name = f.name
        if dataclasses.is_dataclass(hint) and f.name not in fields:  # a nested config from its own options
            names = {g.name for g in _all_fields(hint)}
            out[f.name] = config_from_options(hint, {k: fields.pop(k) for k in list(fields) if k in names})
            continue
        if name not in fields:
            continue
        value = fields.pop(name)
        if _is_pairs(hint):
            value = parse_pairs(value, f.metadata.get("flag") or flag(name.removesuffix("s")))
        elif typing.get_origin(hint) is tuple and isinstance(value, str):
            value = tuple(v.strip() for v in value.split(",") if v.strip())
        elif typing.get_origin(hint) is tuple and isinstance(value, list):  # a positional list
            value = tuple(value)
        elif typing.get_origin(hint) is list and value is None:  # a repeatable option not given: the field's default
            continue
        out[f.name] = value
    return cls(**out, **fields)


def _all_fields(cls: type) -> list[dataclasses.Field]:
    """The fields of `cls` and of its nested configs, at any depth (the options they take)."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        hint, _ = _optional(hints[f.name])
        out += _all_fields(hint) if dataclasses.is_dataclass(hint) else [f]
    return out
