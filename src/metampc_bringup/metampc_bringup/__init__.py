"""Recorder, orchestration and MCAP analysis of metampc runs."""
