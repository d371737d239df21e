"""The parts of a training run's config (`TrainConfig`), each a dataclass of its own settings:
PPO's hyperparameters (`PPOConfig`), how the bonus and iLLM's heads are trained and paid
(`BonusConfig`), and where the LLM targets come from, the cache and the live fallback
(`TargetsConfig`). Each validates its own settings; what needs another part (the env, the method)
is checked by `TrainConfig`. A setting's flat name (its option, its name in specs) is its field's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from illm_tools.errors import UsageError
from illm_tools.intrinsic.presets import DEFAULT_SETTINGS
from illm_tools.tasks.calibration import ACTION_TARGETS, CALIBRATIONS
from illm_tools.settings import setting

LIVE_MODES = ("sync", "async")


@dataclass
class PPOConfig:
    """PPO's hyperparameters (CleanRL's names; values: rl-starter-files' BabyAI settings)."""

    learning_rate: float = 1e-3
    """AdamW learning rate (rl-starter-files' BabyAI value; weight decay stays at AdamW's default)."""
    anneal_lr: bool = True
    """Linearly anneal the learning rate to zero over the run."""
    gamma: float = 0.99
    """Discount of the extrinsic return."""
    gae_lambda: float = 0.95
    """GAE lambda, for both value streams."""
    num_minibatches: int = 4
    """Minibatches per epoch."""
    update_epochs: int = 4
    """Passes over each rollout."""
    norm_adv: bool = True
    """Normalise advantages per minibatch."""
    clip_coef: float = 0.2
    """PPO surrogate clipping range."""
    clip_vloss: bool = True
    """Clip the value loss around the rollout's value estimates."""
    ent_coef: float = 0.01
    """Entropy bonus coefficient."""
    vf_coef: float = 0.5
    """Value loss coefficient (applies to both value heads)."""
    max_grad_norm: float = 0.5
    """Gradient norm clip (paper: 0.5)."""
    target_kl: float | None = None
    """Stop the epoch loop early when the approximate KL exceeds this; None never stops."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_numbers

        check_numbers(self, positive=("num_minibatches", "update_epochs", "learning_rate", "clip_coef",
                                      "max_grad_norm", "target_kl"),
                      non_negative=("ent_coef", "vf_coef"), unit=("gamma", "gae_lambda"))


@dataclass
class BonusConfig:
    """How the intrinsic bonus reaches the advantages, and how iLLM's heads are sized and trained."""

    head_hidden: int = 1024
    """Hidden units of the f^a and f^hc heads (paper: 1024)."""
    distill_coef: float = 1.0
    """Weight of the head distillation losses in the total loss."""
    distill_epochs: int = 1
    """Epochs of each update that train the heads (the 2 x 1024-unit heads cost as much as the rest
    of the update on CPU; later epochs train the policy alone)."""
    heads_bf16: bool | None = setting(None, resumes=True)
    """Run the heads' matmuls in bfloat16 on CPU (float32 parameters and losses); None: when a
    timed matmul says bf16 is faster on this CPU (it is on some, not on others; `illm_tools.llm.dtype`).
    The run records the answer in config.json and keeps it on resume, on any machine."""
    action_target: str = setting(DEFAULT_SETTINGS["action_target"], preset=True)
    """f^a's target: distribution (softmax of the calibrated scores) or argmax (the one-hot of the
    best one: the paper's Algorithm 1 line 7 and Appendix A select the highest log-probability)."""
    int_gamma: float = 0.99
    """Discount of the intrinsic return and of its normaliser (RND uses 0.99)."""
    int_episodic: bool = False
    """Cut the intrinsic return at episode ends; False is RND's non-episodic stream."""
    ext_coef: float = setting(DEFAULT_SETTINGS["ext_coef"], preset=True)
    """Weight of the extrinsic advantage in the summed advantage."""
    int_coef: float = setting(DEFAULT_SETTINGS["int_coef"], preset=True)
    """Weight of the intrinsic advantage (summed with the extrinsic one; two streams, see `reward_streams`)."""
    reward_streams: int = setting(DEFAULT_SETTINGS["reward_streams"], preset=True)
    """2: the bonus has its own value head and GAE (RND's two streams; `int_gamma`, `int_episodic`);
    1: the paper's Algorithm 1, r* = ext_coef r + int_coef b in one episodic stream with one critic."""
    bonus_schedule: str = setting(DEFAULT_SETTINGS["bonus_schedule"], preset=True)
    """The intrinsic advantage's weight over the run (`illm_tools.rl.bonus_schedule`): constant,
    anneal (linear to 0 over the run), or success (1 - the running success rate: it fades as the
    level is solved)."""
    int_ext_cap: float = setting(DEFAULT_SETTINGS["int_ext_cap"], preset=True)
    """Cap the intrinsic advantage at this multiple of the extrinsic one (mean |.| per rollout) where
    the task paid anything in the rollout; 0: no cap (the bonus alone steers until a reward is found)."""

    def __post_init__(self) -> None:
        from illm_tools.rl.bonus_schedule import SCHEDULES
        from illm_tools.settings import check_numbers

        check_numbers(self, positive=("head_hidden",),
                      non_negative=("ext_coef", "int_coef", "int_ext_cap", "distill_coef", "distill_epochs"),
                      unit=("int_gamma",))
        if self.action_target not in ACTION_TARGETS:
            raise UsageError(f"--action-target must be distribution or argmax, got {self.action_target!r}")
        if self.reward_streams not in (1, 2):
            raise UsageError(f"--reward-streams is 1 (the paper's one critic) or 2 (RND's two value heads), got "
                             f"{self.reward_streams!r}")
        if self.bonus_schedule not in SCHEDULES:
            raise UsageError(f"--bonus-schedule must be one of {', '.join(SCHEDULES)}, got {self.bonus_schedule!r}")


