"""`illm serve`: one LLM annotating the live requests of many `illm train --annotator URL` runs."""

from __future__ import annotations

import inspect

import typer

from cli.common import counted, stop_on_signals
from cli.errors import friendly

EXAMPLE = ("Example: illm serve --cache data/ann --model smollm2-135m --history 0 --port 8765, then "
           "illm train ... --cache data/ann --history 0 --annotator http://127.0.0.1:8765. For a cluster: "
           "export ILLM_SERVE_TOKEN=... (on the server and the trainers), illm serve --host 0.0.0.0 ...")


def _parameters() -> list[inspect.Parameter]:
    from cli.options import dataclass_parameters
    from illm_tools.serve import ServeConfig

    return dataclass_parameters(ServeConfig, exclude={"setup.obs_mode"})  # it answers text and hop states


def register(app: typer.Typer) -> None:
    def serve(**options) -> None:
        """Serve live annotation to several training runs from one loaded model.

        Requests are batched round-robin across runs into the shared cache, under the server's own setup
        (--history, --layout, --tasks, --hop-seed, --hop-beta: the trainers' options). GET /stats reports the queue
        and throughput. Beyond loopback it needs a token (--token or ILLM_SERVE_TOKEN), which every
        request must carry."""
        import asyncio
        import dataclasses
        import os

        import torch

        from cli.options import config_from_options
        from illm_tools.cache.store import AnnotationCache
        from illm_tools.errors import UsageError
        from illm_tools.llm.spec import LLMSpec
        from illm_tools.serve import AnnotationServer, ServeConfig, serve as run

        from illm_tools.tasks.served import REACHED
        from illm_tools.tasks.annotation_setup import adopt_model

        # what names the model; where a served one is reached (REACHED) is the user's alone, never the cache's
        chosen = [f.name for f in dataclasses.fields(LLMSpec) if f.name not in ("device", *REACHED)]
        adopting = all(options[k] == LLMSpec.__dataclass_fields__[k].default for k in chosen)
        reach = {k: options[k] for k in REACHED if options[k]} if adopting else {}
        config = config_from_options(ServeConfig, {**options, **dict.fromkeys(reach)})
        store = AnnotationCache(config.cache)  # refuses a folder that is not a cache before loading a model
        if adopting:  # no model options: the cache's model setup, reached where the user's options say
            held = adopt_model(store, reach)
            if held is not None or reach:  # an empty cache: the options given refused as without --cache
                config = dataclasses.replace(config, llm=LLMSpec(**(held or reach), device=config.llm.device))
            if held is not None:
                typer.echo(f"serving the cache's model setup: {config.llm.options()} (give model options to "
                           "choose another)", err=True)
        torch.set_num_threads(config.threads or os.cpu_count() or 1)
        llm = config.llm.placed()
        server = AnnotationServer.of_config(llm.load(), store, llm, config)
        host, port, model, cache = config.host, config.port, llm.model, config.cache
        access = "every request must carry the token" if config.token else "no token: this machine only"

        def ready(addresses) -> None:
            where = ", ".join(f"http://{a[0]}:{a[1]}" for a in addresses)
            typer.echo(f"serving {model} on {where} for the cache {cache} ({access}; {server.setup.options()}; GET /stats "
                       "for the queue); Ctrl-C or SIGTERM stops after the batch in progress", err=True)

        async def main(stop_flag) -> None:
            stop = asyncio.Event()

            async def watch() -> None:  # the signal handler sets a flag; the loop turns it into the event
                while not stop_flag.requested:
                    await asyncio.sleep(0.2)
                stop.set()

            watcher = asyncio.ensure_future(watch())
            try:
                await run(server, host, port, stop, on_ready=ready, token=config.token)
            except OSError as e:
                raise UsageError(f"cannot listen on {host}:{port} ({e.strerror or e}): check --host (an address of this "
                                 "machine) and --port (a free one, or 0)") from None
            finally:
                watcher.cancel()

        with stop_on_signals("the batch in progress (written whole)") as stop_flag:
            asyncio.run(main(stop_flag))
        s = server.stats()
        typer.echo(f"served {s['requests']:,} requests: {s['annotated_states']:,} states annotated ({s['rows']:,} rows) "
                   f"in {counted(s['batches'], 'batch', 'batches')}, {s['states_per_s']:.2f} states/s while annotating; "
                   f"{s['queue']:,} states left queued, {s['failed_states']:,} failed in the engine; refused: {s['refused']:,} "
                   f"malformed, {s['unauthorized']:,} without the token, {s['forbidden']:,} cross-origin or another "
                   f"host, {s['throttled']:,} over a client's cap (429), {s['busy']:,} busy (503), {s['timeouts']:,} too "
                   "slow (408)")

    serve.__signature__ = inspect.Signature(_parameters())
    app.command(epilog=EXAMPLE)(friendly(serve))
