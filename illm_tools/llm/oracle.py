"""The oracle backend: the oracles (annotators that know a game, one per suite: `illm_tools.oracles`)
behind the `Backend` protocol, for a positive control of iLLM.

`--backend oracle` answers every language task from the rendered prompt alone (the mission, the
history of observations and actions, the valid actions; never the environment's state): it reads
the prompt's frame (`illm_tools.oracles.base.parse_prompt`) and hands the state to the oracle of the
game the prompt names (`illm_tools.oracles.registry.oracle_for`: BabyAI and MiniGrid's is
`illm_tools.oracles.babyai`), as an LLM that knows the game would answer:

- `action` (ranking): each valid action's log-probability is log softmax(-KAPPA * cost), the cost
  being the oracle's count of steps left after the action (the best actions share most of the
  mass: a step worse is e^-2 as likely). One "token" per candidate, so `--action-score sum`,
  `mean` and `pmi` (the neutral prompt scores every action alike) rank the same, and
  `--action-target argmax` and `distribution` both work.
- text tasks: `summary`, `goal` and `plan`, the oracle's texts; the task is read from the prompt's
  instruction line, and a task the oracle does not know gets the summary. The texts are embedded
  with all-MiniLM-L6-v2 (`illm_tools.llm.sentence`, the sentence model ELLM already uses; unit
  vectors of 384, the run's `embedding_dim`): a goal or plan whole, a summary as the normalised mean
  of its sentences' embeddings (one fact a sentence, so the sentence model runs once per distinct
  sentence: annotation stays above 1,000 states/s on one core; `benchmarks/oracle.py`).

The quality knob (`--oracle-noise P`, the model spec "oracle:noise=P"): a fixed, keyed share P of
the states (a keyed hash of the state, not of the task's prompt, so all of a state's tasks go
together) gets a random answer instead: random action costs, and the oracle's random texts of its
grammar. Both the choice and the random answer are deterministic per state, so P = 1 is an
annotator that knows nothing and answers each state the same way every time.

Its fingerprint carries every registered oracle's version (the backend does not know the state's
game when it is fingerprinted, so a new or changed oracle re-keys every oracle row), this file's
answer version, the noise and the sentence model's identity (`sentence.embedder_id`: its package
version, texts embedded alone), never a dtype or quantisation (the oracle has neither), so its rows
never mix with an LLM's and every `--dtype` reads them. It refuses, in one line, an env of a game no
oracle reads (naming those one does) and `--mode hop` (it reads text, it has no embedding space).
"""

from __future__ import annotations

import hashlib
import json
import math
import random
import re
from collections.abc import Sequence

import numpy as np

from illm_tools.errors import UsageError
from illm_tools.oracles.base import NotAScene, Oracle, Scene, family_of, parse_prompt
from illm_tools.oracles.registry import ORACLES, known_families, named, oracle_for, versions

ORACLE_VERSION = 1
"""Version of how the oracles' answers become the backend's (KAPPA, the texts' use, the noise scheme).
How the texts are embedded is the embedder's (`sentence.embedder_id`, in the fingerprint)."""
KAPPA = 2.0
"""Inverse temperature of the ranking: log P(a) = log softmax(-KAPPA * cost(a))."""
NAME = "oracle"
NOISE_KEY = b"illm-oracle-noise@1"
_SPEC = re.compile(r"^oracle(?::noise=(?P<noise>[0-9.eE+-]+))?$")


def oracle_spec(noise: float = 0.0) -> str:
    """The model spec of the oracle at a noise level ("oracle", "oracle:noise=0.5")."""
    if not 0.0 <= noise <= 1.0:
        raise UsageError(f"--oracle-noise must lie in [0, 1], got {noise}")
    return NAME if noise == 0 else f"{NAME}:noise={noise:g}"


def parse_spec(model: str) -> float:
    """The noise of an oracle model spec; anything else is refused in one line."""
    m = _SPEC.match(model or "")
    if m is None:
        raise UsageError(f"the oracle backend serves the model 'oracle' (with --oracle-noise P), not {model!r}: "
                         "leave --model out or pass --model oracle")
    noise = float(m.group("noise") or 0.0)
    oracle_spec(noise)
    return noise


