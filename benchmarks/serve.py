"""Live annotation for 2 trainers through one `illm serve` server against 2 trainers each with its
own worker (`--live-mode async`), measured in the same run.

Both setups train the same two iLLM runs (seeds 0 and 1, the same frames, an empty cache of their
own, the same live budget) on the same model. Measured for each: the wall time of the two runs,
the states the LLM put in the cache per second of it (live-annotation throughput), and the peak
of the summed resident memory of every process involved (trainers, their workers, the server),
sampled every 0.25 s with psutil. Prints both, the throughput ratio (server / own workers) and the
memory saved.

    python benchmarks/serve.py [--model smollm2-135m] [--frames 16384] [--backend transformers]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from record import options, record, settings  # noqa: E402

ENV = {**os.environ, "HF_HUB_OFFLINE": "1", "PYTHONWARNINGS": "ignore"}


class PeakMemory:
    """Peak of the summed RSS of some processes and all their children, sampled in a thread."""

    def __init__(self) -> None:
        self.roots: list[psutil.Process] = []
        self.peak = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def add(self, pid: int) -> None:
        self.roots.append(psutil.Process(pid))

    def _run(self) -> None:
        while not self._stop.is_set():
            total = 0
            for root in list(self.roots):
                try:
                    for p in [root, *root.children(recursive=True)]:
                        total += p.memory_info().rss
                except psutil.Error:
                    continue
            self.peak = max(self.peak, total)
            time.sleep(0.25)

    def stop(self) -> int:
        self._stop.set()
        self._thread.join()
        return self.peak


def trainers(folder: Path, args, extra: list[str], memory: PeakMemory) -> float:
    """Run the two trainers side by side; returns their wall time."""
    base = [sys.executable, "-m", "cli.main", "train", "--env", args.env, "--method", "illm", "--cache",
            str(folder / "ann"), "--backend", args.backend, "--model", args.model, "--dtype", args.dtype,
            "--history", "0", "--num-envs", "8", "--num-steps", "64", "--frames", str(args.frames),
            "--live-budget", str(args.budget), "--no-tensorboard", *extra]
    start = time.perf_counter()
    procs = [subprocess.Popen([*base, "--seed", str(i), "--out", str(folder / f"run{i}")], env=ENV, cwd=ROOT,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    for p in procs:
        memory.add(p.pid)
    for p in procs:
        out, err = p.communicate()
        if p.returncode:
            raise SystemExit(f"a trainer failed: {err.strip().splitlines()[-1] if err.strip() else p.returncode}")
    return time.perf_counter() - start


def annotated(cache: Path) -> int:
    from illm_tools.cache import AnnotationCache

    return AnnotationCache(cache).tasks().get("action", 0)


def own_workers(folder: Path, args) -> dict:
    memory = PeakMemory()
    wall = trainers(folder, args, ["--live-mode", "async", "--llm-threads", "1"], memory)
    return {"wall_s": wall, "states": annotated(folder / "ann"), "peak_rss_mb": memory.stop() / 2**20}


def one_server(folder: Path, args) -> dict:
    memory = PeakMemory()
    server = subprocess.Popen([sys.executable, "-m", "cli.main", "serve", "--cache", str(folder / "ann"), "--backend",
                               args.backend, "--model", args.model, "--dtype", args.dtype, "--history", "0", "--port", "0",
                               "--threads", str(args.server_threads)],
                              env=ENV, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    memory.add(server.pid)
    line = server.stderr.readline()
    found = re.search(r"(http://[\d.]+:\d+)", line)
    if not found:
        raise SystemExit(f"the server did not start: {line}{server.stderr.read()}")
    try:
        wall = trainers(folder, args, ["--annotator", found.group(1)], memory)
        with __import__("urllib.request").request.urlopen(found.group(1) + "/stats") as r:
            stats = json.loads(r.read())
    finally:
        server.send_signal(2)
        server.wait(120)
    return {"wall_s": wall, "states": annotated(folder / "ann"), "peak_rss_mb": memory.stop() / 2**20,
            "server_states_per_s": stats["states_per_s"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="smollm2-135m")
    parser.add_argument("--backend", default="transformers")
    parser.add_argument("--dtype", default="float32")
    parser.add_argument("--env", default="BabyAI-GoToLocal-v0")
    parser.add_argument("--frames", type=int, default=16384, help="per trainer (the model loads take the first ~15 s)")
    parser.add_argument("--budget", type=int, default=16, help="missed states sent per rollout")
    parser.add_argument("--server-threads", type=int, default=0, help="torch threads of the server (0: every core)")
    options(parser)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        own = own_workers(Path(tmp) / "own", args)
        shared = one_server(Path(tmp) / "server", args)
    for name, r in (("own workers", own), ("one server", shared)):
        print(f"{name:12s} wall {r['wall_s']:6.1f} s  states annotated {r['states']:5d}  "
              f"{r['states'] / r['wall_s']:.2f} states/s  peak memory {r['peak_rss_mb']:7.0f} MB")
    ratio = f"{(shared['states'] / shared['wall_s']) / (own['states'] / own['wall_s']):.2f}x" if own["states"] else \
        "n/a (the own workers annotated nothing: give more --frames)"
    print(f"throughput ratio (one server / own workers): {ratio}; memory saved: "
          f"{own['peak_rss_mb'] - shared['peak_rss_mb']:.0f} MB ({1 - shared['peak_rss_mb'] / own['peak_rss_mb']:.0%}); "
          f"{os.cpu_count()} cores, model {args.model} ({args.backend}), {args.frames} frames per trainer")
    if not args.no_record:
        figures = {f"{name}:{k}": r[k] for name, r in (("own_workers", own), ("one_server", shared)) for k in r}
        figures.update({"own_workers:states_per_s": own["states"] / own["wall_s"],
                        "one_server:states_per_s": shared["states"] / shared["wall_s"],
                        "memory_saved_mb": own["peak_rss_mb"] - shared["peak_rss_mb"]})
        value = figures["one_server:states_per_s"] / figures["own_workers:states_per_s"] if own["states"] else None
        record("serve", figures, ratio={"name": "one server / own workers, states annotated per second", "value": value},
               out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()
