"""recording stage of vla-ladder."""
