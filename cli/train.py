"""`illm train` and `illm eval`: PPO with the iLLM heads on cached LLM targets, and evaluation."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.common import emit_json, progress, stop_on_signals
from cli.errors import friendly

# `illm train` option -> TrainConfig field, where the names differ
FIELDS = {"env": "env_id", "out": "run_dir", "method": "mode", "frames": "total_steps", "history": "history_len",
          "dtype": "model_dtype", "bonus_option": "bonus_options", "network_option": "network_options"}
WEIGHTS = ("lambda_a", "beta_hc", "ext_coef", "int_coef")


def _pairs(values: list[str], flag: str) -> dict[str, str]:
    """KEY=VALUE strings as a dict (typed and checked later by the option's owner)."""
    from illm_tools.errors import UsageError

    out = {}
    for value in values:
        key, sep, rest = value.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"{flag} takes KEY=VALUE, got {value!r}")
        out[key.strip()] = rest.strip()
    return out


def _given(ctx: typer.Context) -> set[str]:
    """The options the user typed (not left at their defaults)."""
    # by name: Typer may carry its own copy of click, whose ParameterSource is another enum
    return {name for name in ctx.params if getattr(ctx.get_parameter_source(name), "name", "") == "COMMANDLINE"}


def resumed_config(ctx: typer.Context, out: Path, fields: dict):
    """The TrainConfig of `illm train --out RUN --resume`: the run's own settings from its
    config.json, with the options given now applied where a resumed run may change them
    (RESUMABLE_CHANGES: --frames, --live-budget, threads, ...). Any other option that differs
    from the run's setting is refused in one line naming it; the run folder may have moved."""
    from illm_tools.errors import UsageError
    from illm_tools.rl.checkpoint import RESUMABLE_CHANGES, read_config
    from illm_tools.rl.config import TrainConfig

    stored = read_config(out)
    given = _given(ctx) - {"resume", "out"}
    flag = {FIELDS.get(name, name): name for name in ctx.params}
    if "bonus_preset" in given:  # a preset stands for its four weights
        given |= {w for w in WEIGHTS if w not in given}
    changes = {FIELDS.get(name, name): fields[FIELDS.get(name, name)] for name in given if name != "bonus_preset"}
    refused = sorted(f"--{flag.get(k, k).replace('_', '-')} (the run has {stored.get(k)!r})"
                     for k, v in changes.items() if stored.get(k) != v and k not in RESUMABLE_CHANGES)
    if refused:
        allowed = sorted(f"--{flag[k].replace('_', '-')}" for k in RESUMABLE_CHANGES if k in flag and k != "resume")
        raise UsageError(f"--resume continues {out} with its own settings, and {', '.join(refused)} would change what "
                         f"it learns: leave {'them' if len(refused) > 1 else 'it'} out, or train into a new --out (a resumed run may change {', '.join(allowed)})")
    return TrainConfig.from_dict({**stored, **changes, "run_dir": str(out), "resume": True})