def parse_budget(value: int | str) -> int | str:
    """A live budget: a whole number >= 0, or "all"."""
    if isinstance(value, str) and value.strip().lower() == "all":
        return "all"
    try:
        budget = int(value)
    except (TypeError, ValueError):
        budget = -1
    if budget < 0 or (isinstance(value, float) and value != budget):
        raise UsageError(f"--live-budget is a number of states >= 0 or 'all', got {value!r}")
    return budget


@dataclass
class TargetsConfig:
    """Where a run's LLM targets come from: the annotation cache, and the live fallback for the
    states it has not seen (an annotator of the run's own, or an `illm serve` server)."""

    cache: Path | None = setting(None, resumes=True)
    """Annotation cache the targets are read from (and live annotations written back to)."""
    action_score: str = "sum"
    """Calibration of the stored action log-probs: sum (paper), mean per token, or pmi."""
    live_budget: int | str = setting(16, resumes=True)
    """Missed states handed to the live LLM after each rollout, most visited first: sync annotates
    them before the update; async gives them to the worker in place of its queue. 0: cache only;
    all: every missed state (with sync, a target on every step: for fast annotators such as the
    oracle, or an LLM on a GPU)."""
    live_mode: str = setting("async", resumes=True)
    """sync: annotate in the trainer's process, which waits (with --annotator: the server answers once
    the rollout's states have landed); async: a worker process (or the server) beside the rollouts,
    whose answers later rollouts use (the trainer never waits)."""
    annotator: str | None = setting(None, resumes=True)
    """URL of an `illm serve` server (http://127.0.0.1:PORT) that annotates the run's missed states,
    shared with other runs, instead of the run's own worker; `live_budget` states per rollout."""
    new_setup: bool = setting(False, resumes=True)
    """Accept a cache that holds annotations, none of them for this run's setup (model, dtype,
    quantisation, history length, layout, templates, renderer): live annotation starts it."""
    llm_threads: int = setting(0, resumes=True)
    """Torch threads for live annotation; 0: sync all cores, async the cores the policy leaves
    (one of 2). Give 1 when runs share the machine."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_folder, check_numbers

        self.cache = Path(self.cache) if self.cache is not None else None
        check_numbers(self, non_negative=("llm_threads",))
        check_folder(self.cache, "--cache")
        if self.action_score not in CALIBRATIONS:
            raise UsageError(f"--action-score must be {', '.join(CALIBRATIONS)}, got {self.action_score!r}")
        if self.live_mode not in LIVE_MODES:
            raise UsageError(f"--live-mode must be {' or '.join(LIVE_MODES)}, got {self.live_mode!r}")
        if self.annotator is not None and not self.annotator.startswith(("http://", "https://")):
            raise UsageError(f"--annotator is the URL of an `illm serve` server (http://127.0.0.1:PORT), got "
                             f"{self.annotator!r}")
        self.live_budget = parse_budget(self.live_budget)

    @property
    def live_limit(self) -> int | None:
        """The live budget as a number of states per rollout; None: all of them."""
        return None if self.live_budget == "all" else int(self.live_budget)

