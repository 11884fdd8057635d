"""The models: ODMO (its networks, loss terms and mode discovery, `latent`) and its baselines, and the
action classifier used for evaluation."""
