"""vla-ladder."""
