"""Benchmark of the LLM backend on this machine: model load, candidate scoring, generation.

Every figure is reported next to a baseline measured in the same run:
scoring with the context KV cache reused vs one full forward per candidate, batched (sorted by
length) vs one state at a time; generation batched vs transformers' own `generate`.

    .venv/bin/python benchmarks/llm_backend.py --model smollm2-135m --dtype bfloat16
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import tempfile
import time

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from record import options, record, settings  # noqa: E402

ACTIONS = ["turn left", "turn right", "go forward", "pick up", "drop", "toggle"]
COLOURS = ["red", "green", "blue", "purple", "yellow", "grey"]
OBJECTS = ["ball", "box", "key", "door"]


def babyai_prompt(rng: random.Random, n_objects: int) -> str:
    """The paper's action prompt (B.2) around a 3-step BabyAI-Text history."""
    def observation() -> str:
        seen = [f"a {rng.choice(COLOURS)} {rng.choice(OBJECTS)} {rng.randint(1, 4)} steps "
                f"{rng.choice(['left', 'right'])} and {rng.randint(1, 5)} steps forward" for _ in range(n_objects)]
        return "You see a wall 3 steps forward, " + ", ".join(seen)

    history = "\n".join(f"Observation {i}: {observation()}\nAction {i}: {rng.choice(ACTIONS)}" for i in range(3))
    return ("You are an expert player playing BabyAI, go to the red ball\n"
            f"Valid actions: {', '.join(ACTIONS)}\nYou see: {history}\n"
            "Suggest the best action the player can take. Do not recommend actions that are not possible "
            "or not desirable, such as ''Eat door''. Prioritize actions which involve the object you are "
            "facing or which the agent has not achieved before. What do you do?\nAction:")


def plain_score(lm, context: str, candidates: list[str]) -> list[float]:
    """Baseline: one full forward per candidate over context + candidate (logits computed only
    where they are used, so the baseline is not slowed by the unused vocabulary projections)."""
    import torch

    ctx = lm.encode(context)
    sums = []
    for cand in candidates:
        ids = lm.encode(context + cand)
        keep = len(ids) - len(ctx) + 1
        with torch.inference_mode():
            logits = lm.model(input_ids=torch.tensor([ids]), logits_to_keep=keep).logits[0, :-1].float()
        logprobs = torch.log_softmax(logits, -1)
        sums.append(sum(float(logprobs[i, t]) for i, t in enumerate(ids[len(ctx):])))
    return sums


def timed(fn, repeats: int = 1) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def matmul_gflops(dtype_name: str) -> float:
    """Calibration: the machine's matmul speed now (others' jobs share these cores)."""
    import torch

    dtype = getattr(torch, dtype_name)
    a, b = torch.randn(2048, 576, dtype=dtype), torch.randn(576, 1536, dtype=dtype)
    return 2 * 2048 * 576 * 1536 / timed(lambda: a @ b, repeats=20) / 1e9


def main() -> None:
    import torch

    from illm_tools.llm.driver import generate
    from illm_tools.llm.loading import load_model
    from illm_tools.llm.driver import score_candidates

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="smollm2-135m")
    parser.add_argument("--dtype", default="bfloat16")
    parser.add_argument("--quant", default="none")
    parser.add_argument("--states", type=int, default=24, help="states scored with the KV cache reused")
    parser.add_argument("--plain-states", type=int, default=6, help="states scored by the plain baseline")
    parser.add_argument("--objects", type=int, default=5, help="objects per observation (about 330 tokens)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--cache-dir", default=None, help="illm cache; default: a fresh temporary folder")
    parser.add_argument("--skip", default="", help="comma list of sections to skip: load,score,generate")
    options(parser)
    args = parser.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    if args.threads:
        torch.set_num_threads(args.threads)
    out: dict = {"model": args.model, "dtype": args.dtype, "quant": args.quant, "threads": torch.get_num_threads(),
                 "matmul_bf16_gflops_before": matmul_gflops("bfloat16")}

    cache_dir = args.cache_dir or tempfile.mkdtemp(prefix="illm-bench-")
    start = time.perf_counter()
    lm = load_model(args.model, dtype=args.dtype, quant=args.quant, cache_dir=cache_dir)
    out["load_first_s"] = time.perf_counter() - start
    if "load" not in skip:
        out["load_cached_s"] = timed(lambda: load_model(args.model, dtype=args.dtype, quant=args.quant,
                                                        cache_dir=cache_dir), repeats=3)

    rng = random.Random(0)
    contexts = [babyai_prompt(rng, args.objects - rng.randint(0, 1)) for _ in range(args.states)]
    candidates = [[" " + a for a in ACTIONS]] * len(contexts)
    out["prompt_tokens_mean"] = statistics.mean(len(lm.encode(c)) for c in contexts)
    if "score" not in skip:
        score_candidates(lm, contexts[:2], candidates[:2])  # warm-up
        n_plain = min(args.plain_states, len(contexts))
        plain = timed(lambda: [plain_score(lm, c, k) for c, k in zip(contexts[:n_plain], candidates)])
        out["score_plain_states_per_s"] = n_plain / plain
        for bs in (1, 4, 8):
            t = timed(lambda: score_candidates(lm, contexts, candidates, batch_size=bs))
            out[f"score_kv_bs{bs}_states_per_s"] = len(contexts) / t
        out["score_kv_bs8_vs_plain"] = out["score_kv_bs8_states_per_s"] / out["score_plain_states_per_s"]
        out["score_kv_bs8_vs_bs1"] = out["score_kv_bs8_states_per_s"] / out["score_kv_bs1_states_per_s"]

    if "generate" not in skip:
        from transformers import GenerationConfig

        prompts = contexts[:16]
        for bs in (8, 16):
            out[f"generate_16x64_bs{bs}_s"] = timed(lambda: generate(lm, prompts, max_new_tokens=64, batch_size=bs))
        gens = generate(lm, prompts, max_new_tokens=64, batch_size=16)
        out["generated_tokens_mean"] = statistics.mean(len(g.token_ids) for g in gens)
        ids = [lm.encode(p) for p in prompts]  # baseline: transformers' generate, left padded, no embedding
        width = max(map(len, ids))
        input_ids = torch.tensor([[lm.pad_id] * (width - len(r)) + r for r in ids])
        mask = torch.tensor([[0] * (width - len(r)) + [1] * len(r) for r in ids])
        config = GenerationConfig(do_sample=False, max_new_tokens=64, eos_token_id=list(lm.eos_ids),
                                  pad_token_id=lm.pad_id)
        with torch.inference_mode():
            out["hf_generate_16x64_bs16_s"] = timed(lambda: lm.model.generate(
                input_ids=input_ids, attention_mask=mask, generation_config=config))
    out["matmul_bf16_gflops_after"] = matmul_gflops("bfloat16")
    print(json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}, indent=1))
    if not args.no_record:
        figures = {k: v for k, v in out.items() if isinstance(v, (int, float))}
        ratio = {"name": "scoring states/s, context KV reused (batch 8) / one forward per candidate",
                 "value": out["score_kv_bs8_vs_plain"]} if "score_kv_bs8_vs_plain" in out else None
        record("llm_backend", figures, ratio=ratio, out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()
