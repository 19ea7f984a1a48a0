"""Agent models (the :class:`~swarmpc.model.agent_model.AgentModel` seam, its registry and the
double integrator, the kinematic car) and geometry: the bottom layer, numpy plus each model's CasADi dynamics."""
