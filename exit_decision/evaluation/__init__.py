"""Evaluation: episode metrics (SPEC section 6), evaluation runs and plots."""
