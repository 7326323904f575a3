"""Errors a user can cause, kept free of heavy imports so the command line can catch them."""


class PolicyError(RuntimeError):
    """A policy file that is missing, unreadable, or does not fit; the message names the path."""
