"""Evaluation: TAP-Vid metrics, covariance coverage, ground-truth readers (``condtrack eval``).

The click command lives in ``condtrack_cli.cli.eval`` (``eval_command``);
this package's numerics take plain arrays and do not import click.
"""

from condtrack_cli.evaluate.groundtruth import (  # noqa: F401
    Aligned,
    GroundTruth,
    align,
    load_gt_csv,
    load_gt_tapvid,
    pixels_to_tapvid,
    tapvid_to_pixels,
)
from condtrack_cli.evaluate.metrics import METRIC_KEYS, THRESHOLDS, coverage_inside, tapvid_metrics  # noqa: F401
