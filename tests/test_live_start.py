"""The async live worker starts first: `illm train` starts it from its options before the config is
built (which imports torch), `build_run` before the env pool, the provider's checks and the network,
so its start-up runs beside theirs; it gets its spec once the run is configured; a run refused after
it started, or whose config turns out not to want it, leaves no worker behind; and its first shards
are small, so the first answer lands soon after the model is loaded."""

from __future__ import annotations

import pytest

from illm_tools.errors import UsageError
from illm_tools.rl.config import TrainConfig
from illm_tools.rl.live import first_chunks

ENV = "BabyAI-GoToRedBallNoDists-v0"


def _config(tmp_path, **settings) -> TrainConfig:
    base = dict(env_id=ENV, run_dir=tmp_path / "run", method="illm", cache=tmp_path / "ann", live_mode="async",
                live_budget=8, history_len=0, num_envs=2, num_steps=8, total_steps=16, tensorboard=False)
    return TrainConfig.from_dict({**base, **settings}).resolved()


class Worker:
    """Stands in for `AsyncLive`: records when it starts, its spec and whether it is closed."""

    made: list = []

    def __init__(self, spec=None, *, budget, max_restarts=3, early=None):
        self.spec, self.budget, self.early, self.closed = spec, budget, early, False
        Worker.made.append(self)
        EVENTS.append("worker")

    def configure(self, spec, *, budget):
        assert self.spec is None and not self.closed
        self.spec, self.budget = spec, budget

    def landed(self):
        return 0

    def close(self):
        self.closed = True


EVENTS: list[str] = []


@pytest.fixture
def fake_worker(monkeypatch):
    import illm_tools.rl.live as live_module

    EVENTS.clear()
    Worker.made.clear()
    monkeypatch.setattr(live_module, "AsyncLive", Worker)
    return Worker


def test_the_async_worker_starts_before_the_pool_and_is_closed_when_the_run_is_refused(tmp_path, monkeypatch,
                                                                                      fake_worker):
    import illm_tools.rl.run as run_module

    def refused_pool(cfg, start_step=0):
        EVENTS.append("pool")
        raise UsageError("refused after the worker started")

    monkeypatch.setattr(run_module, "make_pool", refused_pool)
    with pytest.raises(UsageError):
        with run_module.build_run(_config(tmp_path)):
            pass
    assert EVENTS == ["worker", "pool"]
    assert len(fake_worker.made) == 1 and fake_worker.made[0].closed
    assert fake_worker.made[0].spec.setup.history_len == 0 and fake_worker.made[0].budget == 8


def test_the_provider_takes_over_the_worker_the_run_started(tmp_path, fake_worker):
    from illm_tools.rl.run import build_run

    with build_run(_config(tmp_path)) as trainer:
        assert trainer.provider.live is fake_worker.made[0] and not fake_worker.made[0].closed
    assert len(fake_worker.made) == 1 and fake_worker.made[0].closed  # one worker, closed with the run


@pytest.mark.parametrize("settings", [dict(live_mode="sync"), dict(live_budget=0), dict(method="ppo")])
def test_no_early_worker_where_the_run_has_none(tmp_path, settings):
    from illm_tools.rl.run import early_live

    assert early_live(_config(tmp_path, **settings)) is None


def test_the_workers_shards_grow_from_one_state_to_its_chunk():
    assert [first_chunks(8, k) for k in range(6)] == [1, 2, 4, 8, 8, 8]
    assert [first_chunks(1, k) for k in range(3)] == [1, 1, 1]
    assert first_chunks(8, 10**6) == 8


def _settings(tmp_path, **given) -> dict:
    """`illm train`'s options as typed (flat names; None: not given)."""
    return {"env_id": ENV, "run_dir": str(tmp_path / "run"), "method": "illm", "cache": str(tmp_path / "ann"),
            "live_mode": "async", "live_budget": "8", "annotator": None, "backend": None, "model": None,
            "resume": False, **given}


