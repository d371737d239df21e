"""`illm collect`'s closing counts are the data's: an episode still running at the end is one whose last
logged step neither terminated nor truncated it, and a finished one is one whose last step did."""
from __future__ import annotations

from illm_tools.collect import CollectConfig, collect
from illm_tools.data.trajectories import open_table


def test_the_running_and_finished_counts_are_what_the_written_steps_say(tmp_path):
    # the BabyAI bot ends its episodes in a few steps, so at the end some envs' last logged step ended one
    summary = collect(CollectConfig(env_id="BabyAI-GoToRedBallNoDists-v0", out=tmp_path / "traj", steps=240,
                                    num_envs=8, seed=0, policy="bot"))
    rows = open_table(tmp_path / "traj", ["episode_id", "step", "terminated", "truncated"]).to_pylist()
    last: dict[int, dict] = {}
    for row in rows:
        if row["episode_id"] not in last or row["step"] > last[row["episode_id"]]["step"]:
            last[row["episode_id"]] = row
    ended = sum(r["terminated"] or r["truncated"] for r in last.values())
    running = len(last) - ended
    assert 0 < running < 8  # a draw that tells "every env running" and "never cleared" apart from the truth
    assert (summary["episodes_running"], summary["episodes_finished"]) == (running, ended)
