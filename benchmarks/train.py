"""Training throughput of `--method illm` against `--method ppo`, same env and settings, in the
same run, in two cases, each as the median (and range) of three paired runs' ratio of steps/s:
- every LLM target cached (target >= 0.85);
- async live annotation (target >= 0.75): the cache starts empty, so every rollout misses and the
  worker process annotates with the real embedded model (SmolLM2-135M, one thread) beside the
  rollouts (one thread) on this machine's cores, as `illm train --live-mode async` does; the
  worker is started before the env pool and the network, as a run starts it, and the time to its
  first answer in the cache is printed.
Each run is 40,960 frames by default (20 updates of 16 x 128); the pairs alternate which method runs
first. A cached pair runs in lockstep (`lockstep`): each method in its own process, as `illm train`
runs, both held to the same core and taking their updates in turn, each rate over its own updates'
time, so that both meet the same state of the machine (this VM's speed drifts by a fifth within
minutes: run one after the other, four pairs of the same code read from 0.78 to 0.97; in
lockstep a run's three pairs lay within 0.031). Each method's mean cost per update (rollout,
target look-up, update) is printed beside its rate, and what illm adds to an update in ms: the
ratio also moves with what both pay (in a slow spell the envs' Python slows more than the heads).

"Every target cached" is made exact without an LLM in the loop: a first illm pass fills an
empty cache through the live-fallback path, with rows of deterministic pseudo-random scores and
embeddings (the trainer's speed does not depend on what the LLM said); training is deterministic
given the seed, so every later pass with the same seed meets exactly the same states and finds
every one of them in the cache (its cache hit rate is printed). On CUDA (`--device cuda`) that
takes torch's deterministic algorithms, which are on for both methods there. Each run starts with
an empty memo of rendered views, as a run in its own process does (a memo the fill pass had filled
made illm's text free in the later passes: about 10 ms an update of a 20-update run).

`--profile` prints instead where a cached illm update and a ppo update spend their time (cProfile's
top entries by own time, one run of each), the figures behind docs/measured.md's reading.

With several `--env`s (the levels form, `levels`) it runs the cached case on each in turn, in one
run: the first env is the reference (BabyAI-GoToLocal-v0 by default), and each other level's line
says its ppo rate beside the target issue 70 set: half the reference's ppo rate, or the env's own
rate where that is lower (the env alone, stepped with random actions by the pool ppo trains on,
text off, held to the same cores as the pairs). That is the form of docs/measured.md's MiniHack
and Crafter figures (`--json FILE` writes them).

With `--mode hop` (iLLM(hop), `illm_tools.hop`) it measures instead what the hop mode costs per
step, in the same run: ppo on the observation alone, ppo reading Z_h (the embedded SmolLM2-135M
run over every env's translated window at every step), and illm in hop mode with every target
cached (as above; the trainer's LLM computes Z_h, the targets are synthetic).

    .venv/bin/python benchmarks/train.py [--env BabyAI-GoToLocal-v0] [--frames 40960] [--pairs 3]
    .venv/bin/python benchmarks/train.py --profile
    .venv/bin/python benchmarks/train.py --env BabyAI-GoToLocal-v0 --env MiniHack-Room-5x5-v0 \
        --env CrafterReward-v1 --frames 20480 --pairs 1 --json levels.json   (the levels form)
    .venv/bin/python benchmarks/train.py --only cached --head-hidden 512   (what narrower heads would cost)
    .venv/bin/python benchmarks/train.py --mode hop --env MiniGrid-MultiRoom-N6-v0 --frames 2048 --num-steps 32
"""

from __future__ import annotations

import argparse
import os
import queue
import statistics
import tempfile
import time
from pathlib import Path


from illm_tools.annotate.engine import Annotator
from illm_tools.llm.spec import LLMSpec
from illm_tools.llm.stub import StubBackend
from illm_tools.cache.store import AnnotationCache
from illm_tools.envs.babyai import forget_rendered
from illm_tools.rl.config import TrainConfig
from illm_tools.rl.live import SyncLive
from illm_tools.rl.ppo import Trainer
from illm_tools.rl.run import build_run, make_pool
from illm_tools.rl.threads import torch_threads
from illm_tools.rl.targets import CachedTargets
from record import cpu_name, machine, options, record, settings

