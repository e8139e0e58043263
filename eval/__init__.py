"""Evaluation of trained policies: uniform goals and the five-goal protocol, scored by the world's one metrics function; opens checkpoints only through training.checkpoint.load_checkpoint."""
