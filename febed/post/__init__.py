"""Post-processing of febed runs: time/depth-averaged particle fields, profiles, probe time series, figures.

Python API:
    >>> from febed.post import average_fields, post_run
    >>> res = post_run("runs/C1", window=(5.0, 20.0))      # writes runs/C1/post/*.csv, *.png
    >>> res.fields.alpha_p, res.summary.dp_ratio

Command line: `febed post RUN_DIR` (or `python -m febed.post RUN_DIR`).
"""

from febed.post.fields import AveragedFields, average_fields, default_bins, make_grid
from febed.post.grid import KERNELS, Grid, TimeAverage, bin_sums, bin_weights, snapshot_fields
from febed.post.report import PostResult, post_run
from febed.post.rundata import RunInfo, list_snapshots, read_snapshot, run_info, select_window
from febed.post.series import SeriesSummary, read_series, summarize, weight_per_area

__all__ = [
    "KERNELS",
    "AveragedFields",
    "Grid",
    "PostResult",
    "RunInfo",
    "SeriesSummary",
    "TimeAverage",
    "average_fields",
    "bin_sums",
    "bin_weights",
    "default_bins",
    "list_snapshots",
    "make_grid",
    "post_run",
    "read_series",
    "read_snapshot",
    "run_info",
    "select_window",
    "snapshot_fields",
    "summarize",
    "weight_per_area",
]
