"""Environment registry: which env ids illm can run as text environments, the renderer (name@version)
that describes each one, and `make_env` to build one. One `Suite` per family of environments
(one file per suite beside this one); only BabyAI/MiniGrid is wired in so far.
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable


from illm_tools.errors import UnknownEnvError

if TYPE_CHECKING:
    import gymnasium as gym


@dataclass(frozen=True)
class Suite:
    """A family of environments rendered to text by one renderer."""

    name: str
    prefixes: tuple[str, ...]
    """Env ids starting with one of these belong to the suite."""
    renderer: str
    """"<renderer name>@<version>": part of every annotation cache key."""
    module: str
    """Module holding the maker, `env_ids()` and optionally `default_action_space(env_id)`; imported
    only when needed."""
    maker: str
    """Name of the module's `maker(env_id, *, action_space, num_dists, **options) -> gym.Env`."""

    def load(self, attr: str) -> Callable[..., Any]:
        import importlib

        return getattr(importlib.import_module(self.module), attr)


def _babyai() -> Suite:
    from illm_tools.envs.babyai import RENDERER_NAME, RENDERER_VERSION

    return Suite(name="babyai", prefixes=("BabyAI-", "MiniGrid-"), renderer=f"{RENDERER_NAME}@{RENDERER_VERSION}",
                 module="illm_tools.envs.babyai", maker="make_babyai_text")


def suites() -> tuple[Suite, ...]:
    """Every suite illm knows (MiniHack, Atari, ... are added here as their renderers land)."""
    return (_babyai(),)


def known_env_ids() -> list[str]:
    """Every env id that `make_env` accepts, sorted."""
    return sorted(env_id for suite in suites() for env_id in suite.load("env_ids")())


def _suite_of(env_id: str) -> Suite:
    for suite in suites():
        if env_id.startswith(suite.prefixes) and env_id in suite.load("env_ids")():
            return suite
    known = known_env_ids()
    close = difflib.get_close_matches(env_id, known, n=3, cutoff=0.6)
    hint = f"did you mean {', '.join(close)}? " if close else ""
    raise UnknownEnvError(f"unknown environment id {env_id!r}; {hint}"
                          f"illm knows {len(known)} ids (illm_tools.envs.known_env_ids() lists them)")


def renderer_of(env_id: str) -> str:
    """The text renderer and its version for this env id, e.g. "babyai-text@1"."""
    return _suite_of(env_id).renderer


def resolve_action_space(env_id: str, action_space: str = "auto") -> str:
    """The action space an env is made with: `action_space` itself, or for "auto" the suite's default
    for this level (BabyAI: "original" for the GoTo levels, paper Tables 1 and 5; else "augmented").
    The one place "auto" is resolved, so collect, annotate and train of one env offer the same
    valid actions (they are part of every prompt and cache key)."""
    if action_space != "auto":
        return action_space
    suite = _suite_of(env_id)
    try:
        return suite.load("default_action_space")(env_id)
    except AttributeError:
        return "augmented"


def make_env(env_id: str, *, action_space: str = "auto", num_dists: int | None = None, **kw: Any) -> gym.Env:
    """The text environment for `env_id`: `info` holds `text`, `mission` and `valid_actions`.

    action_space: "original" (3 actions), "augmented" (6) or "irrelevant" (9), paper Table 5, or
    "auto" (default): `resolve_action_space`.
    num_dists: number of distractors, for levels that take one (paper Table 1).
    Other keywords go to the suite's maker (e.g. render_text=False) and then to gym.make.
    """
    suite = _suite_of(env_id)
    return suite.load(suite.maker)(env_id, action_space=resolve_action_space(env_id, action_space),
                                   num_dists=num_dists, **kw)
