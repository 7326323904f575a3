"""Graph Q-learning: replay with m-step targets and demonstrations, GQN/MDGQN, training (the
networks and the policy they are saved as: ``exit_decision.model``)."""
