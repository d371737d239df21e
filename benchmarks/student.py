"""The student annotator's annotation rate against its teacher's and its base model's, in the same run.

States: distinct BabyAI states of a random-policy collection (UnlockLocal by default, history 0, the
setup `experiments/distil.sh` teaches), annotated for both tasks (action ranking and summary) by
- the teacher: the oracle (`--backend oracle`; the student's teacher in experiments/distil.sh);
- the base model (`smollm2-135m`) and the student (`smollm2-135m-babyai`, or `--student PATH`), each
  through `Annotator.annotate` (the path of `illm annotate` and of train's live fallback) with the same
  dtype, batch size and threads.
Prints states/s of each, the student's rate as a multiple of its base's (the figure issue 29 asks
for), and the mean length of each model's summaries: a student that writes its teacher's short
summaries stops generating sooner than a base model that runs to the 64-token limit.

    .venv/bin/python benchmarks/student.py [--states 64] [--student smollm2-135m-babyai] [--dtype float32]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

from annotate import babyai_states  # noqa: E402  (benchmarks/annotate.py: distinct states of a collection)
from record import options, record, settings  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--student", default="smollm2-135m-babyai", help="The student: an alias or folder.")
    parser.add_argument("--base", default="smollm2-135m", help="The student's base model.")
    parser.add_argument("--env", default="BabyAI-UnlockLocal-v0")
    parser.add_argument("--states", type=int, default=64, help="Distinct states each annotator answers.")
    parser.add_argument("--dtype", default="float32", help="float32 (a CPU without bf16), bfloat16 or auto.")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (as `illm annotate`).")
    options(parser)
    args = parser.parse_args()

    import torch

    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.devices import resolve_device
    from illm_tools.envs import renderer_of
    from illm_tools.llm.dtype import resolve_dtype
    from illm_tools.llm.spec import LLMSpec
    from illm_tools.tasks.prompts import SUMMARY_TOKENS

    args.device = resolve_device(args.device)
    args.dtype = resolve_dtype(args.dtype, args.device)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        records = babyai_states(args.states, 0, Path(tmp), env_id=args.env, seed=3_000_000,
                                steps=max(8 * args.states, 256))
        envs, renderers = [args.env] * len(records), [renderer_of(args.env)] * len(records)
        for name, model in (("teacher (oracle)", None), ("base", args.base), ("student", args.student)):
            spec = LLMSpec(backend="oracle") if model is None else LLMSpec(model=model, dtype=args.dtype,
                                                                           device=args.device)
            annotator = Annotator(spec.load(), AnnotationCache(Path(tmp) / f"ann-{len(results)}"),
                                  model=spec.model, batch_size=args.batch_size, chunk=len(records), history_len=0)
            plan = annotator.plan(annotator.visited(records, envs, renderers))
            if model is not None:
                annotator.neutral_scores(plan[0][0].prompt.candidates)  # once per model; not timed
            start = time.perf_counter()
            rows = annotator.annotate(plan)
            seconds = time.perf_counter() - start
            lengths = [r["_tokens"] for r in rows if r["task"] == "summary" and "_tokens" in r]
            results.append((name, spec.model, len(plan) / seconds, lengths))
    print(f"{len(records)} distinct {args.env} states (random policy, history 0), action ranking + summary, "
          f"{args.dtype} on {args.device}, batch {args.batch_size}, {torch.get_num_threads()} threads")
    for name, model, rate, lengths in results:
        said = (f"; summaries {sum(lengths) / len(lengths):.1f} tokens on average, "
                f"{sum(n < SUMMARY_TOKENS for n in lengths)}/{len(lengths)} ended at end-of-text") if lengths else ""
        print(f"{name:17s} {rate:9.2f} states/s  ({model}){said}")
    base, student = results[1][2], results[2][2]
    print(f"student / base    {student / base:9.2f}x  (same states, dtype and batch)")
    if not args.no_record:
        figures = {"states": len(records)}
        for (name, _, rate, lengths), key in zip(results, ("teacher", "base", "student")):
            figures[f"{key}_states_per_s"] = rate
            if lengths:
                figures[f"{key}_summary_tokens_mean"] = sum(lengths) / len(lengths)
        record("student", figures, ratio={"name": "student / base states/s", "value": student / base},
               out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()
