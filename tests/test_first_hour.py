"""The first hour of a new user (issue 49): nothing overwritten without an option, a cache that cannot
help a run named, live counts that include the shutdown, every error in one line, suffixes that match
their format, `illm cache show`, and `illm eval`'s interval."""

from __future__ import annotations

from typer.testing import CliRunner

from cli.main import app
from fakes import fake_run


def invoke(*args: str):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_report_refuses_an_out_folder_holding_files_unless_overwrite(tmp_path):
    fake_run(tmp_path / "run", 0, [(100, 1.0, 1), (200, 1.0, 1)])
    out = tmp_path / "rep"
    out.mkdir()
    (out / "report.md").write_text("my own notes")
    refused = invoke("report", tmp_path / "run", "--every", "100", "--out", out)
    assert refused.exit_code == 1, refused.output
    assert len(refused.output.strip().splitlines()) == 1 and "already holds report.md" in refused.output
    assert "--overwrite" in refused.output
    assert (out / "report.md").read_text() == "my own notes"  # nothing written
    assert sorted(p.name for p in out.iterdir()) == ["report.md"]
    merged = invoke("report", tmp_path / "a", tmp_path / "b", "--merge", "--out", out)
    assert merged.exit_code == 1 and "already holds report.md" in merged.output, merged.output
    empty = tmp_path / "empty"
    empty.mkdir()  # an empty folder is written into: it holds nothing to lose
    assert invoke("report", tmp_path / "run", "--every", "100", "--out", empty).exit_code == 0
    again = invoke("report", tmp_path / "run", "--every", "100", "--out", out, "--overwrite")
    assert again.exit_code == 0, again.output
    assert (out / "report.md").read_text() != "my own notes" and (out / "results.json").is_file()


def fake_training(monkeypatch, coverage: float, live: float = 0.0, at_close: int = 0, first: float | None = None):
    """`illm train`'s CLI around a stand-in run: one update with `coverage` of steps given a target,
    `live` states landed during it (the first `first` seconds after the run's start) and `at_close`
    written by the worker while the run shut down."""
    import illm_tools.rl.run as run_module

    def train(cfg, on_metrics=None, should_stop=None, started=None):
        on_metrics({"global_step": cfg.batch_size, "charts/target_coverage": coverage,
                    "charts/live_annotations": live, "charts/score": 0.0,
                    **({"charts/live_first_answer_s": first} if first is not None else {})})
        return {"global_step": cfg.batch_size, "live_at_close": at_close}

    monkeypatch.setattr(run_module, "train", train)
    monkeypatch.setattr(run_module, "early_live_of_settings", lambda settings: None)  # no worker for a stand-in run


def train_args(tmp_path, cache):
    return ["train", "--method", "illm", "--cache", cache, "--frames", 64, "--num-envs", 2, "--num-steps", 32,
            "--out", tmp_path / "run"]


def test_train_names_a_cache_that_holds_nothing_and_a_run_with_no_target(tmp_path, monkeypatch):
    fake_training(monkeypatch, coverage=0.0)
    typo = invoke(*train_args(tmp_path, tmp_path / "an"))
    assert typo.exit_code == 0, typo.output
    warned = [line for line in typo.output.splitlines() if line.startswith("warning: --cache")]
    assert len(warned) == 1 and f"--cache {tmp_path / 'an'} holds no folder" in warned[0], typo.output
    closing = [line for line in typo.output.splitlines() if line.startswith("warning: no step had an LLM target")]
    assert len(closing) == 1 and str(tmp_path / "an") in closing[0], typo.output

    fake_training(monkeypatch, coverage=0.25)  # a run with targets: neither line
    fine = invoke(*train_args(tmp_path, tmp_path / "an2"), "--live-budget", "8")
    assert fine.exit_code == 0, fine.output
    assert "no step had an LLM target" not in fine.output, fine.output
    assert "; 0 states annotated live -> " in fine.output, fine.output  # no split of nothing


