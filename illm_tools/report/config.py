"""The options of `illm report` (`cli/report.py` builds its command line from them) and the checks
that refuse a bad combination in one line before any run is read; `build.py` writes the report."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from illm_tools.errors import UsageError


@dataclass
class ReportConfig:
    """An `illm report`: which runs, how their curves are windowed, and the report folder's settings."""

    runs: tuple[Path, ...]
    """Run folders written by `illm train`, or folders holding them (an `illm experiment` results folder)."""
    every: int = 20_000
    """Frames per curve point (window of the score)."""
    out: Path | None = None
    """Also write a report folder: report.md (IQM [95% CI] and mean ± std per configuration), learning-curve
    and visitation PNGs, results.json."""
    final_points: int = 1
    """With --out: a seed's final score is the mean of its last this many curve points."""
    bootstrap: int = 2000
    """With --out: bootstrap resamples of the 95% intervals (rliable's stratified bootstrap, seeded)."""
    probe: list[Path] = field(default_factory=list)
    """With --out: an `illm probe --out` file (repeatable): final score against the annotator's probe agreement
    (quality.png); probes of models not trained with are marked on it."""
    redraw: bool = False
    """Draw a report folder's figures and report.md again from its results.json (the runs may be gone;
    heatmaps are kept): `illm report docs/results/table1 --redraw`."""
    merge: bool = False
    """Join report folders (each written by `illm report --out`, the runs may be gone) into the --out folder:
    a grid run in parts, one report per part, read as one: every part's rows, heatmaps and diagnostics, and the
    aggregate over all their envs (`illm report docs/results/part1 docs/results/part2 --merge --out DIR`). The
    parts must share --every, --final-points and --bootstrap, and no env may be in two of them."""
    overwrite: bool = False
    """Write into an --out folder that already holds files (a report drawn again there): without it, a folder that is
    not empty is refused, so that no file the report did not write is replaced."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_numbers

        self.runs = tuple(Path(r) for r in self.runs)
        self.out = Path(self.out) if self.out is not None else None
        self.probe = [Path(p) for p in self.probe or []]
        if self.redraw:
            if len(self.runs) != 1 or self.out is not None or self.probe:
                raise UsageError("--redraw takes one report folder and no --out or --probe: `illm report DIR --redraw`")
            if self.runs[0].exists() and not self.runs[0].is_dir():
                raise UsageError(f"{self.runs[0]} is a file: --redraw takes a folder `illm report --out` wrote")
            return
        if self.merge:
            if len(self.runs) < 2 or self.out is None or self.probe:
                raise UsageError("--merge takes two or more report folders and --out, no --probe: "
                                 "`illm report PART1 PART2 --merge --out DIR`")
            if self.out.exists() and not self.out.is_dir():
                raise UsageError(f"--out {self.out} is a file: pass a folder for the report")
            self._refuse_full_out()
            return
        check_numbers(self, positive=("every", "final_points", "bootstrap"))
        if self.out is not None and self.out.exists() and not self.out.is_dir():
            raise UsageError(f"--out {self.out} is a file: pass a folder for the report")
        self._refuse_full_out()
        if self.probe and self.out is None:
            raise UsageError("--probe adds the quality curve to a report folder: pass --out DIR too")
        not_files = [str(p) for p in self.probe if not p.is_file()]
        if not_files:
            raise UsageError(f"no probe file at {', '.join(not_files[:3])}: pass files `illm probe --out FILE` wrote")
        missing = [str(r) for r in self.runs if not r.is_dir()]
        if missing or not self.runs:
            raise UsageError(f"no run folder at {', '.join(missing[:3]) or '(none given)'}: pass folders written by "
                             "`illm train`")

    def _refuse_full_out(self) -> None:
        """An --out folder that holds anything is written into only with --overwrite (one line otherwise)."""
        if self.out is None or self.overwrite or not self.out.is_dir():
            return
        held = sorted(p.name for p in self.out.iterdir())
        if held:
            shown = ", ".join(held[:3]) + (f" and {len(held) - 3} more" if len(held) > 3 else "")
            raise UsageError(f"--out {self.out} already holds {shown}: pass a new folder, or --overwrite to write the "
                             "report over what is there")

    def run_folders(self) -> list[Path]:
        """The runs: each folder given, or, for a folder that is not a run (an `illm experiment`
        results folder), the runs below it; none is refused in one line."""
        runs = [run for r in self.runs for run in ([r] if (r / "metrics.csv").is_file() or (r / "config.json").is_file()
                                                  else sorted(p.parent for p in r.rglob("metrics.csv")))]
        runs = list({run.resolve(): run for run in runs}.values())  # a folder given twice is one run, not two seeds
        if not runs:
            raise UsageError("no training run in the folders given: pass folders written by `illm train` or "
                             "`illm experiment`")
        return runs
