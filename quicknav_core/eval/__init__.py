"""Held-out evaluation: navigation metrics, the shortest-path planner and the scripted baselines.

    evaluate.py   run_eval / evaluate, metrics (success with its interval, SPL, steps, collisions)
    agents.py     the Agent interface, a trained policy as an agent (agent_from_run)
    scripted.py   the random and oracle baselines
    planning.py   shortest collision-free disc paths, the oracle controller
"""
