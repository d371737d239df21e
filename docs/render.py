"""Tables rendered from their results files, never typed by hand: README's results table and the prior
probe's table (docs/experiments/prior-probe.md).

`python docs/render.py` rewrites each page's block between `<!-- NAME:begin -->` and `<!-- NAME:end -->`
(`blocks()`: README.md's `results`, prior-probe.md's `probe`, measured.md's `measured`, ...); `python
docs/render.py --check` exits 1 when a block differs from what the files say (tests/test_claims.py and
tests/test_benchmark_records.py run the same comparison, so a hand-edited number fails the test suite).

Sources (docs/results/, written by `illm report`):
- suite-report/results.json: each level's final success rate per method (IQM [95% CI], 5 seeds) and
  the aggregate over the 8 levels with the probability of improvement over ppo;
- suite-report-half/results.json: the aggregate over the 4 levels of the report half;
- suite-tune/results.json: which levels are the tune half (its `envs`);
- oracle/probes/GoToLocal-MODEL.json (`illm probe --out`): the prior probe's table, one row per model
  and calibration, its baselines from the same file;
- seeds-candidate/results.json and seeds-candidate-report/results.json: the default since issue 71 (cap 1)
  per level, docs/experiments/suite.md's `default` block;
- oracle/acting/ENV.json (`illm act --out`): the oracles acting on their own rankings, one row per env
  (docs/experiments/oracle-acting.md's `acting` block);
- measured/records/*.json (benchmarks/record.py, written by every script in benchmarks/): one row per
  benchmark run, newest first, its headline ratio met or missed (docs/measured.md's `measured` block).

Numbers are printed with the report's own formatting (`illm_tools.report.markdown.num`, 3 decimals),
so README and report.md read the same digits. Two words, two counts: illm is *above* a control on a
level when its IQM is higher, *clear of* it when its 95% interval lies wholly above the control's.
Bold marks only the levels where illm is clear of both ppo and the shuffled control.

The tie rule, the one place it is written (docs/experiments/suite.md quotes it): values are compared as
printed, at 3 decimals (`beats`, illm_tools/report/markdown.py; docs/refs.py checks the pages' verdict words
with it), for *above* (the IQMs) and *clear* (illm's lower end against the
control's upper end) alike; two values that print the same are a tie, which is neither. One verdict
turns on it: PutNextLocal, illm 0.011699 against the shuffled control's 0.011668, both 0.012 printed,
is a tie; compared as raw floats it would be *above*, and the count 7 of 8 instead of 6. (In the tune
half's report a seventh configuration's UnlockLocal interval, 0.0161 against the shuffled control's
0.0156, prints 0.016 against 0.016: not *clear* under this rule.)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from illm_tools.report.markdown import beats, iqm_cell, num

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"
README = ROOT / "README.md"
PROBE_PAGE = ROOT / "docs" / "experiments" / "prior-probe.md"
ACTING_PAGE = ROOT / "docs" / "experiments" / "oracle-acting.md"
SUITE_PAGE = ROOT / "docs" / "experiments" / "suite.md"
MEASURED_PAGE = ROOT / "docs" / "measured.md"
RECORDS = RESULTS / "measured" / "records"
"""The benchmarks' records (benchmarks/record.py), docs/measured.md's `measured` block."""
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
PROBE_MODELS = (("SmolLM2-135M", "smollm2-135m"), ("Gemma-3-270M", "gemma3-270m"))
"""The prior probe's rows: the name a page prints, and the file's model (oracle/probes/GoToLocal-MODEL.json)."""
CALIBRATIONS = ("sum", "mean", "pmi")
METHODS = ("illm", "ppo", "illm-shuffled", "rnd", "illm-noreward")
CONTROLS = ("ppo", "illm-shuffled")


def _load(name: str) -> dict:
    return json.loads((RESULTS / name / "results.json").read_text())


def _short(env_id: str) -> str:
    return env_id.split("-", 1)[1].rsplit("-v", 1)[0]


def counts(suite: dict) -> dict:
    """Per level: illm's final IQM above both controls' IQMs; illm's interval clear of both intervals;
    both under the tie rule (`beats`)."""
    finals = {(r["env_id"], r["label"]): r["final"] for r in suite["rows"]}
    above, clear = [], []
    for env in suite["envs"]:
        mine = finals[(env, "illm")]
        others = [finals[(env, c)] for c in CONTROLS]
        if all(beats(mine["iqm"], o["iqm"]) for o in others):
            above.append(env)
        if all(beats(mine["ci_low"], o["ci_high"]) for o in others):
            clear.append(env)
    return {"above": above, "clear": clear, "n": len(suite["envs"])}


def render() -> str:
    """The markdown block between the markers (markers excluded)."""
    suite, half, tune = _load("suite-report"), _load("suite-report-half"), _load("suite-tune")
    tune_envs = set(tune["envs"])
    finals = {(r["env_id"], r["label"]): r["final"] for r in suite["rows"]}
    c = counts(suite)
    order = [e for e in suite["envs"] if e in tune_envs] + [e for e in suite["envs"] if e not in tune_envs]
    lines = [
        "| level (half, frames) | " + " | ".join(METHODS) + " |",
        "|---|" + "---|" * len(METHODS),
    ]
    for env in order:
        half_name = "tune" if env in tune_envs else "report"
        frames = finals[(env, "illm")]["frames"]
        cells = [iqm_cell(finals[(env, m)]) for m in METHODS]
        if env in c["clear"]:
            cells[0] = f"**{cells[0]}**"
        lines.append(f"| {_short(env)} ({half_name}, {frames:,}) | " + " | ".join(cells) + " |")
    for title, source in ((f"all {c['n']}, IQM over all runs", suite), ("report half (4 levels)", half)):
        agg = {r["label"]: r for r in source["aggregate"]["rows"]}
        lines.append(f"| {title} | " + " | ".join(iqm_cell(agg[m]) for m in METHODS) + " |")
    agg = {r["label"]: r for r in suite["aggregate"]["rows"]}
    rh = {r["label"]: r for r in half["aggregate"]["rows"]}
    clear_half = sorted("tune" if e in tune_envs else "report" for e in c["clear"])
    lines += [
        "",
        f"illm's IQM is **above** both ppo's and the shuffled control's on {len(c['above'])} of the "
        f"{c['n']} levels; its 95% interval is **clear of** both on {len(c['clear'])} of {c['n']} "
        f"(bold; {clear_half.count('tune')} on the tune half, {clear_half.count('report')} on the report "
        f"half). Probability of improvement over ppo: all {c['n']} levels "
        f"{iqm_cell({'iqm': agg['illm']['poi'], 'ci_low': agg['illm']['poi_low'], 'ci_high': agg['illm']['poi_high']})}, "
        f"report half {iqm_cell({'iqm': rh['illm']['poi'], 'ci_low': rh['illm']['poi_low'], 'ci_high': rh['illm']['poi_high']})}.",
    ]
    return "\n".join(lines)


def render_probe() -> str:
    """The prior probe's table: each model's agreement with the expert, log-loss, pairwise AUROC, mutual
    information, top-1 entropy and favourite action per calibration, then always "go forward" and
    uniform chance (the baselines the same files hold)."""
    lines = ["| model | calibration | agreement | log-loss (nats) | pairwise AUROC | MI state;ranking (bits) | "
             "top-1 entropy (bits) | LLM's top action |", "|---|---|---|---|---|---|---|---|"]
    for shown, model in PROBE_MODELS:
        probe = json.loads((RESULTS / "oracle" / "probes" / f"GoToLocal-{model}.json").read_text())
        for i, name in enumerate(CALIBRATIONS):
            c = probe["calibrations"][name]
            lines.append(f"| {shown if i == 0 else ''} | {name} | {num(c['agreement'])} | {num(c['log_loss'])} | "
                         f"{num(c['auroc'])} | {num(c['mutual_information_bits'])} | "
                         f"{num(c['top_choice_entropy_bits'])} | {c['top_action']} in {c['top_action_share']:.0%} of states |")
    base = probe["baselines"]
    lines += [f"| always \"{base['majority_action']}\" | | **{num(base['majority_agreement'])}** | "
              f"**{num(base['marginal_log_loss'])}** (the expert's own frequencies, in sample) | | 0 | 0 | "
              f"{base['majority_action']} in 100% |",
              f"| uniform chance | | {num(base['chance_agreement'])} | {num(base['uniform_log_loss'])} | {num(0.5)} | 0 | | |"]
    return "\n".join(lines)


def render_acting() -> str:
    """The oracles acting greedily on their own rankings (`illm act --out` files), one row per env: the
    oracle's and a random policy's success rate [95% Wilson interval] (Crafter: its score) and mean
    episode length, over the same episodes."""
    tables: list[str] = []
    lines = ["| env | history | episodes | oracle | random | oracle's mean length | random's | file |",
             "|---|---|---|---|---|---|---|---|"]
    for path in sorted((RESULTS / "oracle" / "acting").glob("*.json")):
        figures = json.loads(path.read_text())
        mine, other = figures["policies"]["annotator"], figures["policies"]["random"]

        def cell(r: dict) -> str:
            if r["success_rate"] is None:
                return f"score {r['metrics']['score']:.2f}"
            low, high = r["success_interval"]
            return f"{num(r['success_rate'])} [{num(low)}, {num(high)}]"

        lines.append(f"| {figures['config']['env_id']} | {figures['config']['history']} | {mine['episodes']} | "
                     f"{cell(mine)} | {cell(other)} | {mine['mean_length']:.1f} | {other['mean_length']:.1f} | "
                     f"[json](../results/oracle/acting/{path.name}) |")
        achieved = {k.removeprefix("achievement_"): (v, other["metrics"][k]) for k, v in mine["metrics"].items()
                    if k.startswith("achievement_")}
        if achieved:  # Crafter: each achievement's success rate, the oracle's and random's
            tables.append(f"\n{figures['config']['env_id']}, each achievement's success rate (oracle / random):\n\n"
                          "| achievement | oracle | random |\n|---|---|---|\n" + "\n".join(
                              f"| {k} | {num(a)} | {num(b)} |" for k, (a, b) in achieved.items()))
    return "\n".join(lines + tables)


def render_default() -> str:
    """The default since issue 71 (the small weights, int_ext_cap 1) per level: the tune half's 10 seeds
    (seeds-candidate/results.json, beside ppo's 10) and the report half's 5 (seeds-candidate-report, beside
    the uncapped rows of suite-report), each cell IQM [95% CI] of the final success rate."""
    tune, report, old = _load("seeds-candidate"), _load("seeds-candidate-report"), _load("suite-report")
    lines = ["| level (half, seeds) | illm, the default (cap 1) | illm before the cap | ppo |", "|---|---|---|---|"]
    rows = {(r["env_id"], r["label"]): r["final"] for r in tune["rows"]}
    for env in tune["envs"]:
        cells = [rows[(env, "illm (int_ext_cap 1)")], rows[(env, "illm (int_ext_cap 0)")], rows[(env, "ppo")]]
        lines.append(f"| {_short(env)} (tune, 10) | " + " | ".join(iqm_cell(c) for c in cells) + " |")
    mine = {r["env_id"]: r["final"] for r in report["rows"] if r["label"] == "illm"}
    before = {(r["env_id"], r["label"]): r["final"] for r in old["rows"]}
    for env in report["envs"]:
        cells = [mine[env], before[(env, "illm")], before[(env, "ppo")]]
        lines.append(f"| {_short(env)} (report, 5) | " + " | ".join(iqm_cell(c) for c in cells) + " |")
    return "\n".join(lines)


def figure(value) -> str:
    """A benchmark's figure as the measured block prints it: whole numbers with separators, three
    significant digits or so otherwise; n/a for a figure the run could not take."""
    if value is None:
        return "n/a"
    if isinstance(value, int):
        return f"{value:,}"
    size = abs(value)
    return f"{value:,.0f}" if size >= 100 else f"{value:.1f}" if size >= 10 else f"{value:.2f}" if size >= 1 else f"{value:.3g}"


def machine_cell(entry: dict) -> str:
    """The record's machine in short: model name, CPU family and model, the AVX-512/AMX flags, cores,
    and the load average when the run ended."""
    m = entry["machine"]
    flags = set(m.get("Flags", "").split())
    vector = [name for name, found in (("AVX512-BF16", "avx512_bf16" in flags),
                                       ("AVX-512", "avx512f" in flags and "avx512_bf16" not in flags),
                                       ("AMX", any(f.startswith("amx") for f in flags)),
                                       ("AVX2 only", "avx2" in flags and "avx512f" not in flags)) if found]
    parts = [m.get("Model name", m.get("cpu", "unknown CPU"))]
    if "CPU family" in m:
        parts.append(f"family {m['CPU family']} model {m.get('Model', '?')}")
    parts += vector + [f"{entry['cores']} cores"]
    load = entry.get("load_average_at_end")
    return ", ".join(parts) + (f"; load {load[0]:.1f} at the end" if load else "")


def ratio_cells(ratio: dict | None) -> list[str]:
    """The headline ratio, its target and the verdict: **met** or **missed** (a miss is shown, never
    dropped); blank where the benchmark states no target."""
    if ratio is None:
        return ["(none recorded)", "", ""]
    target = "" if ratio["target"] is None else f"{'≥' if ratio['direction'] == 'at_least' else '≤'} {ratio['target']:g}"
    verdict = {True: "**met**", False: "**missed**", None: ""}[ratio["met"]]
    return [f"{ratio['name']}: **{figure(ratio['value'])}**", target, verdict]


def measured_row(path: Path, entry: dict) -> str:
    """One record's row (cells' pipes escaped: a command may hold one)."""
    code = entry.get("code") or {}
    commit = f" at {code['commit'][:7]}{', dirty' if code.get('dirty') else ''}" if code.get("commit") else ""
    figures = "; ".join(f"{name} {figure(v)}" for name, v in entry["figures"].items())
    cells = [f"[{entry['benchmark']}](results/measured/records/{path.name})", f"{entry['date']}{commit}",
             machine_cell(entry), *ratio_cells(entry["ratio"]), figures, f"`{entry['command']}`"]
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def render_measured() -> str:
    """docs/measured.md's recorded benchmark outputs: one row per record in `RECORDS`, newest first."""
    entries = []
    for path in RECORDS.glob("*.json"):
        try:
            entries.append((path, json.loads(path.read_text())))
        except ValueError as e:
            raise SystemExit(f"{path}: not a benchmark record ({e})") from None
    if not entries:
        return "no record yet"
    entries.sort(key=lambda pe: (pe[1]["date"], pe[0].name), reverse=True)
    lines = ["| benchmark | date, code | machine | headline ratio | target | verdict | figures | command |",
             "|---|---|---|---|---|---|---|---|"]
    return "\n".join(lines + [measured_row(path, entry) for path, entry in entries])


def blocks() -> dict:
    """Each rendered block: name -> (the page, the block's rendering)."""
    return {"results": (README, render), "probe": (PROBE_PAGE, render_probe), "acting": (ACTING_PAGE, render_acting),
            "default": (SUITE_PAGE, render_default), "measured": (MEASURED_PAGE, render_measured)}


def splice(text: str, block: str, name: str = "results") -> str:
    """`text` with the block between NAME's markers replaced; one-line error if the markers are missing."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    if begin not in text or end not in text:
        raise SystemExit(f"the page lacks the markers {begin} ... {end}: add them where the table goes")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{begin}\n{block}\n{end}{tail}"


def main(argv: list[str]) -> int:
    stale = []
    for name, (page, make) in blocks().items():
        text = page.read_text()
        wanted = splice(text, make(), name)
        if wanted == text:
            continue
        if "--check" in argv:
            stale.append(f"{page.name} ({name})")
        else:
            page.write_text(wanted)
    if stale:
        print(f"{', '.join(stale)}: the table differs from docs/results: run `python docs/render.py`")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