DIM = 576  # SmolLM2-135M's hidden size: the f^hc head is as large as with the embedded model


class Turns:
    """A lockstep run's clock: before each of its updates the run waits for its `turn` (a
    semaphore), and when the next one begins, or the run ends, it hands `other` the turn; `spent`
    sums the time from each turn taken to the turn handed on: the run's own updates. Both runs meet
    at `together` (a barrier) once built and once done, so that neither's start nor its exit falls
    in the other's turns (without it, the run that went second paid for the first one's exit in its
    last turns: its pairs read 0.90-0.95 with illm first against 0.82-0.84 with ppo first)."""

    def __init__(self, turn, other, together):
        self.turn, self.other, self.together = turn, other, together
        self.spent, self.since, self.started = 0.0, None, False

    def hand_on(self) -> None:
        if self.since is not None:
            self.spent += time.perf_counter() - self.since
            self.since = None
            self.other.release()

    def __call__(self) -> bool:  # Trainer.train's should_stop: called before each update
        if not self.started:
            self.started = True
            self.together.wait()
        self.hand_on()
        self.turn.acquire()
        self.since = time.perf_counter()
        return False

    def done(self) -> None:
        self.hand_on()
        self.together.wait()


def run(cfg: TrainConfig, cache_dir: Path | None, live_async: bool = False, turns: Turns | None = None) -> tuple[float, dict]:
    """One training run: (steps/s over its updates, its last metrics with `phases`: the mean cost
    per update of each phase, in seconds; and `close_s`, the time its shutdown took after training).
    Async live annotation runs as `illm train` assembles it (`build_run`: the worker started first);
    the cached case reads a synthetic cache through `CachedTargets` (see the module docstring).
    With `turns` the run takes its updates in turn with another process's (`lockstep`), and its
    rate is over its own updates' time."""
    phases = {k: 0.0 for k in (*PHASES, "episodes")}  # episodes: their resets are part of the rollout's cost
    forget_rendered()  # each run renders its views' text from scratch, as a run in its own process does

    def on_metrics(m: dict) -> None:
        for k in PHASES:
            phases[k] += m[f"time/{k}_s"] / cfg.num_updates
        phases["episodes"] += m["charts/episodes"] / cfg.num_updates

    if live_async:
        cfg = cfg.resolved()
        with build_run(cfg, on_metrics) as trainer:
            start = time.perf_counter()
            last = trainer.train()
            trained = closing = time.perf_counter()  # the training's rate; the worker's shutdown is timed apart
        last.update(phases=phases, close_s=time.perf_counter() - closing)
        return cfg.num_updates * cfg.batch_size / (trained - start), last
    pool, provider = make_pool(cfg), None
    if cfg.uses_heads:
        cache = AnnotationCache(cache_dir)
        annotator = Annotator(StubBackend(f"synthetic-benchmark:{DIM}"), cache, model="synthetic", history_len=cfg.setup.history_len,
                              chunk=10_000)
        builder = annotator.builder(cfg.env_id, cfg.annotation_setup.renderer)
        live = SyncLive(annotator, cfg.annotation_setup, cfg.targets.live_budget) if cfg.targets.live_budget else None
        provider = CachedTargets(cache, builder, calibration="sum", num_actions=len(pool.action_names),
                                 embedding_dim=DIM, live=live)
    trainer = Trainer(cfg.resolved(), pool, provider, on_metrics=on_metrics)
    start = time.perf_counter()
    try:
        last = trainer.train(should_stop=turns)
        trained = time.perf_counter() - start
    finally:
        pool.close()
        if turns is not None:
            turns.done()
    if turns is not None:
        trained = turns.spent
    last.update(phases=phases, close_s=0.0)
    return cfg.num_updates * cfg.batch_size / trained, last


PHASES = ("rollout", "targets", "update")


