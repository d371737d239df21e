"""`illm report` says when a configuration's seeds split: some end near 0 while others solve the level
(0.70, 0.73, 0.28, 0.02, 0.00 against another method's 0.27-0.46, as seen on a navigation level), where
an IQM and its interval over the seeds describe no seed; it names the split, lists the seeds' finals and
draws that configuration's seeds as separate curves, and its diagnostics (|A_int| / |A_ext|, f^a's
agreement, the bonus paid per step) seed by seed."""

from __future__ import annotations

import json

from fakes import fake_run

SPLIT = {"illm": (0.70, 0.73, 0.28, 0.02, 0.00), "ppo": (0.27, 0.31, 0.35, 0.40, 0.46)}


def _runs(tmp_path, finals: dict[str, tuple], diagnosed: bool = False) -> list:
    """Fake runs, one per method and final success rate (half of it at frame 100); `diagnosed`: the illm
    runs also log the diagnostics' columns in metrics.jsonl, a seed's bonus 0.1 x (its seed + 1)."""
    runs = []
    for method, seed_finals in finals.items():
        for seed, final in enumerate(seed_finals):
            run = tmp_path / f"{method}-seed{seed}"
            fake_run(run, seed, [(100, final / 2, 4), (200, final, 4)], mode=method)
            if diagnosed and method == "illm":
                rows = [{"global_step": step, "charts/success_rate": final, "charts/adv_int_ext_ratio": 0.5 + seed,
                         "charts/head_agreement": 0.9, "charts/intrinsic_reward": 0.1 * (seed + 1),
                         "charts/bonus_weight": 1.0} for step in (100, 200)]
                (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
            runs.append(run)
    return runs


def test_a_report_of_seeds_that_split_says_so_and_draws_them_one_by_one(tmp_path):
    from illm_tools.report.build import build_report

    out = tmp_path / "report"
    results = build_report(_runs(tmp_path, SPLIT), out, every=100, final_points=1)
    rows = {r["label"]: r for r in results["rows"]}
    assert rows["illm"]["final"]["split"] and not rows["ppo"]["final"]["split"]
    report = (out / "report.md").read_text()
    assert "**Seeds that split**" in report
    assert "- illm: seeds' finals 0.70, 0.73, 0.28, 0.02, 0.00" in report and "- ppo:" not in report
    png = results["files"]["seeds"]["BabyAI-GoToLocal-v0 / illm"]
    assert (out / png).is_file() and f"]({png})" in report
    assert [s["points"] for s in rows["illm"]["final"]["seed_curves"]][0] == [0.35, 0.70]
    assert json.loads((out / "results.json").read_text())["rows"][0]["final"]["split"] in (True, False)


def test_the_diagnostics_of_seeds_that_split_are_drawn_seed_by_seed(tmp_path):
    from illm_tools.report.build import build_report, redraw_report

    out = tmp_path / "report"
    results = build_report(_runs(tmp_path, SPLIT, diagnosed=True), out, every=100, reps=50)
    png = results["files"]["seeds_diagnostics"]["BabyAI-GoToLocal-v0 / illm"]
    assert png == "seeds-diagnostics-BabyAI-GoToLocal-v0-illm.png" and (out / png).is_file()
    assert list(results["files"]["seeds_diagnostics"]) == ["BabyAI-GoToLocal-v0 / illm"]  # ppo: no bonus to draw
    report = (out / "report.md").read_text()
    assert f"- illm: ![diagnostics per seed, illm]({png})" in report
    assert report.index("**Seeds that split**") < report.index("Their diagnostics seed by seed") < report.index(png)
    seeds = {r["label"]: r for r in results["rows"]}["illm"]["diagnostics"]["per_seed"]
    assert [s["seed"] for s in seeds] == [0, 1, 2, 3, 4]
    assert [s["bonus_paid"] for s in seeds][4] == [0.5, 0.5] and seeds[1]["adv_ratio"] == [1.5, 1.5]
    (out / png).unlink()  # the runs' series are in results.json: a redraw draws it again without them
    assert redraw_report(out)["files"]["seeds_diagnostics"] == {"BabyAI-GoToLocal-v0 / illm": png}
    assert (out / png).is_file()


def test_seeds_that_do_not_split_get_no_per_seed_diagnostics(tmp_path):
    from illm_tools.report.build import build_report

    out = tmp_path / "report"
    together = {"illm": (0.60, 0.70, 0.80), "ppo": SPLIT["ppo"][:3]}
    results = build_report(_runs(tmp_path, together, diagnosed=True), out, every=100, reps=50)
    assert {r["label"]: r for r in results["rows"]}["illm"]["diagnostics"]  # drawn over seeds, as always
    assert results["files"]["seeds_diagnostics"] == {} and not list(out.glob("seeds-*.png"))
    report = (out / "report.md").read_text()
    assert "**Seeds that split**" not in report and "seeds-diagnostics" not in report


def test_a_suite_without_a_success_rate_has_no_success_panel_and_no_solved_split(tmp_path, monkeypatch):
    """Crafter logs no success rate: its diagnostics split no bonus into solved and unsolved windows (every
    window read as unsolved before), and its figure has no empty success panel."""
    from illm_tools.report import diagnostics, plots

    run = tmp_path / "crafter-illm"
    run.mkdir()
    rows = [{"global_step": step, "charts/adv_int_ext_ratio": 0.2, "charts/head_agreement": 0.5,
             "charts/intrinsic_reward": 0.01, "charts/bonus_weight": 1.0} for step in (100, 200)]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    d = diagnostics.row_diagnostics({"runs": [str(run)], "frames": [100, 200], "final": {"split": False}}, 100)
    assert d["bonus_paid"] == [0.01, 0.01] and d["paid_solved"] is None and d["paid_unsolved"] is None
    drawn = []
    monkeypatch.setattr(plots, "save_figure", lambda fig, path: drawn.append([ax.get_title() for ax in fig.axes]))
    diagnostics.diagnostics_png("CrafterReward-Semantic-v1", [{"label": "illm", "diagnostics": d}], tmp_path / "d.png", {})
    assert drawn == [["|A_int| / |A_ext|", "f^a agrees with the annotator", "bonus paid per step"]]
