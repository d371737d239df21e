"""TrainConfig: every setting of a PPO / iLLM training run, one documented field each, composed
of its parts as vLLM's `VllmConfig` is of sub-configs.

The run's own settings are fields (the env, the method, the rollout's size, devices and
bookkeeping); the rest are its parts, each a dataclass declared and validated once where it lives:
`ppo` (`PPOConfig`), `bonus` (`BonusConfig`: how the bonus is paid and iLLM's heads trained),
`targets` (`TargetsConfig`: the cache and the live fallback), `setup` (`PromptConfig`: how a state
becomes a prompt, as `illm annotate`, `illm serve` and `illm probe` hold it), `llm` (`LLMSpec`) and
`illm` (`ILLMConfig`). Every setting also has one flat name, its field's (`PART_NAMES` gives the two
the LLM's part renames: model_dtype, llm_device), which is its option (`cli.options`), its key in
experiment specs and in the config.json files written before the config was composed: `flat()`
gives a config's settings so, `from_dict` reads them (and the composed form `to_dict` writes).
`illm_tools.rl.build.run_config` builds a run's config from what was given (presets, a resumed
run, the cache's setup). `TrainConfig()` is what `illm train` trains with no option (the illm
method, the `small` preset); for another method `run_config({"method": ...})` adds its preset.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from illm_tools.errors import UsageError
from illm_tools.intrinsic.illm_config import ILLMConfig
from illm_tools.intrinsic.registry import get_method
from illm_tools.llm.spec import LLMSpec
from illm_tools.rl.run_parts import BonusConfig, PPOConfig, TargetsConfig
from illm_tools.settings import setting
from illm_tools.tasks.prompt_config import PromptConfig
from illm_tools.tasks.annotation_setup import AnnotationSetup


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
class TrainConfig:
    """One training run: environment, PPO, iLLM bonus, and bookkeeping."""

    # --- run -------------------------------------------------------------------------------
    env_id: str = setting("BabyAI-GoToLocal-v0", flag="--env")
    """Id of the environment (BabyAI/MiniGrid, MiniHack, Crafter, Atari: `illm envs` lists them)."""
    run_dir: Path = setting(Path("data/runs/default"), flag="--out", resumes=True)
    """Folder for config.json, metrics.jsonl, TensorBoard events and checkpoint.pt."""
    method: str = "illm"
    """The method, a name in the registry `illm_tools.intrinsic.registry` (its bonus and network)."""
    network_options: dict = setting(factory=dict, flag="--network-option")
    """Settings of the method's policy network by name (e.g. chibit's blocks; `--network-option
    KEY=VALUE`); unset ones keep their defaults."""
    bonus_options: dict = setting(factory=dict, flag="--bonus-option")
    """Settings of the method's bonus by name (the fields of its config dataclass, e.g. rnd's
    update_proportion; `--bonus-option KEY=VALUE`); unset ones keep their defaults."""
    seed: int = 0
    """Seed of the network initialisation, action sampling, minibatch order and env pool."""
    total_steps: int = setting(200_000, flag="--frames", resumes=True)
    """Environment steps to train for, summed over the parallel envs."""
    num_envs: int = 16
    """Environments stepped side by side."""
    num_steps: int = 128
    """Steps per env in one rollout; a rollout holds num_envs * num_steps transitions."""
    action_space: str = setting("auto", auto=True)
    """Action vocabulary: BabyAI's original (3), augmented (6) or irrelevant (9), paper Table 5
    (other suites offer one each, `illm envs`); auto: the suite's default (BabyAI: original for the
    GoTo levels, paper Tables 1 and 5, augmented otherwise). The run records the resolved name."""
    num_dists: int | None = None
    """Distractor count for levels that take it; None keeps the level's default."""
    mission_max_len: int = 32
    """Mission words kept (longer missions are truncated)."""
    threads: int = setting(1, resumes=True)
    """Torch threads for the policy (small nets run best on one)."""
    device: str = setting("auto", resumes=True, machine=True)
    """Where the policy, the bonus's models and the rollout live: cpu, cuda, cuda:N or auto (a GPU
    where there is one; for many small runs side by side on one GPU machine, cpu). Actions are sampled on the CPU from the run's seeded generator; a run may
    resume on another device."""
    # --- bookkeeping -----------------------------------------------------------------------
    checkpoint_every: int = setting(10, resumes=True)
    """Save a checkpoint every this many updates, after the first and the last one, and when a
    signal stops the run; 0: only those."""
    checkpoint_minutes: float = setting(5.0, resumes=True)
    """Also save a checkpoint when this many minutes have passed since the last one."""
    resume: bool = setting(False, resumes=True)
    """Continue from run_dir/checkpoint.pt instead of starting fresh."""
    tensorboard: bool = setting(True, resumes=True)
    """Also write TensorBoard events beside metrics.jsonl."""
    env_seeds: tuple[int, ...] = ()
    """Episode seeds the envs cycle through instead of a new seed every episode: a fixed set of
    layouts (one seed: one MultiRoom map, so a visitation heatmap shows one map, as paper Figure 1);
    evaluation then plays the same layouts. Empty: every episode its own seed."""
    env_options: dict = setting(factory=dict, flag="--env-option")
    """Options of the environment, its suite's (`--env-option KEY=VALUE`, e.g. max_episode_steps;
    `illm envs` lists the suites)."""
    vector: str = setting("auto", resumes=True)
    """How the envs step: sync (all in this process), async (a process each: slow envs such as
    Crafter), auto (the suite's choice)."""

    # --- the parts ---------------------------------------------------------------------------
    ppo: PPOConfig = field(default_factory=PPOConfig)
    """PPO's hyperparameters (`illm_tools.rl.run_parts.PPOConfig`)."""
    bonus: BonusConfig = field(default_factory=BonusConfig)
    """How the bonus reaches the advantages and iLLM's heads are trained (`BonusConfig`)."""
    targets: TargetsConfig = field(default_factory=TargetsConfig)
    """Where the LLM targets come from: the cache and the live fallback (`TargetsConfig`)."""
    setup: PromptConfig = field(default_factory=PromptConfig)
    """How a state becomes a prompt (`illm_tools.tasks.prompt_config.PromptConfig`): --history, --layout,
    --mode, --hop-seed, --hop-beta, as in `illm annotate`."""
    llm: LLMSpec = field(default_factory=LLMSpec)
    """The LLM whose annotations are the targets (its fingerprint is part of every cache key), the live
    annotator's and hop's (options --backend, --model, --dtype, --quant, --oracle-noise, --endpoint, ...,
    as in `illm annotate`; its device --llm-device, unset: the run's --device). `resolved()` records its
    device, dtype and quantisation as chosen on this machine."""
    illm: ILLMConfig = field(default_factory=ILLMConfig)
    """iLLM's own settings (`illm_tools.intrinsic.illm_config.ILLMConfig`; options --lambda-a, --beta-hc,
    --tasks, --task-weight, --summary-loss, --action-similarity). Defaults: the `small` preset."""

    def __post_init__(self) -> None:
        from illm_tools.devices import check_device
        from illm_tools.settings import check_folder, check_numbers

        self.run_dir = Path(self.run_dir)
        for name, part in PARTS.items():  # a part's dict form (config.json): validated by the part
            value = getattr(self, name)
            if not isinstance(value, part):
                setattr(self, name, part(**part_settings(name, value)))
        check_numbers(self, positive=("total_steps", "num_envs", "num_steps", "mission_max_len", "checkpoint_minutes",
                                      "threads"),
                      non_negative=("seed", "num_dists", "checkpoint_every"))
        check_folder(self.run_dir, "--out")
        check_device(self.device)
        self.env_seeds = parse_seeds(self.env_seeds)
        if self.bonus.bonus_schedule == "success":
            from illm_tools.envs import suite_of

            if suite_of(self.env_id).score_name != "success rate":
                raise UsageError(f"--bonus-schedule success fades the bonus with the success rate, and "
                                 f"{self.env_id}'s score is its {suite_of(self.env_id).score_name}: use constant or "
                                 "anneal")
        method = get_method(self.method)  # refuses an unknown method
        if self.illm.tasks != ILLMConfig().tasks and not method.policy_heads:
            reads = ", ".join(method.target_tasks) if method.needs_targets else ""
            raise UsageError(f"--tasks chooses the language tasks of iLLM's heads; --method {self.method} has none "
                             f"(it reads {reads or 'no language task'})")
        method.make_config({"illm": self.illm}, self.bonus_options)  # refuses unknown or ill-typed bonus options
        method.network_options(self.network_options)
        if self.batch_size % self.ppo.num_minibatches:
            raise UsageError(f"num_envs * num_steps = {self.batch_size} is not divisible by "
                             f"num_minibatches = {self.ppo.num_minibatches}")

    def resolved(self) -> TrainConfig:
        """This config with the machine's and the env's choices made, as the run records them in
        config.json (and keeps on resume, on any machine); a run resolves its config once, when it
        starts (`illm_tools.rl.run.train`). `device` and the LLM's device auto (or unset: the run's)
        -> cpu or cuda (these two may change on resume); when the run uses an LLM, its dtype auto ->
        the dtype `illm_tools.llm.dtype` measures and its quantisation auto -> the model's alias on
        CUDA, else none; `heads_bf16` None -> whether bf16 is faster for the heads (when the method
        has them); `action_space` auto -> the suite's default for the env (`resolve_action_space`). Resolving a resolved config changes nothing."""
        from illm_tools.devices import resolve_device
        from illm_tools.llm.backend import backend_dtype, backend_quant

        changes: dict = {"device": resolve_device(self.device), "action_space": self.resolved_action_space()}
        if self.uses_llm:
            llm = self.llm
            device = resolve_device(llm.device or self.device, flag="--llm-device")
            dtype = backend_dtype(llm.backend, "auto", device) if llm.dtype == "auto" else llm.dtype
            changes["llm"] = dataclasses.replace(llm, device=device, dtype=dtype,
                                                 quant=backend_quant(llm.backend, llm.model, llm.quant, device))
        if self.bonus.heads_bf16 is None and self.uses_heads:
            from illm_tools.rl.networks import bf16_is_faster

            changes["bonus"] = dataclasses.replace(self.bonus, heads_bf16=bf16_is_faster())
        if all(getattr(self, k) == v for k, v in changes.items()):
            return self
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """JSON-ready form, as config.json holds it: the run's own settings, each part as a dict of
        its settings (paths as strings)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in PARTS}
        out.update({name: part_settings(name, getattr(self, name)) for name in PARTS})
        out.update(env_seeds=list(self.env_seeds), run_dir=str(self.run_dir), network_options=dict(self.network_options),
                   bonus_options=dict(self.bonus_options), env_options=dict(self.env_options))
        out["targets"]["cache"] = None if self.targets.cache is None else str(self.targets.cache)
        return out

    def flat(self) -> dict:
        """The settings under their flat names (the options', as specs name them), values as this
        config holds them: how runs are compared (resume, `illm report`)."""
        out = {}
        for flat, (part, name) in FLAT.items():
            value = getattr(self if part is None else getattr(self, part), name)
            out[flat] = list(value) if isinstance(value, tuple) else str(value) if isinstance(value, Path) else value
        return {**out, **self.illm.to_dict()}  # its tasks and task weights as it writes them

    @classmethod
    def from_dict(cls, data: Mapping) -> TrainConfig:
        """Inverse of `to_dict`; also reads settings under their flat names and an older run's
        config.json (`upgrade_config`); unknown keys are refused."""
        data = upgrade_config(data)
        unknown = set(data) - set(cls.__dataclass_fields__)
        if unknown:
            raise UsageError(f"unknown training settings {sorted(unknown)}")
        return cls(**data)

    # --- what the run derives from its settings (nothing here is a setting) -------------------
    @property
    def batch_size(self) -> int:
        """Transitions per rollout."""
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        """Transitions per minibatch."""
        return self.batch_size // self.ppo.num_minibatches

    @property
    def num_updates(self) -> int:
        """Rollout + update iterations in the run (at least one)."""
        return max(1, self.total_steps // self.batch_size)

    def resolved_action_space(self) -> str:
        """`action_space`, or for auto the suite's default for the env
        (`illm_tools.envs.resolve_action_space`); a resumed run's config comes with the space it
        recorded (`illm_tools.rl.build.resumed`)."""
        from illm_tools.envs import resolve_action_space

        return resolve_action_space(self.env_id, self.action_space)

    @property
    def uses_heads(self) -> bool:
        """Whether the network carries f^a / f^hc and the loss distils the LLM (the method says)."""
        return get_method(self.method).policy_heads

    @property
    def needs_targets(self) -> bool:
        """Whether the run reads LLM targets (an annotation cache; the method says)."""
        return get_method(self.method).needs_targets

    @property
    def pays_bonus(self) -> bool:
        """Whether the intrinsic rewards reach the advantages."""
        return get_method(self.method).pays

    @property
    def uses_llm(self) -> bool:
        """Whether the run loads or reads an LLM: its targets (the bonus reads them) or hop's translation."""
        return self.needs_targets or self.setup.hop

    @property
    def embedding_dim(self) -> int:
        """Width of the LLM's text embeddings (its hidden size; 576 for SmolLM2-135M), what each text
        head of the policy predicts: read from the model's config, without loading weights."""
        cache = self.targets.cache
        return _hidden_size(self.llm.backend, self.llm.model, None if cache is None else str(cache))

    @property
    def annotation_setup(self) -> AnnotationSetup:
        """The key inputs of the run's targets besides the state and the model: env, renderer (text,
        or hop's translation), the tasks it reads, history and layout."""
        return self.setup.of(self.env_id, self.target_tasks)

    @property
    def target_tasks(self) -> tuple[str, ...]:
        """The language tasks whose cache rows the run reads: the heads' (`illm.tasks`), or those the
        method's bonus reads (ELLM: goal)."""
        method = get_method(self.method)
        return self.illm.tasks if method.policy_heads else method.target_tasks

    @property
    def text_tasks(self) -> tuple[str, ...]:
        """The text tasks among the heads' (each a head of `embedding_dim` outputs)."""
        from illm_tools.tasks.registry import text_tasks

        return text_tasks(self.illm.tasks) if get_method(self.method).policy_heads else ()


PARTS = {"ppo": PPOConfig, "bonus": BonusConfig, "targets": TargetsConfig, "setup": PromptConfig, "llm": LLMSpec,
         "illm": ILLMConfig}
"""TrainConfig's parts: field -> its config class."""
PART_NAMES = {(part, f.name): f.metadata["flat"] for part, cls in PARTS.items() for f in dataclasses.fields(cls)
              if "flat" in f.metadata}
"""The flat names of the part fields whose own name a run's other settings take (`setting(flat=...)`: the LLM's
dtype and device, model_dtype and llm_device)."""
NOT_SETTINGS = {(part, f.name) for part, cls in PARTS.items() for f in dataclasses.fields(cls)
                if f.metadata.get("run_setting") is False}
"""Part fields that are no run setting (`setting(run_setting=False)`: a run never downloads what it lacks,
and its live annotator's batches take the default budget)."""
FLAT = {f.name: (None, f.name) for f in dataclasses.fields(TrainConfig) if f.name not in PARTS and f.name != "illm"}
FLAT.update({PART_NAMES.get((part, f.name), f.name): (part, f.name) for part, cls in PARTS.items()
             for f in dataclasses.fields(cls) if (part, f.name) not in NOT_SETTINGS})
"""Every setting's flat name -> (its part, None for the run's own, and its field there)."""
RENAMED = {"mode": "method"}
"""Settings renamed since runs were first written (old name -> new): config.json files and
checkpoints of older runs are read under the new names."""
DERIVED = ("embedding_dim",)
"""Settings older versions wrote that are now derived from others: dropped on reading."""


def part_settings(part: str, value) -> dict:
    """A part's value (its config object or dict form) as a dict of its settings (`NOT_SETTINGS` left out)."""
    if value is None:
        return {}
    if isinstance(value, Mapping):
        return dict(value)
    if hasattr(value, "to_dict"):
        return value.to_dict()
    return {f.name: getattr(value, f.name) for f in dataclasses.fields(value) if (part, f.name) not in NOT_SETTINGS}


def upgrade_config(data: Mapping) -> dict:
    """A run's settings as written by any version (flat, composed or a mix: a flat name wins) in
    this version's shape: renamed names (`RENAMED`) under their new names, derived ones dropped,
    flat names (`FLAT`) moved into their parts."""
    out = dict(data)
    for old, new in RENAMED.items():
        if old in out and new not in out:
            out[new] = out.pop(old)
    for name in DERIVED:
        out.pop(name, None)
    for part in PARTS:
        if part in out and not isinstance(out[part], Mapping):
            out[part] = part_settings(part, out[part])
    for flat, (part, name) in FLAT.items():
        if part is not None and flat in out and flat not in PARTS:
            out[part] = {**out.get(part, {}), name: out.pop(flat)}
    return out


def flat_settings(data: Mapping) -> dict:
    """A config's settings (`TrainConfig.to_dict()` or a config.json of any version) under their
    flat names, as `TrainConfig.flat` gives them, with any key this version does not know kept."""
    out = upgrade_config(data)
    known = {k: out.pop(k) for k in list(out) if k in TrainConfig.__dataclass_fields__}
    return {**out, **TrainConfig.from_dict(known).flat()}


def flag_of(name: str) -> str:
    """The option that sets the setting of flat name `name` ("--frames" for total_steps)."""
    from illm_tools.settings import flag_of as own_flag

    part, field_name = FLAT.get(name, (None, name))
    if (part, field_name) in PART_NAMES:
        return own_flag(name)
    return own_flag(field_name, TrainConfig if part is None else PARTS[part])


@functools.lru_cache(maxsize=None)
def _hidden_size(backend: str, model: str, cache: str | None = None) -> int:
    """A model's hidden size, read once per process (`LLMSpec.hidden_size`); for a model only its
    engine can describe (openai) when none answers, the width of the embeddings `cache` holds of it."""
    from illm_tools.errors import EngineUnreachableError

    try:
        return LLMSpec(backend=backend, model=model).hidden_size()
    except EngineUnreachableError:
        from illm_tools.tasks.served import cached_identity

        found = cached_identity(cache, backend, model)
        if found is None or found[1] is None:
            raise
        return found[1]
