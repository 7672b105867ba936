"""`ccfit report`: tables and plots over continual runs, in the layout of the paper.

`build` writes the report (`write_report`); the runs it reads and how they group are `runs`;
its parts are `stages` (scores stage by stage), `orderings` (the paper's four orderings),
`axes` (by composition axis), `cost` (CPU-hours), `stats` (rliable's intervals) and `plots`
(figures and cell formats). `page` writes the results page over a folder of published runs.
"""

from ccfit.report.build import (
    METRICS_SHOWN,
    SUMMARY_JSON,
    group_metrics,
    group_runs,
    load_groups,
    table_frame,
    write_overview_of,
    write_report,
)
from ccfit.report.page import write_page
from ccfit.report.plots import plot_bars, plot_curves

__all__ = [
    "METRICS_SHOWN",
    "SUMMARY_JSON",
    "group_metrics",
    "group_runs",
    "load_groups",
    "plot_bars",
    "plot_curves",
    "table_frame",
    "write_overview_of",
    "write_page",
    "write_report",
]
