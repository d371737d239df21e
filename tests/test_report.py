"""`illm report`: curve points are episode-weighted windows, aligned by frame across seeds.

Over 400 lines: the report's tests share rliable's IQM by hand (`iqm_by_hand`); split, the second
file would import it from the first (the fake runs, `fake_run`, are tests/fakes/' own)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from illm_tools.report.curves import summarise
from fakes import fake_run



def test_points_are_weighted_windows_aligned_by_frame(tmp_path):
    # run a: 4 updates of 50 frames; run b killed after 2 updates plus a short one at 120
    fake_run(tmp_path / "a", 0, [(50, 1.0, 1), (100, 0.0, 3), (150, 0.5, 2), (200, 0.5, 2)])
    fake_run(tmp_path / "b", 1, [(50, 0.0, 1), (100, 0.0, 1), (120, 1.0, 1)])
    (group,) = summarise([tmp_path / "a", tmp_path / "b"], every=100).values()
    assert group["frames"] == [100]  # b's short window (100, 120] has no partner in a
    assert group["mean"] == [(0.25 + 0.0) / 2]  # a: (1*1 + 0*3) / 4; b: 0
    assert group["coverage"] == 0.5 and group["hit_rate"] == 0.25
    (alone,) = summarise([tmp_path / "b"], every=100).values()
    assert alone["frames"] == [100, 120] and alone["mean"] == [0.0, 1.0]


def test_runs_with_other_bonus_weights_are_reported_apart(tmp_path):
    from illm_tools.report.curves import group_labels

    base = {"mode": "illm", "env_id": "E", "lambda_a": 0.8, "ext_coef": 1.0, "seed": 0, "run_dir": "a"}
    assert group_labels([{**base, "mode": "ppo"}, base]) == ["ppo", "illm"]  # other methods are not compared
    assert group_labels([base, {**base, "ext_coef": 2.0, "seed": 1, "run_dir": "b"}]) == \
        ["illm (ext_coef 1)", "illm (ext_coef 2)"]
    fake_run(tmp_path / "a", 0, [(100, 1.0, 1)])
    fake_run(tmp_path / "b", 0, [(100, 0.0, 1)])
    cfg = json.loads((tmp_path / "b" / "config.json").read_text())
    (tmp_path / "b" / "config.json").write_text(json.dumps({**cfg, "ext_coef": 2.0}))
    groups = summarise([tmp_path / "a", tmp_path / "b"], every=100)
    # a run without the setting in its config.json (an older run) compares at the setting's default
    assert sorted(method for _, method in groups) == ["illm (ext_coef 1)", "illm (ext_coef 2)"]


def test_a_report_reads_each_run_once_so_a_run_still_training_gives_one_set_of_points(tmp_path, monkeypatch):
    """`illm report --out` of a grid still training: a run's metrics.csv grows between two reads, and a
    report that read it twice met points the first read did not have (a KeyError, seen on a Crafter grid)."""
    from typer.testing import CliRunner

    import illm_tools.report.curves as curves
    from cli.main import app

    fake_run(tmp_path / "a", 0, [(100, 1.0, 1), (200, 0.5, 2)])
    fake_run(tmp_path / "b", 1, [(100, 0.0, 1), (150, 1.0, 1)])
    read, load = [], curves.load_curve

    def growing(run_dir, every):  # each read of b finds 30 more frames trained
        read.append(run_dir.name)
        if run_dir.name == "b":
            with open(run_dir / "metrics.csv") as f:
                header, *rows = f.read().splitlines()
            step = header.split(",").index("global_step")
            last = rows[-1].split(",")
            last[step] = str(int(last[step]) + 30)
            with open(run_dir / "metrics.csv", "a") as f:
                f.write(",".join(last) + "\n")
        return load(run_dir, every)

    monkeypatch.setattr(curves, "load_curve", growing)
    out = CliRunner().invoke(app, ["report", str(tmp_path / "a"), str(tmp_path / "b"), "--every", "100",
                                   "--out", str(tmp_path / "report")])
    assert out.exit_code == 0, out.output
    assert sorted(read) == ["a", "b"]
    results = json.loads((tmp_path / "report" / "results.json").read_text())
    (row,) = results["rows"]
    assert row["frames"] == [100] and row["trained_frames"][str(tmp_path / "b")] == 180  # b as read once


def test_duplicate_seeds_are_refused_and_short_runs_are_named(tmp_path):
    import pytest
    from typer.testing import CliRunner

    from cli.main import app
    from illm_tools.errors import UsageError

    fake_run(tmp_path / "a", 0, [(100, 1.0, 1)])
    fake_run(tmp_path / "copy", 0, [(100, 1.0, 1)])
    with pytest.raises(UsageError, match="same configuration with the same seed 0"):
        summarise([tmp_path / "a", tmp_path / "copy"], every=100)
    fake_run(tmp_path / "short", 1, [(50, 1.0, 1)])
    out = CliRunner().invoke(app, ["report", str(tmp_path / "a"), str(tmp_path / "short"), "--every", "100"])
    assert out.exit_code == 0, out.output
    assert "short left out: trained for 50 frames, too short for a point at --every 100" in out.output
    alone = CliRunner().invoke(app, ["report", str(tmp_path / "short"), "--every", "1000"])  # no run has a point
    assert alone.exit_code == 0 and "short left out" in alone.output, alone.output
    missing = CliRunner().invoke(app, ["report", str(tmp_path / "runs-*"), "--every", "100"])
    assert missing.exit_code == 1 and "no run folder at" in missing.output
    table = [line for line in out.output.splitlines() if line.startswith("|")]
    assert len({line.count("|") for line in table}) == 1  # every row has the header's columns
    assert "| 1 | 1.00 | 50.0% |" in out.output  # one seed: no spread shown


PNG = b"\x89PNG\r\n\x1a\n"


def iqm_by_hand(scores):
    """The interquartile mean as rliable computes it (scipy's trim_mean at 0.25): int(n / 4) scores
    cut from each end, so 3 seeds keep all three (the IQM is their mean), 4 keep the middle two."""
    x = np.sort(np.asarray(scores, dtype=float))
    cut = int(0.25 * len(x))
    return float(x[cut:len(x) - cut].mean())


def test_iqm_and_intervals_follow_rliable(tmp_path):
    from illm_tools.report.stats import curve_band, final_scores, iqm_interval

    three = iqm_interval([0.1, 0.5, 0.6], reps=500)
    assert three["iqm"] == pytest.approx(iqm_by_hand([0.1, 0.5, 0.6])) == pytest.approx(0.4)  # nothing trimmed
    assert (three["ci_low"], three["ci_high"]) == pytest.approx((0.1, 0.6))  # 3 seeds: the interval is [min, max]
    assert three["mean"] == pytest.approx(0.4) and three["std"] == pytest.approx(np.std([0.1, 0.5, 0.6]))
    assert iqm_interval([0.0, 0.2, 0.4, 1.0], reps=200)["iqm"] == pytest.approx(0.3)  # the middle two
    state = np.random.get_state()[1].copy()
    six = [0.1, 0.5, 0.9, 0.3, 0.35, 0.8]
    assert iqm_interval(six, reps=300, seed=3) == iqm_interval(six, reps=300, seed=3)  # seeded
    assert (np.random.get_state()[1] == state).all()  # the caller's random state is left alone
    one = iqm_interval([0.7, float("nan")])
    assert one["n"] == 1 and one["iqm"] == pytest.approx(0.7) and one["ci_low"] is None
    assert final_scores(np.array([[0.0, 1.0, 0.5], [0.2, np.nan, 0.4]]), 2).tolist() == [0.75, 0.4]
    mean, low, high = curve_band(np.array([[0.0, 1.0], [0.5, 1.0], [1.0, 1.0]]), reps=200)
    assert mean == [0.5, 1.0] and low[0] < 0.5 < high[0] and low[1] == high[1] == 1.0


def test_report_folder_tables_figures_and_grouping(tmp_path):
    from typer.testing import CliRunner

    from cli.main import app
    from illm_tools.report.plots import summed_counts

    finals = {"illm": [0.9, 0.5, 0.8], "ppo": [0.1, 0.4, 0.2]}
    runs = []
    for mode, scores in finals.items():
        for seed, final in enumerate(scores):
            runs.append(tmp_path / f"{mode}-s{seed}")
            fake_run(runs[-1], seed, [(50, 0.0, 2), (100, final / 2, 2), (150, final, 1), (200, final, 3)], mode=mode)
    other = tmp_path / "other-env"
    fake_run(other, 0, [(100, 0.25, 1), (200, 0.75, 1)], env_id="BabyAI-GoToObj-v0")
    np.save(runs[0] / "visitation.npy", np.array([[1, 0], [2, 3]], dtype=np.int64))
    np.save(runs[1] / "visitation.npy", np.array([[5, 0, 1]], dtype=np.int64))
    assert summed_counts([np.array([[1, 0], [2, 3]]), np.array([[5, 0, 1]])]).tolist() == [[6, 0, 1], [2, 3, 0]]

    out = tmp_path / "rep"
    result = CliRunner().invoke(app, ["report", *map(str, runs + [other]), "--every", "100", "--out", str(out),
                                      "--bootstrap", "500"])
    assert result.exit_code == 0, result.output
    assert "| BabyAI-GoToLocal-v0 | ppo | 3 |" in result.output and "report written to" in result.output
    for name in ["curves-BabyAI-GoToLocal-v0.png", "curves-BabyAI-GoToObj-v0.png", "final.png",
                 "visitation-BabyAI-GoToLocal-v0-illm.png"]:
        assert (out / name).read_bytes()[:8] == PNG, name
    assert not list(out.glob("visitation-*ppo*"))  # no ppo seed saved visitation.npy

    results = json.loads((out / "results.json").read_text())
    rows = {(r["env_id"], r["label"]): r for r in results["rows"]}
    assert set(rows) == {("BabyAI-GoToLocal-v0", "illm"), ("BabyAI-GoToLocal-v0", "ppo"), ("BabyAI-GoToObj-v0", "illm")}
    md = (out / "report.md").read_text()
    for mode, scores in finals.items():
        final = rows["BabyAI-GoToLocal-v0", mode]["final"]
        assert [s["score"] for s in final["per_seed"]] == pytest.approx(scores)  # the 200-frame point
        assert final["iqm"] == pytest.approx(iqm_by_hand(scores)) == pytest.approx(np.mean(scores))
        assert (final["ci_low"], final["ci_high"]) == pytest.approx((min(scores), max(scores)))
        assert final["mean"] == pytest.approx(np.mean(scores)) and final["std"] == pytest.approx(np.std(scores))
        assert (f"| {mode} | {iqm_by_hand(scores):.3f} [{min(scores):.3f}, {max(scores):.3f}] | "
                f"{np.mean(scores):.3f} ± {np.std(scores):.3f} | 3 | 200 |") in md
    assert rows["BabyAI-GoToLocal-v0", "illm"]["visitation"]["runs"] == [str(runs[0]), str(runs[1])]
    assert "| illm | 0.750 (1 seed: no interval) | 0.750 | 1 | 200 |" in md  # the other env's single run
    assert "## All envs" in md and "| illm | 0.733 [0.500, 0.900] | 0.750 (1 seed: no interval) |" in md
    assert "7 run folders → 3 rows over 2 envs" in md
    assert "BabyAI-GoToLocal-v0: 6 runs in 2 rows; BabyAI-GoToObj-v0: 1 run in 1 row (reported separately)" in md
    assert "BabyAI-GoToLocal-v0, ppo (success rate): seeds 0, 1, 2; budget: trained 200 frames" in md
    for link in ["curves-BabyAI-GoToLocal-v0.png", "final.png", "visitation-BabyAI-GoToLocal-v0-illm.png"]:
        assert f"]({link})" in md  # relative links
    local, obj = md.split("## BabyAI-GoToObj-v0")[0], md.split("## BabyAI-GoToObj-v0")[1]
    assert "shaded: pointwise 95% bootstrap band" in local  # 3 seeds: a band drawn and named
    assert "no band: one seed per line" in obj and "bootstrap band" not in obj.split("## ")[0]  # one seed: none named

    again = tmp_path / "rep2"  # final score over the last two points, (0, 100] and (100, 200], episode-weighted
    CliRunner().invoke(app, ["report", *map(str, runs), "--every", "100", "--out", str(again), "--final-points", "2",
                             "--bootstrap", "200", "--json"])
    two = json.loads((again / "results.json").read_text())["rows"]
    illm = next(r for r in two if r["label"] == "illm")
    expected = [np.mean([(0 * 2 + f / 2 * 2) / 4, (f * 1 + f * 3) / 4]) for f in finals["illm"]]
    assert [s["score"] for s in illm["final"]["per_seed"]] == pytest.approx(expected)
    assert illm["final"]["points"] == [100, 200]


def test_episode_length_per_run_is_windowed_like_the_score_and_set_beside_the_time_limit(tmp_path):
    """results.json's episode length: each seed's final length is the episode-weighted mean over the same
    last points as its score, with IQM [95% CI] over seeds, the first and last window's mean over seeds and
    the env's time limit; report.md shows it; a report written before lengths were logged redraws without."""
    from typer.testing import CliRunner

    from cli.main import app
    from illm_tools.report.lengths import time_limit

    # (step, success, episodes, mean length): windows (0, 100] and (100, 200]
    lengths = {0: [(50, 0.0, 1, 64), (100, 0.0, 3, 32), (150, 1.0, 1, 10), (200, 0.5, 3, 30)],
               1: [(50, 0.0, 2, 64), (100, 0.0, 0), (150, 0.0, 1, 64), (200, 0.0, 1, 64)],
               2: [(50, 0.0, 1, 64), (100, 0.5, 2, 40), (150, 0.0, 0), (200, 1.0, 2, 8)]}
    runs = []
    for seed, rows in lengths.items():
        runs.append(tmp_path / f"s{seed}")
        fake_run(runs[-1], seed, rows)
    out = tmp_path / "rep"
    result = CliRunner().invoke(app, ["report", *map(str, runs), "--every", "100", "--out", str(out),
                                      "--bootstrap", "200"])
    assert result.exit_code == 0, result.output
    (row,) = json.loads((out / "results.json").read_text())["rows"]
    first = [(64 + 32 * 3) / 4, 64.0, (64 + 40 * 2) / 3]
    last = [(10 + 30 * 3) / 4, 64.0, 8.0]  # seed 2's (100, 200] window: one update with no episode
    length = row["episode_length"]
    assert [s["length"] for s in length["per_seed"]] == pytest.approx(last)
    assert length["iqm"] == pytest.approx(iqm_by_hand(last)) and length["n"] == 3
    assert (length["ci_low"], length["ci_high"]) == pytest.approx((min(last), max(last)))
    assert length["curve"] == pytest.approx([np.mean(first), np.mean(last)])
    assert (length["first"], length["last"]) == pytest.approx((np.mean(first), np.mean(last)))
    assert length["time_limit"] == time_limit("BabyAI-GoToLocal-v0") == 64  # BabyAI sets it at reset
    assert time_limit("NoSuchEnv-v0") is None
    md = (out / "report.md").read_text()
    assert f"| illm | {np.mean(last):.1f} [8.0, 64.0] | {np.mean(last):.1f} ± {np.std(last):.1f} | " \
           f"{np.mean(first):.1f} → {np.mean(last):.1f} | 64 |" in md
    two = tmp_path / "rep2"  # --final-points 2: both windows, each seed's the mean of its two points
    CliRunner().invoke(app, ["report", *map(str, runs), "--every", "100", "--out", str(two), "--final-points", "2",
                             "--bootstrap", "200"])
    (row,) = json.loads((two / "results.json").read_text())["rows"]
    assert [s["length"] for s in row["episode_length"]["per_seed"]] == \
        pytest.approx([(a + b) / 2 for a, b in zip(first, last)])

    results = json.loads((out / "results.json").read_text())  # an older report: no episode_length
    for r in results["rows"]:
        del r["episode_length"]
    (out / "results.json").write_text(json.dumps(results))
    assert CliRunner().invoke(app, ["report", str(out), "--redraw"]).exit_code == 0
    assert "episode length IQM" not in (out / "report.md").read_text()


def test_the_quality_curve_places_each_configuration_at_its_annotators_probe_agreement(tmp_path):
    """`illm report --probe FILE`: an illm row sits at the agreement of the probe of its env, backend,
    model (oracle noise included), history and layout; ppo is a reference line; a probe no run used
    (an LLM) is a marker; a file that is not a probe is refused in one line."""
    from typer.testing import CliRunner

    from cli.main import app

    def probe_file(name, model, backend, agreement):
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps({
            "config": {"env_id": "BabyAI-UnlockLocal-v0", "model": model, "backend": backend, "history": 0,
                       "layout": "shared"},
            "calibrations": {c: {"agreement": agreement} for c in ("sum", "mean", "pmi")},
            "baselines": {"chance_agreement": 1 / 6, "majority_agreement": 0.49, "majority_action": "go forward"}}))
        return path

    runs = []
    for noise, final in ((0, 0.9), (0.5, 0.5), (1, 0.1)):
        for seed in range(2):
            runs.append(tmp_path / f"illm-{noise}-s{seed}")
            fake_run(runs[-1], seed, [(100, final, 2), (200, final, 2)], env_id="BabyAI-UnlockLocal-v0")
            cfg = json.loads((runs[-1] / "config.json").read_text())
            cfg.update(backend="oracle", oracle_noise=noise, history_len=0)
            (runs[-1] / "config.json").write_text(json.dumps(cfg))
    runs.append(tmp_path / "ppo-s0")
    fake_run(runs[-1], 0, [(100, 0.2, 2), (200, 0.2, 2)], mode="ppo", env_id="BabyAI-UnlockLocal-v0")
    probes = [probe_file("o0", "oracle", "oracle", 0.85), probe_file("o5", "oracle:noise=0.5", "oracle", 0.6),
              probe_file("o1", "oracle:noise=1", "oracle", 0.3), probe_file("smol", "smollm2-135m", "transformers", 0.25)]
    out = tmp_path / "rep"
    result = CliRunner().invoke(app, ["report", *map(str, runs), "--every", "100", "--out", str(out), "--bootstrap",
                                      "200", *[x for p in probes for x in ("--probe", str(p))]])
    assert result.exit_code == 0, result.output
    quality = json.loads((out / "results.json").read_text())["quality"]
    points = {p["label"]: (p["agreement"], p["final"]["iqm"]) for p in quality["points"]}
    assert points == {"illm (oracle_noise 0)": (0.85, pytest.approx(0.9)), "illm (oracle_noise 0.5)": (0.6, pytest.approx(0.5)),
                      "illm (oracle_noise 1)": (0.3, pytest.approx(0.1))}
    assert [line["label"] for line in quality["lines"]] == ["ppo"]
    assert [(m["model"], m["agreement"]) for m in quality["markers"]] == [("smollm2-135m", 0.25)]
    assert (out / "quality.png").read_bytes()[:8] == PNG
    md = (out / "report.md").read_text()
    assert "## Annotator quality" in md and "| BabyAI-UnlockLocal-v0 | illm (oracle_noise 0.5) | 0.600 |" in md

    # a probe of a model no configuration trained with: said in one line, no quality.png
    alone = CliRunner().invoke(app, ["report", *map(str, runs), "--every", "100", "--out", str(tmp_path / "r3"),
                                     "--bootstrap", "50", "--probe", str(probes[-1])])
    assert alone.exit_code == 0 and "quality.png is not drawn" in alone.output
    assert not (tmp_path / "r3" / "quality.png").exists()

    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    refused = CliRunner().invoke(app, ["report", *map(str, runs), "--out", str(tmp_path / "r2"), "--probe", str(bad)])
    assert refused.exit_code == 1 and "is not a probe file" in refused.output and "Traceback" not in refused.output


