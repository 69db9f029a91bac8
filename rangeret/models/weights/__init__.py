"""Weights: checkpoint files and what they hold, the published models' registry, the model hub,
the bundled demo weights, and the profile a checkpoint runs with."""
