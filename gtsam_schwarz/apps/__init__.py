"""Applications on top of the library: the ``gtsam-schwarz`` command, bench, paper reproduction,
dataset validation, comparisons with GTSAM, plots, reports and process tuning. Nothing in the
library imports this package."""
