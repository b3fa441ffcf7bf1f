"""tmrl 0.7's path of the module helpers the tutorial imports (``copy_shared``, ``no_grad``): they
live in :mod:`tmrl.nn`."""

from tmrl.nn import copy_shared, no_grad

__all__ = ["copy_shared", "no_grad"]
