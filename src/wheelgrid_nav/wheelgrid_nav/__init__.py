"""The safe 2D grid map (wheelchair-sized cells) and the Q-learning planner."""