def test_curves_are_small_multiples_of_the_settings_methods_share():
    """A paper table's grid (Table 1: distractors for every method) gives one panel per value; a
    setting of one method alone (illm's obs_mode, the oracle's noise) stays in the line's name."""
    from illm_tools.report.plots import panels

    rows = [{"method": m, "settings": {"num_dists": n, **extra}} for n in ("4", "8")
            for m, extra in (("ppo", {}), ("illm", {"obs_mode": "hop"}), ("illm", {"obs_mode": "obs"}))]
    keys, placed = panels(rows)
    assert keys == ["num_dists"]
    assert placed[:3] == [("num_dists 4", "ppo"), ("num_dists 4", "illm (obs_mode hop)"),
                          ("num_dists 4", "illm (obs_mode obs)")]
    keys, placed = panels([{"method": "ppo", "settings": {}}, {"method": "illm", "settings": {"oracle_noise": "0.5"}}])
    assert keys == [] and placed == [("", "ppo"), ("", "illm (oracle_noise 0.5)")]


def test_redraw_draws_an_old_report_again_from_its_results_json(tmp_path):
    """`illm report DIR --redraw`: the runs are gone; an older results.json has no settings per row,
    so they come from the labels, as numbers (panels 4, 8, 16 in that order); a damaged file is one
    line and is left as it was."""
    from typer.testing import CliRunner

    from cli.main import app
    from illm_tools.report.plots import panel_titles

    runs = []
    for seed in range(2):
        for mode, final in (("ppo", 0.2), ("illm", 0.6)):
            runs.append(tmp_path / f"{mode}-{seed}")
            fake_run(runs[-1], seed, [(100, final / 2, 1), (200, final, 1)], mode=mode)
    out = tmp_path / "rep"
    assert CliRunner().invoke(app, ["report", *map(str, runs), "--every", "100", "--out", str(out),
                                    "--bootstrap", "100"]).exit_code == 0
    results = json.loads((out / "results.json").read_text())
    old = []
    for n in (16, 4, 8):  # a distractor grid as an older version wrote it: no settings, labels carry them
        for row in results["rows"]:
            old.append({k: v for k, v in row.items() if k != "settings"} | {"label": f"{row['method']} (num_dists {n})"})
    results["rows"] = old
    (out / "results.json").write_text(json.dumps(results))
    for name in ("final.png", "curves-BabyAI-GoToLocal-v0.png", "report.md"):
        (out / name).unlink()
    for run in runs:
        for f in run.iterdir():
            f.unlink()
        run.rmdir()

    result = CliRunner().invoke(app, ["report", str(out), "--redraw"])
    assert result.exit_code == 0, result.output
    redrawn = json.loads((out / "results.json").read_text())
    assert [r["settings"] for r in redrawn["rows"]][:2] == [{"num_dists": 16}, {"num_dists": 16}]
    assert panel_titles(redrawn["rows"]) == ["num_dists 4", "num_dists 8", "num_dists 16"]
    for name in ("final.png", "curves-BabyAI-GoToLocal-v0.png"):
        assert (out / name).read_bytes()[:8] == PNG, name
    assert "| illm (num_dists 4) |" in (out / "report.md").read_text()
    assert "| method | num_dists 4 | num_dists 8 | num_dists 16 |" in (out / "report.md").read_text()  # by value

    (out / "results.json").write_text("{not json")
    result = CliRunner().invoke(app, ["report", str(out), "--redraw"])
    assert result.exit_code != 0 and "is damaged" in result.output and len(result.output.strip().splitlines()) == 1
    assert (out / "results.json").read_text() == "{not json"
    result = CliRunner().invoke(app, ["report", str(tmp_path / "none"), "--redraw"])
    assert result.exit_code != 0 and "no results.json" in result.output


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_merge_joins_the_reports_of_a_grid_run_in_parts(tmp_path):
    """`illm report PART1 PART2 --merge --out DIR`: the parts' runs are gone; the joined report has
    every part's rows and the aggregate over all their envs that one report of all the runs has;
    parts reported otherwise, an env in two parts or one folder alone are refused in one line."""
    from typer.testing import CliRunner

    from cli.main import app

    def report(args):
        return CliRunner().invoke(app, ["report", *map(str, args)])

    envs = ("BabyAI-GoToLocal-v0", "BabyAI-UnlockLocal-v0")
    runs = {env: [] for env in envs}
    for k, env in enumerate(envs):
        for seed in range(3):
            for mode, final in (("ppo", 0.2 + 0.1 * seed), ("illm", 0.5 + 0.1 * seed + 0.1 * k)):
                runs[env].append(tmp_path / f"{env}-{mode}-{seed}")
                fake_run(runs[env][-1], seed, [(100, final / 2, 1), (200, final, 1)], mode=mode, env_id=env)
    flags = ["--every", "100", "--bootstrap", "200"]
    assert report([*runs[envs[0]], *runs[envs[1]], *flags, "--out", tmp_path / "whole"]).exit_code == 0
    for k, env in enumerate(envs):
        assert report([*runs[env], *flags, "--out", tmp_path / f"part{k}"]).exit_code == 0
    assert report([*runs[envs[0]], "--every", "50", "--out", tmp_path / "other"]).exit_code == 0
    for env_runs in runs.values():
        for run in env_runs:
            for f in run.iterdir():
                f.unlink()
            run.rmdir()

    result = report([tmp_path / "part0", tmp_path / "part1", "--merge", "--out", tmp_path / "joined"])
    assert result.exit_code == 0, result.output
    whole = json.loads((tmp_path / "whole" / "results.json").read_text())
    joined = json.loads((tmp_path / "joined" / "results.json").read_text())
    assert joined["envs"] == list(envs) and len(joined["rows"]) == 4
    assert [r["final"] for r in joined["rows"]] == [r["final"] for r in whole["rows"]]
    assert joined["aggregate"] is not None and joined["aggregate"] == whole["aggregate"]
    assert [p["folder"] for p in joined["settings"]["parts"]] == [str(tmp_path / "part0"), str(tmp_path / "part1")]
    text = (tmp_path / "joined" / "report.md").read_text()
    assert "IQM over 2 levels" in text and "| illm |" in text
    assert (tmp_path / "joined" / "final.png").read_bytes()[:8] == PNG

    for args, message in (([tmp_path / "part0", tmp_path / "other"], "other every"),
                          ([tmp_path / "part0", tmp_path / "part0"], "in two of the parts"),
                          ([tmp_path / "part0"], "two or more report folders"),
                          ([tmp_path / "part0", tmp_path / "nowhere"], "no results.json")):
        result = report([*args, "--merge", "--out", tmp_path / "refused"])
        assert result.exit_code != 0 and message in result.output, result.output
        assert len(result.output.strip().splitlines()) == 1 and "Traceback" not in result.output
    assert not (tmp_path / "refused").exists()


