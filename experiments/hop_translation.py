"""How much of an observation iLLM(hop)'s Hopfield translation keeps, per model, suite and beta.

For each suite, `--steps` random-policy observations of one level (each suite's `hop_frame`: what
the translation reads, Crafter's pictures grey-scaled), each with its previous action; for each model
its frozen input-embedding matrix E and the translation x_t = E^T softmax(beta cos(E, P [o; a]))
(`illm_tools.hop.translate.FrozenHopfield`, seed 0). Printed per (model, suite, beta):

- effective tokens: 1 / sum(w^2) of the softmax weights w over the vocabulary, median over the
  observations (the vocabulary size means uniform: the translation forgets the observation);
- spread: 1 - cos between the translations of two different observations, median and max over all
  pairs of distinct observations (near 0: every observation looks the same to the LLM);
- the same observation translated twice gives the same x_t (max |difference|).

    python experiments/hop_translation.py [--model smollm2-135m --model gemma3-270m] [--steps 40]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

LEVELS = {"babyai": "MiniGrid-MultiRoom-N6-v0", "atari": "ALE/MontezumaRevenge-v5", "crafter": "CrafterReward-v1",
          "minihack": "MiniHack-River-Monster-v0"}


def observations(env_id: str, steps: int, seed: int = 0):
    """`steps` (hop frame, previous action) pairs of a random-policy episode (reset when it ends)."""
    import numpy as np

    from illm_tools.envs import make_env, suite_of

    suite = suite_of(env_id)
    env = make_env(env_id, render_text=False)
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out, prev = [], -1
    for _ in range(steps):
        out.append((suite.hop_frame(suite.raw_obs(suite.policy_obs(obs))), prev))
        prev = int(rng.integers(env.action_space.n))
        obs, _, term, trunc, _ = env.step(prev)
        if term or trunc:
            obs, _ = env.reset()
            prev = -1
    env.close()
    return out, int(env.action_space.n)


def measure(embeddings, frames, num_actions: int, beta: float) -> dict:
    import numpy as np
    import torch

    from illm_tools.hop.translate import FrozenHopfield

    obs = torch.as_tensor(np.stack([f.reshape(-1) for f, _ in frames]))
    prev = torch.as_tensor([a for _, a in frames])
    hop = FrozenHopfield(embeddings, obs.shape[1], num_actions, seed=0, beta=beta)
    x = hop(obs, prev)
    query = torch.nn.functional.normalize(torch.cat([obs.float(), torch.nn.functional.one_hot(
        prev.clamp_min(0), num_actions).float() * (prev >= 0)[:, None]], 1) @ hop.projection.T, dim=1)
    weights = torch.softmax(beta * (query @ hop.unit.T), dim=1)
    effective = (1.0 / (weights.double() ** 2).sum(1)).median().item()
    unit = torch.nn.functional.normalize(x.double(), dim=1)
    distinct = [(i, j) for i in range(len(frames)) for j in range(i + 1, len(frames))
                if not (np.array_equal(frames[i][0], frames[j][0]) and frames[i][1] == frames[j][1])]
    gaps = torch.tensor([1.0 - float(unit[i] @ unit[j]) for i, j in distinct], dtype=torch.float64)
    again = (hop(obs, prev) - x).abs().max().item()
    return {"vocab": int(embeddings.shape[0]), "effective_tokens": effective, "spread_median": gaps.median().item(),
            "spread_min": gaps.min().item(), "spread_max": gaps.max().item(), "pairs": len(distinct), "same_again": again}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", action="append", help="Model alias (repeatable; default smollm2-135m, gemma3-270m).")
    parser.add_argument("--suite", action="append", choices=sorted(LEVELS), help="Default: all four.")
    parser.add_argument("--beta", action="append", type=float, help="Default: 1, 10, 100.")
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()

    import torch

    from illm_tools.llm.backend import load_backend

    torch.set_num_threads(2)
    data = {suite: observations(LEVELS[suite], args.steps) for suite in (args.suite or list(LEVELS))}
    print("| model | suite (level) | beta | vocabulary | effective tokens (median) | 1 - cos between different "
          "observations: median [min, max] | same observation twice: max abs diff |")
    print("|---|---|---|---|---|---|---|")
    for model in args.model or ["smollm2-135m", "gemma3-270m"]:
        embeddings = load_backend("transformers", model, dtype="float32").input_embeddings().detach().float()
        for suite, (frames, num_actions) in data.items():
            for beta in args.beta or [1.0, 10.0, 100.0]:
                m = measure(embeddings, frames, num_actions, beta)
                print(f"| {model} | {suite} ({LEVELS[suite]}) | {beta:g} | {m['vocab']:,} | {m['effective_tokens']:,.0f} | "
                      f"{m['spread_median']:.2e} [{m['spread_min']:.2e}, {m['spread_max']:.2e}] ({m['pairs']} pairs) | "
                      f"{m['same_again']:.1e} |", flush=True)


if __name__ == "__main__":
    main()
