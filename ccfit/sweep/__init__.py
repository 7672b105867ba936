"""Sweeps: a grid of continual runs (suites x models x methods x seeds) through one command.

    ccfit sweep --suites Reach,Grasp --methods ft,er,ewc,packnet --seeds 0,1,2 --preset cpu \
        --out RUNS [--models M1,M2] [--launcher local|slurm]

Layout of RUNS:
    sweep.json          the grid, every run's config, code version, submissions (job ids)
    <run name>/         one `ccfit run` directory per grid point (config.json, metrics.json)
    scratch/<key>/      from-scratch references, one per (suite, model, seed, options)
    report/             `ccfit report` over the finished runs, and status.json
    slurm/<job id>/     submitit logs and pickles (SLURM); local/ tracebacks of failed jobs

Modules: `grid` (expansion, sweep.json), `jobs` (the job callables), `launch` (local pool,
SLURM through submitit), `status`, `cli`. The SLURM settings, options and probes are
`ccdata.slurm`'s, shared with `ccdata generate --launcher slurm`.
"""

from ccfit.sweep.grid import Grid, Sweep, expand, load_sweep
from ccfit.sweep.jobs import ReportJob, RunJob, ScratchJob
from ccfit.sweep.status import sweep_status

__all__ = [
    "Grid",
    "ReportJob",
    "RunJob",
    "ScratchJob",
    "Sweep",
    "expand",
    "load_sweep",
    "sweep_status",
]
