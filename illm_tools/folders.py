"""Which stage owns a folder: a trajectory dataset (`illm collect`), an annotation cache (`illm
annotate`) or a training run (`illm train`). Each stage refuses to write into a folder another
stage owns, so a mistyped `--out` never mixes or deletes another stage's files.

Recognised by the file each stage writes last and always: `state.json` (trajectories, the
`datasets` layout), `manifest.json` with the cache's format name, `config.json` with a run's
settings.

And what a file may name inside a folder (`bare_name`): a name that a file or spec gives for a path
(a report's heatmap, an experiment's name or bundle) is a bare name, never a path that leaves its folder.
"""

from __future__ import annotations

import json
from pathlib import Path

from illm_tools.errors import IllmError, OutputExistsError, UsageError

STATE = "state.json"
"""The file a trajectory dataset writes last (`illm_tools.data.trajectories`)."""
MANIFEST = "manifest.json"
"""The annotation cache's list of shards (`illm_tools.cache.layout`)."""
FORMAT = "illm.annotation-cache"
"""The `format` of a cache's manifest."""


def owner(folder: str | Path) -> str | None:
    """"trajectory dataset", "annotation cache", "training run", or None (absent, empty, other)."""
    folder = Path(folder)
    if not folder.is_dir():
        return None
    if (folder / STATE).is_file():
        return "trajectory dataset"
    if (folder / MANIFEST).is_file():
        try:
            if json.loads((folder / MANIFEST).read_text()).get("format") == FORMAT:
                return "annotation cache"
        except (OSError, ValueError, AttributeError):
            return "annotation cache"  # damaged, still the cache's: `illm cache repair` is its tool
    if (folder / "config.json").is_file() and ((folder / "metrics.jsonl").exists() or
                                              any(folder.glob("checkpoint*.pt"))):
        return "training run"
    return None


def refuse_foreign(folder: str | Path, own: str, option: str) -> None:
    """Refuse `folder` when another stage than `own` owns it (one line naming both)."""
    kind = owner(folder)
    if kind is not None and kind != own:
        raise OutputExistsError(f"{folder} holds {'an' if kind[0] in 'aeiou' else 'a'} {kind}, which this command "
                                f"would mix with its {own}: choose another {option}")


MAX_NAME_BYTES = 255
"""The longest file name most file systems take (ext4, APFS, NTFS: 255)."""


def bare_name(name: object, where: str, fix: str, error: type[IllmError] = UsageError) -> str:
    """`name` where it names a file or folder directly inside its folder: a string of 1 to 255 bytes,
    no separator (/ or \\), not . or .., no control character. Anything else (an absolute path,
    `../x`, `a/b`, a number) raises `error` in one line: `where` says which file or option named it,
    `fix` what to do."""
    if not (isinstance(name, str) and name not in ("", ".", "..") and not any(c in name for c in "/\\")
            and name.isprintable() and len(name.encode("utf-8", "surrogatepass")) <= MAX_NAME_BYTES):
        shown = repr(name) if len(repr(name)) <= 80 else repr(name)[:76] + "...'"
        raise error(f"{where}: {shown} is not a bare name (a name inside its folder, without / or \\, "
                    f"not . or ..): {fix}")
    return name
