"""softac's version, in a module of its own so that what records it (exports, run directories) need not import
the package root."""

__version__ = "0.1.0"