@pytest.mark.slow
def test_a_suite_report_aggregates_over_levels_and_shows_why_the_bonus_helps_or_hurts(tmp_path):
    """Over levels: rliable's IQM of all runs and the probability of improvement over ppo; per level:
    the diagnostics (the bonus's share of the advantage, f^a's agreement, the bonus paid before and
    after the level is solved) and where the bonus was paid, from real (tiny) training runs."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from fakes import FakePool, make_trainer

    from illm_tools.report.build import build_report, redraw_report

    runs = []
    for env in ("BabyAI-GoToLocal-v0", "BabyAI-UnlockLocal-v0"):
        for mode in ("ppo", "illm"):
            for seed in (0, 1):
                folder = tmp_path / env / mode / f"seed{seed}"
                trainer, _ = make_trainer(folder, mode=mode, updates=3, seed=seed, env_id=env,
                                          pool=FakePool(4, seed=seed, positions=True))
                trainer.train()
                runs.append(folder / "run")
    results = build_report(runs, tmp_path / "report", every=128, reps=200)
    across = results["aggregate"]
    assert across["envs"] == ["BabyAI-GoToLocal-v0", "BabyAI-UnlockLocal-v0"] and across["baseline"] == "ppo"
    rows = {r["label"]: r for r in across["rows"]}
    assert rows["ppo"]["poi"] is None and 0 <= rows["illm"]["poi"] <= 1 and rows["illm"]["seeds"] == [0, 1]
    assert rows["illm"]["ci_low"] <= rows["illm"]["iqm"] <= rows["illm"]["ci_high"]
    illm = [r for r in results["rows"] if r["label"] == "illm"]
    assert all(r["diagnostics"] and len(r["diagnostics"]["head_agreement"]) == len(r["frames"]) for r in illm)
    assert all(r["diagnostics"] is None for r in results["rows"] if r["label"] == "ppo")  # no bonus, no heads
    assert all(r["bonus_map"] and (tmp_path / "report" / r["bonus_map"]["png"]).is_file() for r in illm)
    text = (tmp_path / "report" / "report.md").read_text()
    assert "## Across the levels" in text and "P(improvement over ppo)" in text and "f^a agreement" in text
    assert (tmp_path / "report" / "diagnostics-BabyAI-UnlockLocal-v0.png").is_file()
    again = redraw_report(tmp_path / "report")  # the aggregate and the diagnostics survive a redraw
    assert again["aggregate"] == results["aggregate"] and "## Across the levels" in \
        (tmp_path / "report" / "report.md").read_text()


def test_an_experiments_runs_are_named_by_its_grid_labels(tmp_path):
    """Runs of an `illm experiment` (RESULTS/ENV/LABEL/seedN beside RESULTS/spec.yaml) whose configurations
    differ in settings take the grid's labels; plain methods keep theirs, and a grid label that would name
    two configurations (two results folders merged) falls back to the settings."""
    from illm_tools.report.curves import group_labels

    base = {"mode": "illm", "env_id": "E", "model": "a", "backend": "transformers", "seed": 0}
    configs = [base, {**base, "model": "b"}, {**base, "mode": "ppo"}, {**base, "env_id": "F", "model": "b"}]
    runs = [tmp_path / "r" / "E" / "illm-annotator=a" / "seed0", tmp_path / "r" / "E" / "illm-annotator=b" / "seed0",
            tmp_path / "r" / "E" / "ppo" / "seed0", tmp_path / "r" / "F" / "illm-annotator=b" / "seed0"]
    assert group_labels(configs, runs) == ["illm (model a)", "illm (model b)", "ppo", "illm"]  # no spec.yaml
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "spec.yaml").write_text("name: r\n")
    assert group_labels(configs, runs) == ["illm-annotator=a", "illm-annotator=b", "ppo", "illm"]
    other = tmp_path / "s" / "E" / "illm-annotator=a" / "seed0"  # another experiment's, for model c
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "spec.yaml").write_text("name: s\n")
    assert group_labels([*configs, {**base, "model": "c"}], [*runs, other]) == \
        ["illm (model a)", "illm-annotator=b", "ppo", "illm", "illm (model c)"]
