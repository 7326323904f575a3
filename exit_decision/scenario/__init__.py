"""The highway-exit scenario: SUMO network, traffic and the libsumo simulation wrapper."""
