"""Issue 71's intervention: a run continued from a checkpoint with one setting changed, beside the same
run continued unchanged.

A seed that collapsed (its success rate fell to 0 while other seeds solved the level) is re-trained
from scratch under its own config.json to frame AT (`--at`: a checkpoint inside the collapse, which the
run folder no longer holds: it keeps its last two), checked against the original run's metrics (the
oracle's runs repeat bit for bit, so every logged number up to AT must be the same: a run that parts
from the original is refused, since the arms would not continue the collapse it showed), then
continued twice from that checkpoint to the original's last frame: `control` as it was, and `changed`
with the --set settings (e.g. `int_coef=0`: the bonus no longer in the advantages, the heads still
distilled; `int_ext_cap=1`: the intrinsic part capped at the task's). Both arms end at the original
frame count, so the learning-rate schedule is the original's. A resumed run starts new episodes (the
checkpoint holds no env state), so the control is not a copy of the original's future but another draw
of it under the same settings; the arms differ in the changed settings alone.
If the changed arm recovers and the control does not, the changed setting is what held the seed down;
a correlation in the diagnostics cannot say that.

    python experiments/seed_intervention.py RUN --out DIR --at 32768 --set int_coef=0

writes DIR/base (the re-trained run, stopped at AT), DIR/control and DIR/changed (copies of base, the
latter with the changes in its config.json and its checkpoint's own settings, under their flat names:
`illm_tools.rl.config.upgrade_config` moves them into their parts), each trained on with `illm train
--out ARM --resume --frames TOTAL`, and DIR/intervention.json (what was done, and each arm's success
rate per window of `--window` frames after AT). RUN is only read. Its cache is not: the arms annotate
live into DIR/ann, the oracle's answers being the same in any cache. Hand-written rather than an
`illm train` option: continuing under changed settings is what `--resume` refuses on purpose (a resumed
run is one run), and only an experiment asks for it.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

from illm_tools import provenance
from illm_tools.rl.checkpoint import load_checkpoint, save_checkpoint
from illm_tools.rl.config import FLAT, TrainConfig, upgrade_config
from illm_tools.rl.saved import read_config, write_config

COMPARED = ("charts/success_rate", "charts/episodic_return", "losses/entropy", "charts/adv_int_ext_ratio")
"""The logged numbers a re-trained base must share with the original at every update up to AT."""


def value_of(text: str):
    """A --set value as YAML reads it (0 -> int, 0.5 -> float, true -> bool, else the text)."""
    import yaml

    return yaml.safe_load(text)


def metrics(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]


def same(a, b) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


def base_run(run: Path, out: Path, at: int) -> int:
    """RUN's config trained from scratch into OUT/base until the update that reaches `at` frames (a
    checkpoint there); refused unless every COMPARED number equals RUN's at every update. Its frame."""
    from illm_tools.rl.run import train

    config = upgrade_config(read_config(run))
    config.update(run_dir=str(out / "base"), resume=False)
    config["targets"] = {**config["targets"], "cache": str(out / "ann"), "new_setup": True}
    cfg = TrainConfig.from_dict(config)
    seen: list[int] = []
    result = train(cfg, on_metrics=lambda m: seen.append(int(m["global_step"])),
                   should_stop=lambda: bool(seen) and seen[-1] >= at)
    original = {m["global_step"]: m for m in metrics(run)}
    for mine in metrics(out / "base"):
        theirs = original.get(mine["global_step"], {})
        parted = [k for k in COMPARED if k in mine and not same(mine[k], theirs.get(k))]
        if parted:
            raise SystemExit(f"the re-trained run parts from {run} at frame {mine['global_step']:,} ({parted[0]}: "
                             f"{mine[parted[0]]} against {theirs.get(parted[0])}): the arms would not continue its run")
    return int(result["global_step"])


def fork(base: Path, out: Path, changes: dict) -> None:
    """OUT as a copy of BASE with `changes` (flat names) in its settings and its checkpoint's."""
    state = load_checkpoint(base)
    shutil.copytree(base, out, ignore=shutil.ignore_patterns("events.out.tfevents.*", ".lock", "checkpoint*"))
    state["config"] = {**state["config"], **changes, "run_dir": str(out)}
    save_checkpoint(out, state)
    write_config(out, {**read_config(base), **changes, "run_dir": str(out)})


def windows(run: Path, start: int, width: int) -> list[float | None]:
    """The success rate of the episodes that ended in each window of `width` frames after `start`
    (episode-weighted over the updates in it; None where none ended)."""
    out: dict[int, list[float]] = {}
    for m in metrics(run):
        if m["global_step"] > start and "charts/success_rate" in m and not math.isnan(m["charts/success_rate"]):
            n = m.get("charts/episodes", 1) or 1
            w = out.setdefault((m["global_step"] - start - 1) // width, [0.0, 0.0])
            w[0] += m["charts/success_rate"] * n
            w[1] += n
    last = max(out, default=-1)
    return [round(out[i][0] / out[i][1], 4) if i in out and out[i][1] else None for i in range(last + 1)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--at", type=int, required=True, help="the frame to continue from (a checkpoint there)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", required=True,
                        help="a setting changed in the `changed` arm from AT on (flat name)")
    parser.add_argument("--window", type=int, default=16384, help="frames per success-rate window in the summary")
    args = parser.parse_args(argv)
    changes = {k: value_of(v) for k, _, v in (s.partition("=") for s in args.set)}
    unknown = sorted(set(changes) - set(FLAT))
    if unknown:
        raise SystemExit(f"--set names no setting: {', '.join(unknown)} (flat names, as specs write them)")
    if args.out.exists():
        raise SystemExit(f"{args.out} exists: choose another --out")
    total = int(read_config(args.run)["total_steps"])
    at = base_run(args.run, args.out, args.at)
    illm = Path(sys.executable).with_name("illm")
    for arm, arm_changes in (("control", {}), ("changed", changes)):
        fork(args.out / "base", args.out / arm, arm_changes)
        code = subprocess.call([str(illm), "train", "--out", str(args.out / arm), "--resume", "--frames", str(total)],
                               stdout=subprocess.DEVNULL)
        if code:
            return code
    summary = {"from": str(args.run), "at_frame": at, "to_frame": total, "changes": changes,
               "command": provenance.command(), "window_frames": args.window,
               "original": windows(args.run, at, args.window),
               **{arm: windows(args.out / arm, at, args.window) for arm in ("control", "changed")}}
    (args.out / "intervention.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps({k: summary[k] for k in ("at_frame", "changes", "original", "control", "changed")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
