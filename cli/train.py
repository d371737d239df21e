"""`illm train` and `illm eval`: PPO with the iLLM heads on cached LLM targets, and evaluation."""

from __future__ import annotations

import inspect
import typing
from pathlib import Path

import typer

from cli.common import emit_json, progress, stop_on_signals
from cli.errors import friendly
EXAMPLE = ("Example: illm train --env BabyAI-GoToLocal-v0 --cache data/ann --method illm --frames 200000 --seed 0 "
           "--out runs/gotolocal-illm")


def _rate(value) -> str:
    """A score for people: "no episode ended yet" where the metrics hold NaN or nothing (none ended)."""
    return "no episode ended yet" if value is None or value != value else f"{value:.2f}"


def _given(ctx: typer.Context) -> set[str]:
    """The options the user typed (not left at their defaults)."""
    # by name: Typer may carry its own copy of click, whose ParameterSource is another enum
    return {name for name in ctx.params if getattr(ctx.get_parameter_source(name), "name", "") == "COMMANDLINE"}


def train_config(ctx: typer.Context, options: dict):
    """The run's TrainConfig from the generated options (KEY=VALUE parsed), built by `run_config`:
    presets expanded, a resumed run's own settings merged, the cache's setup adopted (said in one line)."""
    from illm_tools.intrinsic.registry import get_method
    from illm_tools.rl.build import run_config
    from illm_tools.settings import parse_pairs

    from cli.options import pair_fields
    from illm_tools.rl.config import TrainConfig, flag_of

    settings = dict(options)
    for name in pair_fields(TrainConfig):  # repeatable KEY=VALUE options
        settings[name] = parse_pairs(options.get(name), flag_of(name))
    settings["bonus_options"] = get_method(options["method"]).typed_options(settings["bonus_options"])
    return run_config(settings, _given(ctx), say=lambda line: typer.echo(line, err=True))


def cache_holds(path: Path) -> str:
    """What the folder at `path` holds, for a line about a cache that gave no targets ("no folder",
    "no annotations", "1,200 entries: action 600, summary 600")."""
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.folders import owner

    if not path.exists():
        return "no folder"
    if owner(path) != "annotation cache":
        return "no annotation cache"
    cache = AnnotationCache(path)
    tasks = cache.tasks()
    return f"{len(cache):,} entries: " + ", ".join(f"{t} {n:,}" for t, n in sorted(tasks.items())) if tasks \
        else "no annotations"


def warn_empty_cache(cfg) -> None:
    """One line before a run whose --cache holds nothing (a mistyped path, a new folder): its targets
    come only from live annotation. (A cache holding annotations of another setup is refused by
    `illm_tools.tasks.annotation_setup.check_setup`; an empty one with --live-budget 0 by `make_provider`.) Not with
    --annotator: a fresh cache that the server fills is how a run with a server starts."""
    if not cfg.needs_targets or cfg.targets.cache is None or cfg.resume or cfg.targets.live_budget == 0 or cfg.targets.annotator:
        return
    held = cache_holds(cfg.targets.cache)
    if held in ("no folder", "no annotations"):
        budget = "every missed state" if cfg.targets.live_limit is None else f"{cfg.targets.live_limit} states a rollout"
        typer.echo(f"warning: --cache {cfg.targets.cache} holds {held}: the run's targets come only from live annotation "
                   f"({budget}); check the path if you meant a cache `illm annotate` wrote", err=True)


def no_target_line(cfg, coverage: list[float], live: float = 0.0) -> str | None:
    """The closing line of a run in which no step had an LLM target (a cache of another level, a
    mistyped --cache, live answers that came too late): it names the cache and what it holds."""
    if not cfg.needs_targets or not coverage or max(coverage) > 0:
        return None
    held = cache_holds(cfg.targets.cache)
    line = f"warning: no step had an LLM target, so the bonus paid nothing: --cache {cfg.targets.cache} holds {held}"
    if live:
        return (f"{line}; the {live:,.0f} states annotated live landed after the rollouts that asked for them (a longer "
                "run uses them, --live-mode sync waits for them, `illm annotate` gives them ahead)")
    if held.startswith("no "):
        return f"{line}; check the path, or annotate into it first (`illm annotate DATA --cache {cfg.targets.cache}`)"
    return (f"{line}, none of them a state this run visited on {cfg.env_id}; annotate states of this level "
            f"(`illm collect --env {cfg.env_id}`, then `illm annotate`) or check --cache")


