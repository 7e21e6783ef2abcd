"""Training the PPO privileged-state expert (`vla-ladder train-expert`)."""
