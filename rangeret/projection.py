"""Spherical projection's long-standing path (`rangeret.projection.project`); it lives in
`rangeret.dataset.projection`."""

from rangeret.dataset.projection import Projection, ProjectionConfig, project, project_with

__all__ = ["Projection", "ProjectionConfig", "project", "project_with"]
