"""Experiment configs (ml_collections), loaded by path: `--config=configs/gqn.py[:quick|:smoke]`."""