def _train_parameters() -> list[inspect.Parameter]:
    from cli.options import dataclass_parameters
    from illm_tools.intrinsic.registry import method_help  # light: names only, no torch
    from illm_tools.rl.config import NOT_SETTINGS, PART_NAMES, TrainConfig
    from illm_tools.rl.live_remote import AnnotatorAccess
    from illm_tools.intrinsic.presets import BONUS_PRESETS, preset_text
    from illm_tools.rl.declared import PRESET_FIELDS as WEIGHTS

    params = dataclass_parameters(
        TrainConfig, exclude={".".join(n) for n in NOT_SETTINGS}, required={"run_dir"},
        names={".".join(k): v for k, v in PART_NAMES.items()}, defaults={w: None for w in WEIGHTS},
        extra_help={"method": "One of: " + method_help() + ".",
                    **{w: "Default: from --bonus-preset." for w in WEIGHTS},
                    "bonus_options": "See illm_tools.intrinsic.registry (e.g. rnd: update_proportion=0.5).",
                    "network_options": "chibit: blocks=1, model=smollm2-135m."})
    preset = inspect.Parameter("bonus_preset", inspect.Parameter.KEYWORD_ONLY, annotation=typing.Optional[str],
                               default=typer.Option(None, "--bonus-preset", help=(
                                   " | ".join(f"{k} ({preset_text(k)})" for k in BONUS_PRESETS)
                                   + f"; default: the method's own ({own_presets()}); explicit settings win.")))
    ctx = inspect.Parameter("ctx", inspect.Parameter.POSITIONAL_OR_KEYWORD, annotation=typer.Context)
    return [ctx, *params, preset, *dataclass_parameters(AnnotatorAccess)]


def own_presets() -> str:
    """The methods' own `--bonus-preset`s, from the registry ("illm: small, rnd: rnd, ..., others: paper")."""
    from illm_tools.intrinsic.registry import METHODS

    own = [f"{name}: {method.preset}" for name, method in METHODS.items() if method.preset != "paper"]
    return ", ".join([*own, "others: paper"])


def use_token(token: str | None, annotator: str | None) -> None:
    """Hand `--annotator-token` to the run's `RemoteLive` through the environment variable it reads
    (so the token never enters the run's settings, which are written to its folder)."""
    import os

    from illm_tools.annotate.wire import TOKEN_ENV, check_token
    from illm_tools.errors import UsageError

    if token is None:
        return
    if annotator is None:
        raise UsageError("--annotator-token is the token of an --annotator server: give --annotator URL too, or "
                         "leave the token out")
    os.environ[TOKEN_ENV] = check_token(token, "--annotator-token")


