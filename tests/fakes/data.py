"""Files the tests build or damage: `run_wide` (a folder built once per test run, read by every
xdist worker), annotation cache rows (`make_rows`, `keys_of`, `run_writers`, and `stub_annotated`, a
cache of the stub's real rows), trajectory rows (`trajectory_rows`), file damage (`flip`,
`truncate`) and fake run folders for `illm report` (`fake_run`). Used by conftest.py, test_docs.py,
test_cache_store.py, test_cache_share.py, test_first_hour.py, test_trust_import.py,
test_trajectories.py, test_faults.py, test_resume.py, test_report*.py and test_trust_files.py."""

from __future__ import annotations

import csv
import json
import os
import random
import stat
from pathlib import Path

from illm_tools.llm.stub import StubBackend

from .serving import STUB_LLM, STUB_MODEL, serve_state


def run_wide(tmp_path_factory, name: str, build, *, read_only: tuple[str, ...] = (".",)) -> Path:
    """A folder built once per test run, whichever xdist worker asks first (the others wait on a file
    lock, then read it): `build(folder)` fills it; then the paths `read_only` names under it (the
    folder itself by default) are made read-only, so a test that writes there fails instead of
    changing what the other tests read. Under xdist the workers' base temp folders are siblings, and
    the folder lies beside them; without xdist, in the run's own base temp folder."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent
    folder, done = base / name, base / f"{name}.done"
    with FileLock(str(base / f"{name}.lock")):
        if not done.exists():
            folder.mkdir(exist_ok=True)
            build(folder)
            for part in read_only:
                _read_only(folder / part)
            done.touch()
    return folder


def _read_only(root: Path) -> None:
    """Write permission off every file and folder under `root` (pytest's clean-up restores it)."""
    writable = stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH
    for path in sorted(root.rglob("*"), reverse=True) + [root]:
        path.chmod(path.stat().st_mode & ~writable)


# --- annotation cache rows (tests/test_cache_store.py, test_cache_share.py, test_first_hour.py) -----------
def make_rows(start: int, stop: int, tag: str = "t") -> list[dict]:
    """Valid rows: even i are action rows, odd i summary rows (embedding dim 4)."""
    from illm_tools.cache import make_key

    rows = []
    for i in range(start, stop):
        action = i % 2 == 0
        rows.append({
            "key": make_key(tag=tag, i=i), "task": "action" if action else "summary",
            "template_version": 1, "renderer": "babyai-text@1", "model": "smollm2-135m",
            "model_fingerprint": "f" * 64, "decoding": '{"temperature":0}', "history_len": 3,
            "goal": "go to the red ball", "history": "turn left", "observation": f"obs {i}",
            "prompt": f"prompt {i}",
            "candidates": ["turn left", "go forward"] if action else None,
            "cand_token_logprobs": [[-0.5, -0.25], [-1.5]] if action else None,
            "cand_logprob_sum": [-0.75, -1.5] if action else None,
            "cand_token_count": [2, 1] if action else None,
            "neutral_logprob_sum": [-1.0, -2.0] if action else None,
            "chosen_index": 0 if action else None,
            "text": None if action else f"summary {i}",
            "embedding": None if action else [float(i), 0.5, -0.25, 1.0],
            "embedding_dim": None if action else 4,
            "created_unix": 1700000000.5,
        })
    return rows


def stub_annotated(root, n: int = 6) -> Path:
    """A cache at `root` of `n` BabyAI-like states annotated by the stub backend (history 0, action and
    summary): real rows, whose keys their own columns give (what an import checks)."""
    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache

    annotator = Annotator(StubBackend(STUB_MODEL), AnnotationCache(root), model=STUB_LLM.model, history_len=0)
    annotator.annotate_states([serve_state(i) for i in range(n)], "BabyAI-GoToLocal-v0", "babyai-text@1")
    return Path(root)



def keys_of(rows: list[dict]) -> list[str]:
    return [r["key"] for r in rows]


def run_writers(target, root, count: int, timeout: float = 90) -> list[int]:
    """Start `count` spawned processes `target(root, worker, barrier)` together; their exit codes."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(count)
    procs = [ctx.Process(target=target, args=(str(root), w, barrier)) for w in range(count)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout)
    return [p.exitcode for p in procs]


# --- trajectory rows, damage, fake runs (test_trajectories.py, test_faults.py, test_resume.py, test_report.py) --
def trajectory_rows(n: int, episode: int = 0) -> dict:
    """`n` valid rows of one episode of a trajectory dataset, as columns."""
    return {
        "episode_id": [episode] * n,
        "step": list(range(n)),
        "env_id": ["BabyAI-GoToLocal-v0"] * n,
        "mission": ["go to the red ball"] * n,
        "obs_text": [f"You see a wall {i + 1} steps forward" for i in range(n)],
        "renderer": ["babyai-text@1"] * n,
        "obs_raw": [bytes(147)] * n,
        "obs_shape": [[7, 7, 3]] * n,
        "obs_dtype": ["uint8"] * n,
        "action": [2] * n,
        "action_text": ["go forward"] * n,
        "valid_actions": [["turn left", "turn right", "go forward"]] * n,
        "reward": [0.0] * (n - 1) + [0.5],
        "terminated": [False] * (n - 1) + [True],
        "truncated": [False] * n,
        "seed": [7] * n,
        "policy": ["random"] * n,
    }


def truncate(path, rng: random.Random) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:rng.randrange(len(data))])


def flip(path, rng: random.Random) -> None:
    data = bytearray(path.read_bytes())
    at = rng.randrange(len(data))
    data[at] ^= 1 << rng.randrange(8)
    path.write_bytes(bytes(data))


def fake_run(path, seed, rows, mode="illm", env_id="BabyAI-GoToLocal-v0"):
    """A run folder `illm report` reads: config.json and metrics.csv of `rows` (global step, success
    rate, episodes[, mean length])."""
    from illm_tools.rl.metrics_log import CSV_COLUMNS

    path.mkdir()
    (path / "config.json").write_text(json.dumps({"mode": mode, "env_id": env_id, "seed": seed}))
    with open(path / "metrics.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for step, success, episodes, *length in rows:  # (global step, success rate, episodes[, mean length])
            writer.writerow({"global_step": step, "success_rate": success, "episodes": episodes,
                             "target_coverage": 0.5, "cache_hit_rate": 0.25,
                             "episodic_length": length[0] if length and episodes else ""})


