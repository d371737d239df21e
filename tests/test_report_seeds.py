"""`illm report` says when a configuration's seeds split: some end near 0 while others solve the level
(0.70, 0.73, 0.28, 0.02, 0.00 against another method's 0.27-0.46, as seen on a navigation level), where
an IQM and its interval over the seeds describe no seed; it names the split, lists the seeds' finals and
draws that configuration's seeds as separate curves."""

from __future__ import annotations

import json

from fakes import fake_run


def test_a_report_of_seeds_that_split_says_so_and_draws_them_one_by_one(tmp_path):
    from illm_tools.report.build import build_report

    runs = []
    for method, finals in (("illm", (0.70, 0.73, 0.28, 0.02, 0.00)), ("ppo", (0.27, 0.31, 0.35, 0.40, 0.46))):
        for seed, final in enumerate(finals):
            run = tmp_path / f"{method}-seed{seed}"
            fake_run(run, seed, [(100, final / 2, 4), (200, final, 4)], mode=method)
            runs.append(run)
    out = tmp_path / "report"
    results = build_report(runs, out, every=100, final_points=1)
    rows = {r["label"]: r for r in results["rows"]}
    assert rows["illm"]["final"]["split"] and not rows["ppo"]["final"]["split"]
    report = (out / "report.md").read_text()
    assert "**Seeds that split**" in report
    assert "- illm: seeds' finals 0.70, 0.73, 0.28, 0.02, 0.00" in report and "- ppo:" not in report
    png = results["files"]["seeds"]["BabyAI-GoToLocal-v0 / illm"]
    assert (out / png).is_file() and f"]({png})" in report
    assert [s["points"] for s in rows["illm"]["final"]["seed_curves"]][0] == [0.35, 0.70]
    assert json.loads((out / "results.json").read_text())["rows"][0]["final"]["split"] in (True, False)
