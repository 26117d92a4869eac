"""The predictive safety filter: the expert's LTV plan with the agent's action as its target."""
