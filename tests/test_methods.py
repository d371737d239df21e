"""Every training method of the registry (`illm_tools.intrinsic.registry.METHODS`), the same checks
each: its bonus reaches the advantages the loss uses (GAE is linear in the reward; the update step
receives exactly the two-stream advantages of the bonus the trainer computed, changed by it), and a
method that needs no LLM target trains end to end through `illm train --method M --bonus-option ...`
(its options in config.json, its own model trained and checkpointed, its loss logged) and `illm eval`
reads the run. A method added to the registry is in both by default: `OWN` says what it logs and
keeps, and its absence there fails the end-to-end case. ELLM pays only where a caption matches a
goal the LLM suggested: test_ellm.py follows its reward into the loss with a goal provider.

The two checks are plain functions in tests/fakes/methods.py (`bonus_reaches_the_advantages`,
`trains_end_to_end`), so that a method registered only inside another test gets the same ones
(test_example_bonus.py: the docs' example bonus)."""

from __future__ import annotations

import pytest

from illm_tools.intrinsic.registry import METHODS, get_method
from fakes import bonus_reaches_the_advantages, trains_end_to_end

pytestmark = pytest.mark.usefixtures("one_torch_thread")

OWN = {  # method: (a --bonus-option, the loss it logs, its part of the checkpoint's bonus state)
    "illm": (None, "losses/distill_action", None),
    "illm-shuffled": (None, "losses/distill_action", None),
    "rnd": ("update_proportion=0.5", "losses/rnd_predictor_loss", "predictor"),
    "ngu": ("k=5", "losses/ngu_embedding_loss", "embedding"),
    "apt": ("k=8", "losses/apt_embedding_loss", "embedding"),
}
SLOW_END_TO_END = {"rnd", "ngu"}  # 6 s each on a quiet 2-core EPYC: slow keeps the fast tier under 90 s


def paying() -> list[str]:
    """Every registered method whose bonus's reward is paid, but ELLM (see the docstring)."""
    return [name for name in METHODS if get_method(name).pays_reward and name != "ellm"]


def without_targets() -> list:
    """Every method with a bonus that needs no LLM target: trains from nothing but the environment."""
    return [pytest.param(name, marks=[pytest.mark.slow] if name in SLOW_END_TO_END else [])
            for name, method in METHODS.items()
            if method.entry_point is not None and not method.needs_targets and method.pays_reward]


@pytest.mark.parametrize("method", paying())
def test_the_bonus_reaches_the_advantages_the_loss_uses(tmp_path, monkeypatch, method):
    bonus_reaches_the_advantages(tmp_path, monkeypatch, method, OWN[method][1])


@pytest.mark.parametrize("method", without_targets())
def test_a_method_without_llm_targets_trains_end_to_end(tmp_path, method):
    trains_end_to_end(tmp_path, method, *OWN[method])