def register(app: typer.Typer) -> None:
    from illm_tools.intrinsic.registry import method_help  # light: names only, no torch

    @app.command(epilog="Example: illm train --env BabyAI-GoToLocal-v0 --cache data/ann --method illm "
                        "--frames 200000 --seed 0 --out runs/gotolocal-illm")
    @friendly
    def train(
        ctx: typer.Context,
        env: str = typer.Option("BabyAI-GoToLocal-v0", "--env", help="Environment id."),
        out: Path = typer.Option(..., "--out", help="Run folder: config.json, checkpoint.pt, metrics.csv, TensorBoard events."),
        method: str = typer.Option("illm", "--method", help=method_help() + "."),
        cache: Path = typer.Option(None, "--cache", help="Annotation cache with the LLM targets (needed by illm methods)."),
        model: str = typer.Option("smollm2-135m", "--model", help="LLM whose annotations are the targets (as in `illm annotate`)."),
        frames: int = typer.Option(200_000, "--frames", help="Environment steps to train for."),
        seed: int = typer.Option(0, "--seed", help="Seed of the network, sampling and episodes."),
        live_budget: int = typer.Option(16, "--live-budget", help="Missed states handed to the live LLM after each rollout, most visited first (sync: about 1 s each on 2 CPU cores); 0: cache only."),
        live_mode: str = typer.Option("async", "--live-mode", help="async: the LLM annotates in a worker process beside the rollouts, later rollouts use its answers | sync: the trainer waits for them."),
        new_setup: bool = typer.Option(False, "--new-setup", help="Accept a cache whose annotations are all of another setup (model, dtype, quant, history, layout): live annotation starts this one."),
        action_score: str = typer.Option("sum", "--action-score", help="Calibration of the action log-probs: sum | mean | pmi."),
        action_target: str = typer.Option("distribution", "--action-target", help="f^a's target: distribution (softmax of the scores) | argmax (one-hot of the best: the paper's Alg. 1 line 7)."),
        history: int = typer.Option(3, "--history", help="History pairs in the prompts (must match the annotation)."),
        layout: str = typer.Option("shared", "--layout", help="Prompt layout (must match the annotation): shared | paper."),
        dtype: str = typer.Option("bfloat16", "--dtype", help="LLM compute dtype (must match the annotation)."),
        quant: str = typer.Option("none", "--quant", help="LLM quantisation (must match the annotation): none | 4bit | 8bit."),
        bonus_preset: str = typer.Option(None, "--bonus-preset", help="paper (lambda 0.8, beta 0.5, ext/int advantage weights 1, 1) | rnd (CleanRL RND's weights 2, 1); default: the method's own (rnd: rnd, others: paper); explicit flags win."),
        network_option: list[str] = typer.Option(None, "--network-option", help="KEY=VALUE setting of the method's policy network, repeatable (chibit: blocks=1, model=smollm2-135m)."),
        bonus_option: list[str] = typer.Option(None, "--bonus-option", help="KEY=VALUE setting of the method's bonus, repeatable (e.g. rnd: update_proportion=0.5); see illm_tools.intrinsic.registry."),
        lambda_a: float = typer.Option(None, "--lambda-a", help="Weight of the action bonus r^a (from --bonus-preset: 0.8)."),
        beta_hc: float = typer.Option(None, "--beta-hc", help="Weight of the summary bonus r^hc (from --bonus-preset: 0.5)."),
        ext_coef: float = typer.Option(None, "--ext-coef", help="Weight of the extrinsic advantage (from --bonus-preset: paper 1, rnd 2)."),
        int_coef: float = typer.Option(None, "--int-coef", help="Weight of the intrinsic advantage (from --bonus-preset: 1)."),
        num_envs: int = typer.Option(16, "--num-envs", help="Parallel environments."),
        num_steps: int = typer.Option(128, "--num-steps", help="Steps per env per rollout."),
        action_space: str = typer.Option("auto", "--action-space", help="original | augmented | irrelevant | auto: original for GoTo levels (paper Tables 1, 5), augmented otherwise."),
        num_dists: int = typer.Option(None, "--num-dists", help="Distractors, for levels that take it."),
        threads: int = typer.Option(1, "--threads", help="Torch threads for the policy."),
        llm_threads: int = typer.Option(0, "--llm-threads", help="Torch threads for live annotation; 0: sync all cores, async the cores --threads leaves."),
        resume: bool = typer.Option(False, "--resume", help="Continue the run in --out from its last checkpoint."),
    ) -> None:
        """Train PPO with the method's intrinsic bonus (iLLM: heads and rewards on LLM targets read from the cache)."""
        from illm_tools.intrinsic.registry import get_method
        from illm_tools.rl.config import TrainConfig, bonus_weights
        from illm_tools.rl.run import train as run

        spec = get_method(method)
        weights = bonus_weights(bonus_preset or spec.preset, lambda_a=lambda_a, beta_hc=beta_hc, ext_coef=ext_coef, int_coef=int_coef)
        fields = dict(env_id=env, run_dir=out, mode=method, seed=seed, total_steps=frames, num_envs=num_envs,
                      num_steps=num_steps, action_space=action_space, num_dists=num_dists, history_len=history,
                      cache=cache, model=model, model_dtype=dtype, quant=quant, layout=layout, action_score=action_score,
                      action_target=action_target, live_budget=live_budget, live_mode=live_mode, new_setup=new_setup,
                      threads=threads, llm_threads=llm_threads, resume=resume,
                      bonus_options=spec.parse_options(bonus_option or []),
                      network_options=_pairs(network_option or [], "--network-option"), **weights)
        cfg = resumed_config(ctx, out, fields) if resume else TrainConfig(**fields)
        method, env = cfg.mode, cfg.env_id
        if cfg.num_updates * cfg.batch_size != cfg.total_steps:
            typer.echo(f"--frames {cfg.total_steps:,} is not a whole number of rollouts ({cfg.num_envs} envs × "
                       f"{cfg.num_steps} steps = {cfg.batch_size:,} frames each): the run trains "
                       f"{cfg.num_updates * cfg.batch_size:,} frames", err=True)
        last: dict = {}
        coverage: list[float] = []
        with stop_on_signals("the current update, then writing a checkpoint") as stop, \
                progress(cfg.num_updates * cfg.batch_size, f"train {method}", unit="steps") as advance:
            def on_metrics(m: dict) -> None:
                last.update(m)
                fields = {"success": f"{m.get('charts/success_rate', float('nan')):.2f}"}
                if cfg.needs_targets:
                    coverage.append(m.get("charts/target_coverage", 0.0))
                    fields["targets"] = f"{coverage[-1]:.2f}"
                    if "charts/live_queue" in m:
                        fields["live_queue"] = f"{m['charts/live_queue']:.0f}"
                advance(cfg.batch_size, m.get("charts/sps"), **fields)

            result = run(cfg, on_metrics, should_stop=lambda: stop.requested)
        if result.get("already_done"):
            typer.echo(f"{out} is already at {result['global_step']:,} frames (--frames {cfg.total_steps:,}): nothing "
                       "to do; pass a larger --frames with --resume to train on")
            return
        targets = f"; steps with an LLM target {sum(coverage) / len(coverage):.0%} on average" if coverage else ""
        if result.get("stopped"):
            typer.echo(f"stopped at {result['global_step']:,} frames{targets}; resume with "
                       f"`illm train --out {out} --resume`")
            raise typer.Exit(stop.exit_code)
        typer.echo(f"trained {method} on {env} to {last.get('global_step', 0):,} frames "
                   f"({last.get('charts/sps', 0):,.0f} steps/s); last success rate "
                   f"{last.get('charts/success_rate', float('nan')):.2f}{targets} -> {out}")

    @app.command("eval", epilog="Example: illm eval runs/gotolocal-illm --episodes 100")
    @friendly
    def evaluate(
        runs: list[Path] = typer.Argument(..., help="Run folders written by `illm train` (several give a table)."),
        episodes: int = typer.Option(100, "--episodes", help="Episodes to play per run."),
        seed: int = typer.Option(0, "--seed", help="Evaluation seed (episodes are disjoint from training seeds)."),
        greedy: bool = typer.Option(False, "--greedy", help="Take the most likely action instead of sampling."),
        as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
    ) -> None:
        """Success rate and mean return of trained policies on the same fresh episodes (a markdown
        table; --json: a list with one object per run)."""
        from illm_tools.errors import UsageError
        from illm_tools.rl.run import evaluate as run

        if episodes <= 0:
            raise UsageError(f"--episodes must be positive, got {episodes}")
        results = [run(r, episodes=episodes, seed=seed, greedy=greedy) for r in runs]
        if as_json:
            emit_json(results)
            return
        typer.echo("| run | method | env | trained frames | success rate | mean return | mean length |")
        typer.echo("|---|---|---|---|---|---|---|")
        for r in results:
            typer.echo(f"| {r['run']} | {r['method']} | {r['env_id']} | {r['frames']:,} | {r['success_rate']:.3f} | "
                       f"{r['mean_return']:.3f} | {r['mean_length']:.1f} |")
        typer.echo(f"\n{episodes} episodes per run (evaluation seed {seed}, the same episodes for every run), actions "
                   + ("greedy (the most likely)" if greedy else "sampled from the policy"))
