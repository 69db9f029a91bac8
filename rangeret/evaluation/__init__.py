"""Scoring predictions: confusion matrices and IoU, evaluating a tree, calibration, comparing
reports, plots, and `rangeret view`'s point clouds."""
