"""Runnable examples of the testbed's public interfaces (not part of the installed package)."""
