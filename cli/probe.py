"""`illm probe`: what an LLM's next-action ranking knows about a BabyAI level, against its expert bot."""

from __future__ import annotations

import inspect
from pathlib import Path

import typer

from cli.common import progress, save_figures
from cli.errors import friendly


EXAMPLE = "Example: illm probe --env BabyAI-GoToLocal-v0 --model smollm2-135m --states 400"


def _parameters() -> list[inspect.Parameter]:
    """`ProbeConfig`'s fields as options (`cli.options`; its LLM's as --backend, --model, ...), then
    what only the command reads: where the figures go."""
    from cli.options import dataclass_parameters
    from illm_tools.probe import ProbeConfig

    params = dataclass_parameters(ProbeConfig, exclude={"setup.obs_mode", "setup.hop_seed", "setup.hop_beta"})
    extra = [("as_json", bool, typer.Option(False, "--json", help="Print the figures as JSON.")),
             ("out", Path, typer.Option(None, "--out", help="Also write the figures as JSON to this file."))]
    return params + [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=kind, default=default)
                     for name, kind, default in extra]


def register(app: typer.Typer) -> None:
    def probe(**options) -> None:
        """Measure how well an LLM's next-action ranking agrees with the BabyAI expert bot.

        Per calibration (sum, mean, pmi): agreement with the bot, against always choosing the expert's
        most frequent action; mutual information between state and ranking; log-loss; pairwise
        AUROC."""
        from cli.options import config_from_options
        from illm_tools.llm.backend import backend_class
        from illm_tools.probe import ProbeConfig, probe as run
        from illm_tools.settings import check_new_file

        as_json, out = options.pop("as_json"), options.pop("out")
        config = config_from_options(ProbeConfig, options)
        check_new_file(out, "--out")  # before the probe runs, not after
        model, env, backend, quant = config.llm.model, config.env_id, config.llm.backend, config.llm.quant
        history, epsilon = config.setup.history_len, config.epsilon
        with progress(0, f"probe {model}", unit="states") as advance:
            done = [0]

            def on_progress(n: int, total: int) -> None:
                advance(n - done[0], total=total)
                done[0] = n

            result = run(config, on_progress=on_progress)
        figures = result.to_dict()
        if save_figures(figures, out, as_json):
            return
        b = result.baselines
        resolved, quant = result.config["dtype"], result.config.get("quant", quant)  # as the probe resolved them
        computes = getattr(backend_class(backend), "computes", True)  # a dtype and quantisation of its own
        setup = f"{backend} backend" if not computes else resolved if quant == "none" else f"{resolved}, {quant}"
        typer.echo(f"probe {model} ({setup}) on {env}: {result.states} states ({result.distinct_states} distinct) from "
                   f"{result.episodes} episodes of minigrid's BabyAI bot with {epsilon:.0%} random actions, "
                   f"history {history}"
                   + (f"; {result.skipped} states whose expert action is not a valid action left out" if result.skipped else "")
                   + (f"; the bot gave up on {result.bot_failures} episodes" if result.bot_failures else ""))
        typer.echo("expert's actions: " + ", ".join(f"{n} {s:.0%}" for n, s in
                                                     sorted(result.expert_share.items(), key=lambda x: -x[1])))
        typer.echo(f"{'':22s} {'agreement':>9s} {'log-loss':>8s} {'AUROC':>6s} {'MI bits':>7s} {'top-1 H':>7s}"
                   "  LLM's top action")
        for name, c in result.calibrations.items():
            typer.echo(f"{'LLM, ' + name:22s} {c['agreement']:9.3f} {c['log_loss']:8.3f} {c['auroc']:6.3f} "
                       f"{c['mutual_information_bits']:7.3f} {c['top_choice_entropy_bits']:7.3f}  "
                       f"{c['top_action']} in {c['top_action_share']:.0%} of states")
        typer.echo(f"{'always ' + b['majority_action']:22s} {b['majority_agreement']:9.3f} "
                   f"{b['marginal_log_loss']:8.3f} {'-':>6s} {0.0:7.3f} {0.0:7.3f}  "
                   "(log-loss: the expert's own frequencies, in sample)")
        typer.echo(f"{'uniform chance':22s} {b['chance_agreement']:9.3f} {b['uniform_log_loss']:8.3f} {0.5:6.3f} "
                   f"{0.0:7.3f} {'-':>7s}")
        typer.echo("MI bits: mutual information between the state and the LLM's distribution (0: it ignores the "
                   "state); top-1 H: entropy of the LLM's top action across states, bits")
        best = result.calibrations[result.best]
        typer.echo(f"agreement per expert action ({result.best}): " + ", ".join(
            f"{n} {a:.2f}" for n, a in sorted(best["per_action"].items(), key=lambda x: -result.expert_share[x[0]])))
        if best["agreement"] <= b["majority_agreement"]:
            typer.echo(f"reading: no calibration beats always \"{b['majority_action']}\" "
                       f"({b['majority_agreement']:.3f}); the best, {result.best}, agrees on {best['agreement']:.3f}")
        else:
            typer.echo(f"reading: {result.best} beats always \"{b['majority_action']}\" "
                       f"({best['agreement']:.3f} against {b['majority_agreement']:.3f})")

    probe.__signature__ = inspect.Signature(_parameters())
    app.command(epilog=EXAMPLE)(friendly(probe))
