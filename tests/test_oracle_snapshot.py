"""The BabyAI/MiniGrid oracle's answers pinned on recorded states: each state's prompts (BabyAI levels
from the renderer's bot trajectories, tests/snapshots/babyai_text.json, and MiniGrid levels walked
with seeded actions; history 2, both layouts), the action ranking (every log-probability, the
chosen action), the summary, goal and plan texts and their embeddings, at noise 0 and 0.5, and
the backend's fingerprint, in tests/snapshots/oracle_answers.json.

Recorded while the planner lived in `illm_tools/llm/` and checked after it moved to
`illm_tools/oracles/` (issue 70): a move changes no answer. A mismatch means an answer changed:
bump the oracle's version (`PLANNER_VERSION` for BabyAI, `ORACLE_VERSION` for how answers are
made), then regenerate with `ILLM_UPDATE_SNAPSHOTS=1 .venv/bin/pytest tests/test_oracle_snapshot.py`.
A fingerprint alone that differs is another oracle registered or bumped (the backend's fingerprint
names every oracle's version): regenerate.

Embeddings are compared bit for bit where the sentence model computes the bits it computed when the
file was written (a probe sentence's embedding tells), and by three fixed projections (to 1e-5)
on a machine whose kernels round otherwise.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
from pathlib import Path

import numpy as np
import pytest

from illm_tools.keys import fingerprint_hash
from illm_tools.llm.backend import load_backend
from illm_tools.llm.oracle import oracle_spec
from illm_tools.tasks.prompts import PromptBuilder
from illm_tools.tasks.state import StateRecord

SNAPSHOTS = Path(__file__).parent / "snapshots"
ANSWERS = SNAPSHOTS / "oracle_answers.json"
NOISES = (0.0, 0.5)
TEXT_TASKS = ("summary", "goal", "plan")
PROBE = "The agent must pick up the purple key."
MINIGRID = (("MiniGrid-DoorKey-5x5-v0", 1), ("MiniGrid-LavaGapS5-v0", 2), ("MiniGrid-Fetch-5x5-N2-v0", 3),
            ("MiniGrid-KeyCorridorS3R1-v0", 4))


def _digest(vector) -> str:
    return hashlib.sha256(np.ascontiguousarray(vector, dtype=np.float32).tobytes()).hexdigest()[:20]


def _projections(vector) -> list[float]:
    directions = np.random.default_rng(70).standard_normal((3, len(vector)))
    return [round(float(x), 7) for x in directions @ np.asarray(vector, dtype=np.float64)]


def _trajectories():
    """(env_id, mission, [(observation, action name)], last observation, valid actions) per recorded trajectory."""
    from illm_tools.envs import make_env

    for case in json.loads((SNAPSHOTS / "babyai_text.json").read_text()).values():
        env = make_env(case["env_id"])
        _, info = env.reset(seed=case["seed"])
        names = tuple(info["valid_actions"])
        env.close()
        yield case["env_id"], case["mission"], case["texts"], [names[a] for a in case["actions"]], names
    for env_id, seed in MINIGRID:
        env, rng = make_env(env_id), random.Random(seed)
        _, info = env.reset(seed=seed)
        names, texts, acts = tuple(info["valid_actions"]), [info["text"]], []
        for _ in range(8):
            act = rng.choice((0, 1, 2, 2, 2, 3, 5))
            _, _, term, trunc, info = env.step(act)
            acts.append(names[act])
            texts.append(info["text"])
            if term or trunc:
                break
        env.close()
        yield env_id, info["mission"], texts, acts, names


def _states() -> list[dict]:
    """Every step of every trajectory with the two steps before it, layouts alternating."""
    states = []
    for env_id, mission, texts, acts, names in _trajectories():
        for i in range(len(texts)):
            states.append({"env_id": env_id, "layout": ("shared", "paper")[i % 2], "mission": mission,
                           "history": list(zip(texts[max(0, i - 2):i], acts[max(0, i - 2):i])),
                           "observation": texts[i], "valid_actions": list(names)})
    return states


def _prompts(state: dict) -> dict:
    """The state's prompt of each task, as annotation renders it."""
    record = StateRecord(state["mission"], tuple(map(tuple, state["history"])), state["observation"],
                         tuple(state["valid_actions"]))
    builder = PromptBuilder(env_id=state["env_id"], renderer="babyai-text@1", model="oracle", model_fingerprint="f",
                            history_len=2, layout=state["layout"])
    return {t: builder.render(t, record) for t in ("action", *TEXT_TASKS)}


