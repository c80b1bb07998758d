"""Orchestration and MCAP analysis of metampc runs."""
