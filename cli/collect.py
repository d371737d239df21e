"""`illm collect`: log trajectories of a policy to an Arrow dataset."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from cli.common import progress, score_text, write_mode
from cli.errors import friendly


def register(app: typer.Typer) -> None:
    @app.command(epilog="Example: illm collect --env BabyAI-GoToLocal-v0 --steps 20000 --out data/traj/gotolocal --seed 0  |  "
                        "illm collect --env CrafterReward-v1 --steps 5000 --out data/traj/crafter  (`illm envs` lists every env)")
    @friendly
    def collect(
        env: str = typer.Option(..., "--env", help="Environment id, e.g. BabyAI-GoToLocal-v0."),
        out: Path = typer.Option(..., "--out", help="Folder of the trajectory dataset to write."),
        steps: int = typer.Option(20_000, help="Total steps to log (summed over envs)."),
        num_envs: int = typer.Option(8, "--num-envs", help="Environments stepped side by side."),
        seed: int = typer.Option(0, help="Base seed for episodes and the random policy."),
        policy: str = typer.Option("random", help="'random', or a training run folder (its policy acts)."),
        action_space: str = typer.Option("auto", "--action-space", help="BabyAI: original (3) | augmented (6) | irrelevant (9) actions (paper Table 5) | auto: the suite's default (BabyAI: original for GoTo levels, paper Tables 1, 5, augmented otherwise), a --policy run's own."),
        num_dists: int = typer.Option(None, "--num-dists", help="Distractors, for levels that take it (paper Table 1)."),
        no_raw: bool = typer.Option(False, "--no-raw", help="Do not store raw observation arrays."),
        append: bool = typer.Option(False, "--append", help="Add to an existing dataset at --out."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace the dataset at --out (only once the new one is complete)."),
        mix_envs: bool = typer.Option(False, "--mix-envs", help="With --append: allow adding another env's steps to the dataset."),
        env_option: list[str] = typer.Option(None, "--env-option", help="KEY=VALUE option of the environment (its suite's; repeatable), e.g. max_episode_steps=500."),
        vector: str = typer.Option("auto", "--vector", help="auto | sync (envs in this process) | async (a process each); auto: the suite's choice (async for Crafter)."),
    ) -> None:
        """Collect trajectories with a policy into an Arrow dataset (one row per step)."""
        from illm_tools.collect import CollectConfig
        from illm_tools.collect import collect as run
        from illm_tools.settings import parse_pairs

        config = CollectConfig(env_id=env, out=out, steps=steps, num_envs=num_envs, seed=seed, policy=policy,
                               action_space=action_space, num_dists=num_dists, save_raw=not no_raw,
                               write=write_mode(append, overwrite), mix_envs=mix_envs, vector=vector,
                               env_options=parse_pairs(env_option, "--env-option"))
        start = time.perf_counter()
        with progress(steps, f"collect {env}") as advance:
            done = [0]

            def on_progress(n: int, stats: dict) -> None:
                done[0] += n
                rate = done[0] / max(time.perf_counter() - start, 1e-9)
                advance(n, rate, episodes=stats["episodes"], score=score_text(stats["score"]))

            summary = run(config, on_progress)
        seconds = time.perf_counter() - start
        ret = f", mean return {summary['mean_return']:.3f}" if summary["score_name"] != "mean return" else ""
        typer.echo(
            f"collected {summary['rows']:,} steps, {summary['episodes_finished']:,} finished episodes "
            f"({summary['score_name']} {score_text(summary['score'])}{ret}) "
            f"from {env} ({summary['action_space']} actions) with policy {summary['policy']} in {seconds:.1f}s "
            f"-> {summary['out']}"
        )
