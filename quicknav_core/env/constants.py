"""Codes shared by the JAX env, the NumPy twin, rendering and clients (no magic numbers)."""

# What a lidar beam reports it hit.
HIT_NONE = 0  # nothing within lidar_max_range
HIT_WALL = 1
HIT_GOAL = 2

# Observation layout (B = lidar_beams): see quicknav_core.env.quicknav.QuickNavEnv.
POSE_DIM = 4  # x / room_size, y / room_size, sin(theta), cos(theta)
GOAL_DIM = 5  # goal x / room_size, goal y / room_size, distance / room_size, sin, cos of bearing
