"""The oracle backend (`--backend oracle`): its planner on hand-written BabyAI-Text states of every
mission kind, its reading of real renderer output and of both prompt layouts, the noise knob, its
keys, its refusals, the probe against the BabyAI bot, and a run with a target on every step."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.keys import fingerprint_hash
from illm_tools.errors import UsageError
from illm_tools.llm.backend import backend_fingerprint, load_backend, resolve_model
from illm_tools.llm.oracle import OracleBackend, oracle_spec
from illm_tools.oracles.babyai_planner import Planner, parse_mission, parse_view
from illm_tools.oracles.base import Scene, parse_prompt
from illm_tools.tasks.prompts import PromptBuilder
from illm_tools.tasks.state import StateRecord

runner = CliRunner()
SIX = ("turn left", "turn right", "go forward", "pick up", "drop", "toggle")
THREE = SIX[:3]


def best(mission: str, observation: str, actions=SIX, history=()) -> str:
    answer = Planner().answer(Scene("BabyAI", mission, tuple(history), observation, tuple(actions)))
    return min(answer.costs, key=answer.costs.get)


@pytest.mark.parametrize("mission, observation, actions, expected", [
    # go to: walk up to the object and face it
    ("go to the red ball", "You see a wall 3 steps forward, You see a red ball 2 steps forward", THREE, "go forward"),
    ("go to the red ball", "You see a red ball 2 steps right", THREE, "turn right"),
    ("go to a ball", "You see a wall 1 step left, You see a blue ball 1 step left and 2 steps forward", THREE,
     "go forward"),
    ("go to the green key", "You see a purple box 1 step forward, You see a green key 3 steps left", THREE,
     "turn left"),
    # pick up: face it, then pick it up
    ("pick up the blue key", "You see a blue key 1 step forward", SIX, "pick up"),
    ("pick up a box", "You see a grey box 1 step right", SIX, "turn right"),
    # open: face the door, toggle it
    ("open the red door", "You see a closed red door 1 step forward", SIX, "toggle"),
    ("open the red door", "You see a wall 2 steps forward, You see a closed red door 1 step left and 2 steps forward",
     SIX, "go forward"),
    # unlock: the key of the locked door's colour first, then the door
    ("open the door", "You see a locked yellow door 3 steps forward, You see a yellow key 2 steps left", SIX,
     "turn left"),
    ("open the door", "You see a locked yellow door 3 steps forward, You see a yellow key 1 step forward", SIX,
     "pick up"),
    ("open the door", "You carry a yellow key, You see a locked yellow door 1 step forward", SIX, "toggle"),
    ("open the door", "You carry a yellow key, You see a locked yellow door 2 steps forward", SIX, "go forward"),
    # put next: pick the first object up, then drop it next to the second
    ("put the red ball next to the blue box", "You see a red ball 1 step forward, You see a blue box 2 steps right",
     SIX, "pick up"),
    ("put the red ball next to the blue box", "You carry a red ball, You see a blue box 2 steps forward", SIX, "drop"),
    ("put the red ball next to the blue box", "You carry a red ball, You see a blue box 2 steps right", SIX,
     "turn right"),  # face the free cell between agent and box, then drop
    ("put the red ball next to the blue box", "You carry a red ball, You see a blue box 1 step left and 3 steps "
     "forward", SIX, "go forward"),
    # DoorKey: key, door, goal
    ("use the key to open the door and then get to the goal", "You see a yellow key 1 step forward", SIX, "pick up"),
    ("use the key to open the door and then get to the goal",
     "You carry a yellow key, You see a locked yellow door 1 step forward", SIX, "toggle"),
    ("use the key to open the door and then get to the goal",
     "You see an open yellow door 1 step forward, You see a green goal 1 step right and 3 steps forward", SIX,
     "go forward"),
    ("get to the green goal square", "You see a green goal 2 steps left", THREE, "turn left"),
])
def test_the_planner_answers_each_mission_kind(mission, observation, actions, expected):
    assert best(mission, observation, actions) == expected


def test_out_of_view_it_turns_toward_the_room_or_where_the_target_went():
    # nothing in view: the side with more room (the BabyAI bot's rule), ties to the right
    assert best("go to the red ball", "You see a wall 1 step forward, You see a wall 1 step right", THREE) == "turn left"
    assert best("go to the red ball", "You see a wall 1 step forward, You see a wall 1 step left", THREE) == "turn right"
    # the history saw the ball 2 steps right; the agent then turned left: it is now behind, on the right
    history = [("You see a red ball 2 steps right", "turn left")]
    assert best("go to the red ball", "You see a wall 1 step forward", THREE, history) == "turn right"
    history = [("You see a red ball 2 steps left", "turn right"), ("You see a wall 3 steps forward", "turn right")]
    assert best("go to the red ball", "You see a wall 2 steps forward", THREE, history) == "turn right"


def test_useless_and_irrelevant_actions_cost_more_than_the_best():
    nine = SIX + ("sleep", "do nothing", "think")
    answer = Planner().answer(Scene("BabyAI", "go to the red ball", (), "You see a red ball 2 steps forward", nine))
    assert answer.costs["go forward"] < min(answer.costs[a] for a in nine if a != "go forward")
    assert all(answer.costs[a] >= answer.costs["go forward"] + 2 for a in ("sleep", "do nothing", "think"))


def test_compound_and_minigrid_missions_parse_in_order():
    assert [i.text for i in parse_mission("open the red door, then pick up the blue key")] == [
        "open the red door", "pick up the blue key"]
    assert [i.text for i in parse_mission("pick up the ball after you go to the grey key")] == [
        "go to the grey key", "pick up the ball"]
    assert [i.verb for i in parse_mission("use the key to open the door and then get to the goal")] == ["open", "enter"]
    assert parse_mission("do a barrel roll") == ()


def test_it_reads_what_the_renderer_writes():
    """parse_view inverts BabyAI-Text on real observations: every object of the view, where it is."""
    from minigrid.core.constants import IDX_TO_COLOR, IDX_TO_OBJECT

    from illm_tools.envs.babyai import describe, make_babyai_text

    for env_id in ("BabyAI-GoToLocal-v0", "BabyAI-UnlockLocal-v0", "BabyAI-PutNextLocal-v0"):
        env = make_babyai_text(env_id)
        obs, info = env.reset(seed=3)
        for step in range(40):
            image = obs["image"]
            view = parse_view(info["text"])
            assert len(view.things) + (view.carrying is not None) + sum(w is not None for w in view.walls) == \
                len(describe(image))
            for t in view.things:
                cell = image[3 + t.x, 6 - t.y]
                assert (IDX_TO_OBJECT[int(cell[0])], IDX_TO_COLOR[int(cell[1])]) == (t.kind, t.colour)
            obs, _, term, trunc, info = env.step(step % 3 if step % 5 else 2)
            if term or trunc:
                obs, info = env.reset(seed=step)
        env.close()


@pytest.mark.parametrize("layout", ["shared", "paper"])
def test_it_reads_both_prompt_layouts(layout):
    record = StateRecord("open the door", (("You see a yellow key 1 step forward", "pick up"),),
                         "You carry a yellow key, You see a locked yellow door 2 steps forward", SIX)
    builder = PromptBuilder(env_id="BabyAI-UnlockLocal-v0", renderer="babyai-text@1", model="oracle",
                            model_fingerprint="f", history_len=1, layout=layout)
    for task in ("action", "summary", "goal", "plan"):
        scene = parse_prompt(builder.render(task, record).text)
        assert (scene.game, scene.mission, scene.history, scene.observation) == \
            ("BabyAI", record.mission, record.history, record.observation)
        assert scene.actions == (SIX if task == "action" else ())


def _records() -> list[StateRecord]:
    """756 distinct GoToLocal-like states: a mission object somewhere in view."""
    colours, kinds = ("red", "green", "blue", "grey", "purple", "yellow"), ("ball", "key", "box")
    out = []
    for c in colours:
        for k in kinds:
            for dx in range(-3, 4):
                for fwd in range(1, 7):
                    side = "" if dx == 0 else f"{abs(dx)} step{'s' if abs(dx) > 1 else ''} {'left' if dx < 0 else 'right'} and "
                    out.append(StateRecord(f"go to the {c} {k}", (), f"You see a {c} {k} {side}{fwd} steps forward",
                                           THREE))
    return out


def _rankings(lm, records):
    builder = PromptBuilder(env_id="BabyAI-GoToLocal-v0", renderer="babyai-text@1", model=lm.model,
                            model_fingerprint="f", history_len=0)
    prompts = [builder.render("action", r) for r in records]
    return [tuple(s.sums) for s in lm.score([p.text for p in prompts], [list(p.candidates) for p in prompts])]


def test_noise_replaces_a_keyed_share_of_the_answers_the_same_way_twice():
    records = _records()
    assert len(set(records)) == len(records) == 756
    clean = _rankings(OracleBackend(), records)
    for p in (0.25, 0.5, 1.0):
        noisy = _rankings(OracleBackend(oracle_spec(p)), records)
        changed = np.mean([a != b for a, b in zip(clean, noisy)])
        assert abs(changed - p) < 0.05, (p, changed)  # a random answer differs from the planner's
        assert noisy == _rankings(OracleBackend(oracle_spec(p)), records)  # the same state, the same answer
    for sums in clean:  # log-probabilities: they sum to one, the best action holds most of the mass
        probs = np.exp(sums)
        assert abs(probs.sum() - 1) < 1e-6 and probs.max() > 0.5


def test_a_noised_state_is_noised_for_every_task():
    lm = OracleBackend(oracle_spec(0.5))
    builder = PromptBuilder(env_id="BabyAI-GoToLocal-v0", renderer="babyai-text@1", model=lm.model,
                            model_fingerprint="f", history_len=0)
    records = _records()[::20]
    noised = [lm._noised(lm._scene(builder.render("action", r).text)) is not None for r in records]
    summaries = [builder.render("summary", r).text for r in records]
    changed = [a.text != b.text for a, b in zip(lm.generate(summaries), OracleBackend().generate(summaries))]
    assert noised == changed and 0 < sum(noised) < len(records)


def test_texts_and_embeddings_are_deterministic_unit_vectors():
    lm = OracleBackend()
    builder = PromptBuilder(env_id="BabyAI-UnlockLocal-v0", renderer="babyai-text@1", model="oracle",
                            model_fingerprint="f", history_len=1)
    record = StateRecord("open the door", (("You see a wall 2 steps forward", "turn left"),),
                         "You see a locked purple door 3 steps forward, You see a purple key 1 step right", SIX)
    prompts = [builder.render(t, record).text for t in ("summary", "goal", "plan")]
    summary, goal, plan = lm.generate(prompts)
    assert summary.text == ("The agent must pick up the purple key. It turned left. The purple key is adjacent to the "
                            "right. It carries nothing.")
    assert goal.text == "pick up the purple key, open the door"
    assert plan.text == "turn right, pick up"
    again = OracleBackend().generate(prompts)
    for a, b in zip((summary, goal, plan), again):
        assert a.text == b.text and np.allclose(a.embedding, b.embedding)
        assert a.embedding.shape == (384,) and abs(np.linalg.norm(a.embedding) - 1) < 1e-5 and a.finished


def test_a_states_embedding_is_the_same_bits_in_any_batch_and_any_process():
    """Runs filling one cache annotate a state among different batch-mates, and a fresh cache
    annotates it again: its targets must not depend on either (padded into one batch, a text's
    embedding moved by up to 1.3e-7 with its batch-mates, and a KeyCorridorS3R1 seed ended at 0.00
    or 1.00 on that alone). A cleared memo stands for another process."""
    from illm_tools.llm.sentence import shared_embedder

    lm = OracleBackend()
    builder = PromptBuilder(env_id="BabyAI-UnlockLocal-v0", renderer="babyai-text@1", model="oracle",
                            model_fingerprint="f", history_len=1)
    views = ["You see a locked purple door 3 steps forward, You see a purple key 1 step right",
             "You see a wall 1 step forward", "You see a purple key 2 steps left and 4 steps forward",
             "You carry a purple key, You see a locked purple door 1 step forward"]
    records = [StateRecord("open the door", (("You see a wall 2 steps forward", "turn left"),), v, SIX) for v in views]
    prompts = [builder.render(task, r).text for r in records for task in ("summary", "goal")]

    def embeddings(batches):
        shared_embedder()._memo.clear()
        return {p: g.embedding for batch in batches for p, g in zip(batch, lm.generate(batch))}

    alone = embeddings([[p] for p in prompts])
    for batches in ([prompts], [prompts[::-1]], [prompts[1::2], prompts[::2]]):
        together = embeddings(batches)
        assert all(np.array_equal(together[p], alone[p]) for p in prompts)


def test_oracle_keys_never_meet_an_llms_and_the_noise_is_in_them():
    oracle = {p: fingerprint_hash(backend_fingerprint("oracle", oracle_spec(p))) for p in (0, 0.5, 1)}
    assert len(set(oracle.values())) == 3
    assert oracle[0] not in (fingerprint_hash(backend_fingerprint("stub", "oracle")),
                             fingerprint_hash(backend_fingerprint("stub", "stub")))
    # the oracle has no dtype or quantisation: every --dtype reads its rows
    assert backend_fingerprint("oracle", "oracle", dtype="bfloat16") == backend_fingerprint("oracle", "oracle",
                                                                                           dtype="float32")
    assert resolve_model("oracle", None) == "oracle" and resolve_model("oracle", None, oracle_noise=0.5) == "oracle:noise=0.5"
    assert resolve_model("transformers", None) == "smollm2-135m"


def test_what_the_oracle_cannot_do_is_refused_in_one_line(tmp_path):
    with pytest.raises(UsageError, match="not 'smollm2-135m'"):
        load_backend("oracle", "smollm2-135m")
    with pytest.raises(UsageError, match="--oracle-noise is the oracle backend's"):
        resolve_model("transformers", None, oracle_noise=0.5)
    with pytest.raises(UsageError, match="must lie in"):
        oracle_spec(1.5)
    for args, message in (
            (["--mode", "hop"], "--mode hop translates"),
            (["--live-budget", "many"], "--live-budget is a number of states >= 0 or 'all'"),
            (["--oracle-noise", "2"], "--oracle-noise must be between 0 and 1")):
        out = runner.invoke(app, ["train", "--method", "illm", "--backend", "oracle", "--cache", str(tmp_path / "c"),
                                  "--history", "0", "--frames", "64", "--num-envs", "2", "--num-steps", "32",
                                  "--out", str(tmp_path / "run"), *args])
        assert out.exit_code == 1 and message in out.output and "Traceback" not in out.output, out.output
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


def test_annotate_and_cache_info_name_the_oracle(tmp_path):
    def ok(*args):
        out = runner.invoke(app, [str(a) for a in args])
        assert out.exit_code == 0, out.output
        return out.output

    ok("collect", "--env", "BabyAI-UnlockLocal-v0", "--steps", 256, "--num-envs", 4, "--out", tmp_path / "traj")
    said = ok("annotate", tmp_path / "traj", "--cache", tmp_path / "ann", "--backend", "oracle", "--oracle-noise", 0.5,
              "--history", 0, "--tasks", "action,summary,goal,plan")
    assert "the cache now answers" in said and "100% of the 256 steps" in said
    info = ok("cache", "info", tmp_path / "ann")
    assert "--backend oracle --oracle-noise 0.5" in info
    again = ok("annotate", tmp_path / "traj", "--cache", tmp_path / "ann", "--backend", "oracle", "--model",
               "oracle:noise=0.5", "--history", 0, "--tasks", "action,summary,goal,plan")
    assert "nothing to annotate" in again  # the same setup, spelled as a model spec


def test_a_run_with_budget_all_has_a_target_on_every_step(tmp_path):
    out = runner.invoke(app, ["train", "--env", "BabyAI-GoToLocal-v0", "--method", "illm", "--backend", "oracle",
                              "--cache", str(tmp_path / "ann"), "--history", "0", "--live-budget", "all",
                              "--live-mode", "sync", "--num-envs", "4", "--num-steps", "64", "--frames", "768",
                              "--out", str(tmp_path / "run")])
    assert out.exit_code == 0, out.output
    assert "steps with an LLM target 100% on average" in out.output
    with open(tmp_path / "run" / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 3 and all(float(r["target_coverage"]) == 1.0 for r in rows)
    assert float(rows[0]["live_annotations"]) > 0 and float(rows[0]["cache_hit_rate"]) == 0.0
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["targets"]["live_budget"] == "all" and config["llm"]["backend"] == "oracle"
    from illm_tools.rl.config import TrainConfig

    assert TrainConfig.from_dict(config).embedding_dim == 384  # derived: the oracle's sentence model's width


def test_the_probe_finds_the_oracle_agrees_with_the_bot(tmp_path):
    out = runner.invoke(app, ["probe", "--env", "BabyAI-GoToLocal-v0", "--backend", "oracle", "--states", "150",
                              "--out", str(tmp_path / "probe.json")])
    assert out.exit_code == 0, out.output
    figures = json.loads((tmp_path / "probe.json").read_text())
    assert figures["calibrations"]["sum"]["agreement"] >= 0.75 > figures["baselines"]["majority_agreement"]
    noisy = runner.invoke(app, ["probe", "--backend", "oracle", "--oracle-noise", "1", "--states", "150", "--json"])
    assert json.loads(noisy.output)["calibrations"]["sum"]["agreement"] < 0.5