def test_illm_train_starts_the_worker_from_its_options_with_the_model_it_preloads(tmp_path, fake_worker):
    from illm_tools.rl.run import early_live_of_settings

    worker = early_live_of_settings(_settings(tmp_path))
    assert worker is fake_worker.made[0] and worker.spec is None  # its spec comes once the run is configured
    assert worker.early.model == "smollm2-135m" and worker.budget == 8


@pytest.mark.parametrize("given", [dict(resume=True), dict(live_budget="0"), dict(live_mode="sync"),
                                   dict(method="ppo"), dict(cache=None), dict(backend="oracle"),
                                   dict(annotator="http://127.0.0.1:1"), dict(live_mode="later")])
def test_no_worker_from_options_that_do_not_ask_for_one(tmp_path, fake_worker, given):
    from illm_tools.rl.run import early_live_of_settings

    assert early_live_of_settings(_settings(tmp_path, **given)) is None and not fake_worker.made


def test_a_worker_the_config_does_not_want_is_closed_and_a_wanted_one_configured(tmp_path, fake_worker):
    from illm_tools.rl.run import build_run, early_live_of_settings

    unwanted = early_live_of_settings(_settings(tmp_path, method="rnd"))  # rnd reads no LLM targets
    with build_run(_config(tmp_path, method="rnd"), started=unwanted) as trainer:
        assert unwanted.closed and trainer.provider is None
    wanted = early_live_of_settings(_settings(tmp_path))
    with build_run(_config(tmp_path), started=wanted) as trainer:
        assert trainer.provider.live is wanted and wanted.spec.setup.history_len == 0 and wanted.budget == 8
    assert wanted.closed and len(fake_worker.made) == 2


