"""Evaluation: episode metrics (defined in ``exit_decision.episode_log``), evaluation runs and plots."""
