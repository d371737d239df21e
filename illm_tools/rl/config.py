"""TrainConfig: every setting of a PPO / iLLM training run, one documented field each.

The CLI builds this dataclass from options (field docstrings become `--help`); the library
validates it in `__post_init__` and derives the rest as properties, never by patching fields.
It is composed: the LLM is one `LLMSpec` (`llm`), iLLM's settings one `ILLMConfig` (`illm`), each
declared and validated once where it lives; `illm_tools.rl.names` maps the flat names of options,
specs and older config.json files onto them. `illm_tools.rl.build.run_config` builds a run's config
from what was given (presets, a resumed run, the cache's setup); the presets live in
`illm_tools.rl.presets`, `EvalConfig` in `illm_tools.rl.eval_config` (all re-exported here).
`TrainConfig()` is what `illm train` trains with no option (the illm method, the `small` preset);
for another method `run_config({"method": ...})` adds that method's preset, as the command line does.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from illm_tools.errors import UsageError
from illm_tools.intrinsic.illm_config import ILLMConfig
from illm_tools.intrinsic.registry import METHODS, get_method
from illm_tools.llm.spec import LLMSpec
from illm_tools.rl.derived import DerivedSettings
from illm_tools.rl.eval_config import EvalConfig  # noqa: F401  (re-exported: where callers found it)
from illm_tools.rl.names import GROUPS, NESTED, RENAMED, flat_settings, group_dict, upgrade_config  # noqa: F401
from illm_tools.rl.presets import (BONUS_PRESETS, DEFAULT_PRESET, PRESET_DEFAULTS, PRESET_FIELDS,  # noqa: F401
                                   bonus_weights, preset_text)
from illm_tools.tasks.calibration import ACTION_TARGETS, CALIBRATIONS

MODES = METHODS  # the bonus registry, name -> method (a live mapping: methods registered later count)
LIVE_MODES = ("sync", "async")
OBS_MODES = ("obs", "hop")


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


def parse_seeds(value) -> tuple[int, ...]:
    """Episode seeds from "0,3" or a sequence: whole numbers >= 0."""
    items = value.split(",") if isinstance(value, str) else list(value or ())
    try:
        seeds = tuple(int(str(s).strip()) for s in items if str(s).strip())
    except ValueError:
        seeds = (-1,)
    if any(s < 0 for s in seeds):
        raise UsageError(f"--env-seeds takes whole numbers >= 0 separated by commas, got {value!r}")
    return seeds


@dataclass
class TrainConfig(DerivedSettings):
    """One training run: environment, PPO, iLLM bonus, and bookkeeping."""

    # --- run -------------------------------------------------------------------------------
    env_id: str = "BabyAI-GoToLocal-v0"
    """Id of the environment (BabyAI/MiniGrid, MiniHack, Crafter, Atari: `illm envs` lists them)."""
    run_dir: Path = Path("data/runs/default")
    """Folder for config.json, metrics.jsonl, TensorBoard events and checkpoint.pt."""
    method: str = "illm"
    """The method, a name in the registry `illm_tools.intrinsic.registry` (its bonus and network)."""
    network_options: dict = field(default_factory=dict)
    """Settings of the method's policy network by name (e.g. chibit's blocks; `--network-option
    KEY=VALUE`); unset ones keep their defaults."""
    bonus_options: dict = field(default_factory=dict)
    """Settings of the method's bonus by name (the fields of its config dataclass, e.g. rnd's
    update_proportion; `--bonus-option KEY=VALUE`); unset ones keep their defaults."""
    seed: int = 0
    """Seed of the network initialisation, action sampling, minibatch order and env pool."""
    total_steps: int = 200_000
    """Environment steps to train for, summed over the parallel envs."""
    num_envs: int = 16
    """Environments stepped side by side."""
    num_steps: int = 128
    """Steps per env in one rollout; a rollout holds num_envs * num_steps transitions."""
    action_space: str = "auto"
    """Action vocabulary: BabyAI's original (3), augmented (6) or irrelevant (9), paper Table 5
    (other suites offer one each, `illm envs`); auto: the suite's default (BabyAI: original for the
    GoTo levels, paper Tables 1 and 5, augmented otherwise). The run records the resolved name."""
    num_dists: int | None = None
    """Distractor count for levels that take it; None keeps the level's default."""

    # --- PPO -------------------------------------------------------------------------------
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

    # --- network ---------------------------------------------------------------------------
    mission_max_len: int = 32
    """Mission words kept (longer missions are truncated)."""
    head_hidden: int = 1024
    """Hidden units of the f^a and f^hc heads (paper: 1024)."""

    # --- iLLM ------------------------------------------------------------------------------
    obs_mode: str = "obs"
    """How the LLM sees a state: obs (the suite's text, written by its renderer) or hop (iLLM(hop):
    the raw observation translated into the LLM's embedding space by a frozen Hopfield layer; the
    policy also reads Z_h, the LLM's state after the translated window; paper Algorithm 1)."""
    hop_seed: int = 0
    """hop: seed of the translation's fixed random projection P (part of every hop cache key)."""
    hop_beta: float = 100.0
    """hop: inverse temperature of the Hopfield retrieval (not beta_hc; part of every hop cache key):
    HELM's 100; at 1 every observation translates to nearly the same embedding."""
    history_len: int = 3
    """(observation, action) pairs before the current observation handed to the LLM (paper: 3)."""
    illm: ILLMConfig = field(default_factory=ILLMConfig)
    """iLLM's own settings (`illm_tools.intrinsic.illm_config.ILLMConfig`; options --lambda-a, --beta-hc,
    --tasks, --task-weight, --summary-loss, --action-similarity). Defaults: the `small` preset."""
    distill_coef: float = 1.0
    """Weight of the head distillation losses in the total loss."""
    distill_epochs: int = 1
    """Epochs of each update that train the heads (the 2 x 1024-unit heads cost as much as the rest
    of the update on CPU; later epochs train the policy alone)."""
    heads_bf16: bool | None = None
    """Run the heads' matmuls in bfloat16 on CPU (float32 parameters and losses); None: when a
    timed matmul says bf16 is faster on this CPU (it is on some, not on others; `illm_tools.llm.dtype`).
    The run records the answer in config.json and keeps it on resume, on any machine."""
    int_gamma: float = 0.99
    """Discount of the intrinsic return and of its normaliser (RND uses 0.99)."""
    int_episodic: bool = False
    """Cut the intrinsic return at episode ends; False is RND's non-episodic stream."""
    ext_coef: float = BONUS_PRESETS[DEFAULT_PRESET]["ext_coef"]
    """Weight of the extrinsic advantage in the summed advantage."""
    int_coef: float = BONUS_PRESETS[DEFAULT_PRESET]["int_coef"]
    """Weight of the intrinsic advantage (summed with the extrinsic one; two streams, see `reward_streams`)."""
    reward_streams: int = PRESET_DEFAULTS["reward_streams"]
    """2: the bonus has its own value head and GAE (RND's two streams; `int_gamma`, `int_episodic`);
    1: the paper's Algorithm 1, r* = ext_coef r + int_coef b in one episodic stream with one critic."""
    bonus_schedule: str = PRESET_DEFAULTS["bonus_schedule"]
    """The intrinsic advantage's weight over the run (`illm_tools.rl.bonus_schedule`): constant,
    anneal (linear to 0 over the run), or success (1 - the running success rate: it fades as the
    level is solved)."""
    int_ext_cap: float = PRESET_DEFAULTS["int_ext_cap"]
    """Cap the intrinsic advantage at this multiple of the extrinsic one (mean |.| per rollout) where
    the task paid anything in the rollout; 0: no cap (the bonus alone steers until a reward is found)."""

    # --- LLM targets -----------------------------------------------------------------------
    cache: Path | None = None
    """Annotation cache the targets are read from (and live annotations written back to)."""
    llm: LLMSpec = field(default_factory=LLMSpec)
    """The LLM whose annotations are the targets (its fingerprint is part of every cache key), the live
    annotator's and hop's (options --backend, --model, --dtype, --quant, --oracle-noise, --endpoint, ...,
    as in `illm annotate`); its device is `llm_device`. `resolved()` records its dtype and
    quantisation as chosen on this machine."""
    layout: str = "shared"
    """Prompt template layout, as in `illm annotate --layout`."""
    action_score: str = "sum"
    """Calibration of the stored action log-probs: sum (paper), mean per token, or pmi."""
    action_target: str = PRESET_DEFAULTS["action_target"]
    """f^a's target: distribution (softmax of the calibrated scores) or argmax (the one-hot of the
    best one: the paper's Algorithm 1 line 7 and Appendix A select the highest log-probability)."""
    live_budget: int | str = 16
    """Missed states handed to the live LLM after each rollout, most visited first: sync annotates
    them before the update; async gives them to the worker in place of its queue. 0: cache only;
    all: every missed state (with sync, a target on every step: for fast annotators such as the
    oracle, or an LLM on a GPU)."""
    live_mode: str = "async"
    """sync: annotate in the trainer's process, which waits (with --annotator: the server answers once
    the rollout's states have landed); async: a worker process (or the server) beside the rollouts,
    whose answers later rollouts use (the trainer never waits)."""
    annotator: str | None = None
    """URL of an `illm serve` server (http://127.0.0.1:PORT) that annotates the run's missed states,
    shared with other runs, instead of the run's own worker; `live_budget` states per rollout."""
    new_setup: bool = False
    """Accept a cache that holds annotations, none of them for this run's setup (model, dtype,
    quantisation, history length, layout, templates, renderer): live annotation starts it."""
    threads: int = 1
    """Torch threads for the policy (small nets run best on one)."""
    device: str = "auto"
    """Where the policy, the bonus's models and the rollout live: cpu, cuda, cuda:N or auto (a GPU
    where there is one; for many small runs side by side on one GPU machine, cpu). Actions are sampled on the CPU from the run's seeded generator; a run may
    resume on another device."""
    llm_device: str | None = None
    """Where the live fallback's and hop mode's LLM run (cpu, cuda, cuda:N, auto); unset: `device`."""
    llm_threads: int = 0
    """Torch threads for live annotation; 0: sync all cores, async the cores the policy leaves
    (one of 2). Give 1 when runs share the machine."""

    # --- bookkeeping -----------------------------------------------------------------------
    checkpoint_every: int = 10
    """Save a checkpoint every this many updates, after the first and the last one, and when a
    signal stops the run; 0: only those."""
    checkpoint_minutes: float = 5.0
    """Also save a checkpoint when this many minutes have passed since the last one."""
    resume: bool = False
    """Continue from run_dir/checkpoint.pt instead of starting fresh."""
    tensorboard: bool = True
    """Also write TensorBoard events beside metrics.jsonl."""
    env_seeds: tuple[int, ...] = ()
    """Episode seeds the envs cycle through instead of a new seed every episode: a fixed set of
    layouts (one seed: one MultiRoom map, so a visitation heatmap shows one map, as paper Figure 1);
    evaluation then plays the same layouts. Empty: every episode its own seed."""
    env_options: dict = field(default_factory=dict)
    """Options of the environment, its suite's (`--env-option KEY=VALUE`, e.g. max_episode_steps;
    `illm envs` lists the suites)."""
    vector: str = "auto"
    """How the envs step: sync (all in this process), async (a process each: slow envs such as
    Crafter), auto (the suite's choice)."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_folder, check_numbers

        self.run_dir = Path(self.run_dir)
        self.cache = Path(self.cache) if self.cache is not None else None
        if not isinstance(self.illm, ILLMConfig):  # its dict form (config.json): validated by ILLMConfig
            self.illm = ILLMConfig(**group_dict("illm", self.illm))
        llm = self.llm if isinstance(self.llm, LLMSpec) else LLMSpec(**group_dict("llm", self.llm))
        check_numbers(self, positive=("total_steps", "num_envs", "num_steps", "num_minibatches", "update_epochs",
                                      "mission_max_len", "head_hidden", "learning_rate", "clip_coef",
                                      "max_grad_norm", "target_kl", "hop_beta", "checkpoint_minutes", "threads"),
                      non_negative=("seed", "num_dists", "hop_seed", "history_len", "ext_coef", "int_coef",
                                    "int_ext_cap", "distill_coef", "distill_epochs", "ent_coef", "vf_coef",
                                    "llm_threads", "checkpoint_every"),
                      unit=("gamma", "gae_lambda", "int_gamma"),
                      flags={"total_steps": "--frames", "history_len": "--history", "run_dir": "--out"})
        check_folder(self.run_dir, "--out")
        check_folder(self.cache, "--cache")
        from illm_tools.devices import check_device

        check_device(self.device)
        if self.llm_device is not None:
            check_device(self.llm_device, "--llm-device")
        # the LLM runs on `llm_device` (default: the run's device): its spec says so, as a stage's does
        self.llm = llm if llm.device == (self.llm_device or self.device) else \
            dataclasses.replace(llm, device=self.llm_device or self.device)
        if self.action_score not in CALIBRATIONS:
            raise UsageError(f"--action-score must be {', '.join(CALIBRATIONS)}, got {self.action_score!r}")
        if self.action_target not in ACTION_TARGETS:
            raise UsageError(f"--action-target must be distribution or argmax, got {self.action_target!r}")
        if self.reward_streams not in (1, 2):
            raise UsageError(f"--reward-streams is 1 (the paper's one critic) or 2 (RND's two value heads), got "
                             f"{self.reward_streams!r}")
        from illm_tools.rl.bonus_schedule import SCHEDULES

        if self.bonus_schedule not in SCHEDULES:
            raise UsageError(f"--bonus-schedule must be one of {', '.join(SCHEDULES)}, got {self.bonus_schedule!r}")
        if self.bonus_schedule == "success":
            from illm_tools.envs import suite_of

            if suite_of(self.env_id).score_name != "success rate":
                raise UsageError(f"--bonus-schedule success fades the bonus with the success rate, and "
                                 f"{self.env_id}'s score is its {suite_of(self.env_id).score_name}: use constant or "
                                 "anneal")
        if self.live_mode not in LIVE_MODES:
            raise UsageError(f"--live-mode must be {' or '.join(LIVE_MODES)}, got {self.live_mode!r}")
        if self.annotator is not None and not self.annotator.startswith(("http://", "https://")):
            raise UsageError(f"--annotator is the URL of an `illm serve` server (http://127.0.0.1:PORT), got "
                             f"{self.annotator!r}")
        self.live_budget = parse_budget(self.live_budget)
        self.env_seeds = parse_seeds(self.env_seeds)
        method = get_method(self.method)  # refuses an unknown method
        if self.illm.tasks != ILLMConfig().tasks and not method.policy_heads:
            reads = ", ".join(method.target_tasks) if method.needs_targets else ""
            raise UsageError(f"--tasks chooses the language tasks of iLLM's heads; --method {self.method} has none "
                             f"(it reads {reads or 'no language task'})")
        method.make_config({"illm": self.illm}, self.bonus_options)  # refuses unknown or ill-typed bonus options
        method.network_options(self.network_options)
        if self.batch_size % self.num_minibatches:
            raise UsageError(f"num_envs * num_steps = {self.batch_size} is not divisible by "
                             f"num_minibatches = {self.num_minibatches}")
        if self.obs_mode not in OBS_MODES:
            raise UsageError(f"--mode is the observation mode, {' or '.join(OBS_MODES)}; got {self.obs_mode!r} "
                             "(the method is --method)")

    def resolved(self) -> "TrainConfig":
        """This config with the machine's and the env's choices made, as the run records them in
        config.json (and keeps on resume, on any machine); a run resolves its config once, when it
        starts (`illm_tools.rl.run.train`). `device` and `llm_device` auto -> cpu or cuda (these two
        may change on resume); when the run uses an LLM, its dtype auto -> the dtype
        `illm_tools.llm.dtype` measures and its quantisation auto -> the model's alias on CUDA, else
        none; `heads_bf16` None -> whether bf16 is faster for the heads (when the method has them);
        `action_space` auto -> a resumed run's recorded space, else the suite's default for the env
        (`resolve_action_space`). Resolving a resolved config changes nothing."""
        from illm_tools.devices import resolve_device
        from illm_tools.llm.backend import backend_dtype, backend_quant

        changes: dict = {"device": resolve_device(self.device), "action_space": self.resolved_action_space()}
        if self.uses_llm:
            device = resolve_device(self.llm_device or self.device, flag="--llm-device")
            llm = self.llm
            dtype = backend_dtype(llm.backend, "auto", device) if llm.dtype == "auto" else llm.dtype
            changes["llm_device"] = device
            changes["llm"] = dataclasses.replace(llm, device=device, dtype=dtype,
                                                 quant=backend_quant(llm.backend, llm.model, llm.quant, device))
        if self.heads_bf16 is None and self.uses_heads:
            from illm_tools.rl.networks import bf16_is_faster

            changes["heads_bf16"] = bf16_is_faster()
        if all(getattr(self, k) == v for k, v in changes.items()):
            return self
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """JSON-ready form (paths as strings; `llm` and `illm` as dicts of their settings, the LLM's
        device left to `llm_device`)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out.update(llm=group_dict("llm", self.llm), illm=self.illm.to_dict(), env_seeds=list(self.env_seeds),
                   run_dir=str(self.run_dir), cache=str(self.cache) if self.cache is not None else None,
                   network_options=dict(self.network_options), bonus_options=dict(self.bonus_options),
                   env_options=dict(self.env_options))
        return out

    def flat(self) -> dict:
        """The settings under their flat names, as options and specs name them (`illm_tools.rl.names`)."""
        return flat_settings(self.to_dict())

    @classmethod
    def defaults(cls, names: Iterable[str]) -> dict:
        """The default of each setting in `names` (flat names), read from the field declarations."""
        def default(owner: type, name: str):
            f = owner.__dataclass_fields__[name]
            return f.default_factory() if f.default is dataclasses.MISSING else f.default

        return {n: default(LLMSpec if NESTED[n][0] == "llm" else ILLMConfig, NESTED[n][1]) if n in NESTED
                else default(cls, n) for n in names}

    @classmethod
    def from_dict(cls, data: Mapping) -> "TrainConfig":
        """Inverse of `to_dict`; also reads an older run's config.json and settings under their flat
        names (`upgrade_config`); unknown keys are refused."""
        data = upgrade_config(data)
        known = set(cls.__dataclass_fields__)
        unknown = set(data) - known
        if unknown:
            raise UsageError(f"unknown training settings {sorted(unknown)}")
        return cls(**data)


