"""Benchmarks that print figures (never timed tests): env throughput, room-bank build time,
training throughput, and the paper's Tables 1 and 2 as a learning benchmark.

    env.py       `quicknav bench`: JAX vs the NumPy twin, steps/s per grid and batch
    rooms.py     `quicknav bench rooms`: seconds to build the train and test room banks per grid
    train.py     `quicknav bench train`: env steps/s of every trainer at the paper's sizes
    learning.py  `quicknav bench learning`: train with seeds, evaluate on held-out rooms, report
    machine.py   the machine every report names
"""
