"""Runs compared by their settings (`illm report`): a config.json of any version under the flat
names, without the settings the run's method and mode ignore."""

from __future__ import annotations

from collections.abc import Mapping

from illm_tools.rl.config import flat_settings, upgrade_config


def comparable(data: Mapping) -> dict:
    """A run's config.json as runs are compared (`illm report`), under the flat names: every
    setting at its value, or its default where an older run lacks it, without the settings the
    run's method and mode ignore: the hop translation's in obs mode, the LLM's dtype and
    quantisation under a backend that has none (the oracle), every LLM and target setting for a
    method that reads no targets and is not in hop mode, and iLLM's settings for a method
    without its heads. The model is named as the backend's default names it (an LLMSpec's model), the
    oracle's noise apart (`oracle_noise`). A config this version cannot read is returned as it is."""
    from illm_tools.llm.backend import backend_class
    from illm_tools.rl.config import TrainConfig

    try:
        cfg = TrainConfig.from_dict({k: v for k, v in upgrade_config(data).items()
                                     if k in TrainConfig.__dataclass_fields__} | {"resume": False})
        out = flat_settings({**data, "resume": False})
        setting_of = getattr(backend_class(cfg.llm.backend), "setting_of", None)
        if setting_of is not None:  # a setting its model spec holds (the oracle's noise), as reports name it
            out.update(setting_of(cfg.llm.model))
    except Exception:  # noqa: BLE001 - another version's run: compared as written
        return dict(data)
    drop = set()
    if not cfg.setup.hop:
        drop |= {"hop_seed", "hop_beta"}
    if not cfg.uses_llm:
        drop |= {"model", "backend", "model_dtype", "quant", "oracle_noise", "history_len", "layout",
                 "action_score", "action_target", "tasks", "task_weights", "live_budget", "live_mode", "annotator"}
    elif not getattr(backend_class(cfg.llm.backend), "computes", True):
        drop |= {"model_dtype", "quant"}
    if not cfg.uses_heads:
        drop |= {"lambda_a", "beta_hc", "distill_coef", "distill_epochs", "summary_loss", "action_similarity",
                 "head_hidden"}
    return {k: v for k, v in out.items() if k not in drop}