def test_nothing_before_the_workers_start_imports_torch():
    """What `illm train` runs before it starts the worker imports no torch (0.9 s of this
    process's start the worker's own imports run beside)."""
    import subprocess
    import sys

    code = ("import sys\n"
            "import cli.main\n"
            "from illm_tools.rl.run import early_live_of_settings\n"
            "made = []\n"
            "import illm_tools.rl.live as live\n"
            "live.AsyncLive = lambda **kw: made.append(kw) or 'worker'\n"
            "assert early_live_of_settings(dict(method='illm', cache='ann', live_mode='async', live_budget='8')) == 'worker'\n"
            "assert 'torch' not in sys.modules, 'torch imported'\n"
            "assert made[0]['early'].model == 'smollm2-135m'\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]


def test_a_preload_imports_the_models_own_code_and_leaves_a_missing_model_to_the_load(tiny_lm_gpt2):
    """What an early worker does before its spec: the model's modeling module imported (read from
    its config); a model not here is left to `load`, which says what is wrong (`LLMSpec.preload`
    downloads nothing, whatever the run's download settings)."""
    import subprocess
    import sys

    code = ("import sys\n"
            "from illm_tools.llm.spec import LLMSpec\n"
            "LLMSpec(model='illm-tests/no-such-model').preload()\n"
            "assert 'transformers.models.gpt2.modeling_gpt2' not in sys.modules\n"
            f"LLMSpec(model={str(tiny_lm_gpt2.spec.path)!r}, dtype='float32').preload()\n"
            "assert 'transformers.models.gpt2.modeling_gpt2' in sys.modules\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]


def _running(pid: int) -> bool:
    """Whether process `pid` still runs (a zombie nobody reaped has ended)."""
    from pathlib import Path

    status = Path(f"/proc/{pid}/status")
    try:
        return "\nState:\tZ" not in status.read_text()
    except OSError:
        return False


def test_a_worker_whose_trainer_is_killed_ends_too(tiny_lm_gpt2):
    """A trainer killed without closing its worker (SIGKILL, the OOM killer) leaves no worker
    holding a core: the worker sees its parent gone, here while it waits for its spec."""
    import subprocess
    import sys
    import time

    code = ("import time\n"
            "from illm_tools.llm.spec import LLMSpec\n"
            "from illm_tools.rl.live import AsyncLive\n"
            f"live = AsyncLive(budget=1, early=LLMSpec(model={str(tiny_lm_gpt2.spec.path)!r}, dtype='float32'))\n"
            "print(live.process.pid, flush=True)\n"
            "time.sleep(600)\n")
    trainer = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:  # (its stderr: the resource tracker of a killed process warns about the semaphores it left)
        line = trainer.stdout.readline()
        assert line.strip().isdigit(), trainer.stderr.read()[-2000:] if trainer.poll() is not None else line
        worker = int(line)
        assert _running(worker)
    finally:
        trainer.kill()
        trainer.wait()
    end = time.monotonic() + 120
    while _running(worker) and time.monotonic() < end:  # a generous bound: the worker's imports come first
        time.sleep(0.2)
    assert not _running(worker)


def _as_from_a_terminal() -> None:
    """In the child before `illm` starts: SIGINT neither ignored nor blocked, as a shell starts a
    command, whatever this test process inherited or was left with (both survive the exec). Two
    fresh-clone CI runs saw the first command (its Ctrl-C 0.05 s in) train on to the end with exit 0;
    a Ctrl-C ignored or blocked from the start is the one way found to give that."""
    import signal

    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.SIG_DFL)


# A `sitecustomize` for the command under test: once `cli/__init__` has run (its Ctrl-C handler in
# place), it writes the file ILLM_TEST_CLI_READY names. Besides its folder on PYTHONPATH, nothing
# else changes in the child.
_CLI_READY_HOOK = """
import os, sys

class _AfterCli:
    def find_spec(self, name, path=None, target=None):
        if name != "cli":
            return None
        sys.meta_path.remove(self)
        import importlib.util
        spec = importlib.util.find_spec(name)
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            open(os.environ["ILLM_TEST_CLI_READY"], "w").close()

        spec.loader.exec_module = exec_module
        return spec

if os.path.basename(sys.argv[0]) == "illm":
    sys.meta_path.insert(0, _AfterCli())
"""


def test_ctrl_c_at_any_moment_of_the_start_ends_in_one_line_and_leaves_no_worker(tmp_path):
    """A Ctrl-C (SIGINT to the process group, as a terminal sends it) while `illm train` imports its
    commands, parses its options, starts its worker or builds its run: no traceback (from the
    command or from the worker's own start), the interrupt's exit code, and no worker left. Where
    each signal lands depends on the machine's speed; what is asserted holds wherever it lands.

    The moments count from the end of `cli/__init__`, where the `illm` script's own handling starts.
    Before it, in CPython's start (`site` importing the editable install's finder: pathlib, re), a
    Ctrl-C is CPython's: it prints "Fatal Python error: init_import_site" and a traceback, for any
    program, and no line of illm has run. Counted from the command's launch, the first moment fell
    there whenever the interpreter started slowly (a fresh clone's first bytecode on 2 cores)."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    illm = Path(sys.executable).with_name("illm")
    (tmp_path / "hook").mkdir()
    (tmp_path / "hook" / "sitecustomize.py").write_text(_CLI_READY_HOOK)
    python_path = os.pathsep.join(filter(None, [str(tmp_path / "hook"), os.environ.get("PYTHONPATH")]))
    for k, delay in enumerate((0.0, 0.1, 0.2, 0.3, 0.45, 0.65, 0.9)):
        (tmp_path / f"ann{k}").mkdir()
        ready = tmp_path / f"cli-ready{k}"
        command = [str(illm), "train", "--env", ENV, "--cache", str(tmp_path / f"ann{k}"), "--method", "illm",
                   "--history", "0", "--frames", "8192", "--out", str(tmp_path / f"run{k}")]
        run = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                               env={**os.environ, "ILLM_CACHE_DIR": str(tmp_path / "illm-cache"),  # nothing of the user's
                                    "PYTHONPATH": python_path, "ILLM_TEST_CLI_READY": str(ready)},
                               preexec_fn=_as_from_a_terminal)
        deadline = time.monotonic() + 120
        while not ready.exists() and run.poll() is None and time.monotonic() < deadline:
            time.sleep(0.002)
        assert ready.exists(), run.communicate(timeout=300)
        time.sleep(delay)
        os.killpg(run.pid, signal.SIGINT)
        out, err = run.communicate(timeout=300)
        assert "Traceback" not in out + err, err[-2000:]
        assert run.returncode == 130, (run.returncode, err[-2000:])
        assert len(err.strip().splitlines()) <= 2, err  # "interrupted", or the graceful stop's two lines
        deadline = time.monotonic() + 30  # the run's own group: its worker, had one been left behind
        while _group_has_a_worker(run.pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not _group_has_a_worker(run.pid)


def _group_has_a_worker(group: int) -> bool:
    """Whether a live (not zombie) multiprocessing child runs in process group `group`."""
    import subprocess

    pids = subprocess.run(["pgrep", "-g", str(group), "-f", "spawn_main"], capture_output=True, text=True).stdout.split()
    return any(_running(int(pid)) for pid in pids)


def _ctrl_c_to_this_thread() -> None:
    """SIGINT sent to this (the main) thread. Sent to the process (`os.kill(os.getpid(), ...)`), the
    kernel may hand it to another thread (pytest-xdist's worker has one) a moment later, after the
    block that should receive it has ended: a fast-tier run failed that way and its worker then took
    the late KeyboardInterrupt."""
    import signal
    import threading

    signal.pthread_kill(threading.get_ident(), signal.SIGINT)


def test_a_ctrl_c_during_the_spawn_reaches_the_trainer_once_the_worker_has_started():
    import signal

    from illm_tools.signals import ctrl_c_deferred

    before, got = signal.getsignal(signal.SIGINT), []
    try:
        signal.signal(signal.SIGINT, lambda signum, frame: got.append(signum))
        with ctrl_c_deferred():
            _ctrl_c_to_this_thread()
            assert not got  # held back, not lost
        assert got == [signal.SIGINT]  # then handled by the trainer's own handler, once
        signal.signal(signal.SIGINT, signal.default_int_handler)
        with pytest.raises(KeyboardInterrupt):
            with ctrl_c_deferred():
                _ctrl_c_to_this_thread()
    finally:
        signal.signal(signal.SIGINT, before)


def test_a_ctrl_c_inside_a_deferred_import_arrives_once_the_module_has_run_to_its_end(tmp_path, monkeypatch):
    """What the `illm` command does for torch's first import (`defer_ctrl_c_in_imports`, cli/__init__.py):
    a Ctrl-C landing inside the module's body lets the body finish (torch's C++ cannot unwind a
    KeyboardInterrupt raised in the Python it calls: the process aborted, exit -6), then the import
    raises it, once; the finder steps aside after that import, and the module is its loader's own."""
    import os
    import signal
    import sys

    from illm_tools.signals import defer_ctrl_c_in_imports

    name = "illm_test_interrupted_midway"
    path = tmp_path / f"{name}.py"
    path.write_text("import os, signal, threading\n"  # to this thread: see _ctrl_c_to_this_thread
                    "signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # the handler would raise next line\n"
                    "os.environ['ILLM_TEST_MIDWAY'] = 'ran to its end'\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("ILLM_TEST_MIDWAY", raising=False)
    monkeypatch.setattr(sys, "meta_path", list(sys.meta_path))
    before = signal.getsignal(signal.SIGINT)
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        defer_ctrl_c_in_imports([name])
        with pytest.raises(KeyboardInterrupt):
            __import__(name)
        assert os.environ["ILLM_TEST_MIDWAY"] == "ran to its end"
        assert not any(type(f).__name__ == "_DeferredImports" for f in sys.meta_path)
        path.write_text("import os\nLOADED_FROM = __file__\n")  # imported again: no deferral, the plain loader's module
        module = __import__(name)
        assert module.LOADED_FROM == str(path) and module.__spec__.origin == str(path)
    finally:
        signal.signal(signal.SIGINT, before)
        sys.modules.pop(name, None)
