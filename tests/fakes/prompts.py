"""BabyAI-like states and the prompt builder that renders them: the action lists (`ACTIONS`, the
augmented six; `SHORT_ACTIONS`, the first three), `state_record` (a StateRecord of a BabyAI
observation) and `prompt_builder` (a PromptBuilder of BabyAI GoToLocal's text). Used by
test_tasks.py, test_ellm.py, test_language_tasks.py, test_coverage.py, and through `serve_state` by
the serving tests."""

from __future__ import annotations

from illm_tools.tasks.state import StateRecord

ACTIONS = ("turn left", "turn right", "go forward", "pick up", "drop", "toggle")
"""BabyAI's augmented action space (`ACTION_SPACES["augmented"]`): the toy pool's and `state_record`'s."""
SHORT_ACTIONS = ("turn left", "turn right", "go forward")
ENV = "BabyAI-GoToLocal-v0"


def state_record(obs: str = "You see a red ball 1 step forward", history=(), actions=ACTIONS) -> StateRecord:
    """A state of mission 'go to the red ball' seeing `obs`, after `history` [(observation, action)]
    (none by default), with the valid `actions`."""
    return StateRecord("go to the red ball", tuple(history), obs, tuple(actions))


def prompt_builder(*, lm=None, **changes):
    """A PromptBuilder of BabyAI GoToLocal (renderer babyai-text@1) for the model 'smollm2-135m' of a
    made-up fingerprint ('f' * 16), its default history (3) and layout; `lm`: a loaded model's path and
    fingerprint hash instead; `changes` (any PromptBuilder field) override."""
    from illm_tools.tasks.prompts import PromptBuilder

    fields = dict(env_id=ENV, renderer="babyai-text@1", model_fingerprint="f" * 16, model="smollm2-135m")
    if lm is not None:
        from illm_tools.keys import fingerprint_hash

        fields.update(model=lm.spec.path, model_fingerprint=fingerprint_hash(lm.fingerprint))
    return PromptBuilder(**{**fields, **changes})