def register(app: typer.Typer) -> None:
    def train(ctx: typer.Context, **options) -> None:
        """Train PPO with a method's bonus; iLLM's heads learn LLM targets from the cache.

        iLLM pays its bonus where those heads still disagree with the targets. Every setting of a run is
        an option named as its field; --resume reads them from the run folder."""
        from illm_tools.rl.run import early_live_of_settings

        token = options.pop("annotator_token")
        live = early_live_of_settings(options)  # before the config is built, which imports torch
        try:
            _train(ctx, options, token, live)
        finally:
            if live is not None:  # closed with the run, or here where the run never started
                live.close()

    def _train(ctx: typer.Context, options: dict, token: str | None, live) -> None:
        from illm_tools.rl.run import train as run

        cfg = train_config(ctx, options)
        use_token(token, cfg.targets.annotator)
        out, method, env = cfg.run_dir, cfg.method, cfg.env_id
        from illm_tools.envs import suite_of

        warn_empty_cache(cfg)

        score_name = suite_of(env).score_name  # an unknown env is refused before anything else is said
        if cfg.num_updates * cfg.batch_size != cfg.total_steps:
            typer.echo(f"--frames {cfg.total_steps:,} is not a whole number of rollouts ({cfg.num_envs} envs × "
                       f"{cfg.num_steps} steps = {cfg.batch_size:,} frames each): the run trains "
                       f"{cfg.num_updates * cfg.batch_size:,} frames", err=True)
        if cfg.needs_targets and cfg.targets.live_budget == "all" and (cfg.targets.annotator or cfg.targets.live_mode == "async"):
            where = "the server's answers" if cfg.targets.annotator else "the worker's answers (it first loads the model)"
            typer.echo(f"--live-budget all promises a target on every step only with --live-mode sync: {where} "
                       "land beside the rollouts, and later rollouts use them; pass --live-mode sync to wait "
                       "for every missed state", err=True)
        last: dict = {}
        coverage: list[float] = []
        live_total = [0.0]  # states the live annotator (worker, server or this process) put in the cache
        with stop_on_signals("the current update, then writing a checkpoint") as stop, \
                progress(cfg.num_updates * cfg.batch_size, f"train {method}", unit="steps") as advance:
            def on_metrics(m: dict) -> None:
                last.update(m)
                fields = {"score": _rate(m.get("charts/score"))}
                if cfg.needs_targets:
                    coverage.append(m.get("charts/target_coverage", 0.0))
                    live_total[0] += m.get("charts/live_annotations", 0.0)
                    fields["targets"] = f"{coverage[-1]:.2f}"
                    if "charts/live_queue" in m:
                        fields["live_queue"] = f"{m['charts/live_queue']:.0f}"
                advance(cfg.batch_size, m.get("charts/sps"), **fields)

            result = run(cfg, on_metrics, should_stop=lambda: stop.requested, started=live)
        if result.get("already_done"):
            typer.echo(f"{out} is already at {result['global_step']:,} frames (--frames {cfg.total_steps:,}): nothing "
                       "to do; pass a larger --frames with --resume to train on")
            return
        targets = f"; steps with an LLM target {sum(coverage) / len(coverage):.0%} on average" if coverage else ""
        if len(coverage) > 1:  # the live fallback's answers raise the share as the run goes on
            targets += f" ({coverage[0]:.0%} in the first rollout, {coverage[-1]:.0%} in the last)"
        during, at_close = live_total[0], result.get("live_at_close", 0)  # at close: the worker's last chunk
        live_total[0] += at_close
        live = f"; {live_total[0]:,.0f} states annotated live" if cfg.needs_targets and cfg.targets.live_budget else ""
        if live and live_total[0]:
            live += f" ({during:,.0f} during the rollouts, {at_close:,} while the run shut down, kept in the cache)"
        if live and during and last.get("charts/live_first_answer_s") is not None:  # the async worker's
            live += f"; the first landed {last['charts/live_first_answer_s']:.1f} s after the run started"
        none = no_target_line(cfg, coverage, live_total[0])
        if result.get("stopped"):
            typer.echo(f"stopped at {result['global_step']:,} frames{targets}; resume with "
                       f"`illm train --out {out} --resume`")
            if none:
                typer.echo(none, err=True)
            raise typer.Exit(stop.exit_code)
        score = last.get("charts/score")
        score = f"last {score_name} {_rate(score)}" if score is not None and score == score else \
            f"no episode ended in the last update ({score_name} unknown)"
        since = f", resumed at {result['resumed_at']:,}" if result.get("resumed_at") is not None else ""
        typer.echo(f"trained {method} on {env} to {last.get('global_step', 0):,} frames{since} "
                   f"({last.get('charts/sps', 0):,.0f} steps/s); {score}{targets}{live} -> {out}")
        if none:
            typer.echo(none, err=True)

    train.__signature__ = inspect.Signature(_train_parameters())
    app.command(epilog=EXAMPLE)(friendly(train))

    def evaluate(**options) -> None:
        """Evaluate trained runs on the same fresh episodes: score, success rate, mean return.

        The score is the suite's (success rate, Crafter score, mean return); a markdown table, or with
        --json a list with one object per run."""
        from cli.options import config_from_options
        from illm_tools.rl.eval_config import EvalConfig
        from illm_tools.rl.run import evaluate as run

        as_json = options.pop("as_json")
        config = config_from_options(EvalConfig, options)
        runs, episodes, seed, greedy = config.runs, config.episodes, config.seed, config.greedy
        from illm_tools.report.stats import wilson_interval

        results = [run(r, episodes=episodes, seed=seed, greedy=greedy) for r in runs]
        for r in results:  # the success rate's 95% Wilson interval over the run's episodes
            rate, n = r["success_rate"], r["episodes"]
            r["success_interval"] = None if rate != rate else list(wilson_interval(round(rate * n), n))
        if as_json:
            emit_json(results)
            return
        typer.echo("| run | method | env | trained frames | episodes | score | success rate [95% CI] | mean return | "
                   "mean length |")
        typer.echo("|---|---|---|---|---|---|---|---|---|")
        for r in results:
            success = "-" if r["success_interval"] is None else \
                f"{r['success_rate']:.3f} [{r['success_interval'][0]:.3f}, {r['success_interval'][1]:.3f}]"
            typer.echo(f"| {r['run']} | {r['method']} | {r['env_id']} | {r['frames']:,} | {r['episodes']} | "
                       f"{r['score']:.3f} ({r['score_name']}) | {success} | {r['mean_return']:.3f} | "
                       f"{r['mean_length']:.1f} |")
        typer.echo("\nsuccess rate: of the episodes run, with its 95% Wilson score interval (episodes as independent "
                   "trials; a run's seed is one draw of training, which the interval does not cover)")
        typer.echo(f"{episodes} episodes per run (--seed {seed}: env seeds from 2^40 + {seed}, apart from training's; "
                   "the same episodes for every run), actions "
                   + ("greedy (the most likely)" if greedy else "sampled from the policy"))
        single = one_run_methods(results)
        if single:
            typer.echo(single)

    evaluate.__signature__ = inspect.Signature(_eval_parameters())
    app.command("eval", epilog="Example: illm eval runs/gotolocal-illm --episodes 100")(friendly(evaluate))


