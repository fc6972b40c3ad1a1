"""Whole runs: the validated run configuration and its presets, the resumable pipeline of
stages, the run report, and the multi-seed portfolio.
"""
