"""Generation: motions from a trained checkpoint (`generate`: sample, interpolate, complete) and
the batch they come in (`batch`: MotionBatch, decoding, writing the samples file)."""
