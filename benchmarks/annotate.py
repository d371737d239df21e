"""`illm annotate` against the loop a user would write first, on the same states, model and dtype.

States: distinct BabyAI GoToLocal steps from a random-policy collection, with the paper's 3-step
history (prompts of about 370 tokens). Both sides answer both language tasks for every state:
- naive: one full forward per candidate action (log-softmax, gather), then one `generate` of 64
  greedy tokens per state and one forward over prompt + summary for the mean-pooled embedding;
- illm: `Annotator.annotate` (context KV reused for all candidates, states batched by length, the
  prompt prefix shared by the two tasks computed once, batched greedy decoding).
Prints states/s of both and the speedup, illm's mean summary length and the share of summaries
that ended at end-of-text (rather than at the 64-token limit), and the share of this machine's
matmul rate in the dtype (measured in the same run) that illm's forward passes reach (2 x non-embedding
parameters x tokens fed, attention left out). Targets: speedup >= 8x; >= 4 states/s for both tasks together.

    .venv/bin/python benchmarks/annotate.py [--states 32] [--naive-states 4] [--batch-size 8]
    .venv/bin/python benchmarks/annotate.py --device cuda [--quant 4bit] [--history 0] --batch-size 32

On CUDA it also prints the peak GPU memory (torch.cuda.max_memory_allocated) of the illm run.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="smollm2-135m")
    parser.add_argument("--dtype", default="auto", help="auto: what `illm annotate` picks on this machine.")
    parser.add_argument("--states", type=int, default=32, help="States annotated by illm.")
    parser.add_argument("--naive-states", type=int, default=4, help="States annotated by the naive loop (slow).")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--layout", default="shared", help="Template layout: shared or paper.")
    parser.add_argument("--history", type=int, default=3, help="History pairs in the prompts (the paper's: 3).")
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (as `illm annotate`).")
    parser.add_argument("--quant", default="none", help="none, 4bit or 8bit (bitsandbytes; CUDA).")
    args = parser.parse_args()

    import torch

    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.devices import resolve_device
    from illm_tools.envs import renderer_of
    from illm_tools.llm.loading import load_model
    from illm_tools.llm.dtype import resolve_dtype
    from illm_tools.tasks.prompts import SUMMARY_TOKENS

    args.device = resolve_device(args.device)
    args.dtype = resolve_dtype(args.dtype, args.device)
    lm = load_model(args.model, dtype=args.dtype, quant=args.quant, device=args.device)
    rate = matmul_rate(getattr(torch, args.dtype), device=args.device)
    gpu = args.device.startswith("cuda")
    with tempfile.TemporaryDirectory() as tmp:
        records = babyai_states(args.states, args.history, Path(tmp))
        annotator = Annotator(lm, AnnotationCache(Path(tmp) / "ann"), model=args.model, layout=args.layout,
                              batch_size=args.batch_size, chunk=args.states, history_len=args.history)
        plan = annotator.plan(annotator.visited(records, ["BabyAI-GoToLocal-v0"] * len(records),
                                                [renderer_of("BabyAI-GoToLocal-v0")] * len(records)))
        jobs = [(s[0], s[1]) for s in plan]
        tokens = [0]

        def count(_module, _args, kwargs):
            tokens[0] += kwargs["input_ids"].numel()

        hook = lm.model.register_forward_pre_hook(count, with_kwargs=True)
        annotator.neutral_scores(jobs[0][0].prompt.candidates)  # once per model; not part of the timing
        tokens[0] = 0
        if gpu:
            torch.cuda.reset_peak_memory_stats()
        start = time.perf_counter()
        rows = annotator.annotate(plan)
        t_illm = time.perf_counter() - start
        peak = torch.cuda.max_memory_allocated() / 2**30 if gpu else None
        hook.remove()
        start = time.perf_counter()
        naive(lm, jobs[: args.naive_states])
        t_naive = time.perf_counter() - start

    params = sum(p.numel() for n, p in lm.model.named_parameters() if "embed" not in n)
    prompt_tokens = sum(len(lm.encode(a.prompt.text)) for a, _ in jobs) / len(jobs)
    illm_rate = len(jobs) / t_illm
    naive_rate = args.naive_states / t_naive
    achieved = 2 * params * tokens[0] / t_illm / 1e9
    lengths = [r["_tokens"] for r in rows if r["task"] == "summary"]  # generated tokens, end-of-text excluded
    ended = sum(n < SUMMARY_TOKENS for n in lengths)  # a summary cut by the limit has exactly SUMMARY_TOKENS
    print(f"model {args.model} ({args.dtype}, quant {args.quant}) on {args.device}, {len(jobs)} BabyAI GoToLocal "
          f"states, {args.history}-step history, action prompt ~{prompt_tokens:.0f} tokens, layout {args.layout}, "
          f"batch {args.batch_size}, {torch.get_num_threads()} threads")
    print(f"naive loop        {naive_rate:6.2f} states/s  ({args.naive_states} states, action ranking + summary)")
    print(f"illm annotate     {illm_rate:6.2f} states/s  ({len(jobs)} states, action ranking + summary)")
    print(f"speedup           {illm_rate / naive_rate:6.1f}x  (target >= 8x; illm target >= 4 states/s)")
    print(f"summaries         {sum(lengths) / len(lengths):6.1f} tokens on average (limit {SUMMARY_TOKENS}); "
          f"{ended}/{len(lengths)} ended at end-of-text")
    print(f"{args.dtype} matmul rate {rate:6.0f} GFLOP/s measured; illm forward passes reach {achieved:.0f} GFLOP/s "
          f"= {100 * achieved / rate:.0f}% of it ({tokens[0] / len(jobs):.0f} tokens fed per state)")
    if peak is not None:
        print(f"peak GPU memory   {peak:6.2f} GiB (torch.cuda.max_memory_allocated, illm annotate)")


if __name__ == "__main__":
    main()
