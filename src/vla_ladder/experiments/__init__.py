"""Orchestration above the stages: the paper's experiments, the grid search, the study and the probes."""