def test_a_foreign_cache_that_gave_no_target_is_named_with_what_it_holds(tmp_path, monkeypatch):
    from cli.train import cache_holds

    assert cache_holds(tmp_path / "none") == "no folder"
    (tmp_path / "other").mkdir()
    assert cache_holds(tmp_path / "other") == "no annotation cache"


def test_the_live_count_includes_what_the_worker_writes_while_shutting_down(tmp_path, monkeypatch):
    from illm_tools.rl.live import AsyncLive
    from illm_tools.rl.targets import CachedTargets

    class Stopping:
        """The worker process: it writes its last chunk of 8 states while the run waits for it to end."""

        def __init__(self, done):
            self.done, self.exitcode, self.alive = done, None, True

        def is_alive(self):
            return self.alive

        def join(self, timeout=None):
            if self.alive:
                self.done.value += 8
                self.alive, self.exitcode = False, 0

        def terminate(self):
            pass

        def close(self):
            pass

    class Worker(AsyncLive):
        def _start(self):
            self.started_at = 0.0
            self._inbox, self._errors, self._stop = self._ctx.Queue(), self._ctx.Queue(), self._ctx.Event()
            self._setup = self._ctx.Queue()
            self.process = Stopping(self._done)

    live = Worker(early="the run's LLM", budget=4)
    live.configure("the run's spec", budget=4)  # configured: closing waits for its last chunk
    live._done.value = 3  # landed during the run's last rollout, after its count
    targets = CachedTargets(None, None, calibration="sum", num_actions=3, embedding_dim=0, live=live)
    targets.close()
    assert targets.landed_at_close == 3 + 8

    fake_training(monkeypatch, coverage=0.5, live=2.0, at_close=8, first=4.25)  # the CLI adds them to the run's count
    out = invoke(*train_args(tmp_path, tmp_path / "ann"))
    assert out.exit_code == 0 and "10 states annotated live" in out.output, out.output
    assert "(2 during the rollouts, 8 while the run shut down, kept in the cache); the first landed 4.2 s after the " \
        "run started" in out.output, out.output


def test_train_says_how_the_target_share_moved_from_the_first_rollout_to_the_last(tmp_path, monkeypatch):
    import illm_tools.rl.run as run_module

    def train(cfg, on_metrics=None, should_stop=None, started=None):
        for update, share in enumerate((0.25, 0.5), 1):  # the live fallback's answers land between rollouts
            on_metrics({"global_step": update * cfg.batch_size, "charts/target_coverage": share,
                        "charts/live_annotations": 3.0, "charts/score": 0.0})
        return {"global_step": 2 * cfg.batch_size, "live_at_close": 0}

    monkeypatch.setattr(run_module, "train", train)
    monkeypatch.setattr(run_module, "early_live_of_settings", lambda settings: None)  # no worker for a stand-in run
    args = train_args(tmp_path, tmp_path / "ann")
    args[args.index("--frames") + 1] = 128
    out = invoke(*args)
    assert out.exit_code == 0, out.output
    assert "steps with an LLM target 38% on average (25% in the first rollout, 50% in the last); 6 states annotated " \
        "live (6 during the rollouts, 0 while the run shut down" in out.output, out.output


def test_annotate_given_a_cache_as_its_dataset_says_what_to_pass(tmp_path):
    import json

    cache = tmp_path / "ann"
    cache.mkdir()
    (cache / "manifest.json").write_text(json.dumps({"format": "illm.annotation-cache", "shards": []}))
    out = invoke("annotate", cache, "--backend", "oracle")
    assert out.exit_code == 1, out.output
    assert len(out.output.strip().splitlines()) == 1 and f"{cache} is an annotation cache, not a trajectory dataset" \
        in out.output and "illm collect --out" in out.output, out.output
    assert f"collect --out {cache}" not in out.output  # never advice that writes into the cache's folder
    assert sorted(p.name for p in cache.iterdir()) == ["manifest.json"]