def _lockstep_run(settings: dict, cache_dir: Path | None, threads: int, turn, other, together, results) -> None:
    """A lockstep pair's run in its own process (`lockstep`); puts (method, steps/s, last metrics).
    Both runs of a pair are held to the same `threads` cores: this VM's two cores need not be
    equally quick at a given time (left to either core, one pair read 1.10)."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:threads])
    if settings["device"].startswith("cuda"):
        deterministic_cuda()
    with torch_threads(threads):
        cfg = TrainConfig.from_dict(settings)
        sps, last = run(cfg, cache_dir, turns=Turns(turn, other, together))
    results.put((cfg.method, sps, {k: v for k, v in last.items() if isinstance(v, (int, float, dict))}))


def lockstep(settings: dict[str, dict], cache_dir: Path, threads: int, first: str) -> dict[str, tuple[float, dict]]:
    """A cached pair run in lockstep: each method in its own process, as `illm train` runs, taking
    their updates in turn (`first` first), so that both meet the same state of the machine. Run
    one after the other, a pair's two runs met different states: this machine's speed drifts by
    a fifth within minutes, and four pairs of the same code read from 0.78 to 0.97.
    Each run's rate is over its own updates' time: {method: (steps/s, last metrics)}."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    sems = {method: ctx.Semaphore(0) for method in settings}
    together, results = ctx.Barrier(len(settings), timeout=3600), ctx.Queue()
    second = next(m for m in settings if m != first)
    procs = [ctx.Process(target=_lockstep_run, args=(settings[m], cache_dir if m == "illm" else None, threads, sems[m],
                                                     sems[second if m == first else first], together, results)) for m in settings]
    for proc in procs:
        proc.start()
    sems[first].release()
    out = {}
    try:
        while len(out) < len(procs):
            try:
                method, sps, last = results.get(timeout=5)
                out[method] = (sps, last)
            except queue.Empty:  # a run that died leaves the other waiting for its turn: end both
                if any(proc.exitcode not in (None, 0) for proc in procs):
                    raise SystemExit(f"a lockstep run failed: exit codes {[proc.exitcode for proc in procs]}") from None
    finally:
        for proc in procs:
            if len(out) < len(procs):
                proc.terminate()
            proc.join(timeout=60)
    return out


def _env_rate(env_id: str, num_envs: int, steps: int, threads: int, results) -> None:
    """The env alone in its own process, held to `threads` cores as a lockstep run is: the pool
    ppo trains on (the suite's vector mode, text off) stepped with random actions; puts steps/s."""
    import numpy as np

    from illm_tools.envs.pool import EnvPool

    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:threads])
    pool = EnvPool(env_id, num_envs, 0, render=False)
    rng = np.random.default_rng(0)
    pool.reset()
    start = time.perf_counter()
    for _ in range(steps):
        pool.step(rng.integers(len(pool.action_names), size=num_envs))
    results.put(steps * num_envs / (time.perf_counter() - start))
    pool.close()


