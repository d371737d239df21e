"""How a state becomes a prompt, as the user chooses it: the history length, the template layout
and the observation mode (the suite's text, or hop's translation with its seed and beta).

Every stage that prompts an LLM holds one `PromptConfig` (`illm annotate`, `illm serve`, `illm
probe`, a training run's `setup`), so that each of these settings is declared once, under one name
and one flag (`--history`, `--layout`, `--mode`, `--hop-seed`, `--hop-beta`), and the renderer
field of a state's keys is derived in one place (`renderer`). With the env and the tasks it makes
the `AnnotationSetup` a cache key carries (`of`).
"""

from __future__ import annotations

from dataclasses import dataclass

from illm_tools.errors import UsageError
from illm_tools.settings import setting
from illm_tools.tasks.prompts import LAYOUTS
from illm_tools.tasks.annotation_setup import AnnotationSetup, hop_renderer, prompt_options

OBS_MODES = ("obs", "hop")


@dataclass(frozen=True)
class PromptConfig:
    """The prompt settings of a stage (see the module docstring)."""

    history_len: int = setting(3, flag="--history", adopted=True)
    """(observation, action) pairs before the current observation in the prompts (paper B.1: 3)."""
    layout: str = setting("shared", adopted=True)
    """Template layout: shared (history first, the prefix computed once) or paper (as printed)."""
    obs_mode: str = setting("obs", flag=("--mode",))
    """How the LLM sees a state: obs (the suite's text, written by its renderer) or hop (iLLM(hop):
    the raw observation translated into the LLM's embedding space by a frozen Hopfield layer; a
    policy also reads Z_h, the LLM's state after the translated window; paper Algorithm 1)."""
    hop_seed: int = setting(0, adopted=True)
    """hop: seed of the translation's fixed random projection P (part of every hop cache key)."""
    hop_beta: float = setting(100.0, adopted=True)
    """hop: inverse temperature of the Hopfield retrieval (not beta_hc; part of every hop cache key):
    HELM's 100; at 1 every observation translates to nearly the same embedding."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_numbers

        check_numbers(self, positive=("hop_beta",), non_negative=("history_len", "hop_seed"))
        if self.layout not in LAYOUTS:
            raise UsageError(f"--layout must be one of {', '.join(LAYOUTS)}, got {self.layout!r}")
        if self.obs_mode not in OBS_MODES:
            raise UsageError(f"--mode is the observation mode, {' or '.join(OBS_MODES)}; got {self.obs_mode!r} "
                             "(the method is --method)")

    @property
    def hop(self) -> bool:
        """Whether states are hop windows (iLLM(hop)) rather than text."""
        return self.obs_mode == "hop"

    @property
    def hop_renderer(self) -> str:
        """The renderer field of hop keys under these settings (the window: history plus the current
        observation)."""
        return hop_renderer(self.hop_seed, self.hop_beta, self.history_len + 1)

    def renderer(self, env_id: str, hop: bool | None = None) -> str:
        """The renderer field of `env_id`'s keys: its suite's text renderer, or for hop states (`hop`;
        None: in hop mode) the translation's settings (`hop_renderer`)."""
        if self.hop if hop is None else hop:
            return self.hop_renderer
        from illm_tools.envs import renderer_of

        return renderer_of(env_id)

    def of(self, env_id: str, tasks: tuple[str, ...], *, renderer: str | None = None,
           hop: bool | None = None) -> AnnotationSetup:
        """The annotation setup of `env_id`'s states for `tasks`: hop states (`hop`; None: in hop mode)
        or text ones (`renderer`: a dataset's own text renderer, default the suite's)."""
        hop = self.hop if hop is None else hop
        return AnnotationSetup(env_id, self.renderer(env_id, hop) if hop or renderer is None else renderer,
                               tuple(tasks), self.history_len, self.layout)

    def options(self) -> str:
        """The flags that select these settings ("--history 3 --layout shared")."""
        hop = {"seed": self.hop_seed, "beta": self.hop_beta} if self.hop else None
        return prompt_options(self.history_len, self.layout, hop)
