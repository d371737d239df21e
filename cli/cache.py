"""`illm cache info|show|verify|merge|repair|export|import`: inspect, check, combine, repair and share
annotation caches."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import typer

from cli.common import counted, emit_json
from cli.errors import friendly

app = typer.Typer(help="Inspect, verify, merge and repair annotation caches.", no_args_is_help=True)


def register(root: typer.Typer) -> None:
    root.add_typer(app, name="cache")


@app.command("info", epilog="Example: illm cache info data/ann --json")
@friendly
def info(
    path: Path = typer.Argument(..., help="Annotation cache folder."),
    as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
) -> None:
    """Entries per task and model, shards, size, and the setups the entries belong to.

    Also the embedding dimension; a setup is the model with its dtype and quantisation, the history
    length, layout, template and renderer."""
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.errors import UsageError

    if not (path / "manifest.json").is_file():
        raise UsageError(f"no annotation cache at {path}: run `illm annotate DATA --cache {path}` first")
    from illm_tools.tasks.annotation_setup import listed_setups

    cache = AnnotationCache(path)
    stats = cache.info()
    stats["setups"] = listed_setups(cache)
    if as_json:
        emit_json(stats)
        return
    typer.echo(f"{path}: annotation cache, {stats['schema']}")
    typer.echo(f"  entries     {stats['entries']:,}")
    for task, n in sorted(stats["tasks"].items()):
        typer.echo(f"  task        {task}: {n:,}")
    for model, n in sorted(stats["models"].items()):
        typer.echo(f"  task/model  {model}: {n:,}")
    typer.echo(f"  embeddings  dim {', '.join(map(str, stats['embedding_dims'])) or '-'}")
    typer.echo(f"  shards      {stats['shards']} ({stats['bytes'] / 1e6:.1f} MB)")
    if stats["setups"]:
        typer.echo("  setups (what `illm train` must be given to use them):")
        typer.echo("    | task | model, dtype, quantisation | history | layout | template | renderer | entries |")
        typer.echo("    |---|---|---|---|---|---|---|")
        for u in stats["setups"]:
            where = f" (served at {', '.join(u['served_at'])})" if u["served_at"] else ""
            typer.echo(f"    | {u['task']} | {u['model_options']}{where} | {u['history_len']} | "
                       f"{'/'.join(u['layouts']) or '?'} | v{u['template_version']} | {u['renderer']} | {u['entries']:,} |")


@app.command("show", epilog="Example: illm cache show data/ann --limit 3")
@friendly
def show(
    path: Path = typer.Argument(..., help="Annotation cache folder (only read)."),
    limit: int = typer.Option(3, "--limit", help="States to show, the first in the cache's shard order."),
    as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
) -> None:
    """The LLM's answers for a few states: prompts, rankings, summaries.

    Each task's prompt, the ranking with log-probs and the chosen action, the summary text.
    Read-only: the cache is not written, locked or repaired."""
    from illm_tools.cache.show import show as run

    states = run(path, limit)
    if as_json:
        emit_json(states)
        return
    if not states:
        typer.echo(f"{path} holds no annotations")
    for i, state in enumerate(states, 1):
        typer.echo(f"state {i} ({state['model']}, history {state['history_len']}, {state['renderer']})")
        typer.echo(f"  goal: {state['goal']}\n  observation: {state['observation']}")
        history = state["history"].strip().splitlines()
        typer.echo("  history: " + ("-" if not history else history[0] if len(history) == 1 else
                                    "\n" + "\n".join("    | " + line for line in history)))
        for answer in state["answers"]:
            typer.echo(f"  {answer['task']} prompt:")
            typer.echo("\n".join("    | " + line for line in answer["prompt"].splitlines()))
            if "ranking" in answer:
                typer.echo(f"  {answer['task']} ranking (log-prob summed over the action's tokens, best first):")
                for r in answer["ranking"]:
                    mark = "  <- chosen" if r["action"] == answer["chosen"] else ""
                    typer.echo(f"    {r['logprob_sum']:9.3f}  {r['action']} ({counted(r['tokens'], 'token')}){mark}")
            if "text" in answer:
                typer.echo(f"  {answer['task']}: {answer['text']}")
        typer.echo("")


@app.command("verify", epilog="Example: illm cache verify data/ann")
@friendly
def verify(
    path: Path = typer.Argument(..., help="Annotation cache folder."),
    as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
) -> None:
    """Check schema, checksums, row counts and duplicate keys of every shard; exit 1 on damage."""
    from illm_tools.cache.verify import verify as run
    from illm_tools.errors import UsageError

    if not (path / "manifest.json").is_file() and not path.is_dir():
        raise UsageError(f"no annotation cache at {path}: pass a folder `illm annotate --cache` wrote")
    report = run(path)
    if as_json:
        emit_json({**dataclasses.asdict(report), "ok": report.ok})
    else:
        typer.echo(f"{path}: {report.schema or 'unknown schema'}, {counted(report.shards, 'shard')}, {counted(report.rows, 'row')}, "
                   f"{report.keys:,} keys")
        for problem in report.problems:
            typer.echo(f"  DAMAGED  {problem}")
        for orphan in report.orphans:
            typer.echo(f"  orphan   {orphan} (from an interrupted write; `illm cache repair` adopts or removes it)")
        typer.echo("ok" if report.ok else f"damaged: run `illm cache repair {path} --drop-damaged` (moves the damaged "
                   "files to damaged/ and drops them from the manifest; annotating again redoes their entries), or "
                   "restore them from a copy")
    if not report.ok:
        raise typer.Exit(1)


@app.command("merge", epilog="Example: illm cache merge data/ann --into data/ann-merged")
@friendly
def merge(
    sources: list[Path] = typer.Argument(..., help="Caches to copy from (left untouched)."),
    into: Path = typer.Option(..., "--into", "--cache", help="Cache to merge into (created if absent)."),
) -> None:
    """Copy into --into every entry it lacks from verified sources; keys are never duplicated.

    Every row is checked before it enters (its task's answer present, its key recomputed from its own
    columns, finite log-probs, its lists and embedding consistent); a bad row is left out and counted."""
    from illm_tools.cache.verify import merge as run

    check, found = _row_check(addresses=True)
    report = run(sources, into, check=check)
    typer.echo(f"merged {counted(len(sources), 'cache')} into {into}: {counted(report.rows_copied, 'row')} copied, "
               f"{report.rows_skipped:,} already present or refused, {counted(len(report.shards_written), 'new shard')}")
    _say_refused(found)


@app.command("export", epilog="Example: illm cache export data/ann --format parquet --out data/share/ann.parquet")
@friendly
def export(
    path: Path = typer.Argument(..., help="Annotation cache folder (verified first; left untouched)."),
    out: Path = typer.Option(..., "--out", help="File to write, named as its format (.parquet)."),
    fmt: str = typer.Option("parquet", "--format", help="parquet (one file; `datasets.Dataset.from_parquet` reads it)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out."),
) -> None:
    """Write every entry of a cache to one file, to share it.

    A model served by an engine is written as its name ("openai:NAME"), never its address or key
    variable: whoever trains on the file gives their own --endpoint. The file can be published as a
    Hugging Face dataset, for one."""
    from illm_tools.cache.share import export as run
    from illm_tools.tasks.rows import shareable

    report = run(path, out, fmt=fmt, overwrite=overwrite, transform=shareable)
    typer.echo(f"exported {counted(report.rows, 'row')} from {counted(report.shards, 'shard')} of {path} -> {report.path}")


@app.command("import", epilog="Example: illm cache import data/share/ann.parquet --into data/ann")
@friendly
def import_(
    path: Path = typer.Argument(..., help="Parquet file written by `illm cache export` (or `datasets`' to_parquet)."),
    into: Path = typer.Option(..., "--into", "--cache", help="Cache to add the entries to (created if absent)."),
) -> None:
    """Add a shared file's entries to a cache; keys it already holds are skipped.

    No key is stored twice. Every row is checked before it enters (its size before it is decoded, its
    model a name and never an address or key variable, its task's answer present, its key recomputed
    from its own columns, finite log-probs, its lists and embedding consistent); a bad row is left out
    and counted."""
    from illm_tools.cache.share import MAX_ROW_BYTES, import_parquet

    check, found = _row_check()
    report = import_parquet(path, into, check=check)
    found.refused[:0] = [(key, f"it decodes to over {MAX_ROW_BYTES >> 10} KiB") for key in report.too_large]
    left = report.rows - report.added - len(found.refused) - len(found.conflicts)
    typer.echo(f"imported {path}: {report.added:,} new entries of its {report.rows:,} rows "
               f"({left:,} already present, {len(found.refused) + len(found.conflicts):,} refused) -> {into}")
    _say_refused(found)


def _row_check(addresses: bool = False):
    """The check every imported or merged row passes (`illm_tools.tasks.rows`), and what it found;
    `addresses`: a row's model may name a served model's address (merge: caches on this disk)."""
    from illm_tools.tasks.rows import Checked, check_rows, model_dims

    found = Checked()
    dims: dict[str, int] = {}

    def check(table, cache):
        if not dims:
            dims.update(model_dims(cache))
        return check_rows(table, cache, dims, found, addresses)

    return check, found


def _say_refused(found) -> None:
    from illm_tools.tasks.rows import summary

    for line in summary(found):
        typer.echo(line)


@app.command("repair", epilog="Example: illm cache repair data/ann --drop-damaged")
@friendly
def repair(
    path: Path = typer.Argument(..., help="Annotation cache folder."),
    drop_damaged: bool = typer.Option(False, "--drop-damaged", help="Also drop shards that fail verification (their "
                                      "files move to damaged/; annotating again redoes their entries)."),
) -> None:
    """Adopt complete shards an interrupted write left unlisted, and remove temp files.

    With --drop-damaged, first take damaged shards (or an unreadable manifest) out of the cache."""
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.cache.verify import DAMAGED_DIR
    from illm_tools.cache.verify import drop_damaged as drop
    from illm_tools.cache.verify import verify as check
    from illm_tools.errors import CacheError

    found = check(path)
    if found.problems and not drop_damaged:
        raise CacheError(f"{len(found.problems)} problem(s), first: {found.problems[0]}; run `illm cache repair {path} "
                         "--drop-damaged` to take the damaged files out (kept in damaged/), or restore them from a copy")
    if drop_damaged:
        dropped = drop(path)
        if dropped.manifest_rebuilt:
            typer.echo(f"{path}: the manifest was unreadable: moved to {DAMAGED_DIR}/, every shard that reads back "
                       "whole is listed again")
        elif dropped.dropped:
            typer.echo(f"{path}: dropped {len(dropped.dropped)} damaged shards ({dropped.rows_lost:,} entries, to be "
                       f"annotated again), files moved to {DAMAGED_DIR}/: {', '.join(dropped.dropped)}")
    report = AnnotationCache(path).adopt_orphans()
    typer.echo(f"{path}: adopted {len(report.adopted)}, rewrote {len(report.rewritten)}, removed "
               f"{len(report.removed)} redundant, rejected {len(report.rejected)}, "
               f"{len(report.temp_removed)} temp files removed")
    final = check(path)
    typer.echo(f"{path}: {counted(final.rows, 'row')} in {counted(final.shards, 'shard')}; " + ("ok" if final.ok else "still damaged: "
               + final.problems[0]))
    if not final.ok:
        raise typer.Exit(1)
