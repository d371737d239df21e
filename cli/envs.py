"""`illm envs`: the environment suites, what the policy and the LLM see of each, its score, and
its env ids."""

from __future__ import annotations

import typer

from cli.common import emit_json
from cli.errors import friendly


def register(app: typer.Typer) -> None:
    @app.command(epilog="Example: illm envs  |  illm envs --suite minihack --ids  |  illm envs --json")
    @friendly
    def envs(
        suite: str = typer.Option(None, "--suite", help="Only this suite (babyai, minihack, crafter, atari)."),
        ids: bool = typer.Option(False, "--ids", help="List every env id of each suite."),
        as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
    ) -> None:
        """List the environment suites: observation, text renderer, score, options and env ids."""
        from illm_tools.envs import SUITES, suites
        from illm_tools.errors import UsageError

        chosen = [s for s in suites() if suite in (None, s.name)]
        if not chosen:
            raise UsageError(f"unknown --suite {suite!r}; choose from {', '.join(SUITES)}")
        rows = []
        for s in chosen:
            env_ids = s.env_ids()
            spec = s.obs_spec(env_ids[0])
            rows.append({"suite": s.name, "description": s.description, "observation": spec.description,
                         "shape": list(spec.shape), "dtype": spec.dtype, "kind": spec.kind,
                         "text": s.renderer, "score": s.score_name, "vector": s.vector, "env_ids": env_ids})
        if as_json:
            emit_json(rows)
            return
        for r in rows:
            typer.echo(f"{r['suite']}: {r['description']}")
            typer.echo(f"  policy sees  {r['observation']} ({r['dtype']} {tuple(r['shape'])}, {r['kind']})")
            typer.echo(f"  text         {r['text'] or 'none (iLLM runs on it with --mode hop; text annotation refuses it)'}")
            typer.echo(f"  score        {r['score']}")
            if ids:  # one per line, to grep
                typer.echo(f"  env ids      ({len(r['env_ids'])})")
                for env_id in r["env_ids"]:
                    typer.echo(f"    {env_id}")
                continue
            more = "" if len(r["env_ids"]) <= 4 else f" ... ({len(r['env_ids'])} ids; --ids lists them)"
            typer.echo(f"  env ids      {', '.join(r['env_ids'][:4])}{more}")