def one_run_methods(results: list[dict]) -> str | None:
    """The closing line of an eval that sets methods side by side with one run of some: what its
    intervals can say (how each trained policy does) and cannot (which method trains better)."""
    from collections import Counter

    runs = Counter(r["method"] for r in results)
    if len(runs) < 2 or min(runs.values()) > 1:
        return None
    rated = [r["success_interval"] for r in results if r["success_interval"]]
    overlap = len(rated) > 1 and max(lo for lo, _ in rated) <= min(hi for _, hi in rated)
    return (f"runs per method: {', '.join(f'{m} {n}' for m, n in runs.items())}. Each interval is one trained "
            "policy's on these episodes" + (", and here they overlap" if overlap else "")
            + ": one seed cannot say which method trains better (another seed may reverse it); compare methods "
            "over several seeds each (`illm experiment`, then `illm report`: IQM with 95% intervals over seeds)")


def _eval_parameters() -> list[inspect.Parameter]:
    from cli.options import dataclass_parameters
    from illm_tools.rl.eval_config import EvalConfig

    as_json = inspect.Parameter("as_json", inspect.Parameter.KEYWORD_ONLY, annotation=bool,
                                default=typer.Option(False, "--json", help="Print machine-readable JSON."))
    return dataclass_parameters(EvalConfig, arguments={"runs"}) + [as_json]