def _answers(states: list[dict], noise: float) -> dict:
    lm = load_backend("oracle", oracle_spec(noise))
    prompts = [_prompts(s) for s in states]
    scores = lm.score([p["action"].text for p in prompts], [list(p["action"].candidates) for p in prompts])
    texts = lm.generate([p[t].text for p in prompts for t in TEXT_TASKS])
    return {"fingerprint": lm.fingerprint, "fingerprint_hash": fingerprint_hash(lm.fingerprint),
            "rankings": [{"logprobs": list(map(float, s.sums)), "chosen": s.best} for s in scores],
            "texts": [{"text": g.text, "tokens": len(g.token_ids), "finished": g.finished,
                       "embedding": _digest(g.embedding), "projections": _projections(g.embedding)} for g in texts]}


def _compact(data: dict) -> str:
    """JSON with one line per state and per answer (a reviewable diff, a file of ~150 kB)."""
    def block(rows: list) -> str:
        return "[\n" + ",\n".join(json.dumps(r) for r in rows) + "\n]"

    answers = ",\n".join(f'"{noise}": {{' + ", ".join(
        f'"{k}": {block(v) if isinstance(v, list) else json.dumps(v)}' for k, v in a.items()) + "}"
        for noise, a in data["answers"].items())
    head = ", ".join(f'"{k}": {json.dumps(v)}' for k, v in data.items() if k not in ("states", "answers"))
    return f'{{{head},\n"states": {block(data["states"])},\n"answers": {{\n{answers}}}}}\n'


def _recorded() -> dict:
    if os.environ.get("ILLM_UPDATE_SNAPSHOTS"):
        from illm_tools.llm.sentence import shared_embedder

        states = _states()
        data = {"about": "tests/test_oracle_snapshot.py", "probe": _digest(shared_embedder().encode([PROBE])[0]),
                "states": states, "answers": {f"{p:g}": _answers(states, p) for p in NOISES}}
        ANSWERS.write_text(_compact(data))
    return json.loads(ANSWERS.read_text())


@pytest.mark.parametrize("noise", NOISES)
def test_the_oracle_answers_recorded_states_as_it_did(noise):
    from illm_tools.llm.sentence import shared_embedder

    recorded = _recorded()
    states, want = recorded["states"], recorded["answers"][f"{noise:g}"]
    assert len(states) >= 60 and {s["env_id"].split("-")[0] for s in states} == {"BabyAI", "MiniGrid"}
    got = _answers(states, noise)
    assert got["fingerprint"] == want["fingerprint"] and got["fingerprint_hash"] == want["fingerprint_hash"]
    assert got["rankings"] == want["rankings"]  # every log-probability to the bit, and the chosen action
    same_bits = _digest(shared_embedder().encode([PROBE])[0]) == recorded["probe"]
    for g, w in zip(got["texts"], want["texts"], strict=True):
        assert (g["text"], g["tokens"], g["finished"]) == (w["text"], w["tokens"], w["finished"])
        if same_bits:
            assert g["embedding"] == w["embedding"], g["text"]
        else:
            assert np.allclose(g["projections"], w["projections"], rtol=0, atol=1e-5), g["text"]


def test_the_recorded_answers_vary_with_the_state():
    """The pinned answers are worth pinning: the chosen action, the goal and the plan differ across states,
    and the noise changes some states' answers and keeps the others'."""
    answers = _recorded()["answers"]
    clean, noisy = answers["0"], answers["0.5"]
    assert len({r["chosen"] for r in clean["rankings"]}) >= 3
    assert len({t["text"] for t in clean["texts"][1::3]}) >= 8  # goals
    changed = [a != b for a, b in zip(clean["rankings"], noisy["rankings"])]
    assert 0.2 < np.mean(changed) < 0.8
    assert clean["fingerprint_hash"] != noisy["fingerprint_hash"]
