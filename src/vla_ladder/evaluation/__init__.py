"""evaluation stage of vla-ladder."""
