"""experts stage of vla-ladder."""
