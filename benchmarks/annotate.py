"""`illm annotate` against the loop a user would write first, and the engine's cost by tokens.

Part 1 (GoToLocal, the paper's 3-step history, prompts of about 370 tokens): the naive loop (one
full forward per candidate action, then one `generate` of 64 greedy tokens per state and one
forward over prompt + summary for the mean-pooled embedding) against `Annotator.annotate`
(candidates packed behind one copy of the prompt, states batched by a token budget, the prompt
prefix shared by the two tasks computed once, batched greedy decoding). Target: speedup >= 8x.

Part 2 (issue 53's table): for each case (GoToLocal at history 0 and 3, Crafter and MiniHack at
history 3; both tasks) and `--batch-size` 4 and 16, the engine before (each candidate behind a copy
of its state's prompt, batches bounded by their state count) and after (candidates packed, batches
bounded by the token budget too): states/s, the peak resident memory above the resident memory
before the run (VmHWM, reset per measurement through /proc/self/clear_refs), the share of
states whose top action equals `--batch-size 1`'s, and the prefill rate: 2 x non-embedding
parameters x tokens fed in the passes of more than one token (prompts, packed candidates) over
those passes' time, as a share of this machine's matmul rate in the dtype (measured in the same
run). Target: prefill >= 50% of the matmul rate.

    .venv/bin/python benchmarks/annotate.py [--states 16] [--naive-states 4] [--cases crafter-h3,minihack-h3]
    .venv/bin/python benchmarks/annotate.py --device cuda [--quant 4bit] --batch-sizes 32,256 --naive-states 0

On CUDA the peak is the device's (torch.cuda.max_memory_allocated).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from record import options, record, settings  # noqa: E402

CASES = {"gotolocal-h0": ("BabyAI-GoToLocal-v0", 0), "gotolocal-h3": ("BabyAI-GoToLocal-v0", 3),
         "crafter-h3": ("CrafterReward-v1", 3), "minihack-h3": ("MiniHack-River-Monster-v0", 3)}
"""Case name -> (env id, history length)."""


def matmul_rate(dtype, seconds: float = 2.0, device: str = "cpu") -> float:
    """GFLOP/s of a matmul in `dtype` shaped like the model's MLP over a batch of tokens."""
    import torch

    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    a = torch.randn(2048, 576, dtype=dtype, device=device)
    b = torch.randn(576, 1536, dtype=dtype, device=device)
    a @ b
    sync()
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        a @ b
        n += 1
    sync()
    return n * 2 * 2048 * 576 * 1536 / (time.perf_counter() - start) / 1e9


def babyai_states(n: int, history: int, workdir: Path, env_id: str = "BabyAI-GoToLocal-v0", seed: int = 0,
                  steps: int | None = None):
    """Up to `n` distinct states of a random-policy collection of `env_id` (`steps` steps, default 4 n), each
    with a full history of `history` steps (benchmarks/student.py shares it)."""
    from illm_tools.collect import CollectConfig, collect
    from illm_tools.data.trajectories import open_table
    from illm_tools.tasks.state import TABLE_COLUMNS, records_from_table

    collect(CollectConfig(env_id=env_id, out=workdir / "traj", steps=steps or max(4 * n, 64), num_envs=4, seed=seed))
    records, _ = records_from_table(open_table(workdir / "traj", columns=TABLE_COLUMNS), history)
    full = [r for r in dict.fromkeys(records) if len(r.history) == history]  # states with a full history
    return full[:n]


def naive(lm, jobs) -> None:
    """One forward per candidate; one generate and one embedding forward per state."""
    import torch

    model, tok = lm.model, lm.tokenizer
    device = model.device
    for action, summary in jobs:
        ctx = tok(action.prompt.text, return_tensors="pt").input_ids
        for cand in action.prompt.candidates:
            ids = tok(action.prompt.text + cand, return_tensors="pt").input_ids.to(device)
            with torch.no_grad():
                logp = model(ids).logits.log_softmax(-1)
            logp[0, ctx.shape[1] - 1:-1].gather(1, ids[0, ctx.shape[1]:, None]).sum()
        ids = tok(summary.prompt.text, return_tensors="pt").input_ids.to(device)
        with torch.no_grad():
            out = model.generate(ids, max_new_tokens=64, do_sample=False, pad_token_id=lm.pad_id)
            hidden = model(out, output_hidden_states=True).hidden_states[-1]
        hidden[0, ids.shape[1]:].mean(0)


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) / 1024 for line in f if line.startswith("VmRSS"))


def peak_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) / 1024 for line in f if line.startswith("VmHWM"))


