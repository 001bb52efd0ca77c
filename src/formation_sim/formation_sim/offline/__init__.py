"""Runs from a recorded bag, without ROS: :mod:`analysis` (``formation-analyze``: the verdict and figures of
a run from its bag) and :mod:`rerun` (``formation-rerun``: every agent's controller re-run on what it received).
"""
