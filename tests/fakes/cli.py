"""`illm` commands run through Typer's test runner: `cli_ok` (a command that must succeed, its
output), `collected` (`illm collect`'s trajectories) and `trains_with_the_engine_stopped` (issue
54's checks of a cache annotated through an engine). Used by test_pipeline.py, test_plugins.py,
test_backends.py, test_language_tasks.py, test_machine_choices.py, test_docs_examples.py,
test_example_level.py, test_oracles.py, test_llama_cpp_engine.py, test_vllm_engine.py and
test_openai_backend.py."""

from __future__ import annotations

import json
from pathlib import Path


def cli_ok(*args, env: dict | None = None) -> str:
    """`illm ARGS` (each turned into a string) through Typer's runner, with `env` (variables set for
    the run, None unsets one) if given: its output, the exit code asserted 0 (the failure shows the
    command, its output and its exception)."""
    from typer.testing import CliRunner

    from cli.main import app

    result = CliRunner().invoke(app, [str(a) for a in args], env=env)
    assert result.exit_code == 0, (args[:1], result.output, result.exception)
    return result.output


def collected(out, steps: int, num_envs: int = 2, env: str = "BabyAI-GoToLocal-v0", seed: int = 0):
    """`illm collect` of `steps` random steps of `env` into `out` (the trajectories a test annotates)."""
    cli_ok("collect", "--env", env, "--steps", steps, "--num-envs", num_envs, "--seed", seed, "--out", out)
    return out


def trains_with_the_engine_stopped(ann, run, entries: int, env: str = "BabyAI-GoToRedBallNoDists-v0",
                                   reach: tuple[str, ...] = ("--endpoint", "http://127.0.0.1:9/v1")) -> str:
    """Issue 54's checks of a cache annotated through an engine at two addresses, the engine stopped:
    `illm cache info` lists one setup per task (served at both addresses, `entries` states each) and
    `illm train --live-budget 0` adopts it and trains on its targets; returns the run's output.
    `reach`: the user's own options that say where the engine is (issue 69: never the cache's)."""
    from illm_tools.llm import openai_wire

    openai_wire.forget_engines()  # what this process asked the engine: a later command starts afresh
    setups = json.loads(cli_ok("cache", "info", ann, "--json"))["setups"]
    assert sorted(u["task"] for u in setups) == ["action", "summary"], setups  # one setup per task
    assert all(len(u["served_at"]) == 2 and u["entries"] == entries for u in setups), setups
    assert all("another file or revision" not in u["model_options"] for u in setups)
    output = cli_ok("train", "--env", env, "--method", "illm", "--cache", ann, "--live-budget", "0", "--num-envs", "4",
                    "--num-steps", "32", "--frames", "256", "--seed", "0", "--out", run, "--device", "cpu", *reach)
    metrics = [json.loads(line) for line in (Path(run) / "metrics.jsonl").read_text().splitlines()]
    assert max(m.get("charts/target_coverage", 0.0) for m in metrics) > 0  # targets of the cached states
    return output
