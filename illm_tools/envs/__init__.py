"""Environment suites: which env ids illm runs, what the policy sees of each, its text (if any),
its score, and `make_env` to build one.

A suite (`illm_tools.envs.suite.Suite`) is one family of environments: BabyAI/MiniGrid, MiniHack,
Crafter, Atari. `SUITES` maps a suite's name to its entry point ("module:attribute", imported only
when an env id is looked up, so `illm --help` imports no simulator). Adding a suite is one new
file with a `Suite` subclass plus one entry here (or `register_suite` from user code: tests plug
in a tiny one from the test file).
"""
from __future__ import annotations

import difflib
from typing import TYPE_CHECKING, Any

from illm_tools.errors import UnknownEnvError, UsageError
from illm_tools.registry import Registry

if TYPE_CHECKING:
    import gymnasium as gym

    from illm_tools.envs.suite import Suite

def _suite_problem(obj) -> str | None:
    from illm_tools.envs.suite import Suite

    return None if isinstance(obj, Suite) else "is not a Suite instance"


SUITES: Registry = Registry("suite", "illm.suites", check=_suite_problem)
"""Suite name -> "module:attribute" of its `Suite` instance (or the instance itself); installed
packages add theirs through `illm.suites` entry points."""
SUITES.register("babyai", "illm_tools.envs.babyai:SUITE")
SUITES.register("minihack", "illm_tools.envs.minihack:SUITE")
SUITES.register("crafter", "illm_tools.envs.crafter:SUITE")
SUITES.register("atari", "illm_tools.envs.atari:SUITE")


def register_suite(suite: Suite | str, name: str | None = None) -> None:
    """Add a suite (an instance, or "module:attribute" with `name`); a name already taken is refused."""
    SUITES.register(name or suite.name, suite)


def _load(name: str) -> Suite:
    return SUITES.load(name)



def suites() -> tuple[Suite, ...]:
    """Every registered suite, loaded."""
    return tuple(_load(name) for name in SUITES)


def known_env_ids() -> list[str]:
    """Every env id that `make_env` accepts, sorted."""
    return sorted(env_id for suite in suites() for env_id in suite.env_ids())


def suite_of(env_id: str) -> Suite:
    """The suite an env id belongs to; an unknown id is refused with the closest known ones."""
    for name in SUITES:
        suite = _load(name)
        if suite.owns(env_id):
            return suite
    known = known_env_ids()
    close = difflib.get_close_matches(env_id, known, n=3, cutoff=0.6)
    hint = f"did you mean {', '.join(close)}? " if close else ""
    raise UnknownEnvError(f"unknown environment id {env_id!r}; {hint}"
                          f"illm knows {len(known)} ids (`illm envs` lists them)")


def renderer_of(env_id: str) -> str:
    """The text renderer and its version for this env id, e.g. "babyai-text@1"; suites without a
    text observation (Atari) are refused in one line."""
    suite = suite_of(env_id)
    if suite.renderer is None:
        raise UsageError(f"{env_id} has no text observation ({suite.name} suite): iLLM on it needs --mode hop "
                         "(annotate and train), or train --method ppo, rnd, ngu or apt")
    return suite.renderer


def resolve_action_space(env_id: str, action_space: str = "auto") -> str:
    """The action space an env is made with: `action_space` itself, or for "auto" the suite's default
    for this env (BabyAI: "original" for the GoTo levels, paper Tables 1 and 5). The one place
    "auto" is resolved, so collect, annotate and train of one env offer the same valid actions
    (they are part of every prompt and cache key)."""
    suite = suite_of(env_id)
    if action_space == "auto":
        return suite.default_action_space(env_id)
    if action_space not in suite.action_spaces(env_id):
        raise UsageError(f"{env_id} has no action space {action_space!r}; it takes "
                         f"{', '.join(('auto', *suite.action_spaces(env_id)))}")
    return action_space


def make_env(env_id: str, *, action_space: str = "auto", num_dists: int | None = None, **kw: Any) -> gym.Env:
    """The environment for `env_id` as its suite makes it: observations are the suite's own
    (`Suite.policy_obs` turns one into the policy's array, `Suite.obs_spec`); `info` holds `text`,
    `mission` and `valid_actions` (and `success` and the suite's episode extras on an episode's
    last step).

    action_space: the suite's named action vocabularies (BabyAI: "original", "augmented",
    "irrelevant", paper Table 5) or "auto" (default): `resolve_action_space`.
    num_dists: number of distractors, for BabyAI levels that take one (paper Table 1).
    Other keywords (render_text=False, and the suite's own options) go to the suite's maker.
    """
    from illm_tools.envs.suite import check_options

    suite = suite_of(env_id)
    if num_dists is not None:
        kw["num_dists"] = num_dists
    check_options(env_id, {k: v for k, v in kw.items() if k != "render_text"}, suite.options(env_id))
    return suite.make(env_id, action_space=resolve_action_space(env_id, action_space), **kw)
