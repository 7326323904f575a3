"""Graph Q-learning: networks, replay with m-step targets and demonstrations, GQN/MDGQN, training."""
