"""A grid's runs share the machine's cores: the live annotator of each run gets its share, not all of
them (`experiment.launch.shared_cores`)."""
from illm_tools.experiment.launch import shared_cores
from illm_tools.experiment.plan import plan
from illm_tools.experiment.spec import load_spec
from illm_tools.rl.run import live_threads


def _sync_illm_run(tmp_path):
    spec = tmp_path / "grid.yaml"
    spec.write_text("name: grid\nframes: 4096\nseeds: 1\nenvs: [MiniGrid-DoorKey-5x5-v0]\nmethods: [illm]\n"
                    "method_settings:\n  illm: {backend: oracle, history_len: 0, live_budget: all, live_mode: sync}\n")
    (run,) = plan(load_spec(spec), tmp_path / "results")
    return run.config


def test_a_sync_annotator_in_a_grid_gets_its_share_of_the_cores(tmp_path, monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 16)
    config = _sync_illm_run(tmp_path)
    assert config.targets.llm_threads == 0 and live_threads(config) == 16
    shared = shared_cores(config, jobs=15)
    assert shared.targets.llm_threads == 1 and live_threads(shared) == 1
    assert shared_cores(config, jobs=4).targets.llm_threads == 4
    assert shared.threads == config.threads == 1 and shared.targets.cache == config.targets.cache


def test_one_job_or_a_given_thread_count_is_left_as_it_is(tmp_path, monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    config = _sync_illm_run(tmp_path)
    assert shared_cores(config, jobs=1) is config
    assert shared_cores(config, jobs=4).targets.llm_threads == 1  # never 0 when jobs outnumber cores
    from dataclasses import replace
    given = replace(config, targets=replace(config.targets, llm_threads=3))
    assert shared_cores(given, jobs=2) is given
