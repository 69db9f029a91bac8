"""From points to labels: the spec of a run (`spec.InferenceSpec`, torch-free) and its one weights
loader (`loader.load_weights`), the predictor and its one batch entry point (`Predictor.label`),
the single-scan worker, kNN refinement, point labels, batch loading, stage timing, what every
runner reports (`results`), the runners of trees, files and bags, and the forward-pass runtime
(`runtime/`)."""
