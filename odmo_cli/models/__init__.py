"""The models: ODMO and its baselines, and the action classifier used for evaluation."""
