"""Seeing a run: rerun recordings (live or from a results folder) and mesh pictures for reports."""
