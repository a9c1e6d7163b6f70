"""QuickNav Python SDK: talks to a QuickNav service without importing JAX."""

__version__ = "0.1.0"
