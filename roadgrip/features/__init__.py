"""Model inputs: feature sets, windows that never cross runs or gaps, scaling fitted on training data only, grouped folds."""
