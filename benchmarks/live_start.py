"""How soon a short async run gets live answers: the demo's level (BabyAI-GoToRedBallNoDists-v0,
history 0), an empty cache, `--live-mode async --live-budget 8`, 8,192 frames (four rollouts of 16 x
128, about 3 s of training on 2 cores), the embedded SmolLM2-135M in the worker. Two ways of
starting, alternated, each in a fresh process:

- `illm train`: the command starts the worker from its options, before it imports torch
  (`illm_tools.rl.run.early_live_of_settings`);
- after torch: the same run through the Python API (`illm_tools.rl.run.train`) from a process that
  has imported torch already, so the worker starts after this process's torch import, as it did
  before the early start: the baseline.

Each run's line: the states that landed in each rollout (`charts/live_annotations`: answers the
trainer counted at that rollout's look-up), the worker's start-up and its first answer from its
spawn. The target: every `illm train` run lands answers during its rollouts.

    .venv/bin/python benchmarks/live_start.py [--runs 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from record import options, record, settings

SETTINGS = dict(env_id="BabyAI-GoToRedBallNoDists-v0", method="illm", history_len=0, total_steps=8192,
                live_mode="async", live_budget=8, seed=0)
OPTIONS = ["--env", SETTINGS["env_id"], "--method", "illm", "--history", "0", "--frames", "8192",
           "--live-mode", "async", "--live-budget", "8", "--seed", "0"]
AFTER_TORCH = ("import sys, torch\n"
               "from illm_tools.rl.build import run_config\n"
               "from illm_tools.rl.run import train\n"
               "train(run_config({**%r, 'cache': sys.argv[1], 'run_dir': sys.argv[2]}))\n")


def one(way: str, tmp: Path, k: int) -> dict:
    """One run the `way` given ("illm train" or "after torch"); its figures from metrics.jsonl."""
    cache, run = tmp / f"ann-{way[0]}{k}", tmp / f"run-{way[0]}{k}"
    cache.mkdir()
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    if way == "illm train":
        command = [str(Path(sys.executable).with_name("illm")), "train", *OPTIONS, "--cache", str(cache), "--out", str(run)]
    else:
        command = [sys.executable, "-c", AFTER_TORCH % SETTINGS, str(cache), str(run)]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"{way} failed: {done.stderr.strip().splitlines()[-1] if done.stderr.strip() else done.returncode}")
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    last = rows[-1]
    return {"landed": [int(r.get("charts/live_annotations", 0)) for r in rows], "sps": last.get("charts/sps", 0.0),
            "startup": last.get("charts/live_worker_startup_s"), "first": last.get("charts/live_first_answer_s")}


def seconds(value) -> str:
    return "-" if value is None else f"{value:.2f} s"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, help="Runs of each way, alternated.")
    options(parser)
    args = parser.parse_args()
    print(f"{SETTINGS['env_id']}, {SETTINGS['total_steps']:,} frames, an empty cache, --live-mode async "
          f"--live-budget 8, the SmolLM2-135M worker; {os.cpu_count()} cores", flush=True)
    during: dict[str, list[int]] = {"illm train": [], "after torch": []}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.runs):
            for way in ("illm train", "after torch") if k % 2 == 0 else ("after torch", "illm train"):
                r = one(way, Path(tmp), k)
                during[way].append(sum(r["landed"]))
                print(f"  {way:11s}  landed per rollout {r['landed']}  startup {seconds(r['startup'])}  first answer "
                      f"{seconds(r['first'])}  ({r['sps']:,.0f} steps/s)", flush=True)
    for way, counts in during.items():
        print(f"{way}: states landed during the rollouts, median {statistics.median(counts):g} "
              f"(range {min(counts)}-{max(counts)}) of {len(counts)} runs")
    print("target: every illm train run lands answers during its rollouts: "
          + ("met" if min(during["illm train"]) > 0 else "not met"))
    if not args.no_record:  # the baseline's median is often 0: the headline is the target's share, the baseline's beside it
        figures = {}
        for way, counts in during.items():
            name = way.replace(" ", "_")
            figures.update({f"{name}:landed_states_median": statistics.median(counts),
                            f"{name}:landed_states_min": min(counts), f"{name}:landed_states_max": max(counts),
                            f"{name}:runs_landing_share": sum(c > 0 for c in counts) / len(counts)})
        record("live_start", figures, ratio={"name": "illm train runs that landed answers during their rollouts / runs",
                                             "value": figures["illm_train:runs_landing_share"], "target": 1.0},
               out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()
