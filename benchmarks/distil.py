"""`illm distil`'s training step against a plain causal-LM fine-tuning step on the same states,
measured in the same run: what the full-size distillation's budget is planned from.

Measured: one optimiser step's forward and backward of `illm_tools.distil.loss.lesson_loss` (the
annotator's scoring path with autograd on: the states' shared prompt part once, then each task's
rest, the action candidates behind the repeated KV cache, the summary by teacher forcing) on
`--batch` states of an oracle cache, SmolLM2-135M in float32 with LoRA rank 16 on every linear
layer (`illm distil`'s defaults), 2 threads. Baseline: the same states as a plain LoRA fine-tuning
step (each task's whole prompt and target as one right-padded sequence, transformers' own LM loss),
same model and adapters. Prints tokens/s of both (tokens the model reads), seconds per step and
seconds per state: at the full run's settings the training takes about states x seconds per state.

    python benchmarks/distil.py [--batch 8] [--repeats 3]
    ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2 python benchmarks/distil.py   # a CPU without bf16 or AVX-512
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

from record import options, record, settings  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=8, help="States per step (illm distil's --batch-size).")
    parser.add_argument("--repeats", type=int, default=3, help="Steps timed per path (the fastest is kept).")
    options(parser)
    args = parser.parse_args()

    import torch

    from illm_tools.annotate.bulk import AnnotateConfig, annotate_dataset
    from illm_tools.tasks.prompt_config import PromptConfig
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.collect import CollectConfig, collect
    from illm_tools.distil.lessons import COLUMNS, lessons_of, tokenise
    from illm_tools.distil.loss import lesson_loss
    from illm_tools.distil.training import quiet_libraries
    from illm_tools.llm.loading import load_model
    from illm_tools.llm.spec import LLMSpec

    torch.set_num_threads(2)
    with tempfile.TemporaryDirectory() as tmp:
        for env in ("BabyAI-UnlockLocal-v0", "BabyAI-GoToLocal-v0"):
            data = Path(tmp) / env
            collect(CollectConfig(env_id=env, out=data, steps=200, num_envs=4, seed=1_000_000, policy="bot"))
            annotate_dataset(AnnotateConfig(data=data, cache=Path(tmp) / "ann", llm=LLMSpec(backend="oracle"), setup=PromptConfig(history_len=0)))
        rows = AnnotationCache(Path(tmp) / "ann").table(COLUMNS).to_pylist()
    lm = load_model("smollm2-135m", dtype="float32")
    lessons = lessons_of(rows, ("action", "summary"))[:args.batch]
    examples = [tokenise(lm, lesson) for lesson in lessons]
    tokens = sum(e.tokens for e in examples)
    with quiet_libraries():
        from peft import LoraConfig, get_peft_model

        model = get_peft_model(lm.model, LoraConfig(r=16, lora_alpha=32, target_modules="all-linear",
                                                    task_type="CAUSAL_LM"))
    model.train()
    student = replace(lm, model=model)
    sequences = [[*e.shared, *b.suffix, *b.continuations[0]] for e in examples for b in e.branches]
    width = max(map(len, sequences))
    ids = torch.full((len(sequences), width), lm.pad_id)
    mask = torch.zeros_like(ids)
    for i, s in enumerate(sequences):
        ids[i, :len(s)], mask[i, :len(s)] = torch.tensor(s), 1
    plain_tokens = int(mask.sum())

    def illm_step() -> None:
        lesson_loss(student, examples, grad=True).loss.backward()

    def plain_step() -> None:
        model(input_ids=ids, attention_mask=mask, labels=ids.masked_fill(mask == 0, -100)).loss.backward()

    times = {"illm": [], "plain": []}
    with quiet_libraries():
        illm_step(), plain_step()  # warm-up
        model.zero_grad()
        for _ in range(args.repeats):
            for name, step in (("illm", illm_step), ("plain", plain_step)):
                start = time.perf_counter()
                step()
                times[name].append(time.perf_counter() - start)
                model.zero_grad()
    best = {k: min(v) for k, v in times.items()}
    print(f"{args.batch} states; illm distil's step: {tokens:,} tokens in {best['illm']:.2f} s, "
          f"{tokens / best['illm']:,.0f} tokens/s, {best['illm'] / args.batch:.2f} s/state")
    print(f"plain LoRA LM step on the same states (no shared prefix, {len(sequences)} sequences): {plain_tokens:,} "
          f"tokens in {best['plain']:.2f} s, {plain_tokens / best['plain']:,.0f} tokens/s")
    print(f"step time illm/plain: {best['illm'] / best['plain']:.2f}; load average {os.getloadavg()[0]:.1f}")
    if not args.no_record:
        record("distil", {"illm_tokens": tokens, "illm_step_s": best["illm"], "illm_tokens_per_s": tokens / best["illm"],
                          "illm_s_per_state": best["illm"] / args.batch, "plain_tokens": plain_tokens,
                          "plain_step_s": best["plain"], "plain_tokens_per_s": plain_tokens / best["plain"]},
               ratio={"name": "illm distil / plain LoRA step time", "value": best["illm"] / best["plain"],
                      "direction": "at_most"},
               out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()
