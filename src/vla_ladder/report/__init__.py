"""report stage of vla-ladder."""
