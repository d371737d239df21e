"""The same states through illm's in-process engine and through vLLM's OpenAI server, on this machine.

States: distinct BabyAI GoToLocal steps of a random-policy collection (history 0 by default). Both
sides serve the embedded SmolLM2-135M's weights in the dtype illm picks here (`--dtype auto`), on
the same cores: the in-process engine with torch's threads, vLLM (its CPU build, from `.venv-engine`:
`make engine`) with `--engine-threads`. vLLM runs two servers of the weights: completions (ranking by
echoed prompt log-probs, greedy summaries) and a pooling runner that embeds the summaries
(`--embed-endpoint`). Servers start before the timings and idle while the in-process engine runs.

Prints, for ranking alone (`--states`) and for ranking with summaries (`--summary-states`):
states/s of both and the ratio vLLM / in-process; then how far their answers agree: the top action
(share of states), the candidates' summed log-probs (median and largest difference), summaries
word for word, and the cosine between vLLM's pooled embedding of a summary and (a) the in-process
mean hidden state of the same text, (b) the in-process embedding of its own summary read with its
prompt (the paper's, what the transformers backend stores).

    .venv/bin/python benchmarks/engines.py [--states 64] [--summary-states 16] [--engine-threads 2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))
from annotate import babyai_states  # noqa: E402  (benchmarks/annotate.py: distinct states of a collection)
from record import options, record, settings  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ENV = "BabyAI-GoToLocal-v0"


def timed(backend, records, tasks, history, folder):
    """(rows by (task, prompt), seconds) of annotating `records` for `tasks` with `backend`."""
    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.envs import renderer_of

    annotator = Annotator(backend, AnnotationCache(folder), model=backend.model, tasks=tasks, history_len=history,
                          chunk=len(records))
    plan = annotator.plan(annotator.visited(records, [ENV] * len(records), [renderer_of(ENV)] * len(records)))
    if "action" in tasks:
        annotator.neutral_scores(plan[0][0].prompt.candidates)  # once per model; not part of the timing
    start = time.perf_counter()
    rows = annotator.annotate(plan)
    return {(r["task"], r["prompt"]): r for r in rows}, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--states", type=int, default=64, help="States ranked (action task alone).")
    parser.add_argument("--summary-states", type=int, default=16, help="States annotated with both tasks.")
    parser.add_argument("--history", type=int, default=0)
    parser.add_argument("--dtype", default="auto", help="auto: what `illm annotate` picks on this machine.")
    parser.add_argument("--engine-threads", type=int, default=2, help="vLLM's torch threads (OMP_NUM_THREADS).")
    options(parser)
    args = parser.parse_args()

    import numpy as np
    import torch

    from illm_tools.llm.dtype import resolve_dtype
    from illm_tools.llm.generation import embed_texts
    from illm_tools.llm.loading import cache_root, dequantised_folder
    from illm_tools.llm.registry import resolve
    from illm_tools.llm.spec import LLMSpec
    from illm_tools.llm.vllm_server import VLLMServer, engine_python

    dtype = resolve_dtype(args.dtype)
    weights, _ = dequantised_folder(resolve("smollm2-135m"), cache_root())
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        records = babyai_states(max(args.states, args.summary_states), args.history, tmp / "states")
        ranked, both = records[: args.states], records[: args.summary_states]
        local = LLMSpec(model="smollm2-135m", dtype=dtype, device="cpu", quant="none").load()
        local_rank, t_local_rank = timed(local, ranked, ("action",), args.history, tmp / "l1")
        local_both, t_local_both = timed(local, both, ("action", "summary"), args.history, tmp / "l2")
        servers = [VLLMServer(weights, served_name="smol", python=engine_python(ROOT), runner=r, dtype=dtype,
                              threads=args.engine_threads, kv_cache_gib=1.0, log=tmp / f"{r}.log")
                   for r in ("generate", "pooling")]
        started = time.perf_counter()
        try:
            for server in servers:
                server.start()
            generate_url, pooling_url = (server.wait() for server in servers)
            t_start = time.perf_counter() - started
            remote = LLMSpec(backend="openai", model="smol", endpoint=generate_url, embed_endpoint=pooling_url).load()
            remote_rank, t_remote_rank = timed(remote, ranked, ("action",), args.history, tmp / "r1")
            remote_both, t_remote_both = timed(remote, both, ("action", "summary"), args.history, tmp / "r2")
        finally:
            for server in servers:
                server.stop()

    print(f"SmolLM2-135M in {dtype}, {ENV} states, history {args.history}; in-process {torch.get_num_threads()} "
          f"threads, vLLM ({remote.fingerprint['engine']}) {args.engine_threads} threads "
          f"(servers started in {t_start:.0f} s, both runners at once)")
    figures = {"servers_start_s": t_start}
    for what, n, t_local, t_remote in (("ranking alone", len(ranked), t_local_rank, t_remote_rank),
                                       ("ranking + summaries", len(both), t_local_both, t_remote_both)):
        print(f"{what:22s} in-process {n / t_local:6.2f} states/s   vLLM {n / t_remote:6.2f} states/s   "
              f"ratio vLLM/in-process {t_local / t_remote:5.2f}  ({n} states)")
        part = what.replace(" + ", "_and_").replace(" ", "_")
        figures.update({f"{part}:states": n, f"{part}:in_process_states_per_s": n / t_local,
                        f"{part}:vllm_states_per_s": n / t_remote, f"{part}:vllm_over_in_process": t_local / t_remote})
    actions = [k for k in local_rank if k in remote_rank]
    same = sum(local_rank[k]["chosen_index"] == remote_rank[k]["chosen_index"] for k in actions)
    diffs = [abs(a - b) for k in actions
             for a, b in zip(local_rank[k]["cand_logprob_sum"], remote_rank[k]["cand_logprob_sum"])]
    print(f"top action equal       {same}/{len(actions)} states; candidates' summed log-probs differ by median "
          f"{statistics.median(diffs):.3f}, at most {max(diffs):.3f} nats")
    summaries = [k for k in local_both if k[0] == "summary" and k in remote_both]
    words = sum(local_both[k]["text"] == remote_both[k]["text"] for k in summaries)
    pooled = np.asarray([remote_both[k]["embedding"] for k in summaries], np.float32)
    same_text = embed_texts(local.lm, [remote_both[k]["text"] for k in summaries])  # the weights loaded above
    paper = np.asarray([local_both[k]["embedding"] for k in summaries], np.float32)

    def cosine(a, b):
        return (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)

    c_text, c_paper = cosine(pooled, same_text), cosine(pooled, paper)
    print(f"summaries equal        {words}/{len(summaries)} word for word")
    print(f"pooled embedding cos   (a) in-process mean hidden state of the same text: min {c_text.min():.4f}, "
          f"median {np.median(c_text):.4f}")
    print(f"                       (b) in-process embedding of its own summary read with its prompt: min "
          f"{c_paper.min():.4f}, median {np.median(c_paper):.4f}")
    figures.update({"top_action_equal_share": same / max(len(actions), 1),
                    "logprob_sum_difference_median_nats": statistics.median(diffs),
                    "logprob_sum_difference_max_nats": max(diffs),
                    "summaries_equal_share": words / max(len(summaries), 1),
                    "pooled_cosine_same_text_min": float(c_text.min()), "pooled_cosine_same_text_median": float(np.median(c_text)),
                    "pooled_cosine_paper_min": float(c_paper.min()), "pooled_cosine_paper_median": float(np.median(c_paper))})
    if not args.no_record:
        record("engines", figures, ratio={"name": "vLLM / in-process states/s, ranking alone",
                                          "value": figures["ranking_alone:vllm_over_in_process"]},
               out=args.record, settings={**settings(args), "dtype_resolved": dtype})


if __name__ == "__main__":
    main()
