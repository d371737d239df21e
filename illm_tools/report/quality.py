"""The annotator-quality curve of a report (`illm report --probe FILE ...`): each configuration's final
score against how well its annotator knows the level, as `illm probe` measured it (agreement of the
annotator's top action with minigrid's BabyAI bot).

A probe file (`illm probe --out FILE`) belongs to a configuration when they name the same env,
backend, model (with the oracle's noise), history length and prompt layout; the configuration's
point is then (the probe's agreement under the run's `--action-score` calibration, the final score
IQM with its 95% interval). Methods whose targets are their state's own (illm, illm-noreward) are
points; the others are horizontal lines to compare with: methods without an annotator (ppo, rnd)
and the shuffled control (its targets are another state's, so the probe does not describe them).
Probes that match no configuration (an LLM not trained with here: SmolLM2, Gemma) are vertical
markers: where on the curve an LLM of that quality sits. Chance and the bot's majority action are
marked on the agreement axis from the probes' own baselines.
"""

from __future__ import annotations

import json
from pathlib import Path

from illm_tools.errors import UsageError


def load_probes(paths: list[Path]) -> list[dict]:
    """The probe files' figures; a file that is not one is refused in one line."""
    probes = []
    for path in paths:
        try:
            data = json.loads(Path(path).read_text())
            data["config"]["env_id"], data["calibrations"]["sum"]["agreement"]  # noqa: B018 - shape check
        except FileNotFoundError:
            raise UsageError(f"no probe file at {path}: write one with `illm probe ... --out {path}`") from None
        except (ValueError, KeyError, TypeError):
            raise UsageError(f"{path} is not a probe file (`illm probe --out FILE` writes them): pass those") from None
        data["file"] = str(path)
        probes.append(data)
    return probes


def _identity(env_id: str, backend: str, model: str, history: int, layout: str) -> tuple:
    return env_id, backend, model, int(history), layout


def probe_identity(probe: dict) -> tuple:
    c = probe["config"]
    from illm_tools.llm.backend import resolve_model

    return _identity(c["env_id"], c.get("backend", "transformers"), resolve_model(c.get("backend", "transformers"),
                     c.get("model")), c.get("history", 0), c.get("layout", "shared"))


def run_identity(config: dict) -> tuple | None:
    """The annotator setup of a run's config.json, or None for a method without one."""
    from illm_tools.rl.config import TrainConfig

    cfg = TrainConfig.from_dict({**config, "resume": False})
    if not cfg.needs_targets:
        return None
    return _identity(cfg.env_id, cfg.llm.backend, cfg.llm.model, cfg.setup.history_len, cfg.setup.layout)


def quality(rows: list[dict], configs: dict[tuple, dict], probes: list[dict]) -> dict:
    """Points, reference lines and LLM markers per env (see the module docstring). `configs` maps
    (env, label) to one run's config.json."""
    from illm_tools.intrinsic.registry import METHODS

    by_identity = {probe_identity(p): p for p in probes}
    used: set[tuple] = set()
    points, lines = [], []
    for row in rows:
        if row["final"]["iqm"] is None:
            continue
        config = configs[(row["env_id"], row["label"])]
        method = METHODS.get(config.get("method", config.get("mode", "")))
        identity = run_identity(config)
        probe = by_identity.get(identity) if identity is not None else None
        own = method is not None and method.needs_targets and method.target_shuffle is None
        final = {k: row["final"][k] for k in ("iqm", "ci_low", "ci_high", "n")}
        if probe is not None and own:
            used.add(identity)
            calibration = config.get("action_score", "sum")
            points.append({"env_id": row["env_id"], "label": row["label"], "method": row["method"],
                           "agreement": probe["calibrations"][calibration]["agreement"], "calibration": calibration,
                           "probe": probe["file"], "final": final})
        else:
            lines.append({"env_id": row["env_id"], "label": row["label"], "final": final})
    envs = {r["env_id"] for r in rows}
    markers = [{"env_id": p["config"]["env_id"], "model": probe_identity(p)[2], "backend": probe_identity(p)[1],
                "agreement": p["calibrations"]["sum"]["agreement"], "probe": p["file"]}
               for p in probes if probe_identity(p) not in used and p["config"]["env_id"] in envs]
    references = {}
    for p in probes:
        b = p["baselines"]
        references.setdefault(p["config"]["env_id"], {"chance": b["chance_agreement"],
                                                      "majority": b["majority_agreement"],
                                                      "majority_action": b["majority_action"]})
    return {"points": points, "lines": lines, "markers": markers, "references": references}


