"""benchmarks/train.py's cached case: its pairs run in lockstep, each method in its own process."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_cached_pairs_in_lockstep_meet_the_fill_pass_states_and_print_the_ratio():
    """Two processes taking their updates in turn: the illm one reads every target from the cache
    its parent filled (training is deterministic), and both report a rate over their own updates."""
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "train.py"), "--no-record", "--only", "cached",
                          "--frames", "2048", "--num-envs", "4", "--num-steps", "128", "--pairs", "2"],
                         capture_output=True, text=True, timeout=600, cwd=ROOT,
                         env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert out.returncode == 0, out.stderr[-2000:]
    pairs = re.findall(r"pair \d: ppo +([\d,]+) steps/s, illm +([\d,]+): ratio ([\d.]+); cache hit rate ([\d.]+)", out.stdout)
    assert len(pairs) == 2, out.stdout
    for ppo, illm, ratio, hits in pairs:
        assert float(hits) == 1.0
        rate = {m: float(v.replace(",", "")) for m, v in (("ppo", ppo), ("illm", illm))}
        # the ratio of the unrounded rates, so it lies where the printed rates (whole steps/s, each
        # within 0.5) allow, widened by its own rounding to 3 places; a fixed tolerance would not
        # hold at a slow machine's rates (0.5 / 75 steps/s is already 0.007)
        lo = (rate["illm"] - 0.5) / (rate["ppo"] + 0.5) - 5e-4
        hi = (rate["illm"] + 0.5) / (rate["ppo"] - 0.5) + 5e-4
        assert lo <= float(ratio) <= hi, (ratio, rate)
    assert re.search(r"illm's added time per update of 512 steps, median over the pairs: -?\d+ ms", out.stdout)
    assert re.search(r"illm/ppo ratio, median of 2 pairs: [\d.]+ \(range [\d.]+-[\d.]+\)", out.stdout)
