"""From points to labels: the predictor, its torch-free settings, kNN refinement, point labels,
batch loading, stage timing, the one-process runner, and the forward-pass runtime (`runtime/`)."""
