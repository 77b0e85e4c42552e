"""A replay's report: loops against ground truth, CSV / JSON, TUM files, ATE, plots."""