def reset_peak() -> None:
    """The process's peak resident memory (VmHWM) set to its resident memory now (Linux)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


class Prefill:
    """Tokens and seconds of the decoder's passes of more than one token (prompts, packed candidates)."""

    def __init__(self, lm, device: str):
        import torch

        self.tokens, self.seconds, self._start = 0, 0.0, 0.0
        self._sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
        decoder = lm.model.get_decoder()
        self._hooks = [decoder.register_forward_pre_hook(self._before, with_kwargs=True),
                       decoder.register_forward_hook(self._after, with_kwargs=True)]
        self._wide = False

    def _before(self, _module, _args, kwargs):
        ids = kwargs.get("input_ids")
        self._wide = ids is not None and ids.shape[1] > 1
        if self._wide:
            self._sync()
            self.tokens += int(ids.numel())
            self._start = time.perf_counter()

    def _after(self, _module, _args, _kwargs, _out):
        if self._wide:
            self._sync()
            self.seconds += time.perf_counter() - self._start

    def remove(self) -> None:
        for h in self._hooks:
            h.remove()


def measure(lm, annotator_of, plan, device: str) -> tuple[float, float, list]:
    """(states/s, peak memory above the start in MB, rows) of annotating `plan` with a fresh cache."""
    import torch

    from illm_tools.serve.memory import release_free_memory

    gpu = device.startswith("cuda")
    annotator = annotator_of()
    annotator.neutral_scores(plan[0][0].prompt.candidates)
    release_free_memory()  # memory freed by earlier measurements handed back: the growth is this one's
    if gpu:
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated() / 2**20
    else:
        base = rss_mb()
        reset_peak()
    start = time.perf_counter()
    rows = annotator.annotate(plan)
    seconds = time.perf_counter() - start
    peak = (torch.cuda.max_memory_allocated() / 2**20 if gpu else peak_mb()) - base
    return len(plan) / seconds, peak, rows


def engine_table(args, lm, rate: float, params: int) -> dict:
    """Part 2: the before/after table over the cases and batch sizes; returns its figures (the record's),
    each named "CASE batch N:WHAT"."""
    import dataclasses

    import torch

    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.envs import renderer_of

    before = dataclasses.replace(lm, pack_candidates=False, batch_tokens=None)
    print(f"\nengine by tokens: {args.states} states a case, both tasks; budget {lm.batch_tokens:,} tokens a batch "
          f"(after); peak = resident memory above the run's start")
    print("| case | prompt tokens | batch | before: states/s | before: peak MB | after: states/s | after: peak MB "
          "| after: same top action as batch 1 | after: prefill % of matmul |")
    print("|---|---|---|---|---|---|---|---|---|")
    figures = {}
    for name in args.cases.split(","):
        env_id, history = CASES[name]
        with tempfile.TemporaryDirectory() as tmp:
            records = babyai_states(args.states, history, Path(tmp), env_id=env_id)
            if not records:
                print(f"| {name} | no states with a full history | | | | | | | |")
                continue

            def annotator_of(model=lm, batch=1, folder=[0]):
                folder[0] += 1
                return Annotator(model, AnnotationCache(Path(tmp) / f"ann{folder[0]}"), model=args.model,
                                 layout=args.layout, batch_size=batch, chunk=len(records), history_len=history)

            probe = annotator_of()
            plan = probe.plan(probe.visited(records, [env_id] * len(records), [renderer_of(env_id)] * len(records)))
            tokens = sum(len(lm.encode(jobs[0].prompt.text)) for jobs in plan) / max(len(plan), 1)
            _, _, rows = measure(lm, lambda: annotator_of(lm, 1), plan, args.device)
            best1 = {r["key"]: r["chosen_index"] for r in rows if r["task"] == "action"}
            for batch in (int(b) for b in args.batch_sizes.split(",")):
                old_rate, old_peak, _ = measure(before, lambda: annotator_of(before, batch), plan, args.device)
                counter = Prefill(lm, args.device)
                new_rate, new_peak, rows = measure(lm, lambda: annotator_of(lm, batch), plan, args.device)
                counter.remove()
                same = sum(best1[r["key"]] == r["chosen_index"] for r in rows if r["task"] == "action")
                share = 2 * params * counter.tokens / max(counter.seconds, 1e-9) / 1e9 / rate
                print(f"| {name} | {tokens:.0f} | {batch} | {old_rate:.2f} | {old_peak:.0f} | {new_rate:.2f} | "
                      f"{new_peak:.0f} | {same}/{len(best1)} | {100 * share:.0f}% |", flush=True)
                figures.update({f"{name} batch {batch}:{k}": v for k, v in (
                    ("prompt_tokens", tokens), ("before_states_per_s", old_rate), ("before_peak_mb", old_peak),
                    ("after_states_per_s", new_rate), ("after_peak_mb", new_peak),
                    ("after_same_top_action_share", same / max(len(best1), 1)), ("after_prefill_share_of_matmul", share))})
                torch.cuda.empty_cache() if args.device.startswith("cuda") else None
    return figures


