"""`illm experiment SPEC.yaml`: a grid of training runs (methods x envs x settings x seeds) under one
results folder, run N at a time, finished runs skipped and unfinished ones resumed.

A spec (YAML; experiments/specs/ holds the paper's tables at CPU budgets):

    name: table1-distractors
    frames: 50000                 # per run (the paper: 100M; `--frames` overrides, env_frames too)
    env_frames:                   # per env, over `frames` (a level that needs more)
      BabyAI-GoToLocal-v0: 60000
    seeds: [0, 1, 2]              # or a count: 3 (`--seeds` overrides)
    envs: [BabyAI-GoToLocal-v0]
    methods: [ppo, rnd, illm]
    grid:                         # every combination of these values (`illm train`'s settings by
      num_dists: [4, 8, 16]       # name, or env_options.KEY for an env option)
    method_grid:                  # per method, more values crossed with `grid` (e.g. the oracle's
      illm: {oracle_noise: [0, 0.5, 1]}   # quality for illm alone)
    settings:                     # for every run (`illm train`'s settings by name)
      num_envs: 16
    method_settings:              # per method, over `settings`
      illm: {cache: data/ann, history_len: 0, live_budget: 16}
    paper:                        # what the paper sets (not run; checked by the test suite): its
      source: Table 1             # rows, grid values, frames and seeds, and `differs`: each setting
      methods: [rnd, illm]        # this spec sets otherwise, with the reason
      grid: {num_dists: [4, 8, 16]}
      frames: 100000000
      seeds: 10
      differs: {frames: "a CPU budget", seeds: "a CPU budget"}

A grid value may be a mapping: a bundle of settings applied together, named by its `name` key (the
label's value), e.g. `annotator: [{name: oracle, backend: oracle}, {name: gpt2, model: gpt2}]`. The
spec's name, a bundle's name and a plain grid value become folders, so each must be a bare name
(`illm_tools.folders.bare_name`: no `/`, `\\` or `..`); a grid of paths is written as bundles.

Everything is checked before anything runs: the top-level keys, the method names, the env ids, the
setting names (each a setting of `illm train` under its flat name, `illm_tools.rl.config.FLAT`: model,
model_dtype, lambda_a, ...; or `env_options.<name>`, which its suite checks) and their values (every
run's TrainConfig is built, by `illm_tools.rl.build.run_config` as `illm train` builds one: the
preset expanded, the cache's setup adopted where no model option is set, a resumed run's own
settings merged); a bad one is refused in one line naming the spec's line. A run's folder is RESULTS/<env>/<label>/seed<n> (the label: the method
and the grid values, e.g. `illm-num_dists=8`); the spec is copied to RESULTS/spec.yaml, and a
results folder made from another spec is refused (grids never mix). A run whose checkpoint has
reached its frames is skipped, one with a checkpoint short of them is resumed (`--resume`), the
rest start; runs go `jobs` at a time, each in a process of its own with one torch thread.
`--only PATTERN` (repeatable) trains a part of the grid: the runs whose label (`ppo`,
`illm-annotator=student`) or path under the results folder (`BabyAI-GoToLocal-v0/ppo/seed0`) a
pattern matches (shell wildcards); the rest are left as they are, for a later call.

Modules: spec.py, the spec file read and checked (`Spec`, `load_spec`, `Cluster`); config.py, the
command's options (`ExperimentConfig`); plan.py, the grid planned into runs (`plan`, `select`,
`claim_results`); launch.py, the runs trained (`run_experiment`).
"""
from illm_tools.experiment.config import LAUNCHERS, ExperimentConfig, check_launcher
from illm_tools.experiment.launch import POLL_S, run_experiment
from illm_tools.experiment.plan import SPEC_COPY, Run, claim_results, plan, select, unavailable_models
from illm_tools.experiment.spec import TOP_KEYS, Cluster, Spec, load_spec

__all__ = ["LAUNCHERS", "POLL_S", "SPEC_COPY", "TOP_KEYS", "Cluster", "ExperimentConfig", "Run", "Spec",
           "check_launcher", "claim_results", "load_spec", "plan", "run_experiment", "select", "unavailable_models"]
