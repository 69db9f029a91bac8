"""Benchmark submissions: SemanticKITTI archives and the leaderboard description they carry."""
