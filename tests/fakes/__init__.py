"""The helpers the tests share, their one home (no test module imports another): `from fakes import X`
(conftest.py's folder, tests/, is on the import path) finds each here, whatever module of this
package holds it:

- `cli`: `illm` commands through Typer's runner (`cli_ok`, `collected`, `trains_with_the_engine_stopped`);
- `training`: the trainer's fakes (`FakePool`, `FakeProvider`, `RefusingProvider`, `make_trainer`,
  `one_update_seen`);
- `methods`: the checks every training method gets (`bonus_reaches_the_advantages`, `trains_end_to_end`);
- `prompts`: BabyAI-like states and prompts (`ACTIONS`, `SHORT_ACTIONS`, `state_record`, `prompt_builder`);
- `plugins`: what a package outside illm adds (`plugins_installed`, `TinyBackend`, `TinySuite`, `TINY`,
  `Corridor`, `EXAMPLES`);
- `data`: files built or damaged (`run_wide`, `make_rows`, `keys_of`, `run_writers`, `stub_annotated`,
  `trajectory_rows`, `flip`, `truncate`, `fake_run`);
- `serving`: `illm serve`'s requests and servers (`STUB_MODEL`, `STUB_LLM`, `stub_fingerprint`,
  `serve_state`, `serve_request`, `hop_states`, `stub_server`, `running_server`, `SLOW_SERVER`, `call`,
  `server_stats`, `wait_for`);
- `web`: fake HTTP peers (`QuietHandler`, `http_fake`, `fake_hub`).

A helper a second test module needs moves here rather than being copied; where copies differed, the
one helper takes the union of their options."""

from .cli import cli_ok, collected, trains_with_the_engine_stopped
from .data import fake_run, flip, keys_of, make_rows, run_wide, run_writers, stub_annotated, trajectory_rows, truncate
from .methods import bonus_reaches_the_advantages, trains_end_to_end
from .plugins import EXAMPLES, TINY, Corridor, TinyBackend, TinySuite, plugins_installed
from .prompts import ACTIONS, SHORT_ACTIONS, prompt_builder, state_record
from .serving import (SLOW_SERVER, STUB_LLM, STUB_MODEL, call, hop_states, running_server, serve_request, serve_state,
                      server_stats, stub_fingerprint, stub_server, wait_for)
from .training import FakePool, FakeProvider, RefusingProvider, make_trainer, one_update_seen
from .web import QuietHandler, fake_hub, http_fake

__all__ = [
    "ACTIONS", "bonus_reaches_the_advantages", "call", "cli_ok", "collected", "Corridor", "EXAMPLES", "fake_hub",
    "fake_run", "FakePool", "FakeProvider", "flip", "hop_states", "http_fake", "keys_of", "make_rows",
    "make_trainer", "one_update_seen", "plugins_installed", "prompt_builder", "QuietHandler", "RefusingProvider",
    "run_wide", "run_writers", "running_server", "serve_request", "serve_state", "server_stats", "SHORT_ACTIONS",
    "SLOW_SERVER", "state_record", "stub_annotated", "stub_fingerprint", "STUB_LLM", "STUB_MODEL", "stub_server",
    "TINY", "TinyBackend", "TinySuite", "trains_end_to_end", "trains_with_the_engine_stopped", "trajectory_rows",
    "truncate", "wait_for",
]
