"""What an `illm experiment` is given: `ExperimentConfig`, its options (the spec, the results folder,
how runs start: `LAUNCHERS`), which `load` turns into the spec read (spec.py), the cluster settings
with the options over them, and the results folder."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from illm_tools.errors import UsageError
from illm_tools.experiment.spec import Cluster, Spec, load_spec

LAUNCHERS = ("local", "slurm", "submitit-local")
"""How runs start: local (`--jobs` processes here), slurm (a job each through submitit, one array),
submitit-local (submitit's local executor: the slurm path on this machine, for trying it)."""


@dataclass
class ExperimentConfig:
    """An `illm experiment`: the spec, where its results go, and how its runs are started."""

    spec: Path
    """The experiment's YAML spec (experiments/specs/ has the paper's tables)."""
    out: Path | None = None
    """Results folder (default: results/<spec name>)."""
    jobs: int = 1
    """Runs trained at a time, each in its own process with one thread."""
    frames: int | None = None
    """Frames per run, over the spec's (the paper: 100000000)."""
    seeds: int | None = None
    """Seeds 0..N-1, over the spec's (the paper: 10)."""
    dry_run: bool = False
    """Check the spec and list the runs; train nothing."""
    launcher: str = "local"
    """How runs start: local (--jobs processes here), slurm (one job array through submitit, --jobs tasks at a
    time), submitit-local (the slurm path on this machine, to try it)."""
    partition: str | None = None
    """SLURM partition (over the spec's cluster: block)."""
    time_minutes: int | None = None
    """Time limit of one run's job (default 240)."""
    cpus: int | None = None
    """CPUs of one run's job, its torch threads (default 1)."""
    gpus: int | None = None
    """GPUs of one run's job (default 0)."""
    mem_gb: float | None = None
    """Memory of one run's job in GB (default: the partition's)."""
    only: list[str] = field(default_factory=list)
    """Train only the runs whose label or path a pattern matches (repeatable, shell wildcards), e.g.
    --only ppo --only 'illm-annotator=*' or --only '*/seed0'; the others wait for a later call."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_folder, check_numbers

        self.spec = Path(self.spec)
        self.out = Path(self.out) if self.out is not None else None
        check_numbers(self, positive=("jobs", "frames", "seeds"))  # the cluster's: `Cluster.merged` in `load`
        check_folder(self.out, "--out")
        check_launcher(self.launcher)

    def load(self) -> tuple[Spec, Cluster, Path]:
        """The spec with --frames and --seeds applied, its cluster settings with the options over
        them, and the results folder."""
        spec = load_spec(self.spec, frames=self.frames, seeds=self.seeds)
        cluster = spec.cluster.merged(partition=self.partition, time_minutes=self.time_minutes, cpus=self.cpus,
                                      gpus=self.gpus, mem_gb=self.mem_gb)
        return spec, cluster, self.out or Path("results") / spec.name


def check_launcher(launcher: str) -> None:
    if launcher not in LAUNCHERS:
        raise UsageError(f"--launcher must be one of {', '.join(LAUNCHERS)}, got {launcher!r}")
