"""Simulation: the crowd AI, plain numpy in and frame contracts (layers, instances) out. No GL."""
