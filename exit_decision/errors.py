"""Errors a user can cause, kept free of heavy imports so the command line can catch them."""


class PolicyError(RuntimeError):
    """A policy file that is missing, unreadable, or does not fit; the message names the path."""


class ParameterError(ValueError):
    """A start-up parameter value a node cannot use; the text names the parameter and what is allowed."""


class StackError(RuntimeError):
    """The ROS stack could not run (``ros/stack/launcher.py``): a node exited early, the nodes did not
    come up or the run did not finish in time; one line, with where the logs are."""


class UsageError(ValueError):
    """A file or option given on the command line that cannot be used; the message names the
    value and what is allowed."""
