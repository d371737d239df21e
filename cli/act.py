"""`illm act`: how well an annotator plays acting greedily on its own ranking, beside a random policy."""

from __future__ import annotations

import inspect
from pathlib import Path

import typer

from cli.common import progress, save_figures
from cli.errors import friendly

EXAMPLE = ("Example: illm act --env MiniHack-Room-5x5-v0 --backend oracle --episodes 100  |  "
           "illm act --env CrafterReward-v1 --backend oracle --episodes 20 --env-option length=2000")


def _parameters() -> list[inspect.Parameter]:
    """`ActConfig`'s fields as options (its LLM's as --backend, --model, ...), then where the figures go."""
    from cli.options import dataclass_parameters
    from illm_tools.acting import ActConfig

    params = dataclass_parameters(ActConfig,
                                  exclude={"setup.obs_mode", "setup.hop_seed", "setup.hop_beta"},
                                  extra_help={"env_options": "E.g. length=2000 (Crafter), max_episode_steps=200."})
    extra = [("as_json", bool, typer.Option(False, "--json", help="Print the figures as JSON.")),
             ("out", Path, typer.Option(None, "--out", help="Also write the figures as JSON to this file."))]
    return params + [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=kind, default=default)
                     for name, kind, default in extra]


def _line(name: str, r: dict) -> str:
    success = "-" if r["success_rate"] is None else \
        f"{r['success_rate']:.2f} [{r['success_interval'][0]:.2f}, {r['success_interval'][1]:.2f}]"
    score = r["metrics"].get("score")
    return (f"{name:10s} {r['episodes']:8d} {success:>20s} {r['mean_return']:8.2f} {r['mean_length']:8.1f}"
            + (f" {score:8.2f}" if score is not None and r["success_rate"] is None else ""))


def register(app: typer.Typer) -> None:
    def act(**options) -> None:
        """Play episodes greedily on an annotator's action ranking, beside a random policy.

        Each state is prompted as `illm annotate` prompts it; the best-scored action is taken (ties at
        random). Per policy: success rate with its 95% interval, mean return and length, and the suite's
        own figures (Crafter: score and each achievement's rate)."""
        from cli.options import config_from_options
        from illm_tools.acting import POLICIES, ActConfig, act as run
        from illm_tools.settings import check_new_file

        as_json, out = options.pop("as_json"), options.pop("out")
        config = config_from_options(ActConfig, options)
        check_new_file(out, "--out")  # before the episodes are played, not after
        with progress(len(POLICIES) * config.episodes, f"act {config.llm.model or config.llm.backend}",
                      unit="episodes") as advance:
            figures = run(config, on_episode=lambda _policy, _done, _total: advance(1))
        if save_figures(figures, out, as_json):
            return
        c = figures["config"]
        typer.echo(f"act {c['model']} ({c['backend']} backend) on {c['env_id']}: {c['episodes']} episodes a policy "
                   f"from seed {c['seed']}, history {c['history']}, {c['calibration']} scores"
                   + (f", cut at {c['max_steps']} steps" if c["max_steps"] else ""))
        policies = figures["policies"]
        has_score = next(iter(policies.values()))["success_rate"] is None
        typer.echo(f"{'policy':10s} {'episodes':>8s} {'success [95% CI]':>20s} {'return':>8s} {'length':>8s}"
                   + (f" {'score':>8s}" if has_score else ""))
        for name, r in policies.items():
            typer.echo(_line(name, r))
        rates = {k.removeprefix("achievement_"): {p: r["metrics"][k] for p, r in policies.items()}
                 for k in policies["annotator"]["metrics"] if k.startswith("achievement_")}
        if rates:
            typer.echo("achievements (annotator / random): " + ", ".join(
                f"{k} {v['annotator']:.2f}/{v['random']:.2f}" for k, v in rates.items()))

    act.__signature__ = inspect.Signature(_parameters())
    app.command(epilog=EXAMPLE)(friendly(act))
