"""The QuickNav environment: a JAX (gymnax) env and its NumPy twin."""
