"""The values a training run derives from its settings (`TrainConfig`'s properties): batch sizes,
what the method needs, the LLM's embedding width, the annotation setup of its targets. A base
class of `TrainConfig`, kept apart so that the settings' declarations read on their own; nothing
here is a setting, nothing is written to config.json.
"""

from __future__ import annotations

import functools

from illm_tools.intrinsic.registry import get_method
from illm_tools.llm.spec import LLMSpec
from illm_tools.tasks.setup import AnnotationSetup


class DerivedSettings:
    """The derived values of a `TrainConfig` (read from its fields; see the module docstring)."""

    @property
    def batch_size(self) -> int:
        """Transitions per rollout."""
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        """Transitions per minibatch."""
        return self.batch_size // self.num_minibatches

    @property
    def num_updates(self) -> int:
        """Rollout + update iterations in the run (at least one)."""
        return max(1, self.total_steps // self.batch_size)

    def resolved_action_space(self) -> str:
        """`action_space`, or for auto a resumed run's own as its config.json recorded it, else the
        suite's default for the env (`illm_tools.envs.resolve_action_space`)."""
        from illm_tools.envs import resolve_action_space

        space = self.action_space
        if space == "auto" and self.resume and (self.run_dir / "config.json").is_file():
            from illm_tools.rl.names import read_config

            space = read_config(self.run_dir).get("action_space", space)
        return resolve_action_space(self.env_id, space)

    @property
    def uses_heads(self) -> bool:
        """Whether the network carries f^a / f^hc and the loss distils the LLM (the bonus says)."""
        return get_method(self.method).policy_heads

    @property
    def needs_targets(self) -> bool:
        """Whether the run reads LLM targets (an annotation cache; the bonus says)."""
        return get_method(self.method).needs_targets

    @property
    def pays_bonus(self) -> bool:
        """Whether the intrinsic rewards reach the advantages."""
        return get_method(self.method).pays

    @property
    def uses_llm(self) -> bool:
        """Whether the run loads or reads an LLM: its targets (the bonus reads them) or hop's translation."""
        return self.needs_targets or self.obs_mode == "hop"

    @property
    def embedding_dim(self) -> int:
        """Width of the LLM's text embeddings (its hidden size; 576 for SmolLM2-135M), what each text
        head of the policy predicts: read from the model's config, without loading weights."""
        return _hidden_size(self.llm.backend, self.llm.model, None if self.cache is None else str(self.cache))

    @property
    def tasks(self) -> tuple[str, ...]:
        """The language tasks of iLLM's heads (`illm.tasks`)."""
        return self.illm.tasks

    @property
    def llm_model(self) -> str:
        """The model spec the backend serves: `model` or the backend's default, with the oracle's noise."""
        return self.llm.model

    @property
    def annotation_setup(self) -> AnnotationSetup:
        """The key inputs of the run's targets besides the state and the model: env, renderer (text,
        or hop's translation), the tasks it reads, history and layout."""
        return AnnotationSetup(self.env_id, self.renderer, self.target_tasks, self.history_len, self.layout)

    @property
    def live_limit(self) -> int | None:
        """The live budget as a number of states per rollout; None: all of them."""
        return None if self.live_budget == "all" else int(self.live_budget)

    @property
    def renderer(self) -> str:
        """The renderer field of the run's cache keys: the suite's text renderer, or in hop mode the
        translation's settings (`illm_tools.tasks.setup.hop_renderer`)."""
        if self.obs_mode == "hop":
            from illm_tools.tasks.setup import hop_renderer

            return hop_renderer(self.hop_seed, self.hop_beta, self.history_len + 1)
        from illm_tools.envs import renderer_of

        return renderer_of(self.env_id)

    @property
    def live_threads(self) -> int:
        """Torch threads of the live LLM (see `llm_threads`)."""
        import os

        cores = os.cpu_count() or 1
        if self.llm_threads:
            return self.llm_threads
        return cores if self.live_mode == "sync" else max(1, cores - self.threads)

    @property
    def target_tasks(self) -> tuple[str, ...]:
        """The language tasks whose cache rows the run reads: the heads' `tasks`, or those the
        method's bonus reads (ELLM: goal)."""
        return self.tasks if get_method(self.method).policy_heads else get_method(self.method).target_tasks

    @property
    def text_tasks(self) -> tuple[str, ...]:
        """The text tasks among `tasks` (each a head of `embedding_dim` outputs)."""
        from illm_tools.tasks.registry import text_tasks

        return text_tasks(self.tasks) if get_method(self.method).policy_heads else ()


@functools.lru_cache(maxsize=None)
def _hidden_size(backend: str, model: str, cache: str | None = None) -> int:
    """A model's hidden size, read once per process (`LLMSpec.hidden_size`); for a model only its
    engine can describe (openai) when none answers, the width of the embeddings `cache` holds of it."""
    from illm_tools.llm.openai_engine import EngineUnreachableError

    try:
        return LLMSpec(backend=backend, model=model).hidden_size()
    except EngineUnreachableError:
        from illm_tools.tasks.setup import cached_identity

        found = cached_identity(cache, backend, model)
        if found is None or found[1] is None:
            raise
        return found[1]
