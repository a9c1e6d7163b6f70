"""Held-out evaluation: navigation metrics, the shortest-path planner and the scripted baselines.

    evaluate.py   run_eval / evaluate: run, count and draw, and write eval.json
    episodes.py   running the fixed-seed episodes (vmapped, one scan), replay.json
    statistics.py success with its Wilson interval, SPL, steps, collisions, difficulty bins
    pictures.py   trajectories.png, difficulty.png, episodes.gif (a failure is a warning)
    agents.py     the Agent interface, a trained policy as an agent (agent_from_run)
    scripted.py   the random and oracle baselines
    planning.py   the oracle controller (on the planner of env.plan)
"""
