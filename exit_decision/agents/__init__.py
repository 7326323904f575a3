"""Controllers in the action space: the safety shield (action masks) and the rule-based driver."""
