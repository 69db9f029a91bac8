"""kNN refinement's long-standing path (`rangeret.knn.refine`); it lives in
`rangeret.inference.knn`."""

from rangeret.inference.knn import refine, refine_batch

__all__ = ["refine", "refine_batch"]