def env_rate(env_id: str, num_envs: int, frames: int, threads: int) -> float:
    """`_env_rate` in a spawned process (its affinity stays its own): steps/s of the env alone."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    results = ctx.Queue()
    proc = ctx.Process(target=_env_rate, args=(env_id, num_envs, max(frames // num_envs, 1), threads, results))
    proc.start()
    rate = results.get(timeout=3600)
    proc.join(timeout=60)
    return rate


def levels(args, config_of, tmp: Path) -> dict:
    """The cached case on each of `args.env` (the first the reference), then a line per level:
    ppo's and illm's rates (median over the pairs), their ratio, the env alone, and ppo's rate
    against the target (half the reference's ppo, or the env's own rate where lower)."""
    rows = {}
    for env_id in args.env:
        config = config_of(env_id)
        print(f"--- {env_id}: every target cached", flush=True)
        cached = tmp / f"ann-{len(rows)}"
        run(config("illm", f"fill-{len(rows)}", 10**9), cached)  # fills the cache
        out = pairs(args, config, cached, f"{len(rows)}", tmp)
        alone = env_rate(env_id, args.num_envs, args.frames, args.threads)
        print(f"  the env alone (random actions, text off): {alone:,.0f} steps/s", flush=True)
        rows[env_id] = {"ppo": statistics.median(p["ppo_sps"] for p in out),
                        "illm": statistics.median(p["illm_sps"] for p in out),
                        "ratio": statistics.median(p["ratio"] for p in out), "env_alone": alone,
                        "ppo_phases": {k: statistics.median(p["ppo"]["phases"][k] for p in out) for k in PHASES},
                        "illm_phases": {k: statistics.median(p["illm"]["phases"][k] for p in out) for k in PHASES}}
    reference = args.env[0]
    half = rows[reference]["ppo"] / 2
    print(f"steps/s, median over {args.pairs} pair(s); target: ppo at least half {reference}'s ppo "
          f"({half:,.0f}), or the env's own rate where that is lower")
    for env_id, row in rows.items():
        target = min(half, row["env_alone"])
        row["target"] = None if env_id == reference else target
        said = "the reference" if env_id == reference else \
            f"target {target:,.0f} ({'half the reference' if target == half else 'the env alone'}): " \
            f"{'met' if row['ppo'] >= target else 'not met'}"
        print(f"  {env_id:32s} ppo {row['ppo']:7,.0f}  illm {row['illm']:7,.0f}  ratio {row['ratio']:.3f}  "
              f"env alone {row['env_alone']:8,.0f}  {said}", flush=True)
    return rows


def phase_text(runs: list[dict]) -> str:
    """Each phase's median cost per update over `runs`, and the episodes that ended in an update (an
    agent that ends more of them resets more: BabyAI generates a level at each reset, which the
    rollout pays)."""
    return "  ".join([f"{k} {statistics.median(r['phases'][k] for r in runs):.3f}s" for k in PHASES]
                     + [f"({statistics.median(r['phases']['episodes'] for r in runs):.0f} episodes ended)"])


def write_json(args, rows: dict) -> None:
    """The levels form's `--json` file: its command, date, machine (lscpu's lines, `record.machine`) and
    figures (the form docs/results/measured/train-levels-issue70.json holds)."""
    import datetime
    import importlib.util
    import json
    import sys

    environment = {k: os.environ[k] for k in ("NUMBA_DISABLE_JIT", "PYTHONPATH", "OMP_NUM_THREADS") if k in os.environ}
    levels_file = {"command": " ".join(["python", *sys.argv]), "environment": environment,
                   "numba": importlib.util.find_spec("numba") is not None and os.environ.get("NUMBA_DISABLE_JIT") != "1",
                   "date": datetime.datetime.now().isoformat(timespec="seconds"),
                   "load_average_at_end": os.getloadavg() if hasattr(os, "getloadavg") else None,
                   "machine": machine(), "cores": os.cpu_count(), "threads": args.threads,
                   "frames": args.frames, "pairs": args.pairs, "num_envs": args.num_envs, "num_steps": args.num_steps,
                   "levels": rows}
    args.json.write_text(json.dumps(levels_file, indent=2) + "\n")
    print(f"wrote {args.json}")


def levels_figures(rows: dict, reference: str) -> tuple[dict, dict]:
    """The levels form's record: each level's medians (steps/s, ratio, the env alone, ppo's target), and
    the headline: the lowest ppo rate over its target among the levels other than the reference."""
    names = {"ppo": "ppo_steps_per_s", "illm": "illm_steps_per_s", "ratio": "illm_over_ppo",
             "env_alone": "env_alone_steps_per_s", "target": "ppo_target_steps_per_s"}
    figures = {f"{env_id}:{name}": row[k] for env_id, row in rows.items() for k, name in names.items()
               if row.get(k) is not None}
    shares = {env_id: row["ppo"] / row["target"] for env_id, row in rows.items() if env_id != reference}
    low = min(shares, key=shares.get)
    return figures, {"name": f"ppo steps/s / its target, the lowest over the levels ({low})", "value": shares[low],
                     "target": 1.0}


def case_figures(case: str, out: list[dict]) -> dict:
    """A case's figures over its pairs (`pairs`): the ratio's median and range, each method's median
    steps/s, and what illm adds to an update in ms."""
    ratios = [p["ratio"] for p in out]
    return {f"{case}:illm_over_ppo_median": statistics.median(ratios), f"{case}:illm_over_ppo_min": min(ratios),
            f"{case}:illm_over_ppo_max": max(ratios),
            f"{case}:ppo_steps_per_s_median": statistics.median(p["ppo_sps"] for p in out),
            f"{case}:illm_steps_per_s_median": statistics.median(p["illm_sps"] for p in out),
            f"{case}:illm_added_ms_per_update_median": 1e3 * statistics.median(p["added"] for p in out)}


TARGETS = {"cached": 0.85, "async": 0.75}
"""Each case's target for the median illm/ppo ratio (issue 57)."""


def case_headline(figures: dict) -> dict:
    """The record's ratio: the cached case's median where it ran, else the async case's."""
    case = "cached" if "cached:illm_over_ppo_median" in figures else "async"
    return {"name": f"illm / ppo steps/s, {case} case, median over the pairs",
            "value": figures[f"{case}:illm_over_ppo_median"], "target": TARGETS[case]}


def deterministic_cuda() -> None:
    """torch's deterministic algorithms on CUDA (cuBLAS's fixed workspace, cuDNN's deterministic
    kernels): the cached case's later passes must meet the fill pass's states, and CUDA's atomic
    adds otherwise make each run's weights, and so its trajectories, drift apart (a cache hit rate
    of 0.07 without this on an H100). Both methods pay what it costs."""
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    import torch

    torch.backends.cudnn.benchmark = False
    torch.backends.cudnn.deterministic = True
    torch.use_deterministic_algorithms(True)


def gpu_name(device: str) -> str:
    """' (the GPU's name)' where the policy runs on CUDA, else ''."""
    if not device.startswith("cuda"):
        return ""
    import torch

    return f" ({torch.cuda.get_device_name(torch.device(device))}, torch {torch.__version__})"


def pairs(args, config, cached: Path | None, label: str, tmp: Path) -> list[dict]:
    """`args.pairs` paired runs of ppo and illm, alternating which runs first: cached when `cached`
    names the filled cache, the two in lockstep (`lockstep`); else async live annotation into an
    empty cache each, under `tmp`, one run after the other (in lockstep the illm run's worker would
    annotate on through ppo's turns too, more than in a run of its own)."""
    out = []
    for k in range(args.pairs):
        order = ("illm", "ppo") if k % 2 == 0 else ("ppo", "illm")
        if cached is not None:  # in lockstep: both runs meet the same state of the machine
            pair = lockstep({m: config(m, f"{label}-{m}-{k}", 0, as_settings=True) for m in order}, cached,
                            args.threads, first=order[0])
        else:
            pair = {}
            for method in order:
                if method == "ppo":
                    pair["ppo"] = run(config("ppo", f"{label}-ppo-{k}", 0), None)
                else:
                    cfg = config("illm", f"{label}-illm-{k}", 16, cache=tmp / f"live-ann-{k}", live_mode="async",
                                 history_len=0)
                    pair["illm"] = run(cfg, None, live_async=True)
        ratio = pair["illm"][0] / pair["ppo"][0]
        if cached is None:
            last = pair["illm"][1]
            ready, first = last.get("charts/live_worker_startup_s"), last.get("charts/live_first_answer_s")
            extra = (f"; worker {'not ready during the run' if ready is None else f'ready {ready:.1f}s'}, first answer "
                     f"{'none during the run' if first is None else f'{first:.1f}s after its start'}, targets on "
                     f"{last['charts/target_coverage']:.3f} of the last rollout's steps, shutdown after the run "
                     f"{last['close_s']:.1f}s")
        else:
            extra = f"; cache hit rate {pair['illm'][1]['charts/cache_hit_rate']:.3f}"
        print(f"  pair {k + 1}: ppo {pair['ppo'][0]:7,.0f} steps/s, illm {pair['illm'][0]:7,.0f}: ratio {ratio:.3f}{extra}",
              flush=True)
        # what illm adds to each update (its steps at each method's rate), read beside the ratio: the
        # ratio also moves with what both pay (a slow spell slows the envs' Python more than the heads)
        added = (1 / pair["illm"][0] - 1 / pair["ppo"][0]) * args.num_envs * args.num_steps
        out.append({"ratio": ratio, "added": added, "ppo": pair["ppo"][1], "illm": pair["illm"][1],
                    "ppo_sps": pair["ppo"][0], "illm_sps": pair["illm"][0]})
    ratios = [p["ratio"] for p in out]
    print(f"  per update, median over the pairs: ppo {phase_text([p['ppo'] for p in out])}")
    print(f"                                     illm {phase_text([p['illm'] for p in out])}")
    print(f"  illm's added time per update of {args.num_envs * args.num_steps:,} steps, median over the pairs: "
          f"{1e3 * statistics.median(p['added'] for p in out):.0f} ms")
    print(f"  illm/ppo ratio, median of {len(ratios)} pairs: {statistics.median(ratios):.3f} "
          f"(range {min(ratios):.3f}-{max(ratios):.3f})", flush=True)
    return out


def profile(config, cached: Path, top: int) -> dict:
    """cProfile's top entries by own time of one cached illm run and one ppo run; returns each one's
    steps/s under the profiler."""
    import cProfile
    import io
    import pstats

    rates = {}
    for method in ("illm", "ppo"):
        profiler = cProfile.Profile()
        profiler.enable()
        sps, last = run(config(method, f"profile-{method}", 0), cached if method == "illm" else None)
        profiler.disable()
        text = io.StringIO()
        pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(top)
        body = text.getvalue()
        print(f"--- {method}: {sps:,.0f} steps/s under the profiler; per update "
              f"{phase_text([last])}")
        print(body[body.index("ncalls"):].rstrip())
        rates[method] = sps
    return rates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", action="append", help="The env (default BabyAI-GoToLocal-v0); given more than "
                        "once, the levels form (the cached case on each; the first is the reference).")
    parser.add_argument("--json", type=Path, help="The levels form: write its figures, the machine and the command here.")
    parser.add_argument("--frames", type=int, default=40_960)
    parser.add_argument("--pairs", type=int, default=3, help="Paired ppo/illm runs of each case.")
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--num-steps", type=int, default=128)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu", help="The policy's device (cuda: on a GPU).")
    parser.add_argument("--only", choices=("cached", "async"), help="Run one case only.")
    parser.add_argument("--profile", action="store_true", help="Where the time goes instead (cProfile).")
    parser.add_argument("--mode", choices=("obs", "hop"), default="obs", help="hop: the cost of iLLM(hop) instead.")
    parser.add_argument("--history", type=int, default=3, help="hop: steps of history (the window is one more).")
    parser.add_argument("--dtype", default="bfloat16", help="hop: the LLM's compute dtype (float32 is faster on some CPUs).")
    parser.add_argument("--head-hidden", type=int, help="iLLM's heads' width (default: the run's, the paper's 1,024): "
                        "what another width would cost, for the choice of it.")
    options(parser)
    args = parser.parse_args()
    args.env = args.env or ["BabyAI-GoToLocal-v0"]
    several = len(args.env) > 1
    if several and (args.profile or args.mode == "hop" or args.only == "async"):
        raise SystemExit("several --env run the cached case only (no --profile, --mode hop or --only async)")
    if args.json and not several:
        raise SystemExit("--json writes the levels form's figures: give --env more than once")
    if args.device.startswith("cuda"):
        deterministic_cuda()

    with tempfile.TemporaryDirectory() as tmp, torch_threads(args.threads):
        def config_of(env_id: str):
            return lambda *a, **kw: config(*a, env_id=env_id, **kw)

        def config(mode: str, name: str, live_budget: int, as_settings: bool = False, env_id: str | None = None,
                   **settings) -> TrainConfig | dict:
            """A run's config (or, `as_settings`, what makes it: a lockstep run's process makes its own);
            `settings` by their flat names (`illm_tools.rl.config.FLAT`). Unless the
            run annotates live or reads Z_h (hop), its LLM is a stub of SmolLM2-135M's width: the heads' size without the
            model's package (the cache's rows come from the synthetic annotator either way)."""
            if settings.get("live_mode") != "async" and settings.get("obs_mode") != "hop":
                settings.setdefault("llm", LLMSpec("stub", f"stub:{DIM}"))
            if args.head_hidden:
                settings["head_hidden"] = args.head_hidden
            made = dict(env_id=env_id or args.env[0], run_dir=Path(tmp) / name, method=mode, seed=0, total_steps=args.frames,
                        num_envs=args.num_envs, num_steps=args.num_steps, device=args.device,
                        live_budget=live_budget, tensorboard=False, checkpoint_every=0, threads=args.threads, **settings)
            return made if as_settings else TrainConfig.from_dict(made)

        print(f"env {', '.join(args.env)}, {args.frames:,} frames a run, {args.num_envs} envs x {args.num_steps} steps, "
              f"{'' if not args.head_hidden else f'heads of {args.head_hidden} units, '}"
              f"{args.threads} thread(s), policy on {args.device}{gpu_name(args.device)}; CPU: {cpu_name()}, "
              f"{os.cpu_count()} cores", flush=True)
        if several:
            rows = levels(args, config_of, Path(tmp))
            if args.json:
                write_json(args, rows)
            figures, ratio = levels_figures(rows, args.env[0])
            keep(args, figures, ratio)
            return
        if args.mode == "hop":
            hop = {"obs_mode": "hop", "history_len": args.history, "model_dtype": args.dtype}
            sps_ppo, last_ppo = run(config("ppo", "ppo", 0), None)
            sps_ppo_hop, last_ppo_hop = run(config("ppo", "ppo-hop", 0, **hop), None)
            run(config("illm", "fill", 10**9, **hop), Path(tmp) / "ann")  # fills the cache
            sps_illm, last = run(config("illm", "illm", 0, **hop), Path(tmp) / "ann")
            print(f"hop window {args.history + 1}, SmolLM2-135M {args.dtype}")
            print(f"ppo               {sps_ppo:8,.0f} steps/s  per update: {phase_text([last_ppo])}")
            print(f"ppo, hop (Z_h)    {sps_ppo_hop:8,.0f} steps/s  per update: {phase_text([last_ppo_hop])}")
            print(f"illm, hop (cached){sps_illm:8,.0f} steps/s  per update: {phase_text([last])}  "
                  f"(cache hit rate {last['charts/cache_hit_rate']:.3f})")
            print(f"hop cost per step: {1e3 / sps_ppo_hop - 1e3 / sps_ppo:.2f} ms (ppo hop/ppo ratio "
                  f"{sps_ppo_hop / sps_ppo:.3f}); illm hop/ppo ratio {sps_illm / sps_ppo:.3f}")
            keep(args, {"ppo_steps_per_s": sps_ppo, "ppo_hop_steps_per_s": sps_ppo_hop, "illm_hop_steps_per_s": sps_illm,
                        "hop_cost_ms_per_step": 1e3 / sps_ppo_hop - 1e3 / sps_ppo,
                        "illm_hop_cache_hit_rate": last["charts/cache_hit_rate"]},
                 {"name": "illm hop (cached) / ppo steps/s", "value": sps_illm / sps_ppo})
            return
        cached = Path(tmp) / "ann"
        if args.only != "async" or args.profile:
            run(config("illm", "fill", 10**9), cached)  # pass 1: fills the cache
        if args.profile:
            rates = profile(config, cached, 20)
            keep(args, {f"{m}_steps_per_s_profiled": v for m, v in rates.items()},
                 {"name": "illm / ppo steps/s under the profiler", "value": rates["illm"] / rates["ppo"]})
            return
        figures = {}
        if args.only != "async":
            print(f"every target cached (target: median >= {TARGETS['cached']})", flush=True)
            figures.update(case_figures("cached", pairs(args, config, cached, "cached", Path(tmp))))
        if args.only != "cached":
            print("async live annotation: history 0, an empty cache each run, the SmolLM2-135M worker (1 thread) "
                  f"beside the trainer (target: median >= {TARGETS['async']})", flush=True)
            figures.update(case_figures("async", pairs(args, config, None, "async", Path(tmp))))
        keep(args, figures, case_headline(figures))


def keep(args, figures: dict, ratio: dict) -> None:
    """The run's record (benchmarks/record.py), unless `--no-record`."""
    if not args.no_record:
        record("train", figures, ratio=ratio, out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()