def test_collect_with_an_unknown_policy_lists_every_valid_one(tmp_path):
    out = invoke("collect", "--env", "BabyAI-GoToLocal-v0", "--policy", "expert", "--steps", 8, "--out", tmp_path / "d")
    assert out.exit_code == 1, out.output
    line = out.output.strip()
    assert len(line.splitlines()) == 1 and "random" in line and "bot" in line and "a run folder" in line, line
    assert not (tmp_path / "d").exists()
    (tmp_path / "notarun").mkdir()
    folder = invoke("collect", "--env", "BabyAI-GoToLocal-v0", "--policy", tmp_path / "notarun", "--out", tmp_path / "d")
    assert folder.exit_code == 1 and "without a run's config.json" in folder.output and "random" in folder.output


def test_an_option_click_cannot_parse_is_one_line(tmp_path):
    for args in (["train", "--frames", "1e5"], ["train", "--history", "three"], ["collect"], ["trian"],
                 ["cache", "info"]):
        out = invoke(*args, "--out", tmp_path / "r") if args[0] == "train" else invoke(*args)
        lines = out.output.strip().splitlines()
        assert out.exit_code == 1 and len(lines) == 1 and lines[0].startswith("error: "), (args, out.output)
        assert "--help` lists the options" in lines[0] and "╭" not in out.output, out.output
    assert "--frames" in invoke("train", "--frames", "1e5", "--out", tmp_path / "r").output
    assert not (tmp_path / "r").exists()
    own = invoke("eval", tmp_path / "no-run")  # a command's own error passes through the group untouched
    assert own.exit_code == 1 and type(own.exception) is SystemExit and own.output.startswith("error: no "), own
    bare = invoke("cache")  # a group without its command: its help, as before
    assert bare.exit_code == 2 and "Usage: illm cache" in bare.output and "error:" not in bare.output


def test_cache_export_refuses_a_name_of_another_format(tmp_path):
    from illm_tools.cache import AnnotationCache
    from fakes import make_rows

    cache = tmp_path / "ann"
    AnnotationCache(cache).write(make_rows(0, 8))
    arrow = invoke("cache", "export", cache, "--out", tmp_path / "x.arrow")
    assert arrow.exit_code == 1, arrow.output
    assert len(arrow.output.strip().splitlines()) == 1 and "named .arrow" in arrow.output and ".parquet" in arrow.output
    assert not (tmp_path / "x.arrow").exists()
    parquet = invoke("cache", "export", cache, "--out", tmp_path / "x.parquet")
    assert parquet.exit_code == 0, parquet.output
    assert (tmp_path / "x.parquet").read_bytes()[:4] == b"PAR1"


