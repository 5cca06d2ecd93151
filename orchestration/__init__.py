"""Runs that compose several parts: the paper's experiments, the convergence-domain sweep, the arm run with its
processes (plant, bridge, service) and the demo. Above both `sim` (plants) and `clients` (Zenoh programs)."""
