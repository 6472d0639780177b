"""Agreement between the world-model backend and the ground truth over a zoo of policies."""
