"""Simulation: the crowd AI, plain numpy in and frame contracts (layers, instances) out, with no GL; and
its GPU twin in crowd.sim.gpu (compute passes, GL 4.3), for which the numpy AI is the float64 reference."""
