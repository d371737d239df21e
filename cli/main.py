"""The `illm` command line: one Typer app, one module per command group; the commands only
parse options, build a config and call the library."""

from __future__ import annotations

import logging
import os
import sys

import typer
import typer.core

from illm_tools import __version__

class _OneLineErrors(typer.core.TyperGroup):
    """The app's group: an option click cannot parse (`--frames 1e5`, `--history three`), a missing
    one or an unknown command reaches the user as the one line every other error gets (`cli.errors`),
    not Typer's box. A group or command called without arguments still shows its help."""

    def main(self, *args, standalone_mode: bool = True, **kwargs):
        from typer import _click as click

        from cli import handled_from_here
        from cli.errors import report, usage_line

        handled_from_here()  # the start-up's quiet exit ends here (cli/__init__.py)
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            result = super().main(*args, standalone_mode=False, **kwargs)
        except click.exceptions.NoArgsIsHelpError:
            return super().main(*args, standalone_mode=True, **kwargs)  # the help, as Typer shows it
        except click.exceptions.ClickException as exc:
            raise SystemExit(report(usage_line(exc))) from None
        except (typer.Abort, KeyboardInterrupt):  # KeyboardInterrupt: one landing before Typer's own handling
            raise SystemExit(report(KeyboardInterrupt())) from None
        raise SystemExit(result if isinstance(result, int) else 0)


app = typer.Typer(
    name="illm",
    cls=_OneLineErrors,
    help="Offline LLM annotation and distillation for exploration in RL (iLLM).\n\n"
    "Stages: collect -> annotate -> train -> eval. Each reads what the stage before it wrote.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


def _flags_as_flags() -> None:
    """Typer 0.29's help shows every boolean flag with a `<bool>` type column, as if it took a
    value (`--no-raw <bool>`); click's own help does not. Typer has no setting for it, so its
    display hook returns no type for flags. Display only; a Typer without the hook is left as is."""
    from typer.core import TyperOption

    show = getattr(TyperOption, "display_type_rich", None)
    if show is None or getattr(show, "_illm", False):
        return

    def display_type_rich(self, ctx):
        return None if self.is_flag else show(self, ctx)

    display_type_rich._illm = True
    TyperOption.display_type_rich = display_type_rich


_flags_as_flags()


class _IllmFormat(logging.Formatter):
    """illm's own log lines read as its other output: the message, with "warning:" before warnings."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        return f"{record.levelname.lower()}: {text}" if record.levelno >= logging.WARNING else text


class _Stderr(logging.StreamHandler):
    """A handler writing to the `sys.stderr` of the moment, not the one it was made with: a handler
    made during one call of the app (a test runner's captured stream, a redirect) must not write to
    that stream, closed, in a later call of the same process."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ sets it; the property always answers
        pass


def _logging(verbose: bool) -> None:
    """illm's messages (what a first model load is doing, a worker restart, a checkpoint fallback)
    reach stderr as plain lines; other libraries' only as warnings (all of it with --verbose)."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    ours = logging.getLogger("illm_tools")
    if not any(isinstance(h.formatter, _IllmFormat) for h in ours.handlers):
        handler = _Stderr()
        handler.setFormatter(_IllmFormat("%(message)s"))
        ours.addHandler(handler)
        for other in logging.getLogger().handlers:  # printed once, by our handler (basicConfig's is a plain one)
            if type(other) is logging.StreamHandler:
                other.addFilter(lambda record: not record.name.startswith("illm_tools."))
    ours.setLevel(logging.DEBUG if verbose else logging.INFO)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"illm {__version__}")
        raise typer.Exit()


@app.callback()
def root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details."),
) -> None:
    _logging(verbose)
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")


def _register() -> None:
    from cli import act, annotate, cache, collect, data, distil, envs, experiment, models, probe, report, serve, train

    envs.register(app)
    collect.register(app)
    app.add_typer(data.app, name="data")
    models.register(app)
    annotate.register(app)
    cache.register(app)
    train.register(app)
    report.register(app)
    experiment.register(app)
    serve.register(app)
    probe.register(app)
    act.register(app)
    distil.register(app)
    _unwrapped_help(app)


def _unwrapped_help(typer_app: typer.Typer) -> None:
    """Each command's help as Rich lays it out: its docstring's paragraphs with their hard line breaks
    undone (Rich keeps them, breaking a summary mid-sentence in `illm --help`), and its row in the
    command list the first sentence alone. Groups (`illm data`, `illm cache`) likewise, recursively."""
    import inspect

    for info in typer_app.registered_commands:
        doc = info.help or inspect.getdoc(info.callback) or ""
        paragraphs = [" ".join(p.split()) for p in doc.split("\n\n") if p.strip()]
        if not paragraphs:
            continue
        info.help = "\n\n".join(paragraphs)
        if info.short_help is None:
            first = paragraphs[0]
            end = first.find(". ")
            info.short_help = first if end < 0 else first[:end + 1]
    for group in typer_app.registered_groups:
        _unwrapped_help(group.typer_instance)


_register()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