def _nearby(items: list[dict], *coords, within: float = 0.03) -> list[list[dict]]:
    """`items` (in order) cut into runs whose neighbours are closer than `within` in every coordinate,
    so that one text names them all on the plot."""
    groups: list[list[dict]] = []
    for item in items:
        if groups and all(abs(c(item) - c(groups[-1][-1])) < within for c in coords):
            groups[-1].append(item)
        else:
            groups.append([item])
    return groups


def quality_png(result: dict, score_names: dict[str, str], path: Path) -> Path:
    """One panel per env: final score against probe agreement (see the module docstring)."""
    from illm_tools.report.plots import _pyplot, save_figure

    plt = _pyplot()
    envs = list(dict.fromkeys([p["env_id"] for p in result["points"]]))
    fig, axes = plt.subplots(1, len(envs), figsize=(5.2 * len(envs), 4.2), dpi=100, squeeze=False)
    for ax, env in zip(axes[0], envs):
        methods = list(dict.fromkeys(p["method"] for p in result["points"] if p["env_id"] == env))
        for k, method in enumerate(methods):
            pts = sorted((p for p in result["points"] if p["env_id"] == env and p["method"] == method),
                         key=lambda p: p["agreement"])
            xs = [p["agreement"] for p in pts]
            ys = [p["final"]["iqm"] for p in pts]
            low = [p["final"]["iqm"] - (p["final"]["ci_low"] if p["final"]["ci_low"] is not None else p["final"]["iqm"])
                   for p in pts]
            high = [(p["final"]["ci_high"] if p["final"]["ci_high"] is not None else p["final"]["iqm"]) - p["final"]["iqm"]
                    for p in pts]
            ax.errorbar(xs, ys, yerr=[low, high], marker="o", capsize=3, color=f"C{k}",
                        label=f"{method} (IQM, 95% CI)")
            if len(pts) > 1:  # which configuration each point is; points next to each other share a text
                for g in _nearby(pts, lambda p: p["agreement"], lambda p: p["final"]["iqm"]):
                    right = g[0]["agreement"] < 0.5  # the text on the side with room, inside the axes
                    ax.annotate(", ".join(p["label"] for p in g), (g[0]["agreement"], g[0]["final"]["iqm"]),
                                xytext=(6 if right else -6, -4), textcoords="offset points",
                                ha="left" if right else "right", va="top", fontsize=7, color=f"C{k}")
        for j, line in enumerate(l for l in result["lines"] if l["env_id"] == env):
            colour = f"C{len(methods) + j}"
            ax.axhline(line["final"]["iqm"], linestyle="--", linewidth=1, color=colour,
                       label=f"{line['label']}: {line['final']['iqm']:.2f}")
            if line["final"]["ci_low"] is not None:
                ax.axhspan(line["final"]["ci_low"], line["final"]["ci_high"], color=colour, alpha=0.08)
        markers = sorted((m for m in result["markers"] if m["env_id"] == env), key=lambda m: m["agreement"])
        for group in _nearby(markers, lambda m: m["agreement"]):  # markers next to each other share one label
            for marker in group:
                ax.axvline(marker["agreement"], linestyle=":", color="black", linewidth=1)
            text = ", ".join(f"{m['model']} {m['agreement']:.2f}" for m in group)
            ax.annotate(text, (group[0]["agreement"], 1.0), xycoords=("data", "axes fraction"), rotation=90,
                        va="top", ha="right", fontsize=7)
        ref = result["references"].get(env)
        if ref:
            for x, text in ((ref["chance"], "chance"), (ref["majority"], f"always {ref['majority_action']}")):
                ax.axvline(x, color="grey", alpha=0.4, linewidth=3)
                ax.annotate(f"{text} {x:.2f}", (x, 0.0), xycoords=("data", "axes fraction"), rotation=90,
                            va="bottom", ha="left", fontsize=7, color="grey")
        ax.set_xlim(0, 1)
        ax.set_xlabel("annotator's agreement with the BabyAI bot (illm probe)", fontsize=8)
        ax.set_ylabel(f"final {score_names.get(env, 'score')}", fontsize=8)
        ax.set_title(env, fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="center right")
    return save_figure(fig, path)