def headline(figures: dict) -> dict | None:
    """The record's ratio: part 1's speedup over the naive loop (target 8x) where it ran, else part 2's
    lowest prefill rate as a share of the matmul rate (target 0.5)."""
    if "speedup_over_naive" in figures:
        return {"name": "illm annotate / naive loop states/s", "value": figures["speedup_over_naive"], "target": 8.0}
    shares = {k.split(":")[0]: v for k, v in figures.items() if k.endswith(":after_prefill_share_of_matmul")}
    if not shares:
        return None
    low = min(shares, key=shares.get)
    return {"name": f"prefill rate / matmul rate, the lowest over the cases ({low})",
            "value": shares[low], "target": 0.5}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="smollm2-135m")
    parser.add_argument("--dtype", default="auto", help="auto: what `illm annotate` picks on this machine.")
    parser.add_argument("--states", type=int, default=16, help="States annotated per measurement.")
    parser.add_argument("--naive-states", type=int, default=4, help="States of the naive loop (slow; 0 skips part 1).")
    parser.add_argument("--batch-size", type=int, default=8, help="Part 1's --batch-size.")
    parser.add_argument("--batch-sizes", default="4,16", help="Part 2's batch sizes (comma-separated).")
    parser.add_argument("--cases", default=",".join(CASES), help=f"Part 2's cases: {', '.join(CASES)} ('' skips it).")
    parser.add_argument("--batch-tokens", type=int, default=None, help="The token budget (default: from free memory).")
    parser.add_argument("--layout", default="shared", help="Template layout: shared or paper.")
    parser.add_argument("--history", type=int, default=3, help="Part 1's history pairs (the paper's: 3).")
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (as `illm annotate`).")
    parser.add_argument("--quant", default="none", help="none, 4bit or 8bit (bitsandbytes; CUDA).")
    options(parser)
    args = parser.parse_args()

    import torch

    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.devices import resolve_device
    from illm_tools.envs import renderer_of
    from illm_tools.llm.budget import describe
    from illm_tools.llm.dtype import resolve_dtype
    from illm_tools.llm.loading import load_model
    from illm_tools.tasks.prompts import SUMMARY_TOKENS

    args.device = resolve_device(args.device)
    args.dtype = resolve_dtype(args.dtype, args.device)
    lm = load_model(args.model, dtype=args.dtype, quant=args.quant, device=args.device, batch_tokens=args.batch_tokens)
    rate = matmul_rate(getattr(torch, args.dtype), device=args.device)
    params = sum(p.numel() for n, p in lm.model.named_parameters() if "embed" not in n)
    print(f"model {args.model} ({args.dtype}, quant {args.quant}) on {args.device}, {torch.get_num_threads()} threads; "
          f"{args.dtype} matmul rate {rate:.0f} GFLOP/s measured")
    print(describe(lm, 1000, 16))
    figures = {"matmul_gflops": rate}
    if args.naive_states:
        with tempfile.TemporaryDirectory() as tmp:
            records = babyai_states(args.states, args.history, Path(tmp))
            annotator = Annotator(lm, AnnotationCache(Path(tmp) / "ann"), model=args.model, layout=args.layout,
                                  batch_size=args.batch_size, chunk=args.states, history_len=args.history)
            plan = annotator.plan(annotator.visited(records, ["BabyAI-GoToLocal-v0"] * len(records),
                                                    [renderer_of("BabyAI-GoToLocal-v0")] * len(records)))
            jobs = [(s[0], s[1]) for s in plan]
            annotator.neutral_scores(jobs[0][0].prompt.candidates)  # once per model; not part of the timing
            start = time.perf_counter()
            rows = annotator.annotate(plan)
            t_illm = time.perf_counter() - start
            start = time.perf_counter()
            naive(lm, jobs[: args.naive_states])
            t_naive = time.perf_counter() - start
        prompt_tokens = sum(len(lm.encode(a.prompt.text)) for a, _ in jobs) / len(jobs)
        illm_rate, naive_rate = len(jobs) / t_illm, args.naive_states / t_naive
        lengths = [r["_tokens"] for r in rows if r["task"] == "summary"]  # generated tokens, end-of-text excluded
        ended = sum(n < SUMMARY_TOKENS for n in lengths)  # a summary cut by the limit has exactly SUMMARY_TOKENS
        print(f"part 1: {len(jobs)} BabyAI GoToLocal states, {args.history}-step history, action prompt "
              f"~{prompt_tokens:.0f} tokens, layout {args.layout}, batch {args.batch_size}")
        print(f"naive loop        {naive_rate:6.2f} states/s  ({args.naive_states} states, action ranking + summary)")
        print(f"illm annotate     {illm_rate:6.2f} states/s  ({len(jobs)} states, action ranking + summary)")
        print(f"speedup           {illm_rate / naive_rate:6.1f}x  (target >= 8x)")
        print(f"summaries         {sum(lengths) / len(lengths):6.1f} tokens on average (limit {SUMMARY_TOKENS}); "
              f"{ended}/{len(lengths)} ended at end-of-text")
        figures.update(naive_states_per_s=naive_rate, illm_states_per_s=illm_rate, speedup_over_naive=illm_rate / naive_rate,
                       prompt_tokens_mean=prompt_tokens, summary_tokens_mean=sum(lengths) / len(lengths))
    if args.cases:
        figures.update(engine_table(args, lm, rate, params))
    if not args.no_record:
        record("annotate", figures, ratio=headline(figures), out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()
