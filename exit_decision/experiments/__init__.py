"""Experiments built on the environment, drivers and trainer: the reward sanity sweep, the ablation."""