def test_cache_show_prints_a_few_states_answers_and_writes_nothing(tmp_path):
    import json

    from illm_tools.cache import AnnotationCache
    from fakes import make_rows

    rows = make_rows(0, 8)
    for i, row in enumerate(rows):  # rows 2k (action) and 2k+1 (summary) answer one state
        row["observation"] = f"obs {i // 2}"
    cache = tmp_path / "ann"
    AnnotationCache(cache).write(rows)
    before = sorted((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in cache.rglob("*"))
    out = invoke("cache", "show", cache, "--limit", 2)
    assert out.exit_code == 0, out.output
    assert out.output.count("state ") == 2 and "obs 2" not in out.output  # --limit states, the first ones
    assert "action prompt:" in out.output and "| prompt 0" in out.output and "| prompt 1" in out.output
    assert "-0.750  turn left (2 tokens)  <- chosen" in out.output and "-1.500  go forward (1 token)" in out.output
    assert out.output.index("-0.750  turn left") < out.output.index("-1.500  go forward")  # best first
    assert "summary: summary 1" in out.output and "summary: summary 3" in out.output
    assert sorted((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in cache.rglob("*")) == before
    (state,) = json.loads(invoke("cache", "show", cache, "--limit", 1, "--json").output)
    assert [a["task"] for a in state["answers"]] == ["action", "summary"] and state["answers"][0]["chosen"] == "turn left"
    missing = invoke("cache", "show", tmp_path / "none")
    assert missing.exit_code == 1 and "no annotation cache at" in missing.output and not (tmp_path / "none").exists()


def test_eval_gives_the_success_rate_with_its_wilson_interval_and_the_episode_count(tmp_path, monkeypatch):
    import json

    import illm_tools.rl.run as run_module
    from illm_tools.report.stats import wilson_interval

    low, high = wilson_interval(5, 10)  # the textbook value of 5 successes in 10 trials
    assert round(low, 4) == 0.2366 and round(high, 4) == 0.7634
    assert wilson_interval(0, 50) == (0.0, wilson_interval(0, 50)[1]) and round(wilson_interval(0, 50)[1], 3) == 0.071

    def evaluate(run, episodes, seed, greedy):
        return {"run": str(run), "env_id": "BabyAI-GoToLocal-v0", "method": "illm", "episodes": episodes,
                "score": 0.64, "score_name": "success rate", "success_rate": 0.64, "mean_return": 0.5,
                "mean_length": 20.0, "frames": 8192}

    monkeypatch.setattr(run_module, "evaluate", evaluate)
    fake_run(tmp_path / "run", 0, [(100, 1.0, 1)])
    out = invoke("eval", tmp_path / "run", "--episodes", 50)
    assert out.exit_code == 0, out.output
    assert "| 8,192 | 50 | 0.640 (success rate) | 0.640 [0.501, 0.759] |" in out.output, out.output
    assert "95% Wilson score interval" in out.output
    (row,) = json.loads(invoke("eval", tmp_path / "run", "--episodes", 50, "--json").output)
    assert [round(x, 3) for x in row["success_interval"]] == [0.501, 0.759] and row["episodes"] == 50


def test_a_run_whose_live_answers_came_too_late_says_so(tmp_path, monkeypatch):
    fake_training(monkeypatch, coverage=0.0, live=0.0, at_close=8)
    out = invoke(*train_args(tmp_path, tmp_path / "ann"))
    closing = [line for line in out.output.splitlines() if line.startswith("warning: no step had an LLM target")]
    assert len(closing) == 1 and "the 8 states annotated live landed after the rollouts" in closing[0], out.output
    assert "none of them a state this run visited" not in out.output


def test_eval_of_one_run_per_method_says_one_seed_cannot_compare_methods(tmp_path, monkeypatch):
    from pathlib import Path

    import illm_tools.rl.run as run_module

    rates = {"illm": 0.64, "ppo": 0.5}

    def evaluate(run, episodes, seed, greedy):
        method = Path(run).name
        return {"run": str(run), "env_id": "BabyAI-GoToLocal-v0", "method": method, "episodes": episodes,
                "score": rates[method], "score_name": "success rate", "success_rate": rates[method],
                "mean_return": 0.5, "mean_length": 20.0, "frames": 8192}

    monkeypatch.setattr(run_module, "evaluate", evaluate)
    for name in rates:
        fake_run(tmp_path / name, 0, [(100, 1.0, 1)])
    out = invoke("eval", tmp_path / "illm", tmp_path / "ppo", "--episodes", 50)
    assert out.exit_code == 0, out.output
    (line,) = [line for line in out.output.splitlines() if line.startswith("runs per method")]
    assert "illm 1, ppo 1" in line and "here they overlap" in line and "one seed cannot say which method" in line
    alone = invoke("eval", tmp_path / "illm", "--episodes", 50)  # one method: nothing compared, no line
    assert alone.exit_code == 0 and "runs per method" not in alone.output, alone.output