def _embedder():
    from illm_tools.llm.sentence import shared_embedder

    return shared_embedder()


def _embedding_dim() -> int:
    from illm_tools.llm.sentence import model_dir

    return int(json.loads((model_dir() / "config.json").read_text())["hidden_size"])


class OracleBackend:
    """The oracle behind the `Backend` protocol (see the module docstring)."""

    name = NAME
    device = "cpu"
    shares_prefix = False
    default_model = NAME
    computes = False
    """No dtype: `--dtype` is ignored (and `auto` measures nothing)."""
    chunk_states = 2048
    """States per written shard in bulk annotation (an LLM's chunk of 32 would write a shard every 30 ms)."""

    model_options = ("oracle_noise",)
    """`--oracle-noise` goes into its model spec (`model_spec`)."""

    @staticmethod
    def model_spec(model: str | None, *, oracle_noise: float = 0.0) -> str:
        """The spec of `--model` (None, "oracle" or "oracle:noise=P") and `--oracle-noise`."""
        if model is not None and parse_spec(model) and oracle_noise:
            raise UsageError(f"--model {model} already sets the oracle's noise: leave --oracle-noise out")
        return model if model is not None and parse_spec(model) else oracle_spec(oracle_noise)

    @staticmethod
    def selecting_options(model: str) -> str:
        noise = parse_spec(model)
        return "--backend oracle" + (f" --oracle-noise {noise:g}" if noise else "")

    @staticmethod
    def setting_of(model: str) -> dict:
        """Its noise as a setting of its own, as reports have always named it."""
        return {"model": NAME, "oracle_noise": parse_spec(model)}

    def __init__(self, model: str = NAME):
        self.model = model
        self.noise = parse_spec(model)
        self.fingerprint = self.model_fingerprint(model)
        self.hidden_size = _embedding_dim()
        self._oracles: dict[str, Oracle] = {}
        """A game -> the instance of its oracle this backend answers with (one per oracle, made on the
        oracle's first state: BabyAI and MiniGrid share one planner)."""

    # --- building ------------------------------------------------------------------------------
    @classmethod
    def load(cls, model: str = NAME, *, dtype: str = "float32", quant: str = "none", device: str = "cpu",
             cache_dir=None, batch_tokens=None) -> OracleBackend:
        return cls(model)

    @staticmethod
    def model_fingerprint(model: str, *, dtype: str = "float32", quant: str = "none") -> dict:
        from illm_tools.llm.sentence import embedder_id

        return {"model_id": NAME, "source": "oracle", "sha256": None,
                "revision": "+".join((*versions(), f"answers@{ORACLE_VERSION}")), "noise": parse_spec(model),
                "embedder": embedder_id(), "dtype": "float32", "quant": "none"}

    @staticmethod
    def model_hidden_size(model: str) -> int:
        return _embedding_dim()

    @staticmethod
    def check_use(env_id: str, renderer: str) -> None:
        """Refuse what the oracle cannot read, in one line: hop states and the text of a game no oracle reads."""
        if renderer.startswith("hop@"):
            raise UsageError("the oracle backend reads the text of a state; --mode hop translates "
                             "observations into an LLM's embedding space, which the oracle does not have: use "
                             "--mode obs, or an LLM backend for hop")
        oracle_for(family_of(env_id), env_id)

    # --- reading prompts -----------------------------------------------------------------------
    def _scene(self, text: str, actions: Sequence[str] = ()) -> Scene:
        try:
            scene = parse_prompt(text)
        except NotAScene as e:
            raise UsageError(f"the oracle backend cannot read this prompt ({e}): it answers the prompts illm "
                             f"renders for the states of {named(known_families())}") from None
        self._oracle(scene)  # a game no oracle reads is refused here, before any answer
        return Scene(scene.game, scene.mission, scene.history, scene.observation, tuple(actions) or scene.actions)

    def _oracle(self, scene: Scene) -> Oracle:
        """The oracle of the scene's game (`oracle_for`, asked once per game)."""
        oracle = self._oracles.get(scene.game)
        if oracle is None:
            cls = ORACLES.load(oracle_for(scene.game))
            made = [o for o in self._oracles.values() if type(o) is cls]
            oracle = self._oracles[scene.game] = made[0] if made else cls()
        return oracle

    def _noised(self, scene: Scene) -> random.Random | None:
        """The state's random stream when it is in the noised share, else None (both keyed by the state)."""
        if self.noise <= 0:
            return None
        digest = hashlib.blake2b(scene.state_id.encode(), key=NOISE_KEY, digest_size=16).digest()
        if int.from_bytes(digest[:8], "big") / 2**64 >= self.noise:
            return None
        return random.Random(int.from_bytes(digest[8:], "big"))

    # --- text ----------------------------------------------------------------------------------
    def _ranking(self, context: str, candidates: Sequence[str]):
        from illm_tools.llm.scoring import CandidateScores

        names = [c.strip() for c in candidates]
        if not context.startswith("You are an expert player"):  # no state's prompt (PMI's neutral one): every action alike
            return CandidateScores.from_logprobs([[-math.log(len(names))] for _ in names])
        scene = self._scene(context, names)
        rng = self._noised(scene)
        if rng is not None:
            costs = [rng.uniform(0.0, 2.0) for _ in names]
        else:
            known = self._oracle(scene).costs(scene)
            costs = [known[n] for n in names]
        logits = -KAPPA * np.asarray(costs, dtype=np.float64)
        logp = logits - (logits.max() + np.log(np.exp(logits - logits.max()).sum()))
        return CandidateScores.from_logprobs([[float(x)] for x in logp])

    def _text(self, prompt: str) -> str:
        scene = self._scene(prompt)
        task = _task_of(prompt)
        rng = self._noised(scene)
        oracle = self._oracle(scene)
        return oracle.random_text(scene, task, rng) if rng is not None else oracle.text(scene, task)

    def score(self, contexts, candidates, *, batch_size: int = 8):
        return [self._ranking(c, cands) for c, cands in zip(contexts, candidates)]

    def generate(self, prompts, *, max_new_tokens: int = 64, batch_size: int = 8):
        from illm_tools.llm.generation import Generation

        texts = [self._text(p) for p in prompts]
        embeddings = self._embed_answers(texts, [_task_of(p) == "summary" for p in prompts])
        out = []
        for text, emb in zip(texts, embeddings):
            words = text.split()
            cut = len(words) > max_new_tokens  # the oracle's "tokens" are words
            text = " ".join(words[:max_new_tokens]) if cut else text
            out.append(Generation(text, list(range(min(len(words), max_new_tokens))), not cut, emb))
        return out

    def score_and_generate(self, contexts, candidates, prompts, *, max_new_tokens: int = 64, batch_size: int = 8):
        return self.score(contexts, candidates), self.generate(prompts, max_new_tokens=max_new_tokens)

    def embed(self, texts, *, batch_size: int = 8):
        return _embedder().encode(list(texts))

    def _embed_answers(self, texts: Sequence[str], by_sentence: Sequence[bool]) -> np.ndarray:
        """The answers' embeddings: a summary's is the L2-normalised mean of its sentences' (one fact
        a sentence: the sentence model then runs once per distinct sentence, not per distinct
        summary), a goal's and a plan's the whole text's."""
        parts = [_SENTENCE.split(t) if whole else [t] for t, whole in zip(texts, by_sentence)]
        flat = list(dict.fromkeys(p for ps in parts for p in ps))
        if not flat:
            return np.zeros((len(texts), self.hidden_size), np.float32)
        table = dict(zip(flat, self.embed(flat)))
        out = np.stack([np.mean([table[p] for p in ps], axis=0) for ps in parts]).astype(np.float32)
        return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)

    # --- no embedding space (iLLM(hop)) --------------------------------------------------------
    def _no_hop(self, *_args, **_kwargs):
        self.check_use("", "hop@")

    input_embeddings = last_hidden = spliced = _no_hop


_SENTENCE = re.compile(r"(?<=\.) (?=[A-Z])")


_TASK_LINES = (("Summarize the main points", "summary"), ("Suggest the next goal", "goal"),
               ("Suggest the best sequence of actions", "plan"))


def _task_of(prompt: str) -> str:
    """The text task a prompt asks for, from its instruction line (the summary for any other)."""
    for marker, task in _TASK_LINES:
        if marker in prompt:
            return task
    return "summary"
