"""TrainConfig: every setting of a PPO / iLLM training run, one documented field each.

The CLI builds this dataclass from options (field docstrings become `--help`); the library
validates it in `__post_init__` and derives the rest as properties, never by patching fields.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass, field
from pathlib import Path

from illm_tools.errors import UsageError
from illm_tools.intrinsic.registry import METHODS, get_method
from illm_tools.llm.spec import LLMSpec
from illm_tools.tasks.calibration import ACTION_TARGETS, CALIBRATIONS
from illm_tools.tasks.setup import AnnotationSetup

MODES = METHODS  # the bonus registry, name -> method (a live mapping: methods registered later count)
LIVE_MODES = ("sync", "async")
OBS_MODES = ("obs", "hop")
BONUS_PRESETS = {  # `illm train --bonus-preset`: how the bonus enters the advantages, in one name
    "paper": {"lambda_a": 0.8, "beta_hc": 0.5, "ext_coef": 1.0, "int_coef": 1.0},  # Appendix B
    "rnd": {"lambda_a": 0.8, "beta_hc": 0.5, "ext_coef": 2.0, "int_coef": 1.0},    # CleanRL RND's advantage weights
    "ngu": {"lambda_a": 0.8, "beta_hc": 0.5, "ext_coef": 1.0, "int_coef": 0.3},    # NGU's r = r_e + 0.3 r_i
    # the paper's weights / 10, two streams: the illm methods' default, chosen on the suite's tune half (IQM 0.972 over
    # 4 levels x 3 seeds against paper's 0.645 and paper-literal's 0.057; docs/experiments/suite.md)
    "small": {"lambda_a": 0.08, "beta_hc": 0.05, "ext_coef": 1.0, "int_coef": 1.0},
    # Algorithm 1 as printed: r* = r + r^a + r^hc in one stream (one critic), f^a's target the argmax action
    "paper-literal": {"lambda_a": 0.8, "beta_hc": 0.5, "ext_coef": 1.0, "int_coef": 1.0, "reward_streams": 1,
                      "action_target": "argmax"},
}
PRESET_FIELDS = ("lambda_a", "beta_hc", "ext_coef", "int_coef", "reward_streams", "action_target", "bonus_schedule",
                 "int_ext_cap")
"""The settings a preset names (a preset leaves out those it keeps at TrainConfig's default)."""


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


def bonus_weights(preset: str, **given) -> dict:
    """Every PRESET_FIELDS setting of a BONUS_PRESETS entry (TrainConfig's default where the preset
    names none); `given` values not None win."""
    if preset not in BONUS_PRESETS:
        raise UsageError(f"--bonus-preset must be one of {', '.join(BONUS_PRESETS)}, got {preset!r}")
    defaults = {f.name: f.default for f in dataclasses.fields(TrainConfig) if f.name in PRESET_FIELDS}
    chosen = {**defaults, **BONUS_PRESETS[preset]}
    return {k: v if given.get(k) is None else (float(given[k]) if isinstance(v, float) else given[k])
            for k, v in chosen.items()}


def preset_text(preset: str) -> str:
    """A preset as --help shows it: "lambda_a 0.8, beta_hc 0.5, ...", the settings it names."""
    return ", ".join(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}" for k, v in BONUS_PRESETS[preset].items())


RENAMED = {"mode": "method"}
"""Settings renamed since runs were first written (old name -> new): config.json files and
checkpoints of older runs are read under the new names."""


def upgrade_config(data: dict) -> dict:
    """A run's settings as written by any version, under this version's names (`RENAMED`)."""
    out = dict(data)
    for old, new in RENAMED.items():
        if old in out and new not in out:
            out[new] = out.pop(old)
    return out

@dataclass
class TrainConfig:
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
    embedding_dim: int = 576
    """Dimension of the LLM summary embedding f^hc predicts (576 for SmolLM2-135M)."""
    lambda_a: float = BONUS_PRESETS["paper"]["lambda_a"]
    """Weight lambda of the action-generation bonus r^a (paper: 0.8)."""
    beta_hc: float = BONUS_PRESETS["paper"]["beta_hc"]
    """Weight beta of the history-compression bonus r^hc (paper: 0.5)."""
    tasks: tuple[str, ...] = ("action", "summary")
    """The language tasks the heads distil and the bonus pays for, any combination of action,
    summary, goal and plan (paper Table 2; `illm_tools.tasks.registry`): each has its own head on
    the policy's features and its own bonus, weighted by lambda_a (action), beta_hc (summary) or
    `task_weights`. Methods with iLLM's heads only."""
    task_weights: dict = field(default_factory=dict)
    """Bonus weights of the tasks without a setting of their own by name (`--task-weight plan=0.3`);
    unset ones weigh 0.5, as beta_hc (their heads are trained like f^hc, paper D.2)."""
    distill_coef: float = 1.0
    """Weight of the head distillation losses in the total loss."""
    distill_epochs: int = 1
    """Epochs of each update that train the heads (the 2 x 1024-unit heads cost as much as the rest
    of the update on CPU; later epochs train the policy alone)."""
    heads_bf16: bool | None = None
    """Run the heads' matmuls in bfloat16 on CPU (float32 parameters and losses); None: when a
    timed matmul says bf16 is faster on this CPU (it is on some, not on others; `illm_tools.llm.dtype`).
    The run records the answer in config.json and keeps it on resume, on any machine."""
    summary_loss: str = "cosine"
    """Distillation loss of f^hc: cosine (1 - cos) or mse."""
    action_similarity: str = "tv"
    """Similarity behind r^a = 1 - sim: tv (1 - total variation) or bhattacharyya."""
    int_gamma: float = 0.99
    """Discount of the intrinsic return and of its normaliser (RND uses 0.99)."""
    int_episodic: bool = False
    """Cut the intrinsic return at episode ends; False is RND's non-episodic stream."""
    ext_coef: float = BONUS_PRESETS["paper"]["ext_coef"]
    """Weight of the extrinsic advantage in the summed advantage."""
    int_coef: float = BONUS_PRESETS["paper"]["int_coef"]
    """Weight of the intrinsic advantage; 1 with ext_coef 1 matches r* = r + lambda r^a + beta r^hc."""
    reward_streams: int = 2
    """2: the bonus has its own value head and GAE (RND's two streams; `int_gamma`, `int_episodic`);
    1: the paper's Algorithm 1, r* = ext_coef r + int_coef b in one episodic stream with one critic."""
    bonus_schedule: str = "constant"
    """The intrinsic advantage's weight over the run (`illm_tools.rl.bonus_schedule`): constant,
    anneal (linear to 0 over the run), or success (1 - the running success rate: it fades as the
    level is solved)."""
    int_ext_cap: float = 0.0
    """Cap the intrinsic advantage at this multiple of the extrinsic one (mean |.| per rollout) where
    the task paid anything in the rollout; 0: no cap (the bonus alone steers until a reward is found)."""

    # --- LLM targets -----------------------------------------------------------------------
    cache: Path | None = None
    """Annotation cache the targets are read from (and live annotations written back to)."""
    model: str | None = None
    """LLM whose annotations are the targets (its fingerprint is part of every cache key); None: the
    backend's own (smollm2-135m for transformers, oracle for oracle)."""
    backend: str = "transformers"
    """LLM backend serving `model` (`illm_tools.llm.backend`): transformers, oracle (a rule-based
    annotator that knows BabyAI/MiniGrid: the positive control), or stub (deterministic answers from
    the prompt, no weights: for tests and benchmarks)."""
    oracle_noise: float = 0.0
    """oracle: the share of states (fixed, keyed by the state) whose answers are random (1: an
    annotator that knows nothing); part of the oracle's fingerprint."""
    endpoint: str | None = None
    """openai: the server's OpenAI base URL (http://host:8000/v1); `model` is the model as it serves it."""
    api_key_env: str | None = None
    """openai: the environment variable holding the server's API key (default OPENAI_API_KEY)."""
    embed_endpoint: str | None = None
    """openai: the URL of a pooling server of the same weights that embeds the summaries (as in `illm
    annotate --embed-endpoint`)."""
    model_dtype: str = "auto"
    """Compute dtype of that LLM (part of its fingerprint, as in `illm annotate --dtype`): bfloat16,
    float32, float16, or auto (bfloat16 on CUDA; on a CPU bfloat16 only where a timed matmul says
    it is faster, `illm_tools.llm.dtype`). The run records the resolved dtype in config.json."""
    quant: str = "auto"
    """Quantisation of that LLM (part of its fingerprint, as in `illm annotate --quant`): none, 4bit, 8bit,
    or auto (on CUDA what the model's alias says: 4bit for llama3/llama2; else none)."""
    layout: str = "shared"
    """Prompt template layout, as in `illm annotate --layout`."""
    action_score: str = "sum"
    """Calibration of the stored action log-probs: sum (paper), mean per token, or pmi."""
    action_target: str = "distribution"
    """f^a's target: distribution (softmax of the calibrated scores) or argmax (the one-hot of the
    best one: the paper's Algorithm 1 line 7 and Appendix A select the highest log-probability)."""
    live_budget: int | str = 16
    """Missed states handed to the live LLM after each rollout, most visited first: sync annotates
    them before the update; async gives them to the worker in place of its queue. 0: cache only;
    all: every missed state (with sync, a target on every step: for fast annotators such as the
    oracle, or an LLM on a GPU)."""
    live_mode: str = "async"
    """sync: annotate in the trainer's process, which waits; async: a worker process beside the
    rollouts, whose answers later rollouts use (the trainer never waits)."""
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
        check_numbers(self, positive=("total_steps", "num_envs", "num_steps", "num_minibatches", "update_epochs",
                                      "mission_max_len", "head_hidden", "embedding_dim", "learning_rate", "clip_coef",
                                      "max_grad_norm", "target_kl", "hop_beta", "checkpoint_minutes", "threads"),
                      non_negative=("seed", "num_dists", "hop_seed", "history_len", "lambda_a", "beta_hc", "ext_coef",
                                    "int_coef", "int_ext_cap", "distill_coef", "distill_epochs", "ent_coef", "vf_coef", "llm_threads",
                                    "checkpoint_every"),
                      unit=("gamma", "gae_lambda", "int_gamma", "oracle_noise"),
                      flags={"total_steps": "--frames", "history_len": "--history", "run_dir": "--out"})
        check_folder(self.run_dir, "--out")
        check_folder(self.cache, "--cache")
        from illm_tools.devices import check_device

        check_device(self.device)
        if self.llm_device is not None:
            check_device(self.llm_device, "--llm-device")
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
        from illm_tools.tasks.registry import get_task, parse_tasks

        self.tasks = parse_tasks(self.tasks, "--tasks")
        for name, weight in self.task_weights.items():
            if name not in self.tasks:
                raise UsageError(f"--task-weight {name}=...: {name} is not one of this run's --tasks "
                                 f"({','.join(self.tasks)})")
            if get_task(name).weight_setting is not None:
                raise UsageError(f"the {name} task's weight is --{get_task(name).weight_setting.replace('_', '-')}, "
                                 "not --task-weight")
            if not isinstance(weight, (int, float)) or weight < 0:
                raise UsageError(f"--task-weight {name}={weight!r}: a weight is a number >= 0")
        if self.tasks != ("action", "summary") and not get_method(self.method).policy_heads:
            reads = ", ".join(get_method(self.method).target_tasks) if get_method(self.method).needs_targets else ""
            raise UsageError(f"--tasks chooses the language tasks of iLLM's heads; --method {self.method} has none "
                             f"(it reads {reads or 'no language task'})")
        get_method(self.method).make_config(self.to_dict(), self.bonus_options)  # refuses unknown methods, options
        get_method(self.method).network_options(self.network_options)
        if self.batch_size % self.num_minibatches:
            raise UsageError(f"num_envs * num_steps = {self.batch_size} is not divisible by "
                             f"num_minibatches = {self.num_minibatches}")
        if self.summary_loss not in ("cosine", "mse"):
            raise UsageError(f"summary_loss must be cosine or mse, got {self.summary_loss!r}")
        if self.action_similarity not in ("tv", "bhattacharyya"):
            raise UsageError("action_similarity must be tv or bhattacharyya, "
                             f"got {self.action_similarity!r}")
        if self.needs_targets or self.obs_mode == "hop":  # refuses a bad backend, model, dtype, noise, endpoint, quant
            self.llm  # noqa: B018 - built to be checked
        else:  # a run without an LLM still refuses a backend or dtype that is no such thing
            from illm_tools.llm.backend import check_backend
            from illm_tools.llm.dtype import CHOICES

            if self.model_dtype not in CHOICES:
                raise UsageError(f"--dtype must be one of {', '.join(CHOICES)}, got {self.model_dtype!r}")
            check_backend(self.backend)
        if self.obs_mode not in OBS_MODES:
            raise UsageError(f"--mode is the observation mode, {' or '.join(OBS_MODES)}; got {self.obs_mode!r} "
                             "(the method is --method)")

    def resolved(self) -> "TrainConfig":
        """This config with the machine's choices made, as the run records them in config.json (and
        keeps on resume, on any machine): `device` and `llm_device` auto -> cpu or cuda (these two may
        change on resume), `model_dtype` auto -> the dtype `illm_tools.llm.dtype`
        measures and `quant` auto -> the model's alias on CUDA, else none (when the run uses an LLM), `heads_bf16` None -> whether bf16 is faster for the heads
        (when the method has them)."""
        from illm_tools.devices import resolve_device
        from illm_tools.llm.backend import backend_dtype, backend_quant

        changes: dict = {"device": resolve_device(self.device)}
        if self.needs_targets or self.obs_mode == "hop":
            changes["llm_device"] = resolve_device(self.llm_device or self.device, flag="--llm-device")
            if self.model_dtype == "auto":
                changes["model_dtype"] = backend_dtype(self.backend, "auto", changes["llm_device"])
            changes["quant"] = backend_quant(self.backend, self.llm_model, self.quant, changes["llm_device"])
        if self.heads_bf16 is None and self.uses_heads:
            from illm_tools.rl.networks import bf16_is_faster

            changes["heads_bf16"] = bf16_is_faster()
        return dataclasses.replace(self, **changes)

    # --- derived values ----------------------------------------------------------------------
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
    def llm(self) -> LLMSpec:
        """The run's LLM (its targets' model, the live annotator's, hop's embeddings) as one value; on
        a `resolved()` config its device and dtype are this machine's choices."""
        return LLMSpec(backend=self.backend, model=self.model, dtype=self.model_dtype, quant=self.quant,
                       device=self.llm_device or self.device, oracle_noise=self.oracle_noise, endpoint=self.endpoint,
                       api_key_env=self.api_key_env, embed_endpoint=self.embed_endpoint)

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

    def to_dict(self) -> dict:
        """JSON-ready form (paths as strings)."""
        out = asdict(self)
        out["tasks"] = list(self.tasks)
        out["env_seeds"] = list(self.env_seeds)
        out["run_dir"] = str(self.run_dir)
        out["cache"] = str(self.cache) if self.cache is not None else None
        return out

    @classmethod
    def comparable(cls, data: dict) -> dict:
        """A run's config.json as runs are compared (`illm report`): every setting at its value, or
        its default where an older run lacks it, without the settings the run's method and mode
        ignore: the hop translation's in obs mode, the LLM's dtype and quantisation under a backend
        that has none (the oracle), every LLM and target setting for a method that reads no targets
        and is not in hop mode, and iLLM's bonus weights for a method without its heads. A config
        this version cannot read is returned as it is."""
        data = upgrade_config(data)
        try:
            cfg = cls.from_dict({**{k: v for k, v in data.items() if k in cls.__dataclass_fields__}, "resume": False})
        except Exception:  # noqa: BLE001 - another version's run: compared as written
            return dict(data)
        out = {**data, **cfg.to_dict()}
        drop = set()
        if cfg.obs_mode == "obs":
            drop |= {"hop_seed", "hop_beta"}
        if not cfg.needs_targets and cfg.obs_mode != "hop":
            drop |= {"model", "backend", "model_dtype", "quant", "oracle_noise", "history_len", "layout",
                     "action_score", "action_target", "tasks", "task_weights", "live_budget", "live_mode", "annotator",
                     "embedding_dim"}
        else:
            from illm_tools.llm.backend import backend_class

            if not getattr(backend_class(cfg.backend), "computes", True):
                drop |= {"model_dtype", "quant"}
        if not cfg.uses_heads:
            drop |= {"lambda_a", "beta_hc", "distill_coef", "distill_epochs", "summary_loss", "action_similarity",
                     "head_hidden"}
        if out.get("model") is None and "model" not in drop:  # the backend's default, named as a given one is
            from illm_tools.llm.backend import resolve_model

            out["model"] = resolve_model(cfg.backend, None)
        return {k: v for k, v in out.items() if k not in drop}

    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        """Inverse of `to_dict` (an older run's names upgraded, `upgrade_config`); unknown keys are refused."""
        data = upgrade_config(data)
        known = set(cls.__dataclass_fields__)
        unknown = set(data) - known
        if unknown:
            raise UsageError(f"unknown training settings {sorted(unknown)}")
        return cls(**data)


@dataclass
class EvalConfig:
    """An `illm eval`: which trained runs, on how many fresh episodes, acting how."""

    runs: tuple[Path, ...]
    """Run folders written by `illm train` (several give a table)."""
    episodes: int = 100
    """Episodes to play per run."""
    seed: int = 0
    """Evaluation seed (episodes are disjoint from training seeds)."""
    greedy: bool = False
    """Take the most likely action instead of sampling."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_numbers

        self.runs = tuple(Path(r) for r in self.runs)
        check_numbers(self, positive=("episodes",), non_negative=("seed",))
        missing = [str(r) for r in self.runs if not (r / "config.json").is_file()]
        if missing or not self.runs:
            raise UsageError(f"no training run at {', '.join(missing[:3]) or '(none given)'}: pass folders written "
                             "by `illm train`")
