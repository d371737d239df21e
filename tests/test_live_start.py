"""The async live worker starts first: before the env pool, the provider's checks and the network
(`illm_tools.rl.run.build_run`), so its start-up runs beside theirs; a run refused after it started
leaves no worker behind; and its first shards are small, so the first answer lands soon after the
model is loaded."""

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
    """Stands in for `AsyncLive`: records when it starts and whether it is closed."""

    made: list = []

    def __init__(self, spec, *, budget, max_restarts=3):
        self.spec, self.budget, self.closed = spec, budget, False
        Worker.made.append(self)
        EVENTS.append("worker")

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
