"""training stage of vla-ladder."""
