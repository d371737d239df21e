"""`illm serve`: one LLM annotating the live requests of many `illm train --annotator URL` runs."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.common import API_KEY_ENV, BACKEND, DEVICE, DTYPE, ENDPOINT, MODEL, ORACLE_NOISE, QUANT, stop_on_signals
from cli.errors import friendly


def register(app: typer.Typer) -> None:
    @app.command(epilog="Example: illm serve --cache data/ann --model smollm2-135m --port 8765, then "
                        "illm train ... --cache data/ann --annotator http://127.0.0.1:8765")
    @friendly
    def serve(
        cache: Path = typer.Option(Path("data/ann"), "--cache", help="Annotation cache the answers go to (the trainers' --cache)."),
        model: str = MODEL,
        oracle_noise: float = ORACLE_NOISE,
        endpoint: str = ENDPOINT,
        api_key_env: str = API_KEY_ENV,
        port: int = typer.Option(8765, "--port", help="TCP port (0: any free one, printed when ready)."),
        host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on (localhost by default: the server has no authentication)."),
        dtype: str = DTYPE,
        quant: str = QUANT,
        backend: str = BACKEND,
        device: str = DEVICE,
        batch_size: int = typer.Option(8, "--batch-size", help="States per LLM batch."),
        chunk: int = typer.Option(16, "--chunk", help="States taken per round across all trainers (highest visit counts first), written as one shard."),
        threads: int = typer.Option(0, "--threads", help="Torch threads of the model; 0: every core."),
    ) -> None:
        """Serve live annotation for several training runs with one loaded model: requests are batched
        across runs, highest visit counts first, into the shared cache. GET /stats reports the queue
        and throughput."""
        import asyncio
        import os

        import torch

        from illm_tools.devices import resolve_device
        from illm_tools.cache.store import AnnotationCache
        from illm_tools.errors import UsageError
        from illm_tools.llm.backend import check_backend, load_backend, resolve_model
        from illm_tools.serve import AnnotationServer, serve as run

        check_backend(backend)
        store = AnnotationCache(cache)  # refuses a folder that is not a cache before loading a model
        if model is None and backend == "transformers" and dtype == "auto" and quant == "none" and not oracle_noise:
            from illm_tools.annotate.setups import adopt_model

            held = adopt_model(store)  # no model options: the cache's model setup
            if held is not None:
                backend, model, dtype, quant = held["backend"], held["model"], held["dtype"], held["quant"]
                typer.echo(f"serving the cache's model setup: --backend {backend} --model {model} --dtype {dtype} "
                           f"--quant {quant} (give model options to choose another)", err=True)
        model = resolve_model(backend, model, oracle_noise=oracle_noise, endpoint=endpoint, api_key_env=api_key_env)
        if batch_size <= 0 or chunk <= 0 or threads < 0 or not 0 <= port < 65536:
            raise UsageError("--batch-size and --chunk must be positive, --threads >= 0, --port in 0..65535")
        torch.set_num_threads(threads or os.cpu_count() or 1)
        from illm_tools.llm.backend import backend_dtype

        device = resolve_device(device)
        dtype = backend_dtype(backend, dtype, device)
        lm = load_backend(backend, model, dtype=dtype, quant=quant, device=device)
        server = AnnotationServer(lm, store, model=model, batch_size=batch_size, chunk=chunk, dtype=dtype, quant=quant)

        def ready(addresses) -> None:
            where = ", ".join(f"http://{a[0]}:{a[1]}" for a in addresses)
            typer.echo(f"serving {model} on {where} for the cache {cache} (GET /stats for the queue); "
                       "Ctrl-C stops after the batch in progress", err=True)

        async def main(stop_flag) -> None:
            stop = asyncio.Event()

            async def watch() -> None:  # the signal handler sets a flag; the loop turns it into the event
                while not stop_flag.requested:
                    await asyncio.sleep(0.2)
                stop.set()

            watcher = asyncio.ensure_future(watch())
            try:
                await run(server, host, port, stop, on_ready=ready)
            except OSError as e:
                raise UsageError(f"cannot listen on {host}:{port} ({e.strerror or e}): pick another --port") from None
            finally:
                watcher.cancel()

        with stop_on_signals("the batch in progress (written whole)") as stop_flag:
            asyncio.run(main(stop_flag))
        s = server.stats()
        typer.echo(f"served {s['requests']:,} requests: {s['annotated_states']:,} states annotated ({s['rows']:,} rows) "
                   f"in {s['batches']:,} batches, {s['states_per_s']:.2f} states/s while annotating; "
                   f"{s['queue']:,} states left queued")
