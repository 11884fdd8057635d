"""Evaluation: the papers' metrics (`metrics`: pure functions), the classifier that reads motions
(`classifier`: loading odmo and Action2Motion files), the protocol of the papers (`protocol`: Acc, FID,
Diversity, Multimodality, ...), and `odmo bench` (`bench`: speed and memory)."""
